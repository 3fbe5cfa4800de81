"""Authentication, spec section 5: the 60-byte control packet, the 48-byte request and reply
frames, tags and the key file's text.

Written from the spec alone, on :mod:`hashlib` and :mod:`struct`, so it can check the C core.

- Tag: ``MAC(K, m) = blake2s(m, key=K, digest_size=16)``; tags are compared with
  :func:`hmac.compare_digest`.
- Every ``encode`` takes a key, or ``None`` for a sender without one: the tag is then 16 zero
  bytes (a keyless unit's replies, a keyless remote's stop datagram).
- Every ``decode`` takes a key too. With a key the tag is verified and a wrong one raises
  :class:`TagMismatch`; with ``None`` the tag is *not* checked (a keyless remote cannot).

Layouts (little-endian):

- control packet: ``"ESU2", u32 remote id, u64 session, u64 counter, 20-byte body, tag``;
  tag = MAC(K, bytes 0..43)
- request frame: ``"ESQ2", u32 msg_id, u32 seq, u32 remote id, u64 session, u64 counter,
  tag``; tag = MAC(K, bytes 0..31)
- reply frame: ``"ESR2", u32 ACK/NAK, u32 seq, u8 state, u8 reason, u8 flags, u8 nak code,
  u64 session, u64 counter, tag``; tag = MAC(K, the request's tag, then bytes 0..31)
"""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
from dataclasses import KW_ONLY, dataclass

from estop.protocol import tcp, udp
from estop.protocol.tcp import DEFAULT_STOP_ID, NakCode, Reply
from estop.protocol.udp import ControlPacket

__all__ = [
    "CONTROL_MAGIC",
    "CONTROL_SIZE",
    "KEY_SIZE",
    "REPLY_MAGIC",
    "REPLY_SIZE",
    "REQUEST_MAGIC",
    "REQUEST_SIZE",
    "TAG_SIZE",
    "ZERO_TAG",
    "AuthControlPacket",
    "AuthError",
    "AuthReply",
    "AuthRequest",
    "KeyTextError",
    "TagMismatch",
    "check_key",
    "format_key",
    "mac",
    "parse_key",
    "request_tag",
    "stop_datagram",
]

KEY_SIZE = 32
TAG_SIZE = 16
ZERO_TAG = bytes(TAG_SIZE)
CONTROL_MAGIC = b"ESU2"
REQUEST_MAGIC = tcp.REQUEST_MAGIC  # b"ESQ2"
REPLY_MAGIC = b"ESR2"
CONTROL_SIZE = 60
REQUEST_SIZE = tcp.V2_FRAME_SIZE  # 48
REPLY_SIZE = tcp.V2_FRAME_SIZE  # 48

_CONTROL_HEAD = struct.Struct("<4sIQQ")  # magic, remote id, session, counter: 24 bytes
_REQUEST = struct.Struct("<4sIIIQQ")  # magic, msg_id, seq, remote id, session, counter: 32
_REPLY = struct.Struct("<4sIIBBBBQQ")  # magic, ACK/NAK, seq, state..nak, session, counter: 32
_U32_MAX = 0xFFFFFFFF
_U64_MAX = 0xFFFFFFFFFFFFFFFF

Data = bytes | bytearray | memoryview


class AuthError(tcp.FrameError):
    """A section-5 packet or frame that cannot be accepted (length, magic, field values).
    ``str()`` is a one-line reason."""


class TagMismatch(AuthError):
    """The tag does not verify under the key: the message was not made with the key, was
    changed, or (a reply) does not answer the request it was checked against."""


class KeyTextError(ValueError):
    """Text that is not a key file's content. ``str()`` is a one-line reason."""


# ------------------------------------------------------------------------------- the MAC

def check_key(key: bytes | bytearray | memoryview) -> bytes:
    """Return ``key`` as bytes if it is a key (exactly 32 bytes); else raise ValueError."""
    raw = bytes(key)
    if len(raw) != KEY_SIZE:
        raise ValueError(f"a key is {KEY_SIZE} bytes, got {len(raw)}")
    return raw


def mac(key: bytes, data: Data) -> bytes:
    """MAC(K, m): keyed BLAKE2s with a 16-byte digest (RFC 7693)."""
    return hashlib.blake2s(bytes(data), key=check_key(key), digest_size=TAG_SIZE).digest()


def _tag(key: bytes | None, data: bytes) -> bytes:
    return ZERO_TAG if key is None else mac(key, data)


def _verify(key: bytes | None, data: bytes, tag: bytes, what: str) -> None:
    if key is not None and not hmac.compare_digest(mac(key, data), tag):
        raise TagMismatch(f"{what} tag does not verify (not made with this key, changed, "
                          f"or not an answer to this request)")


def _u32(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= _U32_MAX:
        raise ValueError(f"{name} must be a u32 (0..0xFFFFFFFF), got {value!r}")
    return value


def _u64(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= _U64_MAX:
        raise ValueError(f"{name} must be a u64 (0..2**64-1), got {value!r}")
    return value


def _open(data: Data, size: int, magic: bytes, what: str) -> bytes:
    raw = bytes(data)
    if len(raw) != size:
        raise AuthError(f"{what} must be {size} bytes, got {len(raw)}")
    if raw[:4] != magic:
        raise AuthError(f"{what} must start with {magic.decode()} ({magic.hex(' ').upper()}), "
                        f"got {raw[:4].hex(' ').upper()}")
    return raw


# ------------------------------------------------------------- 5.1 control packet (UDP)

@dataclass(frozen=True, slots=True)
class AuthControlPacket:
    """The 60-byte authenticated control packet: the 20-byte body of section 1 plus remote
    id, session and counter, under a tag."""

    remote_id: int
    session: int
    counter: int
    body: ControlPacket = ControlPacket()

    def encode(self, key: bytes | None, *, validate: bool = True) -> bytes:
        """60 bytes; tag MAC(key, bytes 0..43), or 16 zero bytes when ``key`` is None.
        ``validate=False`` lets the body hold invalid values (as :meth:`ControlPacket.encode`).
        """
        head = _CONTROL_HEAD.pack(CONTROL_MAGIC, _u32("remote id", self.remote_id),
                                  _u64("session", self.session),
                                  _u64("counter", self.counter))
        signed = head + self.body.encode(validate=validate)
        return signed + _tag(key, signed)

    @classmethod
    def decode(cls, data: Data, key: bytes | None, *, validate: bool = True
               ) -> AuthControlPacket:
        """Decode 60 bytes. Raises :class:`AuthError` (length, magic), :class:`TagMismatch`
        (with a key: a wrong tag), then :class:`~estop.protocol.udp.InvalidPacket` for a body
        with invalid values (unless ``validate=False``)."""
        raw = _open(data, CONTROL_SIZE, CONTROL_MAGIC, "control packet")
        _verify(key, raw[:44], raw[44:], "control packet")
        _, remote_id, session, counter = _CONTROL_HEAD.unpack(raw[:24])
        body_raw = raw[24:44]
        if validate:
            body = udp.decode(body_raw)
        else:
            gas, steer, gear, turn, horn = struct.unpack("<ffiii", body_raw)
            body = ControlPacket(float(gas), float(steer), gear, turn, horn)
        return cls(remote_id, session, counter, body)


# ------------------------------------------------------------ 5.2 request frame (TCP, UDP)

@dataclass(frozen=True, slots=True)
class AuthRequest:
    """The 48-byte request frame (TCP, and the UDP stop datagram). ``session`` is 0 while the
    remote does not know the unit's session yet."""

    msg_id: int
    seq: int
    remote_id: int
    session: int
    counter: int

    def encode(self, key: bytes | None) -> bytes:
        """48 bytes; tag MAC(key, bytes 0..31), or 16 zero bytes when ``key`` is None."""
        signed = _REQUEST.pack(REQUEST_MAGIC, _u32("msg_id", self.msg_id),
                               _u32("seq", self.seq), _u32("remote id", self.remote_id),
                               _u64("session", self.session), _u64("counter", self.counter))
        return signed + _tag(key, signed)

    @classmethod
    def decode(cls, data: Data, key: bytes | None) -> AuthRequest:
        """Decode 48 bytes; raise :class:`AuthError`, or :class:`TagMismatch` (with a key).
        Any msg_id is returned (the unit answers unknown ones with NAK 1)."""
        raw = _open(data, REQUEST_SIZE, REQUEST_MAGIC, "request frame")
        _verify(key, raw[:32], raw[32:], "request frame")
        _, msg_id, seq, remote_id, session, counter = _REQUEST.unpack(raw[:32])
        return cls(msg_id, seq, remote_id, session, counter)

    def kind(self, stop_id: int = DEFAULT_STOP_ID) -> str:
        """``"stop"``, ``"lift"``, ``"status"``, ``"release"`` or ``"unknown"`` for a unit with
        ``stop_id``."""
        return tcp.Request(self.msg_id, self.seq).kind(stop_id)


def request_tag(frame: Data) -> bytes:
    """The tag of an encoded request frame (bytes 32..47), which its reply's tag covers."""
    raw = _open(frame, REQUEST_SIZE, REQUEST_MAGIC, "request frame")
    return raw[32:]


def stop_datagram(seq: int, counter: int, *, key: bytes | None = None, session: int = 0,
                  remote_id: int = 0, stop_id: int = DEFAULT_STOP_ID) -> bytes:
    """A stop datagram (spec section 1): a request frame whose msg_id is the stop ID, for the
    UDP control port. The unit stops on it whatever its tag, session and counter say."""
    return AuthRequest(tcp.check_stop_id(stop_id), seq, remote_id, session,
                       counter).encode(key)


# ----------------------------------------------------------------- 5.3 reply frame (TCP)

@dataclass(frozen=True, slots=True)
class AuthReply:
    """The 48-byte reply frame: a reply's fields (as :class:`~estop.protocol.tcp.Reply`) plus
    the unit's session and the request's counter, under a tag that covers the request's tag.
    """

    ack: bool
    seq: int
    state: int
    reason: int
    _: KW_ONLY
    flags: int = 0
    nak_code: int = NakCode.NONE
    session: int
    counter: int

    @property
    def reply(self) -> Reply:
        """The fields every reply shares, as a plain :class:`~estop.protocol.tcp.Reply`."""
        return Reply(self.ack, self.seq, self.state, self.reason, self.flags, self.nak_code)

    @property
    def msg_id(self) -> int:
        return tcp.ACK if self.ack else tcp.NAK

    def validate(self) -> None:
        """Raise :class:`AuthError` unless the fields are a reply spec version 2 allows
        (those of a plain reply, and a session that is not 0)."""
        try:
            self.reply.validate()
        except tcp.FrameError as exc:
            raise AuthError(str(exc)) from None
        _u64("session", self.session)
        _u64("counter", self.counter)
        if self.session == 0:
            raise AuthError("reply session 0 (a unit's session is never zero)")

    def encode(self, key: bytes | None, request_tag: bytes, *, validate: bool = True) -> bytes:
        """48 bytes; tag MAC(key, request_tag + bytes 0..31), or 16 zero bytes when ``key``
        is None (a unit without a key)."""
        if validate:
            self.validate()
        signed = _REPLY.pack(REPLY_MAGIC, self.msg_id, _u32("seq", self.seq), self.state,
                             self.reason, self.flags, self.nak_code,
                             _u64("session", self.session), _u64("counter", self.counter))
        if key is None:
            return signed + ZERO_TAG
        return signed + mac(key, _check_tag(request_tag) + signed)

    @classmethod
    def decode(cls, data: Data, key: bytes | None, request_tag: bytes | None = None, *,
               strict: bool = True) -> AuthReply:
        """Decode 48 bytes.

        With a key the tag must be MAC(key, ``request_tag`` + bytes 0..31), else
        :class:`TagMismatch`: only a reply made with the key *for that request* verifies.
        Then the msg_id must be ACK or NAK and, with ``strict``, the fields valid (see
        :meth:`validate`); else :class:`AuthError`.
        """
        raw = _open(data, REPLY_SIZE, REPLY_MAGIC, "reply frame")
        if key is not None:
            if request_tag is None:
                raise ValueError("verifying a reply needs the request's tag")
            _verify(key, _check_tag(request_tag) + raw[:32], raw[32:], "reply frame")
        _, msg_id, seq, state, reason, flags, nak, session, counter = _REPLY.unpack(raw[:32])
        if msg_id not in (tcp.ACK, tcp.NAK):
            raise AuthError(f"reply msg_id {msg_id:#010x} is neither ACK 0x80 nor NAK 0x81")
        reply = cls(msg_id == tcp.ACK, seq, state, reason, flags=flags, nak_code=nak,
                    session=session, counter=counter)
        if strict:
            reply.validate()
        return reply


def _check_tag(tag: bytes) -> bytes:
    raw = bytes(tag)
    if len(raw) != TAG_SIZE:
        raise ValueError(f"a tag is {TAG_SIZE} bytes, got {len(raw)}")
    return raw


# ---------------------------------------------------------------------- key file's text

_KEY_TEXT = re.compile(rb"[0-9A-Fa-f]{64}\n?")
_HEX_DIGITS = b"0123456789abcdefABCDEF"


def parse_key(text: bytes) -> bytes:
    """The key in a key file's content: exactly 64 hex digits (either case), an optional
    final newline, nothing else. Raise :class:`KeyTextError` (one line) otherwise."""
    if _KEY_TEXT.fullmatch(text):
        return bytes.fromhex(text[:64].decode("ascii"))
    body = text[:-1] if text.endswith(b"\n") else text
    if b"\n" in body:
        raise KeyTextError("must be one line of 64 hex digits (more than one line found)")
    bad = next((c for c in body if c not in _HEX_DIGITS), None)
    if bad is not None:
        shown = f" {chr(bad)!r}" if 0x20 <= bad < 0x7F else ""
        raise KeyTextError(f"must be 64 hex digits only (found byte {bad:#04x}{shown})")
    raise KeyTextError(f"must be exactly 64 hex digits, found {len(body)}")


def format_key(key: bytes) -> bytes:
    """A key file's content for ``key``: 64 lowercase hex digits and a newline."""
    return check_key(key).hex().encode("ascii") + b"\n"
