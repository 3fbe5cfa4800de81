"""The report of ``estop link``: per candidate timeout, the gaps the recording holds and the
fitted model's rate (:mod:`estop.linkfit`), with Poisson bounds, and the recommendation."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from estop.linkfit import Fit, fit, lost_in_row
from estop.linkgaps import Gaps

__all__ = ["ENOUGH", "TIMEOUTS_MS", "Report", "Row", "poisson_lower95", "poisson_upper95",
           "report"]

TIMEOUTS_MS: tuple[int, ...] = (*range(50, 201, 10), 250, 300, 350, 400, 450, 500, 600, 700,
                                800, 900, 1000, 1200, 1500, 2000)
ENOUGH = 10  # gaps at least this many before the recording "can say" a rate (Poisson +-30 %)


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
class Report:
    gaps: Gaps
    fit: Fit
    rows: tuple[Row, ...]
    target: float
    recommended_ms: int | None
    recommended_conservative_ms: int | None


def _poisson_cdf(k: int, mu: float) -> float:
    """P(X <= k) for X ~ Poisson(mu)."""
    if k < 0:
        return 0.0
    term = math.exp(-mu)
    total = term
    for i in range(1, k + 1):
        term *= mu / i
        total += term
    return min(total, 1.0)


def _solve_mu(f: Any, a: float, b: float) -> float:
    """Bisection for the mu between a and b where the monotonic f(mu) crosses 0.05
    (f(a) > 0.05 >= f(b))."""
    for _ in range(100):
        mid = (a + b) / 2.0
        if f(mid) > 0.05:
            a = mid
        else:
            b = mid
    return (a + b) / 2.0


Z95_ONE_SIDED = 1.6448536269514722


def poisson_upper95(k: int) -> float:
    """One-sided 95 % upper limit of a Poisson mean after seeing k events (exact up to 100
    events, then the Wilson-Hilferty approximation, good to a fraction of a percent)."""
    if k > 100:
        m = k + 1
        return m * (1.0 - 1.0 / (9.0 * m) + Z95_ONE_SIDED / (3.0 * math.sqrt(m))) ** 3
    return _solve_mu(lambda mu: _poisson_cdf(k, mu), float(k),
                     float(k) + 10.0 * math.sqrt(k) + 10.0)


def poisson_lower95(k: int) -> float:
    """One-sided 95 % lower limit of a Poisson mean after seeing k events (exact; 0 for 0)."""
    if k == 0:
        return 0.0
    if k > 100:
        return k * (1.0 - 1.0 / (9.0 * k) - Z95_ONE_SIDED / (3.0 * math.sqrt(k))) ** 3
    # P(X >= k) grows with mu: above 0.05 at mu = k, below it at mu = 0
    return _solve_mu(lambda mu: 1.0 - _poisson_cdf(k - 1, mu), float(k), 0.0)


def report(gaps: Gaps, rate_hz: float, target: float = 0.01,
           timeouts_ms: Iterable[int] = TIMEOUTS_MS, tail_from: int | None = None) -> Report:
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
    return Report(gaps, f, tuple(rows), target, rec, cons)


