"""Frames for the tests of the HIL harness: the spec's examples and ESTOP_BRAKE frames by state
(hil/ is on the import path: tests/harness/conftest.py)."""

from __future__ import annotations

from estop.protocol.can import BrakeFrame
from hilcheck import Frame
from vectors import BRAKE_ARMED_7, BRAKE_BOOT_0, BRAKE_SLOWING_5, BRAKE_TIMEOUT_14

BOOT, ARMED7, TIMEOUT14 = BRAKE_BOOT_0, BRAKE_ARMED_7, BRAKE_TIMEOUT_14  # spec section 4


def armed(counter: int) -> bytes:
    return BrakeFrame.for_state(1, 0, 0, counter).encode()


def stopped(counter: int, reason: int = 2) -> bytes:
    return BrakeFrame.for_state(0, reason, 0, counter).encode()


SLOWING5 = BRAKE_SLOWING_5  # spec section 4 example


def slowing(counter: int, level: int = 30, flags: int = 1) -> bytes:
    return BrakeFrame.for_state(2, 0, flags, counter, slow_level=level).encode()


def bus_frames(segments: list[tuple[float, float, str, int]], t0: float = 1000.0) -> list[Frame]:
    """ESTOP_BRAKE every 10 ms: (start, end, state name, reason) relative to ``t0``; a change
    of state sends at once (the period starts over), as the unit does."""
    make = {"ARMED": lambda c, r: armed(c), "SLOWING": lambda c, r: slowing(c),
            "STOPPED": lambda c, r: stopped(c, r)}
    out: list[Frame] = []
    ctr = 0
    for start, end, state, reason in segments:
        t = start
        while t < end - 1e-9:
            out.append(Frame(t0 + t, 0x050, make[state](ctr, reason)))
            ctr = (ctr + 1) % 15
            t += 0.010
    return out
