"""The fitted model against what a version 3 unit counted itself: its slow-downs (silences
that reached its slow time S) and its stops by UDP timeout (silences that reached its timeout
T), from the ``link_histogram`` keys ``slowdowns``, ``timeouts``, ``slow_us``, ``timeout_us``.

The unit counts only while it moves (ARMED or SLOWING): a silence while it is STOPPED is
neither. So the rates are per hour moving, taken from the log's ``state`` events; a log without
them in full (a log that does not show every run from its ``start`` event) falls back to the
recording's length, and then a unit that stood STOPPED part of the time counts fewer than the
model says, which is no contradiction.

The model's rate at S counts every silence reaching S; the unit counts a slow-down only when a
silence begins while it is ARMED, so a silence that begins before 3 packets have arrived
since the last slow-down merges into it. At 50 Hz and bursts of 3 that makes the unit's
count 0.1-0.3 % (S = 200 ms) to about 2 % (S = 100 ms) lower than the model's (measured on
10-hour traces): within its range, and on the cautious side."""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

from estop.link.fit import Fit, lost_in_row
from estop.link.gaps import Gaps, UnitRecord
from estop.link.poisson import poisson_lower95, poisson_upper95

__all__ = ["AGREES", "FEWER", "MORE", "NOT_MOVING", "Check", "UnitCheck", "check_unit"]

AGREES = "agrees"
MORE = "more_than_model"  # the model is optimistic there: trust the unit's count
FEWER = "fewer_than_model"
NOT_MOVING = "never_moving"  # the unit never left STOPPED: it counted nothing


@dataclass(frozen=True)
class Check:
    """One of the unit's counts against the model at the unit's own time."""

    time_ms: float  # S or T
    lost_in_row: int
    recorded: int
    hours: float  # the unit's exposure: hours moving (or recorded, see UnitCheck.hours_from)
    model: float  # the model's rate per hour at this time, and its 95 % range
    model_low: float
    model_high: float
    pauses: int  # gaps the fit left out as sender pauses: each may be one of the recorded

    @property
    def per_hour(self) -> float | None:
        return self.recorded / self.hours if self.hours > 0 else None

    @property
    def upper95(self) -> float | None:
        return poisson_upper95(self.recorded) / self.hours if self.hours > 0 else None

    @property
    def lower95(self) -> float | None:
        return poisson_lower95(self.recorded) / self.hours if self.hours > 0 else None

    @property
    def verdict(self) -> str:
        if self.hours <= 0:
            return NOT_MOVING
        # the pauses the model leaves out may be among the recorded: taken off before the
        # count can say the model is optimistic
        lo = poisson_lower95(max(0, self.recorded - self.pauses)) / self.hours
        hi = poisson_upper95(self.recorded) / self.hours
        if lo > self.model_high:
            return MORE
        if hi < self.model_low:
            return FEWER
        return AGREES


@dataclass(frozen=True)
class UnitCheck:
    record: UnitRecord
    hours: float
    hours_from: str  # "state events" (time ARMED or SLOWING) or "recording" (its length)
    slowdowns: Check | None  # None when the unit ran with S = T: it never slows
    timeouts: Check


def _check(f: Fit, time_us: int, recorded: int, hours: float, pauses: int) -> Check:
    n = lost_in_row(Fraction(time_us, 1000), f.rate_hz)
    lo, hi = f.interval95(n)
    return Check(time_us / 1000, n, recorded, hours, f.false_stops(n), lo, hi, pauses)


def check_unit(gaps: Gaps, f: Fit) -> UnitCheck | None:
    """The unit's counts against the model at its S and T; None without a unit record."""
    u = gaps.unit
    if u is None:
        return None
    if u.moving_s is not None:
        hours, source = u.moving_s / 3600.0, "state events"
    else:
        hours, source = f.hours, "recording"
    slow = (_check(f, u.slow_us, u.slowdowns, hours, gaps.pauses)
            if u.slow_us < u.timeout_us else None)
    return UnitCheck(u, hours, source, slow,
                     _check(f, u.timeout_us, u.timeouts, hours, gaps.pauses))
