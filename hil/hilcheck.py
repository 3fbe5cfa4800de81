"""The pure logic of the HIL harness in one import (no sockets, no threads, no vcan): testable
on any host. It lives in modules by job; this one names them and gathers what the tests use.

- ``hilemu``: the brake-controller emulator (:class:`BrakeController`, graded as spec
  section 7 asks) and its offline :func:`replay`; the :class:`Frame` every part shares;
- ``hilstalls``: the environment's stalls (hil/mon/stallmon's intervals) and the stall-aware
  verdicts: latencies, single times, frame counts, mean periods, gaps, kernel drops;
- ``hilstats``: figures of the protocol (:func:`summary`, :func:`frame_gaps`) and the counts of
  the UDP flood rows (/proc/net/udp, ESTOP_STATUS counting windows, a sender's series);
- ``hilcandump``: the candump cross-check.
"""

from __future__ import annotations

from hilcandump import CrossCheck, crosscheck, read_candump
from hilemu import (
    BRAKE_SILENCE_S,
    STATUS_RESYNC_S,
    BrakeChange,
    BrakeController,
    Frame,
    Issue,
    Trip,
    frame_commands,
    replay,
    share_at,
    shares_between,
)
from hilstalls import (
    CATCH_UP_S,
    RUNNABLE_GAP_S,
    STALL_EXCUSE_S,
    Late,
    Periods,
    Verdict,
    enough_frames,
    excused,
    grid_period,
    judge_drops,
    judge_latencies,
    late,
    merge,
    merge_more,
    overlap,
    periods,
    read_stalls,
    upper_median,
)
from hilstats import (
    StatusWindow,
    frame_gaps,
    in_windows,
    percentile,
    sent_between,
    status_windows,
    summary,
)

__all__ = [
    "BRAKE_SILENCE_S", "CATCH_UP_S", "RUNNABLE_GAP_S", "STALL_EXCUSE_S", "STATUS_RESYNC_S",
    "BrakeChange", "BrakeController", "CrossCheck", "Frame", "Issue", "Late", "Periods",
    "StatusWindow", "Trip", "Verdict", "crosscheck", "enough_frames", "excused",
    "frame_commands", "frame_gaps", "grid_period", "in_windows", "judge_drops",
    "judge_latencies", "late", "merge", "merge_more", "overlap", "percentile", "periods",
    "read_candump", "read_stalls", "replay", "sent_between", "share_at", "shares_between",
    "status_windows", "summary", "upper_median",
]
