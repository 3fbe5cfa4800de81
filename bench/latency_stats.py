"""Statistics of the stop-latency bench (pure; exercised on synthetic data by
tests/harness/test_bench_smoke.py): percentiles, summaries, histogram edges, number formats."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) of already sorted values, linear between closest ranks
    (numpy's default method). NaN for no values."""
    if not sorted_values:
        return math.nan
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile must be 0..100, got {q}")
    pos = (len(sorted_values) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    frac = pos - lo
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * frac


def summarize(values: Sequence[float]) -> dict[str, float]:
    """n, min, p50, p99, p99.9, max and mean of values (in their own unit)."""
    s = sorted(values)
    if not s:
        nan = math.nan
        return {"n": 0, "min": nan, "p50": nan, "p99": nan, "p99.9": nan, "max": nan,
                "mean": nan}
    return {"n": len(s), "min": s[0], "p50": percentile(s, 50.0), "p99": percentile(s, 99.0),
            "p99.9": percentile(s, 99.9), "max": s[-1], "mean": math.fsum(s) / len(s)}


def log_bins(values: Sequence[float], floor: float, n_bins: int = 60) -> list[float]:
    """Log-spaced histogram edges from ``floor`` to just above the largest value."""
    if floor <= 0:
        raise ValueError("floor must be > 0")
    top = max([floor * 10.0, *values]) * 1.05
    lo, hi = math.log10(floor), math.log10(top)
    return [10 ** (lo + (hi - lo) * i / n_bins) for i in range(n_bins + 1)]


def say(text: str = "") -> None:
    """Output for the person running the bench."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def fmt_ms(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.3f}"
