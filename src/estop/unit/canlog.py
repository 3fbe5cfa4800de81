"""Reading estopd's can-log (stamps, stop frames, the lines its alive counters show missing)
and the windows in which its ``output_dropped`` reports (:mod:`estop.unit.events`) say lines
may be missing.

A tool that times frames from the can-log must not mistake a lost line for a late frame:
estopd drops can-log lines when its reader is slow (``output_dropped`` in its event log). Every
line read passes :class:`CanLogLoss` (alive counters) and every ``output_dropped`` report is
kept; :func:`drop_windows` says when lines may be missing. Used by :mod:`estop.unit.daemon`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from estop.protocol import can, canlog
from estop.unit.events import OutputDropped

__all__ = [
    "DROP_REPORT_REACH_S",
    "CanLogLoss",
    "DaemonError",
    "Gap",
    "drop_windows",
    "is_stop_frame",
    "stamp",
]


class DaemonError(RuntimeError):
    """The daemon could not be found, started, or it died, or it answered wrongly. ``str()``
    is one line."""


def stamp(rec: canlog.CanLogRecord) -> float:
    """A can-log record's realtime stamp in seconds (comparable with time.time())."""
    return rec.timestamp_us / 1_000_000


def is_stop_frame(rec: canlog.CanLogRecord) -> bool:
    """An ESTOP_BRAKE frame that requests the brake."""
    return rec.can_id == can.BRAKE_ID and len(rec.data) == can.DLC and rec.data[0] == 1


# --------------------------------------------------------------------------------------------
# Lines missing from the can-log


@dataclass(frozen=True, slots=True)
class Gap:
    """Frames of one CAN ID missing from the can-log, found by the alive counter of the frame
    logged after them: their stamps lie between ``after`` and ``before`` (realtime seconds)."""

    can_id: int
    after: float  # stamp of the last frame of this ID before the gap
    before: float  # stamp of the frame whose counter showed it
    lost: int  # frames missing, modulo 15 (a repeated counter counts as 14)


class CanLogLoss:
    """Follows the alive counters of ESTOP_BRAKE and ESTOP_STATUS (0..14, wrapping) in a
    can-log, line by line, and keeps every gap.

    The counters see a loss at the next frame of the same ID; they cannot see exactly 15 (or
    30, ...) lost frames of one ID, which is why the daemon's own count is needed as well.
    """

    IDS = (can.BRAKE_ID, can.STATUS_ID)

    def __init__(self) -> None:
        self._ctr = {i: can.CounterChecker() for i in self.IDS}
        self._last: dict[int, float] = {}
        self.gaps: list[Gap] = []
        self.frames = 0

    @property
    def lines_lost(self) -> int:
        """Frames the counters found missing so far (a lower bound, see above)."""
        return sum(g.lost for g in self.gaps)

    def take(self, rec: canlog.CanLogRecord) -> Gap | None:
        """Follow one logged frame; the gap it shows, if any."""
        checker = self._ctr.get(rec.can_id)
        if checker is None or len(rec.data) != can.DLC or rec.data[6] & 0xF0:
            return None
        self.frames += 1
        t = stamp(rec)
        prev = self._last.get(rec.can_id)
        status = checker.check(rec.data[6] & 0x0F)
        if status.result is can.CounterResult.INVALID:
            return None
        self._last[rec.can_id] = t
        gap = None
        if status.result is can.CounterResult.JUMP:
            gap = Gap(rec.can_id, -math.inf if prev is None else prev, t, status.lost)
        elif status.result is can.CounterResult.REPEAT:
            gap = Gap(rec.can_id, -math.inf if prev is None else prev, t, can.COUNTER_MODULO - 1)
        if gap is not None:
            self.gaps.append(gap)
        return gap

    def lost_between(self, t0: float, t1: float) -> int:
        """Frames missing with stamps that may lie in [t0, t1] (realtime seconds)."""
        return sum(g.lost for g in self.gaps if g.after < t1 and g.before > t0)

    def seen_after(self, t: float) -> bool:
        """Both IDs have been logged after ``t``: a gap around ``t`` would have shown."""
        return all(self._last.get(i, -math.inf) > t for i in self.IDS)


DROP_REPORT_REACH_S = 2.0
"""How far back an ``output_dropped`` report reaches. estopd reports lost lines at most once a
second (and at exit), from a loop that wakes at least every brake period (10 ms): the lines of
a report were dropped less than about 1 s before it. 2 s leaves room for a loop held up."""


def drop_windows(reports: Iterable[OutputDropped], stream: str = "can_log", *,
                 reach_s: float = DROP_REPORT_REACH_S) -> list[tuple[float, float, int]]:
    """(from, to, lines): daemon-monotonic stretches in which the daemon dropped lines of
    ``stream``, from its reports in order. A report whose ``total`` shows that an earlier
    report is missing (the event log lost lines too) reaches back to the report before it.
    Reports of the event log's own losses (stream ``log``) may hide a ``stream`` report: each
    counts as a window twice as long."""
    out: list[tuple[float, float, int]] = []
    prev_t = -math.inf
    prev_total = 0
    for r in reports:
        if r.dropped <= 0:
            continue
        if r.stream == stream:
            missing = r.total - prev_total > r.dropped
            lo = prev_t if missing else max(prev_t, r.t_mono - reach_s)
            out.append((lo, r.t_mono, r.total - prev_total if missing else r.dropped))
            prev_t, prev_total = r.t_mono, r.total
        elif r.stream == "log" and stream != "log":
            out.append((r.t_mono - 2.0 * reach_s, r.t_mono, r.dropped))
    return out
