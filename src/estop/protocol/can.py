"""CAN frames, unit -> bus (spec section 4, docs/DESIGN.md): ESTOP_BRAKE and ESTOP_STATUS.

Both are classic CAN, 11-bit IDs, DLC 8. Byte 6 bits 0-3 hold an alive counter 0..14 (15 is
never sent), bits 4-7 are zero; byte 7 is CRC-8 SAE J1850 over the data ID's low byte, its
high byte and bytes 0..6 (AUTOSAR E2E profile 1 style; the data ID is never sent).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import Enum, IntEnum
from importlib import resources
from pathlib import Path

from estop.protocol.crc import e2e_crc8

__all__ = [
    "BRAKE_DATA_ID",
    "BRAKE_ID",
    "BRAKE_LEVEL_ARMED",
    "BRAKE_LEVEL_STOPPED",
    "BRAKE_REQUEST_NAMES",
    "COUNTER_MODULO",
    "DEFAULT_SLOW_LEVEL",
    "DLC",
    "FLAG_LINK_DEGRADED",
    "FLAG_NAMES",
    "LINK_AGE_NONE",
    "REASON_NAMES",
    "STATE_NAMES",
    "STATUS_DATA_ID",
    "STATUS_ID",
    "BrakeFrame",
    "BrakeRequest",
    "ContentError",
    "CounterChecker",
    "CounterError",
    "CounterResult",
    "CounterStatus",
    "CrcError",
    "FrameError",
    "LengthError",
    "Reason",
    "State",
    "StatusFrame",
    "check_status_fields",
    "dbc_path",
    "dbc_text",
    "brake_request_name",
    "flag_names",
    "reason_name",
    "state_name",
]

BRAKE_ID = 0x050
STATUS_ID = 0x051
BRAKE_DATA_ID = 0x0E57
STATUS_DATA_ID = 0x0E58
DLC = 8
COUNTER_MODULO = 15  # counter runs 0..14 then back to 0
BRAKE_LEVEL_STOPPED = 100
BRAKE_LEVEL_ARMED = 0
DEFAULT_SLOW_LEVEL = 30  # L: brake_level while SLOWING, percent 1..99 (set on the unit)
SLOW_LEVEL_MIN, SLOW_LEVEL_MAX = 1, 99
FLAG_LINK_DEGRADED = 0x01
_FLAGS_DEFINED = FLAG_LINK_DEGRADED
LINK_AGE_NONE = 0xFFFF
NIBBLE_MAX = 15  # ESTOP_STATUS byte 3: stops (bits 0-3) and slow-downs (bits 4-7) per window


def dbc_path() -> Path:
    """Path of the installed ``estop/dbc/estop.dbc`` (for cantools, SavvyCAN, ...)."""
    return Path(str(resources.files("estop").joinpath("dbc", "estop.dbc")))


def dbc_text() -> str:
    """Text of ``estop/dbc/estop.dbc``."""
    return resources.files("estop").joinpath("dbc", "estop.dbc").read_text(encoding="utf-8")


class State(IntEnum):
    STOPPED = 0
    ARMED = 1
    SLOWING = 2  # controlled stop while the link is silent; not latched (v3)


class Reason(IntEnum):
    NONE = 0
    BOOT = 1
    TCP_STOP = 2
    UDP_TIMEOUT = 3
    FAULT = 4
    LIFT = 5  # the remote's dead-man switch was let go (v3)


class BrakeRequest(IntEnum):
    """ESTOP_BRAKE byte 0. A receiver treats any other value as EMERGENCY (spec section 7)."""

    RELEASE = 0
    EMERGENCY = 1
    CONTROLLED = 2


STATE_NAMES: dict[int, str] = {State.STOPPED: "STOPPED", State.ARMED: "ARMED",
                               State.SLOWING: "SLOWING"}
REASON_NAMES: dict[int, str] = {
    Reason.NONE: "none",
    Reason.BOOT: "boot",
    Reason.TCP_STOP: "tcp_stop",
    Reason.UDP_TIMEOUT: "udp_timeout",
    Reason.FAULT: "fault",
    Reason.LIFT: "lift",
}
BRAKE_REQUEST_NAMES: dict[int, str] = {
    BrakeRequest.RELEASE: "release",
    BrakeRequest.EMERGENCY: "emergency_brake",
    BrakeRequest.CONTROLLED: "controlled_stop",
}
# The brake_request each state sends.
_STATE_REQUEST: dict[int, BrakeRequest] = {
    State.STOPPED: BrakeRequest.EMERGENCY,
    State.ARMED: BrakeRequest.RELEASE,
    State.SLOWING: BrakeRequest.CONTROLLED,
}
FLAG_NAMES: dict[int, str] = {FLAG_LINK_DEGRADED: "link_degraded"}


def state_name(state: int) -> str:
    """``STOPPED`` / ``ARMED`` / ``SLOWING``, or ``state?<n>`` for a value the spec does not
    define."""
    return STATE_NAMES.get(state, f"state?{state}")


def reason_name(reason: int) -> str:
    """``none``, ``boot``, ``tcp_stop``, ``udp_timeout``, ``fault``, ``lift``, or
    ``reason?<n>``."""
    return REASON_NAMES.get(reason, f"reason?{reason}")


def brake_request_name(request: int) -> str:
    """``release``, ``emergency_brake``, ``controlled_stop``, or ``request?<n>``."""
    return BRAKE_REQUEST_NAMES.get(request, f"request?{request}")


def flag_names(flags: int) -> list[str]:
    """Names of the set flag bits (undefined bits as ``bit<n>``)."""
    return [FLAG_NAMES.get(1 << b, f"bit{b}") for b in range(8) if flags & (1 << b)]


class FrameError(ValueError):
    """A CAN frame a receiver must not accept. ``kind`` names the check that failed."""

    kind = "frame"


class LengthError(FrameError):
    kind = "bad_length"


class CrcError(FrameError):
    kind = "bad_crc"


class CounterError(FrameError):
    """Byte 6 is not a legal alive counter (15, or high nibble set)."""

    kind = "bad_counter"


class ContentError(FrameError):
    """Good CRC, but fields the spec does not allow or that contradict each other."""

    kind = "bad_content"


def check_status_fields(state: int, reason: int, flags: int) -> None:
    """Raise :class:`ContentError` unless state/reason/flags are a combination spec section 3
    allows: a known state and reason, reason 0 exactly while ARMED or SLOWING, flags only bit 0
    and only while ARMED or SLOWING."""
    if state not in STATE_NAMES:
        raise ContentError(f"state {state} unknown (0 STOPPED, 1 ARMED, 2 SLOWING)")
    if reason not in REASON_NAMES:
        raise ContentError(f"reason {reason} unknown (0..5)")
    if state != State.STOPPED and reason != Reason.NONE:
        raise ContentError(f"reason {reason_name(reason)} while {state_name(state)} "
                           "(must be none)")
    if state == State.STOPPED and reason == Reason.NONE:
        raise ContentError("reason none while STOPPED")
    if flags & ~_FLAGS_DEFINED & 0xFF or not 0 <= flags <= 0xFF:
        raise ContentError(f"flags {flags:#04x} has undefined bits set")
    if flags & FLAG_LINK_DEGRADED and state == State.STOPPED:
        raise ContentError("link_degraded flag while STOPPED")


def _check_u8(name: str, value: int) -> None:
    if not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ContentError(f"{name} must be a byte 0..255, got {value!r}")


def _check_counter_value(counter: int) -> None:
    if not isinstance(counter, int) or not 0 <= counter < COUNTER_MODULO:
        raise CounterError(f"alive counter {counter!r} out of range 0..14")


def _seal(payload7: bytes, data_id: int) -> bytes:
    return payload7 + bytes((e2e_crc8(data_id, payload7),))


def _problems(raw: bytes, data_id: int) -> list[FrameError]:
    """Length, CRC and counter checks shared by both frames (content checks come after)."""
    if len(raw) != DLC:
        return [LengthError(f"DLC {len(raw)}, must be {DLC}")]
    found: list[FrameError] = []
    want = e2e_crc8(data_id, raw[:7])
    if raw[7] != want:
        found.append(CrcError(f"CRC {raw[7]:#04x}, want {want:#04x}"))
    if raw[6] & 0xF0:
        found.append(CounterError(f"byte 6 {raw[6]:#04x}: bits 4-7 must be zero"))
    elif raw[6] & 0x0F >= COUNTER_MODULO:
        found.append(CounterError("alive counter 15 is never sent"))
    return found


@dataclass(frozen=True, slots=True)
class BrakeFrame:
    """ESTOP_BRAKE (0x050). Build one with :meth:`for_state` to get consistent fields."""

    brake_request: int
    brake_level: int
    state: int
    reason: int
    flags: int
    counter: int
    reserved: int = 0  # byte 5, always 0 on the wire

    DATA_ID = BRAKE_DATA_ID
    CAN_ID = BRAKE_ID

    @classmethod
    def for_state(cls, state: int, reason: int, flags: int = 0, counter: int = 0,
                  slow_level: int = DEFAULT_SLOW_LEVEL) -> BrakeFrame:
        request = _STATE_REQUEST.get(state, BrakeRequest.EMERGENCY)
        level = {BrakeRequest.RELEASE: BRAKE_LEVEL_ARMED,
                 BrakeRequest.CONTROLLED: slow_level}.get(request, BRAKE_LEVEL_STOPPED)
        return cls(int(request), level, state, reason, flags, counter)

    @property
    def brakes(self) -> bool:
        """True when this frame asks for any braking (emergency or controlled)."""
        return self.brake_request != BrakeRequest.RELEASE

    @property
    def emergency(self) -> bool:
        """True when a receiver must brake at full force: brake_request 1, or any value it does
        not know (spec section 7)."""
        return self.brake_request not in (BrakeRequest.RELEASE, BrakeRequest.CONTROLLED)

    @property
    def deceleration_share(self) -> float:
        """The share of the emergency deceleration this frame asks for (spec section 7): 0 on
        release, brake_level/100 on a controlled stop, 1 on an emergency brake and on any
        brake_request a receiver does not know."""
        if self.brake_request == BrakeRequest.RELEASE:
            return 0.0
        if self.brake_request == BrakeRequest.CONTROLLED:
            return min(self.brake_level, 100) / 100.0
        return 1.0

    def validate(self) -> None:
        """Raise :class:`ContentError` / :class:`CounterError` unless the spec allows the frame."""
        for name in ("brake_request", "brake_level", "state", "reason", "flags", "reserved"):
            _check_u8(name, getattr(self, name))
        _check_counter_value(self.counter)
        check_status_fields(self.state, self.reason, self.flags)
        if self.reserved != 0:
            raise ContentError(f"byte 5 is {self.reserved:#04x}, must be 0")
        if self.brake_request not in BRAKE_REQUEST_NAMES:
            raise ContentError(f"brake_request {self.brake_request} (must be 0, 1 or 2)")
        want_request = _STATE_REQUEST[self.state]
        if self.brake_request != want_request:
            raise ContentError(f"brake_request {self.brake_request} while "
                               f"{state_name(self.state)}")
        if want_request == BrakeRequest.CONTROLLED:
            if not SLOW_LEVEL_MIN <= self.brake_level <= SLOW_LEVEL_MAX:
                raise ContentError(f"brake_level {self.brake_level} while SLOWING (must be "
                                   f"{SLOW_LEVEL_MIN}..{SLOW_LEVEL_MAX})")
            return
        want_level = BRAKE_LEVEL_STOPPED if self.state == State.STOPPED else BRAKE_LEVEL_ARMED
        if self.brake_level != want_level:
            raise ContentError(f"brake_level {self.brake_level} while "
                               f"{state_name(self.state)} (must be {want_level})")

    def payload(self) -> bytes:
        """Bytes 0..6 (before the CRC)."""
        return bytes((self.brake_request, self.brake_level, self.state, self.reason,
                      self.flags, self.reserved, self.counter))

    def encode(self, *, validate: bool = True) -> bytes:
        """The 8 data bytes with the CRC in byte 7. ``validate=False`` encodes any bytes as is
        (the CRC is still right), so tests can build contradictory frames."""
        if validate:
            self.validate()
        else:
            for name in ("brake_request", "brake_level", "state", "reason", "flags",
                         "reserved", "counter"):
                _check_u8(name, getattr(self, name))
        return _seal(self.payload(), BRAKE_DATA_ID)

    @classmethod
    def parse(cls, data: bytes | bytearray | memoryview) -> BrakeFrame:
        """Read the fields of an 8-byte frame without checking anything but the length."""
        raw = bytes(data)
        if len(raw) != DLC:
            raise LengthError(f"DLC {len(raw)}, must be {DLC}")
        return cls(raw[0], raw[1], raw[2], raw[3], raw[4], raw[6] & 0x0F, raw[5])

    @classmethod
    def check(cls, data: bytes | bytearray | memoryview) -> list[FrameError]:
        """Every problem with ``data`` as an ESTOP_BRAKE frame (empty list: good frame)."""
        raw = bytes(data)
        found = _problems(raw, BRAKE_DATA_ID)
        if len(raw) == DLC and not found:
            try:
                cls.parse(raw).validate()
            except FrameError as exc:
                found.append(exc)
        return found

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> BrakeFrame:
        """Decode a frame a brake controller may accept; raise the first :class:`FrameError`."""
        found = cls.check(data)
        if found:
            raise found[0]
        return cls.parse(data)


@dataclass(frozen=True, slots=True)
class StatusFrame:
    """ESTOP_STATUS (0x051), layout in docs/DESIGN.md. Every count is per window (since the
    previous ESTOP_STATUS frame); bytes 0-2 saturate at 255, the two nibbles of byte 3 (stops,
    slow-downs) at 15."""

    valid_packets: int
    invalid_packets: int
    auth_failures: int
    stops: int  # transitions into STOPPED (boot not counted), byte 3 bits 0-3
    link_age_ms: int  # 0xFFFF (LINK_AGE_NONE): no valid packet younger than the timeout
    counter: int
    slowdowns: int = 0  # transitions into SLOWING, byte 3 bits 4-7

    DATA_ID = STATUS_DATA_ID
    CAN_ID = STATUS_ID

    @property
    def link_age(self) -> int | None:
        """Link age in ms, or None when there is no live packet (0xFFFF on the wire)."""
        return None if self.link_age_ms == LINK_AGE_NONE else self.link_age_ms

    def validate(self) -> None:
        for name in ("valid_packets", "invalid_packets", "auth_failures"):
            _check_u8(name, getattr(self, name))
        for name in ("stops", "slowdowns"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 0 <= value <= NIBBLE_MAX:
                raise ContentError(f"{name} must be 0..{NIBBLE_MAX}, got {value!r}")
        if not isinstance(self.link_age_ms, int) or not 0 <= self.link_age_ms <= 0xFFFF:
            raise ContentError(f"link_age_ms must be 0..65535, got {self.link_age_ms!r}")
        _check_counter_value(self.counter)

    def payload(self) -> bytes:
        return struct.pack("<BBBBHB", self.valid_packets, self.invalid_packets,
                           self.auth_failures, self.stops | self.slowdowns << 4,
                           self.link_age_ms, self.counter)

    def encode(self, *, validate: bool = True) -> bytes:
        if validate:
            self.validate()
        return _seal(self.payload(), STATUS_DATA_ID)

    @classmethod
    def parse(cls, data: bytes | bytearray | memoryview) -> StatusFrame:
        raw = bytes(data)
        if len(raw) != DLC:
            raise LengthError(f"DLC {len(raw)}, must be {DLC}")
        valid, invalid, auth_failures, counts, age, ctr = struct.unpack("<BBBBHB", raw[:7])
        return cls(valid, invalid, auth_failures, counts & NIBBLE_MAX, age, ctr & 0x0F,
                   counts >> 4)

    @classmethod
    def check(cls, data: bytes | bytearray | memoryview) -> list[FrameError]:
        return _problems(bytes(data), STATUS_DATA_ID)

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> StatusFrame:
        found = cls.check(data)
        if found:
            raise found[0]
        return cls.parse(data)


class CounterResult(Enum):
    FIRST = "first"  # no previous counter to compare with
    OK = "ok"  # previous + 1 (mod 15)
    REPEAT = "repeat"  # same as previous: not a new frame
    JUMP = "jump"  # frames were lost in between (``lost`` says how many, mod 15)
    INVALID = "invalid"  # not 0..14; the checker's state is left unchanged


@dataclass(frozen=True, slots=True)
class CounterStatus:
    result: CounterResult
    counter: int
    expected: int | None = None
    lost: int = 0

    @property
    def ok(self) -> bool:
        return self.result in (CounterResult.FIRST, CounterResult.OK)


class CounterChecker:
    """Follow one alive counter (0..14, wrapping to 0) and classify each new value."""

    def __init__(self, modulo: int = COUNTER_MODULO) -> None:
        self._modulo = modulo
        self._last: int | None = None

    @property
    def last(self) -> int | None:
        return self._last

    @property
    def expected(self) -> int | None:
        return None if self._last is None else (self._last + 1) % self._modulo

    def reset(self) -> None:
        self._last = None

    def check(self, counter: int) -> CounterStatus:
        if not 0 <= counter < self._modulo:
            return CounterStatus(CounterResult.INVALID, counter, self.expected)
        expected = self.expected
        self._last = counter
        if expected is None:
            return CounterStatus(CounterResult.FIRST, counter)
        if counter == expected:
            return CounterStatus(CounterResult.OK, counter, expected)
        delta = (counter - expected + 1) % self._modulo
        if delta == 0:
            return CounterStatus(CounterResult.REPEAT, counter, expected)
        return CounterStatus(CounterResult.JUMP, counter, expected, lost=delta - 1)
