"""Figures of the HIL harness's test protocol (pure logic): summaries of samples, frame gaps,
and the counts of the UDP flood rows (the daemon's socket in /proc/net/udp, ESTOP_STATUS
counting windows, how many packets a sender put out in an interval).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from estop.protocol.can import (
    BRAKE_ID,
    STATUS_ID,
    StatusFrame,
)
from hilemu import Frame

# --------------------------------------------------------------------------- statistics

def percentile(values: Sequence[float], q: float) -> float:
    """Nearest-rank-with-interpolation percentile (q in 0..100) of a non-empty sequence."""
    if not values:
        raise ValueError("percentile of no values")
    xs = sorted(values)
    if len(xs) == 1:
        return xs[0]
    pos = (len(xs) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def summary(values: Sequence[float], digits: int = 3) -> dict[str, float | int]:
    """n, min, p50, p90, max, mean of ``values`` (empty: n 0 only)."""
    if not values:
        return {"n": 0}
    return {
        "n": len(values),
        "min": round(min(values), digits),
        "p50": round(percentile(values, 50), digits),
        "p90": round(percentile(values, 90), digits),
        "max": round(max(values), digits),
        "mean": round(sum(values) / len(values), digits),
    }


def frame_gaps(frames: Sequence[Frame], can_id: int = BRAKE_ID) -> list[float]:
    """Gaps in seconds between consecutive frames with ``can_id``."""
    ts = [f.ts for f in frames if f.can_id == can_id]
    return [b - a for a, b in zip(ts, ts[1:], strict=False)]


def in_windows(t: float, windows: Iterable[tuple[float, float]]) -> bool:
    return any(a <= t <= b for a, b in windows)


# --------------------------------------------------------------------------- UDP flood figures

@dataclass(frozen=True, slots=True)
class StatusWindow:
    """What one ESTOP_STATUS frame counted: the packets of ``(start, end]``, where ``start``
    is the previous ESTOP_STATUS frame's time and ``end`` its own."""

    start: float
    end: float
    valid: int
    invalid: int
    auth_failures: int


def status_windows(frames: Sequence[Frame]) -> list[StatusWindow]:
    """The counting windows of consecutive good ESTOP_STATUS frames (time order); a frame that
    fails its checks ends no window (its counts are lost, and so is the window before it)."""
    out: list[StatusWindow] = []
    prev: float | None = None
    for f in frames:
        if f.can_id != STATUS_ID:
            continue
        if StatusFrame.check(f.data):
            prev = None
            continue
        s = StatusFrame.parse(f.data)
        if prev is not None:
            out.append(StatusWindow(prev, f.ts, s.valid_packets, s.invalid_packets,
                                    s.auth_failures))
        prev = f.ts
    return out


def sent_between(series: Sequence[Sequence[float]], t0: float, t1: float) -> tuple[int, int]:
    """Bounds on how many packets a sender's cumulative ``series`` (``[time, sent so far]``,
    time order) put out in ``[t0, t1]``: (at least, at most)."""
    def before(t: float) -> tuple[int, int]:  # sent by time t: (at least, at most)
        lo, hi = 0, None
        for ts, n in series:
            if ts <= t:
                lo = int(n)
            if ts >= t:
                hi = int(n)
                break
        if hi is None:  # after the last entry: the sender had stopped
            hi = int(series[-1][1]) if series else 0
        return lo, max(lo, hi)

    a_lo, a_hi = before(t0)
    b_lo, b_hi = before(t1)
    return max(0, b_lo - a_hi), max(0, b_hi - a_lo)
