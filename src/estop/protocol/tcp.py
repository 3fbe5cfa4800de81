"""TCP stop channel, remote <-> unit (spec section 2): the plain 16-byte frames.

Every plain frame is 16 bytes, little-endian, the last 4 bytes a CRC-32 (as zlib.crc32) of
bytes 0..11. Requests: ``u32 msg_id, u32 seq, u32 arg, u32 crc``. Replies:
``u32 ACK/NAK, u32 seq, u8 state, u8 reason, u8 flags, u8 nak_code, u32 crc``.

The stream also carries the 48-byte request frames of section 5.2 (codecs in
:mod:`estop.protocol.auth`): the first 4 bytes of each frame decide its form, ``ESQ2`` a
48-byte request, anything else a 16-byte plain frame (:class:`RequestAssembler`).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from enum import IntEnum

from estop.protocol.can import ContentError, check_status_fields
from estop.protocol.crc import crc32

__all__ = [
    "ACK",
    "DEFAULT_PORT",
    "DEFAULT_STOP_ID",
    "FRAME_SIZE",
    "LIFT",
    "NAK",
    "NAK_NAMES",
    "RELEASE",
    "REQUEST_MAGIC",
    "REQUEST_MAGIC_ID",
    "RESERVED_MSG_IDS",
    "STATUS",
    "V2_FRAME_SIZE",
    "CrcMismatch",
    "FrameAssembler",
    "FrameError",
    "NakCode",
    "Reply",
    "Request",
    "RequestAssembler",
    "check_stop_id",
    "lift_request",
    "release_request",
    "status_request",
    "stop_request",
]

DEFAULT_PORT = 5701
FRAME_SIZE = 16
DEFAULT_STOP_ID = 0xE570E570
STATUS = 0x00000001
RELEASE = 0x00000002
LIFT = 0x00000003  # the dead-man switch was let go: a stop request with its own reason (v3)
ACK = 0x00000080
NAK = 0x00000081
RESERVED_MSG_IDS = frozenset((0, STATUS, RELEASE, LIFT))
REQUEST_MAGIC = b"ESQ2"  # first 4 bytes of a 48-byte request frame (section 5.2)
REQUEST_MAGIC_ID = 0x32515345  # the same 4 bytes read as a u32 msg_id: never a stop ID
V2_FRAME_SIZE = 48  # request and reply frames of sections 5.2 and 5.3

_REQ = struct.Struct("<III")
_REP = struct.Struct("<IIBBBB")
_CRC = struct.Struct("<I")
_U32_MAX = 0xFFFFFFFF


class NakCode(IntEnum):
    NONE = 0
    UNKNOWN_MSG_ID = 1
    NO_LIVE_LINK = 2
    NOT_NEUTRAL = 3
    NOT_AUTHENTICATED = 4


NAK_NAMES: dict[int, str] = {
    NakCode.NONE: "none",
    NakCode.UNKNOWN_MSG_ID: "unknown_msg_id",
    NakCode.NO_LIVE_LINK: "no_live_link",
    NakCode.NOT_NEUTRAL: "not_neutral",
    NakCode.NOT_AUTHENTICATED: "not_authenticated",
}


class FrameError(ValueError):
    """A 16-byte TCP frame that cannot be accepted. ``str()`` is a one-line reason."""


class CrcMismatch(FrameError):
    """The CRC-32 does not match: per spec the stream has lost framing (close the connection)."""


def _u32(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= _U32_MAX:
        raise ValueError(f"{name} must be a u32 (0..0xFFFFFFFF), got {value!r}")
    return value


def check_stop_id(stop_id: int) -> int:
    """Return ``stop_id`` if it may be a vehicle's stop ID: a u32 other than 0, 1, 2, 3 and
    0x32515345 (that one would read as the magic of a 48-byte request frame)."""
    _u32("stop ID", stop_id)
    if stop_id in RESERVED_MSG_IDS or stop_id == REQUEST_MAGIC_ID:
        raise ValueError(f"stop ID may not be 0, 1, 2, 3 or 0x32515345, got {stop_id:#x}")
    return stop_id


def _seal(body: bytes) -> bytes:
    return body + _CRC.pack(crc32(body))


def _open(frame: bytes | bytearray | memoryview, what: str) -> bytes:
    raw = bytes(frame)
    if len(raw) != FRAME_SIZE:
        raise FrameError(f"{what} frame must be {FRAME_SIZE} bytes, got {len(raw)}")
    body = raw[:12]
    (got,) = _CRC.unpack(raw[12:])
    want = crc32(body)
    if got != want:
        raise CrcMismatch(f"{what} frame CRC mismatch (got {got:#010x}, want {want:#010x})")
    return body


@dataclass(frozen=True, slots=True)
class Request:
    """A plain request frame. ``arg`` is 0 (spec section 2)."""

    msg_id: int
    seq: int
    arg: int = 0

    def encode(self) -> bytes:
        return _seal(_REQ.pack(_u32("msg_id", self.msg_id), _u32("seq", self.seq),
                               _u32("arg", self.arg)))

    @classmethod
    def decode(cls, frame: bytes | bytearray | memoryview) -> Request:
        """Decode a request; raise :class:`CrcMismatch` / :class:`FrameError`.

        Any msg_id is returned (the unit answers unknown ones with NAK 1).
        """
        msg_id, seq, arg = _REQ.unpack(_open(frame, "request"))
        return cls(msg_id, seq, arg)

    def kind(self, stop_id: int = DEFAULT_STOP_ID) -> str:
        """``"stop"``, ``"lift"``, ``"status"``, ``"release"`` or ``"unknown"`` for a unit with
        ``stop_id``."""
        if self.msg_id == stop_id and self.msg_id not in RESERVED_MSG_IDS:
            return "stop"
        if self.msg_id == LIFT:
            return "lift"
        if self.msg_id == STATUS:
            return "status"
        if self.msg_id == RELEASE:
            return "release"
        return "unknown"


def stop_request(seq: int, stop_id: int = DEFAULT_STOP_ID) -> Request:
    return Request(check_stop_id(stop_id), seq)


def lift_request(seq: int) -> Request:
    return Request(LIFT, seq)


def status_request(seq: int) -> Request:
    return Request(STATUS, seq)


def release_request(seq: int) -> Request:
    return Request(RELEASE, seq)


@dataclass(frozen=True, slots=True)
class Reply:
    """A reply frame: ``ack`` True for ACK (0x80), False for NAK (0x81)."""

    ack: bool
    seq: int
    state: int
    reason: int
    flags: int = 0
    nak_code: int = NakCode.NONE

    def validate(self) -> None:
        """Raise :class:`FrameError` unless the fields are a reply spec version 2 allows
        (known state/reason/flags/nak code, consistent with each other)."""
        _u32("seq", self.seq)
        try:
            check_status_fields(self.state, self.reason, self.flags)
        except ContentError as exc:
            raise FrameError(f"reply: {exc}") from exc
        if self.nak_code not in NAK_NAMES:
            raise FrameError(f"reply nak code {self.nak_code} unknown (0..4)")
        if self.ack and self.nak_code != NakCode.NONE:
            raise FrameError(f"ACK with nak code {self.nak_code} (must be 0)")
        if not self.ack and self.nak_code == NakCode.NONE:
            raise FrameError("NAK with nak code 0 (must say why)")

    @property
    def msg_id(self) -> int:
        return ACK if self.ack else NAK

    def encode(self, *, validate: bool = True) -> bytes:
        if validate:
            self.validate()
        return _seal(_REP.pack(self.msg_id, _u32("seq", self.seq), self.state, self.reason,
                               self.flags, self.nak_code))

    @classmethod
    def decode(cls, frame: bytes | bytearray | memoryview, *, strict: bool = True) -> Reply:
        """Decode a reply; raise :class:`CrcMismatch` / :class:`FrameError`.

        The msg_id must be ACK or NAK. With ``strict`` (default) the other fields must hold
        values spec version 2 defines (see :meth:`validate`).
        """
        msg_id, seq, state, reason, flags, nak_code = _REP.unpack(_open(frame, "reply"))
        if msg_id not in (ACK, NAK):
            raise FrameError(f"reply msg_id {msg_id:#010x} is neither ACK 0x80 nor NAK 0x81")
        reply = cls(msg_id == ACK, seq, state, reason, flags, nak_code)
        if strict:
            reply.validate()
        return reply


class FrameAssembler:
    """Cut a byte stream, split anywhere, into frames of one fixed size (default 16; a client
    that sent 48-byte requests reads 48-byte replies).

    ``feed(data)`` returns the complete frames now available (possibly none, possibly several);
    the remainder is kept for the next call. CRCs are not checked here.
    """

    def __init__(self, frame_size: int = FRAME_SIZE) -> None:
        self._size = frame_size
        self._buf = bytearray()

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        self._buf += data
        return list(self._drain())

    def _drain(self) -> Iterator[bytes]:
        n = len(self._buf) // self._size * self._size
        if n:
            chunk = bytes(self._buf[:n])
            del self._buf[:n]
            for i in range(0, n, self._size):
                yield chunk[i:i + self._size]

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        self._buf.clear()


class RequestAssembler:
    """The unit's side of the stream: cut it, split anywhere, into request frames whose
    length the first 4 bytes decide (``ESQ2``: 48 bytes, anything else: 16).

    ``feed(data)`` returns the complete frames now available, in order; the remainder is
    kept. Neither CRCs nor tags are checked here.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    @staticmethod
    def frame_size(head: bytes | bytearray | memoryview) -> int | None:
        """Length of the frame that starts with ``head``; None while fewer than 4 bytes."""
        if len(head) < 4:
            return None
        return V2_FRAME_SIZE if bytes(head[:4]) == REQUEST_MAGIC else FRAME_SIZE

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        self._buf += data
        frames: list[bytes] = []
        start = 0
        while True:
            size = self.frame_size(self._buf[start:start + 4])
            if size is None or len(self._buf) - start < size:
                break
            frames.append(bytes(self._buf[start:start + size]))
            start += size
        del self._buf[:start]
        return frames

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        self._buf.clear()
