"""Judging helpers of the rows, live: latency samples, single times, frame counts and gaps
against the profile's limits, stall-aware (a CPU stall can only delay: what it may explain is
inconclusive, never a pass).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from estop.protocol.can import BRAKE_ID
from hilclients import NEUTRAL, Exchange, UdpRemote
from hildaemon import Daemon, sched_text
from hilemu import BRAKE_SILENCE_S
from hilroll import Roll
from hilrun import EARLY_TOL_MS, KEEPALIVE_GAP_S, TIMEOUT_MS, Result, Run, ms
from hilstalls import (
    STALL_EXCUSE_S,
    Verdict,
    enough_frames,
    judge_gaps,
    judge_latencies,
    late,
    overlap,
)
from hilstates import LogChange, log_changes
from hilstats import StatusWindow, status_windows, summary


def judge(run: Run, res: Result, key: str, label: str, pairs: list[tuple[float, float]],
          use_median: bool = True, slack_ms: float = 0.0) -> list[float]:
    """Latency samples (reference time, frame time) against the profile's limits.

    Value = frame - reference. A value before its time is never excused; for the other limits
    (median, max: the profile's plus ``slack_ms``) see :func:`hilstalls.judge_latencies`: a
    sample during which a CPU stood still or the daemon queued counts only as an upper bound.
    """
    stalls = run.stalls()
    vals = [ms(b - a) for a, b in pairs]
    stalled = [overlap(stalls, a, b) >= STALL_EXCUSE_S for a, b in pairs]
    res.samples_ms[label] = vals
    res.figures[key] = summary(vals) if len(vals) > 1 else (vals[0] if vals else None)
    if any(stalled):
        res.figures[f"{key}_during_cpu_stall"] = sum(stalled)
    if vals:
        res.check(min(vals) >= -EARLY_TOL_MS, f"{label}: {min(vals)} ms, before its time")
    # The samples of the row's earlier tries count too: a try is repeated only when its own
    # samples could not decide (too many stalled), never when one failed; theirs are samples of
    # the same daemon, and together they may decide where one try's alone could not.
    res.pool[label] = [*res.earlier.get(label, []), *zip(vals, stalled, strict=True)]
    if len(res.pool[label]) > len(vals):
        res.figures[f"{key}_judged_with_earlier_tries"] = len(res.pool[label])
    v = judge_latencies([x for x, _ in res.pool[label]], [st for _, st in res.pool[label]],
                        run.lim.p50 if use_median else None, run.lim.max + slack_ms, label)
    for f in v.fails:
        res.check(False, f)
    if v.inconclusive:
        res.inconclusive = v.inconclusive
    return vals


def judge_spoiled(res: Result, spoiled: int, n: int, judged: int, missing: str, *,
                  keepalive: bool) -> None:
    """The verdict on the samples the harness itself spoiled (its own send came too late, or
    its keepalive paused): counted; more than half of them make the row inconclusive (one
    spoiled by a late send is also not judged); every other sample must have been judged."""
    if spoiled:
        if keepalive:
            res.figures["samples_spoiled_by_keepalive_pause"] = spoiled
        else:
            res.figures["samples_spoiled_by_harness_delay"] = spoiled
        if spoiled > n // 2:
            if keepalive:
                res.inconclusive = f"{spoiled} of {n} samples: the harness's keepalive paused"
                res.spoiled = True
            else:
                res.inconclusive = f"{spoiled} of {n} samples spoiled by the harness"
                res.check(False, f"not judged: {res.inconclusive}")
    res.check(judged == n - spoiled, missing)


def judge_late(run: Run, res: Result, key: str, what: str, t0: float, t1: float,
               limit_s: float) -> None:
    """One time ``t0 -> t1`` against ``limit_s``. Over the limit while a CPU stood still or the
    daemon queued (STALL_EXCUSE_S or more of it) it cannot be judged: a failure that makes the
    row inconclusive (it runs once more), never a pass."""
    lt = late(t0, t1, limit_s, run.stalls())
    res.figures[key] = ms(lt.value_s)
    if lt.ok:
        return
    if lt.stall is not None:
        why = f"a CPU stood still or the daemon queued {ms(lt.stall)} ms of it"
        res.figures[f"{key}_cpu_stall_ms"] = ms(lt.stall)
        res.inconclusive = f"{what}: {ms(lt.value_s)} ms, {why}"
        res.check(False, f"{what} {ms(lt.value_s)} ms > {ms(limit_s)} ms (not judged: {why})")
    else:
        res.check(False, f"{what} {ms(lt.value_s)} ms > {ms(limit_s)} ms")


def judge_frames(run: Run, res: Result, key: str, what: str, t0: float, t1: float,
                 want: int) -> None:
    """At least ``want`` ESTOP_BRAKE frames in ``[t0, t1]``; fewer, with CPU stalls that could
    explain the missing periods, is inconclusive (see :func:`hilstalls.enough_frames`)."""
    run.mon.sync()
    ts = [f.ts for f in run.mon.window(t0, t1) if f.can_id == BRAKE_ID]
    n, verdict = enough_frames(ts, t0, t1, want, 0.010, run.stalls())
    res.figures[key] = n
    if verdict is None:
        stall = overlap(run.stalls(), t0, t1)
        res.inconclusive = (f"{what}: {n} frames, a CPU stood still or the daemon queued "
                            f"{ms(stall)} ms meanwhile")
        res.check(False, f"{what}: {n} < {want} frames (not judged: a CPU stood still or the "
                         f"daemon queued {ms(stall)} ms of the {ms(t1 - t0)} ms)")
    elif not verdict:
        res.check(False, f"{what}: {n} < {want} frames")


def frame_gap_check(run: Run, res: Result, key: str, t0: float, t1: float) -> None:
    """No ESTOP_BRAKE gap of 50 ms in ``[t0, t1]``. A gap the CPU stalls explain
    (hilstalls.judge_gaps) is not a pass either: the row is inconclusive and runs once more."""
    run.mon.sync()
    ts = [f.ts for f in run.mon.window(t0, t1) if f.can_id == BRAKE_ID]
    res.figures[key] = ms(max((b - a for a, b in zip(ts, ts[1:], strict=False)), default=0.0))
    apply_gaps(res, judge_gaps(ts, run.stalls(), BRAKE_SILENCE_S))


def apply_gaps(res: Result, v: Verdict) -> None:
    """A :func:`hilstalls.judge_gaps` verdict into the row's result."""
    if v.inconclusive:
        res.inconclusive = v.inconclusive
    for f in v.fails:
        res.check(False, f)


def windows_in(run: Run, t0: float, t1: float) -> list[StatusWindow]:
    """ESTOP_STATUS counting windows that end after ``t0`` and begin before ``t1``."""
    run.mon.sync()
    frames = run.mon.window(t0 - 0.5, t1 + 0.5)
    return [w for w in status_windows(frames) if w.end > t0 and w.start < t1]


def last_packet(run: Run, res: Result, remote: UdpRemote, i: int,
                spoil_s: float = TIMEOUT_MS / 2000,
                send: Callable[[], float] | None = None, what: str = "last packet") -> float | None:
    """Stop ``remote``'s keepalive and send one last valid packet (or what ``send`` sends; it
    returns the time of its first datagram) just after a periodic ARMED frame, so that a
    deadline falls just after a 10 ms tick: a daemon that waits for its next tick overshoots by
    nearly 10 ms. Returns the send time, or None when the harness itself was too slow: the
    link was silent for ``spoil_s`` (most of the time to the first deadline, by default half
    the timeout) before it (the unit may rightly have acted before it), so this is no sample."""
    t_stop = time.time()
    t_prev = remote.stop()
    assert t_prev is not None
    t_wait = time.time()
    tick = run.next_brake(0.1)
    t_tick = time.time()
    if tick is not None and tick.state != 1:
        # Not ARMED: a failure, unless the harness's own keepalive had paused long enough
        # that the unit may rightly have acted (a local run under load: a STOPPED frame after a
        # keepalive starved for longer than the timeout).
        paused = max(remote.max_gap(t_prev - 1.0, t_prev), t_tick - t_prev)
        if paused < spoil_s:
            res.check(False, f"run {i}: no periodic ARMED frame (state {tick.state}), the "
                             f"harness's keepalive paused at most {ms(paused)} ms")
        else:
            res.notes.append(f"run {i}: not a sample, the harness's keepalive paused "
                             f"{ms(paused)} ms before it (state {tick.state} on the bus)")
        return None
    if tick is None:  # a gap in the frames: the whole-run row judges the gaps, stall-aware
        res.notes.append(f"run {i}: not a sample, no ESTOP_BRAKE frame on the bus within "
                         "100 ms (a gap the whole-run row judges)")
        return None
    t_last = send() if send is not None else remote.send(remote.packet(NEUTRAL))
    if t_last - t_prev >= spoil_s:
        res.notes.append(f"run {i}: not a sample, the harness's {what} came "
                         f"{ms(t_last - t_prev)} ms after the packet before (that one "
                         f"{ms(t_stop - t_prev)} ms before the keepalive was stopped; "
                         f"{ms(t_tick - t_wait)} ms waiting for a tick)")
        return None
    return t_last


def wait_state_lines(d: Daemon, since_mono: float, n: int,
                     timeout: float = 2.0) -> list[LogChange]:
    """The daemon's ``state`` lines for changes at or after ``since_mono`` (its clock,
    CLOCK_MONOTONIC as the harness's): waits (bounded) until ``n`` are there, as a line may be
    written a little after its frame."""
    end = time.monotonic() + timeout
    while True:
        got = log_changes(r for r in d.events("state")
                          if float(r.get("t_mono", 0.0)) >= since_mono)
        if len(got) >= n or time.monotonic() >= end:
            return got
        time.sleep(0.01)


def judge_rolls(res: Result, key: str, label: str, rolls: list[Roll], model_m: float,
                model: str, compare: list[tuple[str, float, float]] | None = None) -> None:
    """How far the car rolled from each moment (hilroll): the figures (metres), the samples
    for the report (with when braking began, the model's figure for an ideal unit, ``model``
    saying which, and model figures to ``compare`` with: (what, metres, of them before braking)),
    and a failure where estop.model.rollout and the harness's emulator disagree."""
    vals = [r.bus.distance for r in rolls]
    res.rollouts[label] = {
        "distance_m": [round(v, 4) for v in vals],
        "braking_after_ms": [None if r.bus.reaction_time is None
                             else round(r.bus.reaction_time * 1000, 3) for r in rolls],
        "before_braking_m": [round(r.bus.distance_before_braking, 4) for r in rolls],
        "model_m": round(model_m, 3), "model": model,
        "compare": [[text, round(m, 4), round(b, 4)] for text, m, b in compare or []]}
    res.figures[key] = summary(vals) if len(vals) > 1 else (round(vals[0], 3) if vals else None)
    for r in rolls:
        if not r.agree:
            res.check(False, f"{label}: the two ways to the distance disagree: "
                             f"{r.disagreement()}")


def no_armed_frame(run: Run, res: Result, start: int,
                   what: str = "an ARMED frame appeared on the bus") -> None:
    """No ESTOP_BRAKE frame with state ARMED from index ``start`` on (the record synced)."""
    run.mon.sync()
    armed = [f for f in run.mon.since(start) if f.can_id == BRAKE_ID and f.data[2] == 1]
    res.check(not armed, what)


def link_died_first(remote: UdpRemote, t_arm: float, t_send: float, reason: int | None) -> bool:
    """Whether a stop sample is void: the unit stopped for the timeout (reason 3) and the
    harness's own keepalive had paused KEEPALIVE_GAP_S or more between arming and sending the
    stop request, so the link may have died before the request (the harness's doing)."""
    return reason == 3 and remote.max_gap(t_arm, t_send) >= KEEPALIVE_GAP_S


def judge_sched(run: Run, res: Result, d: Daemon) -> None:
    """How the daemon ran, as deployed (hilrun.RT_PRIO): its start line's ``rt_prio`` and how
    the kernel schedules its threads; with a priority asked, the loop (the main thread) must
    run SCHED_FIFO at it."""
    res.figures["scheduling"] = sched_text(d.sched)
    start = d.events("start")
    if start:
        res.figures["start_line_rt_prio"] = start[0].get("rt_prio")
    if run.rt_prio:
        res.figures["started_under"] = (f"chrt -f -R {run.rt_prio}" if run.chrt else
                                        "no chrt on PATH: the daemon's own --rt-prio only")
        main = d.sched[0] if d.sched else None
        res.check(main is not None and main.policy == "FIFO" and main.priority == run.rt_prio,
                  f"the daemon's loop does not run SCHED_FIFO {run.rt_prio}: "
                  f"{res.figures['scheduling']}")


def show_ex(ex: Exchange) -> str:
    r = ex.reply
    text = f"{'ACK' if r.ack else 'NAK'} state={r.state} reason={r.reason} nak={r.nak_code}"
    return text if ex.tag_ok is None else f"{text} tag_ok={ex.tag_ok}"

