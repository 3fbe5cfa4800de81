"""Pure logic of the HIL harness (no sockets, no threads, no vcan): testable on any host.

- :class:`BrakeController` emulates the brake controller that receives ESTOP_BRAKE (spec
  sections 4 and 7): it accepts only frames with a good CRC, a legal alive counter that moved
  on, and consistent fields, and it brakes by itself when no good frame has arrived for 50 ms.
  It grades its braking as a real controller does (section 7): the share of the emergency
  deceleration is estop.brakecheck's answer (0 release, brake_level/100 for brake_request 2,
  1 for an emergency brake and for any brake_request it does not know).
  Frame checks use the project's codecs in ``estop.protocol.can`` (``BrakeFrame.check``,
  ``StatusFrame.check``, ``CounterChecker``), which are written independently of the C core.
- :func:`crosscheck` compares the candump log with what python-can saw.
- :func:`summary` and :func:`frame_gaps` turn samples into the figures of the test protocol.

Times are float seconds on the wall clock (CLOCK_REALTIME) that SocketCAN uses to timestamp
frames, so frame times and the harness's own send times can be subtracted directly.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from estop.brakecheck import EMERGENCY, BrakeFrameChecker
from estop.protocol.can import (
    BRAKE_ID,
    STATUS_ID,
    BrakeFrame,
    CounterChecker,
    CounterResult,
    StatusFrame,
)
from estop.protocol.canlog import CanLogError, parse_line

BRAKE_SILENCE_S = 0.050  # spec section 4: brake when no good ESTOP_BRAKE for 50 ms
STATUS_RESYNC_S = 0.200  # two ESTOP_STATUS periods without one: its counter starts over
_EPS = 1e-6  # float seconds near 1.7e9 carry ~0.2 us of rounding


@dataclass(frozen=True, slots=True)
class Frame:
    """One CAN frame as a receiver saw it (kernel timestamp, seconds)."""

    ts: float
    can_id: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Issue:
    """A frame a brake controller must not accept, or a counter anomaly."""

    ts: float
    can_id: int
    kind: str  # bad_length, bad_crc, bad_counter, bad_content, repeat, jump, resync
    detail: str


@dataclass(frozen=True, slots=True)
class Trip:
    """The 50 ms silence watchdog fired: no good frame since ``last_good``."""

    last_good: float
    detected: float  # when the emulator noticed (live: its own clock; offline: deadline)

    @property
    def deadline(self) -> float:
        return self.last_good + BRAKE_SILENCE_S


@dataclass(frozen=True, slots=True)
class BrakeChange:
    """The controller's braking changed at ``ts``: from then on it decelerates the car at
    ``share`` of its emergency deceleration (spec section 7)."""

    ts: float
    share: float
    cause: str  # "frame" (a frame from the unit commanded it) or "silence" (watchdog)

    @property
    def braking(self) -> bool:
        return self.share > 0.0


@dataclass
class BrakeController:
    """Brake-controller emulator for ESTOP_BRAKE (and an integrity checker for ESTOP_STATUS).

    Feed it every frame with :meth:`on_frame` (in time order) and call :meth:`on_tick` with the
    current time whenever possible; it brakes when no good ESTOP_BRAKE frame arrived for
    ``silence_s``. It powers up braking, as a real one would.

    How hard it brakes (:attr:`share`, every change in :attr:`changes`) is
    :class:`estop.brakecheck.BrakeFrameChecker`'s graded answer: what the latest frame from the
    unit commands (a frame with a right CRC and a new counter whose content is wrong, e.g. an
    unknown brake_request, commands an emergency brake), or 1 after the silence. The grader
    starts over whenever this controller's counter does (a new sender, a silence), so both
    agree on which frames came from the unit.
    """

    silence_s: float = BRAKE_SILENCE_S
    share: float = EMERGENCY
    last_good: float | None = None
    last_frame: BrakeFrame | None = None
    good: int = 0
    status_good: int = 0
    issues: list[Issue] = field(default_factory=list)
    trips: list[Trip] = field(default_factory=list)
    changes: list[BrakeChange] = field(default_factory=list)
    tripped: bool = False
    last_status: float | None = None
    _brake_ctr: CounterChecker = field(default_factory=CounterChecker)
    _status_ctr: CounterChecker = field(default_factory=CounterChecker)
    _new_sender_at: float | None = None
    _grader: BrakeFrameChecker = field(
        default_factory=lambda: BrakeFrameChecker(status_id=None))

    @property
    def braking(self) -> bool:
        """Whether it brakes at all (any share above 0)."""
        return self.share > 0.0

    def expect_new_sender(self, since: float | None = None) -> None:
        """A new daemon starts: its counters start over, so no continuity is expected. With
        ``since``, from its first frame stamped at or after that time (a receiver that lags
        behind the bus may still be reading the previous daemon's last frames)."""
        if since is None:
            self._brake_ctr.reset()
            self._status_ctr.reset()
            self._grader.reset()
        self._new_sender_at = since

    def _set(self, ts: float, share: float, cause: str) -> None:
        if share != self.share:
            self.share = share
            self.changes.append(BrakeChange(ts, share, cause))

    def on_frame(self, frame: Frame) -> None:
        """Any frame (of any ID) proves that time has reached ``frame.ts`` on the bus."""
        self.on_tick(frame.ts)
        if self._new_sender_at is not None and frame.can_id in (BRAKE_ID, STATUS_ID) \
                and frame.ts >= self._new_sender_at:
            self._new_sender_at = None
            self._brake_ctr.reset()
            self._status_ctr.reset()
            self._grader.reset()
        if frame.can_id == BRAKE_ID:
            self._on_brake(frame)
        elif frame.can_id == STATUS_ID:
            self._on_status(frame)

    def _counter(self, checker: CounterChecker, frame: Frame, counter: int,
                 resync: bool) -> bool:
        if resync and checker.last is not None:
            # After a silence the counter cannot be followed (15 lost frames look like a
            # repeat): start over, as an E2E receiver does after a timeout, and report it.
            self.issues.append(Issue(frame.ts, frame.can_id, "resync",
                                     f"counter {counter} after a silence, was {checker.last}"))
            checker.reset()
        status = checker.check(counter)
        if status.result is CounterResult.REPEAT:
            self.issues.append(Issue(frame.ts, frame.can_id, "repeat",
                                     f"counter {counter} repeated (stale frame)"))
            return False
        if status.result is CounterResult.JUMP:
            self.issues.append(Issue(frame.ts, frame.can_id, "jump",
                                     f"counter {counter}, expected {status.expected} "
                                     f"({status.lost} lost)"))
        return True

    def _on_brake(self, frame: Frame) -> None:
        if self.tripped:
            self._grader.reset()  # after a silence its counter starts over, as ours does
        verdict = self._grader.feed(frame.ts, frame.can_id, frame.data)
        if verdict is not None and verdict.share is not None:
            self._set(frame.ts, verdict.share, "frame")
        problems = BrakeFrame.check(frame.data)
        if problems:
            for p in problems:
                self.issues.append(Issue(frame.ts, frame.can_id, p.kind, str(p)))
            return
        parsed = BrakeFrame.parse(frame.data)
        if not self._counter(self._brake_ctr, frame, parsed.counter, self.tripped):
            return
        self.good += 1
        self.last_good = frame.ts
        self.last_frame = parsed
        self.tripped = False

    def _on_status(self, frame: Frame) -> None:
        problems = StatusFrame.check(frame.data)
        if problems:
            for p in problems:
                self.issues.append(Issue(frame.ts, frame.can_id, p.kind, str(p)))
            return
        resync = self.last_status is not None and frame.ts - self.last_status >= STATUS_RESYNC_S
        self.last_status = frame.ts
        if self._counter(self._status_ctr, frame, StatusFrame.parse(frame.data).counter, resync):
            self.status_good += 1

    def on_tick(self, now: float) -> None:
        """Apply the silence watchdog at time ``now`` (live: the emulator's clock)."""
        if self.last_good is None or self.tripped:
            return
        if now - self.last_good >= self.silence_s - _EPS:
            self.tripped = True
            self.trips.append(Trip(self.last_good, now))
            self._set(now, EMERGENCY, "silence")


def replay(frames: Iterable[Frame], silence_s: float = BRAKE_SILENCE_S,
           end: float | None = None) -> BrakeController:
    """Offline emulator run: watchdog trips are placed exactly at their deadlines."""
    ctl = BrakeController(silence_s=silence_s)
    for fr in frames:
        if ctl.last_good is not None and fr.ts - ctl.last_good >= silence_s - _EPS:
            ctl.on_tick(ctl.last_good + silence_s)
        ctl.on_frame(fr)
    if end is not None and ctl.last_good is not None and end - ctl.last_good >= silence_s - _EPS:
        ctl.on_tick(ctl.last_good + silence_s)
    return ctl


def share_at(changes: Sequence[BrakeChange], t: float, initial: float = EMERGENCY) -> float:
    """The share the controller braked with at ``t`` (``initial`` before its first change; it
    powers up braking)."""
    share = initial
    for c in changes:
        if c.ts > t:
            break
        share = c.share
    return share


def shares_between(changes: Sequence[BrakeChange], t0: float, t1: float,
                   initial: float = EMERGENCY) -> list[float]:
    """Every share the controller braked with in ``[t0, t1)``, in order (no repeats)."""
    out = [share_at(changes, t0, initial)]
    for c in changes:
        if t0 < c.ts < t1 and c.share != out[-1]:
            out.append(c.share)
    return out


def frame_commands(changes: Iterable[BrakeChange], t0: float = -math.inf,
                   t1: float = math.inf) -> list[tuple[float, float]]:
    """(time, share) of the changes frames commanded in ``[t0, t1]``: the same for the live
    controller and a replay of the bus record, as both see the same kernel timestamps (the
    silence watchdog's changes differ: live they come when it looked)."""
    return [(c.ts, c.share) for c in changes if c.cause == "frame" and t0 <= c.ts <= t1]


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


# --------------------------------------------------------------------------- environment stalls

def read_stalls(lines: Iterable[str]) -> list[tuple[float, float]]:
    """Intervals of a ``stallmon.py`` file (``start end`` per line, ``#`` comments)."""
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


# A sample (a latency, a frame gap) during which a CPU stood still this long is not judged
# against a timing limit: the environment, not the daemon, may have made it late.
STALL_EXCUSE_S = 0.002


# A frame sent within this time after a CPU stall may still be late (the daemon catches up on
# its grid with the next frame or two): it does not start or end a judged stretch.
CATCH_UP_S = 0.020


@dataclass(frozen=True, slots=True)
class Periods:
    """Frame periods judged on stall-free stretches only.

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
    runs: list[list[float]] = []
    for i, t in enumerate(ts):
        if i == 0 or overlap(split, ts[i - 1], t) > 0:
            runs.append([t])
        else:
            runs[-1].append(t)
    judged: list[float] = []
    stretches = 0
    for run in runs:
        clean = [k for k, t in enumerate(run) if overlap(stalls, t - margin_s, t) < excuse_s]
        if len(clean) >= 2:
            judged += [run[k + 1] - run[k] for k in range(clean[0], clean[-1])]
            stretches += 1
    return Periods(gaps, judged, stretches, max(0, len(runs) - 1))


@dataclass(frozen=True, slots=True)
class Late:
    """A single time ``t0 -> t1`` judged against ``limit_s``: ``ok`` when within it; over it,
    ``stall`` says how long a CPU stood still meanwhile when that is ``STALL_EXCUSE_S`` or more
    (then the sample cannot be judged: the environment may have made it late)."""

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


def judge_latencies(vals: Sequence[float], stalled: Sequence[bool], p50: float | None,
                    max_ms: float, label: str) -> Verdict:
    """Latency samples (ms) against a median limit (None: none) and a max limit.

    A CPU stall can only delay, so a sample taken during one is an upper bound of what the
    daemon did: a limit that all samples meet is met. Where they do not, only the samples
    without a stall count (at least 3 for a median, at least half of them in all); when too
    few are left to decide, the verdict is inconclusive, never a pass.
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
    elif max(vals) > max_ms and len(clean) < (len(vals) + 1) // 2:
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


def judge_drops(dropped: int | None, stall_s: float, what: str,
                excuse_s: float = STALL_EXCUSE_S) -> Verdict:
    """Datagrams the kernel dropped at the daemon's socket while ``what`` lasted, against 0: the
    receive buffer has room for all of it. A drop while a CPU stood still ``excuse_s`` or more
    (``stall_s`` of it) cannot be judged (the daemon may not have run to read): inconclusive,
    never a pass. Unknown (no socket found) is a failure."""
    if dropped is None:
        return Verdict([f"{what}: no daemon socket in /proc/net/udp"])
    if not dropped:
        return Verdict([])
    if stall_s >= excuse_s:
        why = (f"the kernel dropped {dropped} datagrams of {what} while a CPU stood still "
               f"{round(stall_s * 1000, 3)} ms of it")
        return Verdict([f"kernel drops not judged: {why}"], why)
    return Verdict([f"the kernel dropped {dropped} datagrams of {what}"])


# --------------------------------------------------------------------------- UDP flood figures

def udp_socket_drops(proc_net_udp: str, port: int) -> tuple[int, int] | None:
    """(rx_queue bytes, drops) of the unconnected UDP socket bound to ``port``, from the text
    of ``/proc/net/udp``; None when there is no such socket."""
    for line in proc_net_udp.splitlines()[1:]:
        f = line.split()
        if len(f) < 13 or ":" not in f[1] or ":" not in f[4]:
            continue
        try:
            lport = int(f[1].rsplit(":", 1)[1], 16)
            rport = int(f[2].rsplit(":", 1)[1], 16)
            rxq = int(f[4].split(":")[1], 16)
            drops = int(f[-1])
        except ValueError:
            continue
        if lport == port and rport == 0:
            return rxq, drops
    return None


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


# --------------------------------------------------------------------------- candump check

def read_candump(lines: Iterable[str]) -> tuple[list[Frame], list[str]]:
    """Frames of a ``candump -L`` log, and the lines that are not frames (reported, not fatal:
    candump also prints e.g. ``interface down`` notices on stderr, never on stdout)."""
    frames: list[Frame] = []
    bad: list[str] = []
    for line in lines:
        if not line.strip():
            continue
        try:
            rec = parse_line(line)
        except CanLogError:
            bad.append(line.rstrip("\n"))
            continue
        frames.append(Frame(rec.timestamp_us / 1e6, rec.can_id, rec.data))
    return frames, bad


@dataclass
class CrossCheck:
    window: tuple[float, float] | None
    matched: int = 0
    only_candump: list[Frame] = field(default_factory=list)
    only_pycan: list[Frame] = field(default_factory=list)
    data_mismatch: list[tuple[Frame, Frame]] = field(default_factory=list)
    candump_total: int = 0
    pycan_total: int = 0

    @property
    def ok(self) -> bool:
        return (self.window is not None and self.matched > 0 and not self.only_candump
                and not self.only_pycan and not self.data_mismatch)

    def figures(self) -> dict[str, object]:
        return {
            "candump_frames": self.candump_total,
            "pycan_frames": self.pycan_total,
            "matched_in_window": self.matched,
            "only_candump": len(self.only_candump),
            "only_pycan": len(self.only_pycan),
            "data_mismatch": len(self.data_mismatch),
        }


def crosscheck(candump: Sequence[Frame], pycan: Sequence[Frame],
               window: tuple[float, float] | None = None,
               tol_s: float = 2e-6) -> CrossCheck:
    """Same frames, in the same order? Both receivers read the kernel timestamp of the same
    skb, so a frame has the same time (to the microsecond candump prints) in both records.

    The order is compared CAN ID by CAN ID: frames of different senders (the daemon's, the
    harness's markers) that came within microseconds of each other on two CPUs may reach two
    sockets in either order (seen: a marker 155 us after a stop frame, read before it by
    candump and after it by python-can). Frames of one ID come from one sender, one at a time.

    Only frames inside ``window`` are compared (default: the span both receivers covered), so
    frames at the start/stop edges, seen by one receiver only, do not count.
    """
    res = CrossCheck(None, candump_total=len(candump), pycan_total=len(pycan))
    if not candump or not pycan:
        return res
    if window is None:
        window = (max(candump[0].ts, pycan[0].ts), min(candump[-1].ts, pycan[-1].ts))
    res.window = window
    lo, hi = window[0] - tol_s, window[1] + tol_s
    a = [f for f in candump if lo <= f.ts <= hi]
    b = [f for f in pycan if lo <= f.ts <= hi]
    for can_id in sorted({f.can_id for f in a} | {f.can_id for f in b}):
        _walk(res, [f for f in a if f.can_id == can_id], [f for f in b if f.can_id == can_id],
              tol_s)
    return res


def _walk(res: CrossCheck, a: list[Frame], b: list[Frame], tol_s: float) -> None:
    """Match two records of one CAN ID in order, by timestamp."""
    i = j = 0
    while i < len(a) and j < len(b):
        fa, fb = a[i], b[j]
        if abs(fa.ts - fb.ts) <= tol_s:
            if fa.data == fb.data:
                res.matched += 1
            else:
                res.data_mismatch.append((fa, fb))
            i += 1
            j += 1
        elif fa.ts < fb.ts:
            res.only_candump.append(fa)
            i += 1
        else:
            res.only_pycan.append(fb)
            j += 1
    res.only_candump.extend(a[i:])
    res.only_pycan.extend(b[j:])
