"""UDP control packets, remote -> unit (spec section 1).

Layout (little-endian): float32 gas_brake, float32 steering, int32 gear, int32 turn_signal,
int32 horn. 20 bytes, or 16 bytes in the older form without horn (horn = 0).

A packet is valid only when its length is 16 or 20 and every field holds a valid value:
finite floats in -1.0..1.0 (as float32), gear in {1, 2, 4, 8}, turn_signal in 0..3, horn 0/1.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

__all__ = [
    "DEFAULT_PORT",
    "LEGACY_SIZE",
    "PACKET_SIZE",
    "ControlPacket",
    "Gear",
    "InvalidPacket",
    "TurnSignal",
    "decode",
    "encode",
    "is_valid",
]

DEFAULT_PORT = 5700
PACKET_SIZE = 20
LEGACY_SIZE = 16

_FULL = struct.Struct("<ffiii")
_LEGACY = struct.Struct("<ffii")
_F32 = struct.Struct("<f")


class Gear(IntEnum):
    PARK = 1
    REVERSE = 2
    NEUTRAL = 4
    DRIVE = 8


class TurnSignal(IntEnum):
    OFF = 0
    LEFT = 1
    RIGHT = 2
    BOTH = 3


_GEARS = frozenset(int(g) for g in Gear)
_TURNS = frozenset(int(t) for t in TurnSignal)


class InvalidPacket(ValueError):
    """A control packet the unit must count as invalid. ``str()`` is a one-line reason."""


def _check_axis(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise InvalidPacket(f"{name} is not finite ({value!r})")
    if not -1.0 <= value <= 1.0:
        raise InvalidPacket(f"{name} {value!r} out of range -1.0..1.0")


def _to_f32(name: str, value: float) -> float:
    """Round a float to float32 like the wire does (overflow becomes inf, NaN stays NaN)."""
    try:
        return float(_F32.unpack(_F32.pack(value))[0])
    except OverflowError:
        return math.copysign(math.inf, value)
    except (struct.error, TypeError) as exc:
        raise InvalidPacket(f"{name} is not a number ({value!r})") from exc


@dataclass(frozen=True, slots=True)
class ControlPacket:
    """One control packet. Floats are as given; they are rounded to float32 when encoded."""

    gas_brake: float = 0.0
    steering: float = 0.0
    gear: int = Gear.NEUTRAL
    turn_signal: int = TurnSignal.OFF
    horn: int = 0

    def validate(self) -> None:
        """Raise :class:`InvalidPacket` unless every field is valid once sent as float32."""
        _check_axis("gas_brake", _to_f32("gas_brake", self.gas_brake))
        _check_axis("steering", _to_f32("steering", self.steering))
        if self.gear not in _GEARS:
            raise InvalidPacket(f"gear {self.gear!r} unknown (valid: 1 park, 2 reverse, "
                                f"4 neutral, 8 drive)")
        if self.turn_signal not in _TURNS:
            raise InvalidPacket(f"turn_signal {self.turn_signal!r} unknown (valid: 0..3)")
        if self.horn not in (0, 1):
            raise InvalidPacket(f"horn {self.horn!r} invalid (valid: 0 off, 1 on)")

    @property
    def is_neutral(self) -> bool:
        """True when the unit would accept a RELEASE after this packet (gas_brake <= 0)."""
        return self.gas_brake <= 0.0

    def encode(self, *, legacy: bool = False, validate: bool = True) -> bytes:
        """Encode to 20 bytes (or the 16-byte older form with ``legacy=True``, horn must be 0).

        With ``validate=False`` any value that fits the wire types is encoded as is, so tests
        can build invalid packets (NaN, out of range, unknown codes).
        """
        if validate:
            self.validate()
        if legacy and self.horn != 0:
            raise InvalidPacket("the 16-byte form has no horn field; horn must be 0")
        try:
            if legacy:
                return _LEGACY.pack(self.gas_brake, self.steering, self.gear, self.turn_signal)
            return _FULL.pack(self.gas_brake, self.steering, self.gear, self.turn_signal,
                              self.horn)
        except (struct.error, OverflowError) as exc:
            raise InvalidPacket(f"cannot encode packet: {exc}") from exc

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> ControlPacket:
        """Decode and validate one datagram; raise :class:`InvalidPacket` if invalid."""
        raw = bytes(data)
        if len(raw) == PACKET_SIZE:
            gas, steer, gear, turn, horn = _FULL.unpack(raw)
        elif len(raw) == LEGACY_SIZE:
            gas, steer, gear, turn = _LEGACY.unpack(raw)
            horn = 0
        else:
            raise InvalidPacket(f"length {len(raw)} invalid (must be 20, or 16 without horn)")
        pkt = cls(float(gas), float(steer), gear, turn, horn)
        pkt.validate()
        return pkt


def encode(packet: ControlPacket, *, legacy: bool = False, validate: bool = True) -> bytes:
    """Encode ``packet``; see :meth:`ControlPacket.encode`."""
    return packet.encode(legacy=legacy, validate=validate)


def decode(data: bytes | bytearray | memoryview) -> ControlPacket:
    """Decode and validate one datagram; raise :class:`InvalidPacket` if invalid."""
    return ControlPacket.decode(data)


def is_valid(data: bytes | bytearray | memoryview) -> bool:
    """True exactly when the unit must accept ``data`` as a valid control packet."""
    try:
        ControlPacket.decode(data)
    except InvalidPacket:
        return False
    return True
