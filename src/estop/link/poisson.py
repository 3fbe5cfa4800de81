"""One-sided 95 % limits of a Poisson mean after seeing k events: how much a count of rare
events (gaps, slow-downs, stops) in a recording of finite length can say about their rate."""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["poisson_lower95", "poisson_upper95"]


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


def _solve_mu(f: Callable[[float], float], a: float, b: float) -> float:
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
