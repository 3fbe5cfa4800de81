"""The environment's stalls told apart from the daemon's (pure logic; see hil/README.md).

``mon/stallmon.c`` records when a CPU could not run at all; these functions read its intervals
and judge samples with them: a CPU stall can only delay, so what a stall may explain is
inconclusive, never a pass (latency samples, single times, frame counts, gaps in the
periodic frames, kernel drops); a period is that of the grid fitted under the frames.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

# --------------------------------------------------------------------------- environment stalls

def read_stalls(lines: Iterable[str]) -> list[tuple[float, float]]:
    """Intervals of a ``mon/stallmon.c`` file (``start end`` per line, ``#`` comments)."""
    out: list[tuple[float, float]] = []
    for line in lines:
        parts = line.split()
        if len(parts) == 2 and not line.startswith("#"):
            try:
                a, b = float(parts[0]), float(parts[1])
            except ValueError:
                continue
            if b > a:
                out.append((a, b))
    return out


def merge(intervals: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    """Union of intervals, sorted and non-overlapping."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def overlap(intervals: Sequence[tuple[float, float]], t0: float, t1: float) -> float:
    """Seconds of ``intervals`` (merged: sorted and disjoint, as :func:`merge` makes them)
    that fall in ``[t0, t1]``. A binary search finds the first one: a loaded run records tens
    of thousands of stalls, and this is asked for every frame."""
    i = max(0, bisect.bisect_left(intervals, (t0,)) - 1)
    total = 0.0
    while i < len(intervals) and intervals[i][0] < t1:
        a, b = intervals[i]
        total += max(0.0, min(b, t1) - max(a, t0))
        i += 1
    return total


def merge_more(merged: list[tuple[float, float]],
               new: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    """:func:`merge` of ``merged`` (already merged) and ``new``, re-merging only the tail that
    ``new`` can touch."""
    more = sorted(new)
    if not more:
        return merged
    cut = max(0, bisect.bisect_left(merged, (more[0][0],)) - 1)
    return merged[:cut] + merge(merged[cut:] + more)


# A sample (a latency, a frame gap) during which a CPU stood still or the daemon queued this long
# is not judged against a timing limit: the environment, not the daemon, may have made it late.
STALL_EXCUSE_S = 0.002


# A frame sent within this time after a CPU stall may still be late (the daemon catches up on
# its grid with the next frame or two): it does not start or end a judged stretch.
CATCH_UP_S = 0.020


@dataclass(frozen=True, slots=True)
class Periods:
    """Frame periods: the grid's (``grid``, what the boot row judges; see grid_period), and
    the mean gap of stall-free stretches (shown beside it).

    The daemon sends on a fixed grid: a frame made late by a stall is followed by a short gap
    that catches up, so within a stretch the gaps average out, and a stretch's mean period is
    its span over its gap count. A stretch ends at a CPU stall of half a period or more (long
    enough to push a frame past its slot, so the daemon may start its grid over, which would
    stretch the mean), and its first and last frames are ones that no stall of
    ``STALL_EXCUSE_S`` or more may have delayed (none within ``CATCH_UP_S`` before them).
    Every gap outside the judged stretches is left out, and shown as such.
    """

    gaps: list[float]  # all gaps, seconds, in order
    judged: list[float]  # the gaps inside judged stretches
    stretches: int
    splits: int  # gaps that held a stall of half a period or more
    grid: float | None = None  # the grid's period (grid_period), seconds
    grid_gaps: int = 0  # the gaps of the runs it was fitted to

    @property
    def mean_judged(self) -> float | None:
        return sum(self.judged) / len(self.judged) if self.judged else None

    @property
    def mean_all(self) -> float | None:
        return sum(self.gaps) / len(self.gaps) if self.gaps else None

    def left_out_text(self) -> str:
        """One line for the protocol: what was left out and what it would have said."""
        n_out = len(self.gaps) - len(self.judged)
        if not n_out:
            return "none"
        return (f"{n_out} of {len(self.gaps)} gaps ({self.splits} held a CPU stall of half a "
                f"period or more; stretch ends trimmed to frames no stall may have delayed); all: "
                f"mean {round((self.mean_all or 0.0) * 1000, 3)}, max "
                f"{round(max(self.gaps) * 1000, 3)} ms")


def periods(ts: Sequence[float], stalls: Sequence[tuple[float, float]], period_s: float,
            margin_s: float = CATCH_UP_S, excuse_s: float = STALL_EXCUSE_S) -> Periods:
    """The gaps between the frame times ``ts`` (sorted), judged on stall-free stretches."""
    gaps = [b - a for a, b in zip(ts, ts[1:], strict=False)]
    split = [(a, b) for a, b in stalls if b - a >= period_s / 2]
    runs = split_runs(ts, lambda a, b: overlap(split, a, b) > 0)
    judged: list[float] = []
    stretches = 0
    for run in runs:
        clean = [k for k, t in enumerate(run) if overlap(stalls, t - margin_s, t) < excuse_s]
        if len(clean) >= 2:
            judged += [run[k + 1] - run[k] for k in range(clean[0], clean[-1])]
            stretches += 1
    grid, grid_gaps = grid_period(split_late(ts, period_s), period_s)
    return Periods(gaps, judged, stretches, max(0, len(runs) - 1), grid, grid_gaps)


# A gap this many periods long ends a run that grid_period fits: the frame after it may be
# the first of a grid the daemon started over (it does so a whole period late). The CPU
# stalls do not cut the runs: they can only delay frames, which the fit allows for, and runs
# cut at every stall of half a period were too short to fit (a heavily loaded TCG run: 9.59 ms
# on 26 gaps in 60 runs, against 10.01 ms on 80 gaps in 11 runs cut at the long gaps only).
RESTART_GAP_PERIODS = 1.5


def split_runs(ts: Sequence[float], cut: Callable[[float, float], bool]) -> list[list[float]]:
    """The frame times ``ts`` in runs, a new one begun after every gap ``(a, b)`` that
    ``cut(a, b)`` says ends a run."""
    out: list[list[float]] = []
    for i, t in enumerate(ts):
        if i == 0 or cut(ts[i - 1], t):
            out.append([t])
        else:
            out[-1].append(t)
    return out


def split_late(ts: Sequence[float], period_s: float) -> list[list[float]]:
    """``ts`` cut after every gap of ``RESTART_GAP_PERIODS`` periods or more."""
    return split_runs(ts, lambda a, b: b - a >= RESTART_GAP_PERIODS * period_s)


def grid_period(runs: Sequence[Sequence[float]], nominal_s: float) -> tuple[float | None, int]:
    """The period of the grid the frames of ``runs`` were sent on, and the gaps it rests on.

    Within a run the daemon sends frame i at ``a + i * P`` plus a delay of zero or more: a
    stall, seen or not, can only delay. So the grid is the line under every frame that leaves
    the least delay above it: P minimises the sum over the runs (each with its own ``a``, the
    least ``t_i - i * P`` of the run) of each frame's delay. Unlike the mean gap of a short
    stretch, it is not shortened by a first frame that came late unseen: the boot row failed
    on a mean of 9.22 ms over stretches of one to five gaps in a TCG guest, where this gives
    10.01 ms over the runs between the gaps of 1.5 periods (split_late;
    tests/harness/test_hil_timing.py). The sum is convex in P (a sum of linear terms
    and maxima of linear terms), so a ternary search over half to twice the nominal period
    finds its minimum. Runs of fewer than three frames say nothing of P and are left out."""
    use = [r for r in runs if len(r) >= 3]
    if not use:
        return None, 0

    def delay(p: float) -> float:
        total = 0.0
        for r in use:
            res = [t - i * p for i, t in enumerate(r)]
            low = min(res)
            total += sum(x - low for x in res)
        return total

    lo, hi = nominal_s / 2, nominal_s * 2
    for _ in range(100):
        a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        if delay(a) <= delay(b):
            hi = b
        else:
            lo = a
    return (lo + hi) / 2, sum(len(r) - 1 for r in use)


@dataclass(frozen=True, slots=True)
class Late:
    """A single time ``t0 -> t1`` judged against ``limit_s``: ``ok`` when within it; over it,
    ``stall`` says how long a CPU stood still or the daemon queued meanwhile when that is
    ``STALL_EXCUSE_S`` or more (then the sample cannot be judged: the environment may have made
    it late)."""

    value_s: float
    ok: bool
    stall: float | None


def late(t0: float, t1: float, limit_s: float, stalls: Sequence[tuple[float, float]],
         excuse_s: float = STALL_EXCUSE_S) -> Late:
    value = t1 - t0
    if value <= limit_s:
        return Late(value, True, None)
    s = overlap(stalls, t0, t1)
    return Late(value, False, s if s >= excuse_s else None)


def enough_frames(ts: Sequence[float], t0: float, t1: float, want: int, period_s: float,
                  stalls: Sequence[tuple[float, float]]) -> tuple[int, bool | None]:
    """Did at least ``want`` frames come in ``[t0, t1]``? Returns (count, verdict): True yes;
    False no, and the CPU stalls do not explain it; None no, but they may: the stall time in
    the window is at least the ``want - count`` missing periods."""
    n = sum(1 for t in ts if t0 <= t <= t1)
    if n >= want:
        return n, True
    return n, None if overlap(stalls, t0, t1) >= (want - n) * period_s else False


def upper_median(values: Sequence[float]) -> float:
    return sorted(values)[len(values) // 2]


@dataclass(frozen=True, slots=True)
class Verdict:
    """What latency samples say about "at once": failures, and why the samples could not
    decide (then the test is inconclusive: it runs once more; the failures say so too)."""

    fails: list[str]
    inconclusive: str | None = None


# Samples without a stall enough to judge the max limit, however many stalled: a loaded TCG
# guest stalled 7 to 11 of 12 TCP STOP samples in each of two tries (a local run, 2026-12-03).
MAX_CLEAN = 5


def judge_latencies(vals: Sequence[float], stalled: Sequence[bool], p50: float | None,
                    max_ms: float, label: str) -> Verdict:
    """Latency samples (ms) against a median limit (None: none) and a max limit.

    A CPU stall can only delay, so a sample taken during one is an upper bound of what the
    daemon did: a limit that all samples meet is met. Where they do not, only the samples
    without a stall count (at least 3 for a median, for the max at least half of them or
    MAX_CLEAN); when too few are left to decide, the verdict is inconclusive, never a pass.
    """
    fails: list[str] = []
    why: str | None = None
    clean = [v for v, st in zip(vals, stalled, strict=True) if not st]
    if not vals:
        return Verdict(fails)
    if p50 is not None and upper_median(vals) > p50:
        if len(clean) >= 3:
            if upper_median(clean) > p50:
                fails.append(f"{label}: median > {p50} ms (waits for the 10 ms tick?)")
        else:
            why = (f"{label}: median {upper_median(vals)} ms with stalls, only {len(clean)} "
                   "samples without one")
            fails.append(f"{label}: median not judged ({why})")
    over = [v for v, st in zip(vals, stalled, strict=True) if v > max_ms and not st]
    if over:
        fails.append(f"{label}: {max(over)} ms > {max_ms} ms")
    elif max(vals) > max_ms and len(clean) < min(MAX_CLEAN, (len(vals) + 1) // 2):
        why = (f"{label}: {max(vals)} ms > {max_ms} ms during a CPU stall, and only "
               f"{len(clean)} of {len(vals)} samples without one")
        fails.append(f"{label}: max not judged ({why})")
    return Verdict(fails, why)


# A gap in the periodic frames is the environment's when, without the CPU stalls inside it,
# the daemon had at most this much time to run: two and a half 10 ms periods.
RUNNABLE_GAP_S = 0.025


def excused(t0: float, t1: float, stalls: Sequence[tuple[float, float]],
            runnable_s: float = RUNNABLE_GAP_S) -> float | None:
    """The stall time that explains a frame gap ``[t0, t1]``, or None if it does not (the
    daemon had more than ``runnable_s`` to send in it)."""
    s = overlap(stalls, t0, t1)
    return s if s > 0 and (t1 - t0) - s <= runnable_s else None


def judge_gaps(ts: Sequence[float], stalls: Sequence[tuple[float, float]], limit_s: float,
               what: str = "ESTOP_BRAKE") -> Verdict:
    """Gaps of ``limit_s`` or more between the frame times ``ts`` (sorted): each one a failure.
    One that the CPU stalls explain (:func:`excused`) is not judged: a failure all the same
    and the verdict inconclusive (the row runs once more), never a pass."""
    fails: list[str] = []
    why: str | None = None
    for a, b in zip(ts, ts[1:], strict=False):
        if b - a < limit_s:
            continue
        gap = round((b - a) * 1000, 3)
        stall = excused(a, b, stalls)
        if stall is None:
            fails.append(f"{what} gap of {gap} ms at {a:.3f}")
        else:
            held = f"a CPU stood still or the daemon queued {round(stall * 1000, 3)} ms of it"
            why = f"{what} gap of {gap} ms, {held}"
            fails.append(f"{what} gap of {gap} ms at {a:.3f} (not judged: {held})")
    # A gap the stalls do not explain decides the verdict: no run more would change it.
    judged_fail = any("not judged" not in f for f in fails)
    return Verdict(fails, None if judged_fail else why)


def judge_drops(dropped: int | None, stall_s: float, what: str,
                excuse_s: float = STALL_EXCUSE_S) -> Verdict:
    """Datagrams the kernel dropped at the daemon's socket while ``what`` lasted, against 0: the
    receive buffer has room for all of it. A drop while a CPU stood still or the daemon queued
    ``excuse_s`` or more (``stall_s`` of it) cannot be judged (the daemon may not have run to
    read): inconclusive, never a pass. Unknown (no socket found) is a failure."""
    if dropped is None:
        return Verdict([f"{what}: no daemon socket in /proc/net/udp"])
    if not dropped:
        return Verdict([])
    if stall_s >= excuse_s:
        why = (f"the kernel dropped {dropped} datagrams of {what} while a CPU stood still or "
               f"the daemon queued {round(stall_s * 1000, 3)} ms of it")
        return Verdict([f"kernel drops not judged: {why}"], why)
    return Verdict([f"the kernel dropped {dropped} datagrams of {what}"])
