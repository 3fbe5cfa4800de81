"""Gap cells for ``estop link``: the gaps between consecutive received control packets, as
counts over cells of k (packets lost in the gap), from arrival times or from estopd's binned
histogram. Everything downstream (:mod:`estop.link.fit`, :mod:`estop.link.report`) works on
these cells; the file readers live in :mod:`estop.link.read`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np
import numpy.typing as npt

from estop.errors import FileFailure, UsageError

__all__ = ["DAEMON_EDGES_US", "F64", "I64", "U32_MAX", "Gaps", "Histogram", "LinkInputError",
           "UnitRecord", "check_rate", "daemon_bins", "gaps_from_histogram", "gaps_from_times"]

U32_MAX = 0xFFFFFFFF
I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]


# estopd's link_histogram bins (docs/DESIGN.md, the core's estop_gap_bin): bin 0 below
# 1024 us, then two bins an octave (at 2^e and 1.5 * 2^e), bin 31 from 2^25 us on
DAEMON_EDGES_US: tuple[int, ...] = (0, *((1 << (10 + (b - 1) // 2))
                                         + ((b - 1) % 2) * (1 << (9 + (b - 1) // 2))
                                         for b in range(1, 32)))


def daemon_bins(gaps_us: npt.ArrayLike) -> I64:
    """The bin estopd files each gap (integer us) in, as the core's estop_gap_bin does: 0
    below 1024 us; else e = floor(log2 g), h = bit e-1 of g, bin 1 + 2 (e - 10) + h, at most
    31 (for simulations of the daemon's log and the bench)."""
    g = np.asarray(gaps_us, dtype=np.int64)
    e = np.frexp(g.astype(np.float64))[1].astype(np.int64) - 1  # floor(log2 g), exact < 2^53
    h = (g >> np.maximum(e - 1, 0)) & 1
    return np.where(g < 1024, 0, np.minimum(1 + 2 * (e - 10) + h, 31)).astype(np.int64)


class LinkInputError(FileFailure):
    """An input file that cannot be read or understood: one line, exit 4."""


@dataclass(frozen=True)
class UnitRecord:
    """What a version 3 unit counted itself (the ``link_histogram`` keys ``slowdowns``,
    ``timeouts``, ``slow_us``, ``timeout_us``), summed over runs that all ran with the same S
    and T. The unit counts only while it moves (ARMED or SLOWING): ``moving_s`` is that time,
    from the log's ``state`` events, or None when the log does not show every run from its
    ``start`` event (then the unit may have moved before the first line)."""

    slowdowns: int  # transitions ARMED -> SLOWING
    timeouts: int  # stops by UDP timeout
    slow_us: int  # S
    timeout_us: int  # T
    moving_s: float | None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Gaps:
    """Gaps between consecutive received packets, as counts over cells of k (packets lost in
    the gap): a cell holds every gap with ``k_lo <= k <= k_hi`` (``k_hi`` -1: no upper end).
    Arrival times give one exact cell per k; the daemon's histogram gives one cell per bin."""

    k_lo: I64
    k_hi: I64
    counts: I64
    pauses: int  # gaps of --max-gap or longer, taken as the sender pausing (finger lifted)
    source: str
    hours_measured: float | None = None  # time covered by the gaps, when measured (not binned)
    notes: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    unit: UnitRecord | None = None  # a version 3 daemon's own counts, when its log has them

    @property
    def exact(self) -> bool:
        return bool(np.all(self.k_lo == self.k_hi))

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def at_least(self, n: int) -> tuple[int, int]:
        """Gaps with at least n lost: (surely, possibly), different only for coarse cells."""
        hi_open = (self.k_hi < 0) | (self.k_hi >= n)
        sure = int(self.counts[self.k_lo >= n].sum())
        return sure, int(self.counts[hi_open].sum())


def check_rate(rate_hz: float) -> None:
    if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 100_000.0):
        raise UsageError(f"--rate-hz must be a send rate in Hz (0 .. 100000], got {rate_hz}")


def gaps_from_times(times: Sequence[float] | F64, rate_hz: float, max_gap: float = 5.0,
                    source: str = "arrival times") -> Gaps:
    """Cells from arrival times (seconds, not decreasing): a gap g holds k = round(g / P) - 1
    lost packets, P the send period (at least 0: early or bunched arrivals count as none).
    Gaps of ``max_gap`` seconds or more (0: no limit) are sender pauses, left out."""
    check_rate(rate_hz)
    t = np.asarray(times, dtype=np.float64)
    if t.size < 2:
        raise LinkInputError(f"{source}: need at least 2 packets, got {t.size}")
    g = np.diff(t)
    if np.any(g < 0):
        raise LinkInputError(f"{source}: arrival times go backwards")
    pause = g >= max_gap if max_gap > 0 else np.zeros(g.shape, dtype=bool)
    g = g[~pause]
    if g.size == 0:
        raise LinkInputError(f"{source}: every gap is a pause (>= {max_gap:g} s)")
    periods = g * rate_hz
    k = np.maximum(np.rint(periods).astype(np.int64) - 1, 0)
    ks, counts = np.unique(k, return_counts=True)
    # share of gaps more than a quarter period off the send grid: arrival jitter
    off_grid = float(np.mean(np.abs(periods - np.rint(periods)) > 0.25))
    notes: tuple[str, ...] = ()
    if off_grid > 0.05:
        notes = (f"{off_grid * 100:.0f} % of gaps are more than P/4 off the send grid: arrival "
                 "jitter, so short gaps are misread as losses or as none",)
    return Gaps(ks.astype(np.int64), ks.astype(np.int64), counts.astype(np.int64),
                int(pause.sum()), source, hours_measured=float(g.sum()) / 3600.0,
                notes=notes, extra={"packets": int(t.size), "off_grid": off_grid,
                                    "longest_gap_s": float(np.diff(t).max())})


@dataclass(frozen=True)
class Histogram:
    """The sum over runs of the last ``link_histogram`` event of each run."""

    edges_us: tuple[int, ...]
    counts: tuple[int, ...]
    valid: int
    invalid: int
    silences: int
    warn_us: int
    runs: int
    saturated: bool
    unit: UnitRecord | None = None  # the runs' slow-downs and timeouts, when all have them
    unit_note: str = ""  # why there is no unit record although some events have the keys
    skipped_note: str = ""  # lines of the log that held no event: how many, the first


def gaps_from_histogram(h: Histogram, rate_hz: float, max_gap: float = 5.0,
                        source: str = "estopd log") -> Gaps:
    """Cells from the daemon's bins: bin [a, b) holds the k whose nominal gap (k+1) P lies in
    it. A bin that holds no multiple of T (its gaps are jittered ones) is credited to the
    nearest multiple. Bins starting at ``max_gap`` or above are sender pauses."""
    check_rate(rate_hz)
    edges = [Fraction(e) for e in h.edges_us]
    t_us = Fraction(1_000_000) / Fraction(rate_hz)
    if len(edges) > 1 and t_us < edges[1]:
        raise UsageError(f"--rate-hz {rate_hz:g} is too fast for the daemon's histogram "
                             f"(its first bin, below {h.edges_us[1]} us, would hold gaps of "
                             "several send periods)")
    max_us = Fraction(max_gap) * 1_000_000
    lo: list[int] = []
    hi: list[int] = []
    cnt: list[int] = []
    pauses = 0
    orphans: list[tuple[int, int]] = []  # (nearest k, count)
    for j, c in enumerate(h.counts):
        a = edges[j]
        b = edges[j + 1] if j + 1 < len(edges) else None
        if max_gap > 0 and a >= max_us:
            pauses += c
            continue
        k_lo = max(0, math.ceil(a / t_us) - 1)
        if b is None:
            k_hi = -1  # open last bin
        else:
            k_hi = math.ceil(b / t_us) - 2
            if k_hi < k_lo:  # no multiple of T in [a, b)
                if c:
                    orphans.append((max(0, round((a + b) / 2 / t_us) - 1), c))
                continue
        lo.append(k_lo)
        hi.append(k_hi)
        cnt.append(c)
    for k, c in orphans:
        for i in range(len(lo)):
            if lo[i] <= k and (hi[i] == -1 or k <= hi[i]):
                cnt[i] += c
                break
        else:  # nearest multiple beyond the last cell: cannot happen with an open last bin
            lo.append(k)
            hi.append(k)
            cnt.append(c)
    if not cnt or sum(cnt) == 0:
        raise LinkInputError(f"{source}: the histogram holds no gap between packets")
    if lo[0] != 0 or hi[0] != 0:
        raise LinkInputError(f"{source}: the histogram's bins cannot tell a gap of one send "
                             f"period at {rate_hz:g} Hz from longer ones")
    notes: list[str] = []
    if orphans:
        notes.append(f"{sum(c for _, c in orphans)} gaps fell in bins holding no multiple of "
                     "the send period (jitter) and were credited to the nearest multiple")
    if h.saturated:
        notes.append("some histogram counts are saturated (u32): the rates are too low")
    if h.unit_note:
        notes.append(h.unit_note)
    if h.skipped_note:
        notes.append(h.skipped_note)
    extra: dict[str, Any] = {"valid": h.valid, "invalid": h.invalid, "silences": h.silences,
                             "warn_us": h.warn_us, "runs": h.runs}
    if h.unit is not None:
        extra.update(slowdowns=h.unit.slowdowns, timeouts=h.unit.timeouts,
                     slow_us=h.unit.slow_us, timeout_us=h.unit.timeout_us)
    order = np.argsort(np.asarray(lo))
    return Gaps(np.asarray(lo, dtype=np.int64)[order], np.asarray(hi, dtype=np.int64)[order],
                np.asarray(cnt, dtype=np.int64)[order], pauses, source, None, tuple(notes),
                extra=extra, unit=h.unit)


