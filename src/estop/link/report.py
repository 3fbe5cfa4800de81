"""The report of ``estop link``: per candidate time, the gaps the recording holds and the
fitted model's rate (:mod:`estop.link.fit`) of silences reaching it, with Poisson bounds, and
the recommended pair of times (PROTOCOL.md 3, version 3).

The same rate reads two ways. As the timeout T it counts latched emergency stops for nothing
(false stops); as the slow time S it counts brief slow-downs, each ended by the link's return.
So T is the shortest time whose rate is below ``target`` (false stops per hour), and S the
shortest one, longer than a send period and not above T nor ``react_ms`` (the longest the car
may roll on a lost link before it brakes), whose rate is below ``slow_target`` (slow-downs per
hour). When none meets ``slow_target``: S = T where T is within ``react_ms`` (one stage),
else the longest time within ``react_ms`` (the fewest slow-downs the reaction allows)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from estop.link.fit import Fit, fit, lost_in_row
from estop.link.gaps import Gaps
from estop.link.poisson import poisson_lower95, poisson_upper95
from estop.link.unitcheck import UnitCheck, check_unit

__all__ = ["DEFAULT_REACT_MS", "DEFAULT_SLOW_TARGET", "DEFAULT_TARGET", "ENOUGH", "TIMEOUTS_MS",
           "Pair", "Report", "Row", "recommend_slow", "report"]

TIMEOUTS_MS: tuple[int, ...] = (*range(50, 201, 10), 250, 300, 350, 400, 450, 500, 600, 700,
                                800, 900, 1000, 1200, 1500, 2000)
ENOUGH = 10  # gaps at least this many before the recording "can say" a rate (Poisson +-30 %)
DEFAULT_TARGET = 0.01  # false emergency stops per hour
# brief slow-downs per hour: one every 3.6 s on average (docs/LINK.md says why)
DEFAULT_SLOW_TARGET = 1000.0
# the longest slow time S: braking begins at most this long after the last packet (200 ms is
# the version 2 unit's single-stage timeout, which version 3 must not make the car roll longer)
DEFAULT_REACT_MS = 200.0


@dataclass(frozen=True)
class Row:
    timeout_ms: int
    lost_in_row: int
    model: float
    model_low: float
    model_high: float
    gaps_sure: int
    gaps_possible: int
    hours: float

    @property
    def enough(self) -> bool:
        return self.gaps_sure >= ENOUGH

    @property
    def empirical(self) -> float | None:
        """Gaps per hour that long, when the recording has enough of them and says exactly."""
        if self.hours <= 0 or not self.enough or self.gaps_sure != self.gaps_possible:
            return None
        return self.gaps_sure / self.hours

    @property
    def empirical_upper95(self) -> float:
        return poisson_upper95(self.gaps_possible) / self.hours if self.hours > 0 else math.inf

    @property
    def empirical_lower95(self) -> float:
        return poisson_lower95(self.gaps_sure) / self.hours if self.hours > 0 else 0.0

    @property
    def contradicted(self) -> bool:
        """The recording holds clearly more such gaps than the model's 95 % range allows."""
        return self.empirical_lower95 > self.model_high

    def meets(self, target: float) -> bool:
        """Model below target, and the recording does not say the rate is above it."""
        return self.model < target and self.empirical_lower95 <= target


@dataclass(frozen=True)
class Pair:
    """One choice of the two stages: the slow time S and the timeout T (S <= T), with the
    model's rates: slow-downs per hour at S (none when S = T: one stage) and emergency stops
    per hour at T."""

    slow_ms: int
    timeout_ms: int
    slowdowns_per_hour: float
    emergency_stops_per_hour: float


@dataclass(frozen=True)
class Report:
    gaps: Gaps
    fit: Fit
    rows: tuple[Row, ...]
    target: float
    recommended_ms: int | None  # T
    recommended_conservative_ms: int | None  # T by the model's 95 % upper bound
    slow_target: float = DEFAULT_SLOW_TARGET
    recommended_slow_ms: int | None = None  # S
    unit: UnitCheck | None = None  # the unit's own counts against the model
    react_ms: float = DEFAULT_REACT_MS  # S is never above it

    def row(self, time_ms: int) -> Row:
        return next(r for r in self.rows if r.timeout_ms == time_ms)

    @property
    def pairs(self) -> tuple[Pair, ...]:
        """Every pair S <= T of the grid (S longer than one send period)."""
        return tuple(Pair(s.timeout_ms, t.timeout_ms, s.model if s is not t else 0.0, t.model)
                     for s in self.rows if s.lost_in_row >= 1
                     for t in self.rows if t.timeout_ms >= s.timeout_ms)

    @property
    def recommendation(self) -> tuple[int, int] | None:
        """The recommended pair (S, T), or None when there is no T or no S within
        ``react_ms``."""
        s, t = self.recommended_slow_ms, self.recommended_ms
        return None if s is None or t is None else (s, t)

    @property
    def slow_target_met(self) -> bool:
        """The recommended S meets the slow target (or S = T: no slow-downs at all)."""
        s = self.recommended_slow_ms
        return s is not None and (s == self.recommended_ms or self.row(s).meets(
            self.slow_target))

    @property
    def two_stage(self) -> bool:
        """S < T recommended: the link gains from a controlled stop before the emergency one."""
        return (self.recommended_slow_ms is not None and self.recommended_ms is not None
                and self.recommended_slow_ms < self.recommended_ms)


def recommend_slow(rows: Iterable[Row], slow_target: float, timeout_ms: int | None,
                   react_ms: float = DEFAULT_REACT_MS) -> int | None:
    """S: the shortest time longer than one send period (at one period every packet would be
    due at the deadline), not above T nor ``react_ms``, whose slow-downs meet
    ``slow_target``. When none does: S = T if T is within ``react_ms`` (one stage), else the
    longest time within it (the fewest slow-downs the reaction allows); None when no time of
    the grid is within it. Without T, the same over the whole grid."""
    cands = [r for r in rows if r.lost_in_row >= 1 and r.timeout_ms <= react_ms
             and (timeout_ms is None or r.timeout_ms <= timeout_ms)]
    slow = next((r.timeout_ms for r in cands if r.meets(slow_target)), None)
    if slow is not None:
        return slow
    if timeout_ms is not None and timeout_ms <= react_ms:
        return timeout_ms
    return cands[-1].timeout_ms if cands else None


def report(gaps: Gaps, rate_hz: float, target: float = DEFAULT_TARGET,
           timeouts_ms: Iterable[int] = TIMEOUTS_MS, tail_from: int | None = None,
           slow_target: float = DEFAULT_SLOW_TARGET,
           react_ms: float = DEFAULT_REACT_MS) -> Report:
    f = fit(gaps, rate_hz, tail_from)
    rows = []
    for d in timeouts_ms:
        n = lost_in_row(d, rate_hz)
        lo, hi = f.interval95(n)
        sure, possible = gaps.at_least(n) if n > 0 else (f.gaps, f.gaps)
        rows.append(Row(d, n, f.false_stops(n), lo, hi, sure, possible, f.hours))
    rec = next((r.timeout_ms for r in rows if r.meets(target)), None) if f.bursts else None
    cons = next((r.timeout_ms for r in rows if r.meets(target) and r.model_high < target),
                None) if f.bursts else None
    slow = recommend_slow(rows, slow_target, rec, react_ms) if f.bursts else None
    return Report(gaps, f, tuple(rows), target, rec, cons, slow_target, slow,
                  check_unit(gaps, f), react_ms)


