"""The whole-run checks, after the rows: bus integrity and the emulator live vs offline (its
graded commands too: release, the SLOWING share, emergency), candump vs python-can, the daemon's
log lines against the state changes on the bus (SLOWING's among them, each kind counted) and
their causes.
"""

from __future__ import annotations

import json
import time
from collections import Counter

from estop.model.brakecheck import grade_text
from estop.protocol.can import BRAKE_ID, STATUS_ID, brake_request_name
from hilbus import MARKER_ID
from hilcandump import crosscheck, read_candump
from hilemu import BRAKE_SILENCE_S, Frame, frame_commands, replay
from hilrun import Result, Row, Run, ms
from hilstalls import excused
from hilstates import bus_transitions, cause_problem, log_changes
from hilstats import in_windows, summary

# =========================================================================== global checks

def sent_order(frames: list[Frame]) -> tuple[list[Frame], int, float]:
    """The frames in the order they were sent (their kernel timestamps, taken as each frame
    entered vcan on the sending CPU), how many a socket read after a frame sent later, and by
    how much at most (s). vcan hands a frame to the readers from the sending CPU's backlog:
    when that CPU stalls (a TCG guest), a frame sent on the other CPU after it is read first.
    A real bus keeps the order; a local run saw two frames read swapped 19.7 ms apart, which a
    counter check in the order read took for 14 lost frames."""
    late = [a.ts - b.ts for a, b in zip(frames, frames[1:], strict=False) if b.ts < a.ts]
    return sorted(frames, key=lambda f: f.ts), len(late), max(late, default=0.0)


def check_bus(run: Run, res: Result) -> None:
    ctl = run.mon.ctl
    wins = [(a, b) for a, b, _ in run.windows]
    # Counters, checks and gaps in the order the daemon sent (sent_order); the live emulator
    # saw the frames as read, and a replay in that same order is compared with it below.
    wire, swapped, most = sent_order([f for f in run.mon.frames if f.can_id != MARKER_ID])
    cut = run.t_closed - 0.1  # see the live emulator's comparison below
    sent = replay(wire, end=cut, new_senders=[d.t_start for d in run.daemons])
    frames = [f for f in wire if f.can_id in (BRAKE_ID, STATUS_ID)]
    res.figures["brake_frames_good"] = sent.good
    res.figures["status_frames_good"] = sent.status_good
    res.figures["frames_read_after_a_later_one"] = (
        f"{swapped}, by up to {ms(most)} ms" if swapped else 0)
    kinds: dict[str, int] = {}
    for iss in sent.issues:
        kinds[iss.kind] = kinds.get(iss.kind, 0) + 1
    res.figures["issues"] = kinds
    lossy = ("jump", "resync")  # frames lost: allowed only in provoked disturbances
    hard = [i for i in sent.issues if i.kind not in lossy]
    for i in hard[:5]:
        res.notes.append(f"{i.kind} at {i.ts:.6f} id {i.can_id:#05x}: {i.detail}")
    res.check(not hard, f"{len(hard)} frames failed CRC/length/counter/content checks")
    gaps = []
    excuses: list[str] = []
    stall_wins: list[tuple[float, float]] = []  # gaps the environment's stalls explain
    stalls = run.stalls()
    brake = [f for f in frames if f.can_id == BRAKE_ID]
    for a, b in zip(brake, brake[1:], strict=False):
        if in_windows(a.ts, wins) or in_windows(b.ts, wins):
            continue
        if b.ts - a.ts >= BRAKE_SILENCE_S:
            stall = excused(a.ts, b.ts, stalls)
            if stall is not None:
                excuses.append(f"{ms(b.ts - a.ts)} ms gap at {a.ts:.3f}: a CPU stood still or "
                               f"the daemon queued {ms(stall)} ms of it")
                stall_wins.append((a.ts, b.ts))  # the trip it caused is excused as well
                continue
        gaps.append((b.ts - a.ts) * 1000)
    # A counter that starts over after such a gap (resync) is its consequence, not a lost
    # frame; an ESTOP_STATUS one after a 200 ms gap likewise when the stalls explain that gap
    # (at most 2.5 of its periods left to run). A jump (a frame missing) is never excused.
    resyncs_excused = 0
    jumps = []
    for i in sent.issues:
        if i.kind in lossy and not in_windows(i.ts, wins):
            prev = max((f.ts for f in frames if f.can_id == i.can_id and f.ts < i.ts),
                       default=None) if i.kind == "resync" else None
            if prev is not None and (in_windows(i.ts, stall_wins) or excused(
                    prev, i.ts, stalls, 2.5 * (0.1 if i.can_id == STATUS_ID else 0.01))):
                resyncs_excused += 1
                continue
            jumps.append(i)
    if resyncs_excused:
        res.figures["resyncs_after_gaps_excused_by_cpu_stalls"] = resyncs_excused
    for i in jumps[:3]:
        res.notes.append(f"{i.kind} at {i.ts:.6f} id {i.can_id:#05x}: {i.detail}")
    res.check(not jumps, f"{len(jumps)} counter jumps (lost frames) outside disturbances")
    wins += stall_wins
    res.figures["brake_gap_ms_outside_disturbances"] = summary(gaps)
    long_stalls = [b - a for a, b in stalls if b - a >= 0.010]
    res.figures["cpu_stalls_10ms_or_more"] = (
        f"{len(long_stalls)}, max {ms(max(long_stalls))} ms" if long_stalls else 0)
    waits = run.stallmon.waits() if run.stallmon else []
    if run.stallmon is not None and run.stallmon.wait_path is not None:
        long_waits = [b - a for a, b in waits if b - a >= 0.010]
        res.figures["daemon_run_queue_waits_10ms_or_more"] = (
            f"{len(long_waits)}, max {ms(max(long_waits))} ms" if long_waits else 0)
    res.figures["stall_monitor_realtime"] = run.stallmon.realtime() if run.stallmon else None
    res.figures["bus_monitor_max_lag_ms"] = ms(run.mon.max_lag)
    res.figures["cpu_s"] = run.cpu
    if excuses:
        res.figures["gaps_excused_by_cpu_stalls"] = excuses[:5]
    res.check(bool(gaps) and max(gaps) < BRAKE_SILENCE_S * 1000,
              "an ESTOP_BRAKE gap outside the provoked disturbances reached 50 ms")
    # A silence is expected when its deadline (last good frame + 50 ms) falls in a provoked
    # disturbance (link down, full queue, kill, exit).
    trips = [t for t in ctl.trips if not in_windows(t.deadline, wins)]
    for t in trips[:3]:
        res.notes.append(f"silence after the frame at {t.last_good:.6f}")
    res.figures["emulator_trips"] = len(ctl.trips)
    res.figures["emulator_trips_unexpected"] = len(trips)
    res.check(not trips, f"{len(trips)} spurious brake-controller timeouts")
    # The live emulator (real time) and a replay of the bus record (kernel timestamps) must
    # agree; the end of the run is left out (the live one may not have looked yet).
    # Where no frame was read out of its send order, that is the replay above (the marker
    # frames change nothing in a replay); a whole run's replay takes seconds to tens of seconds
    # under TCG, so it is made again only where the order read differed.
    off = sent if not swapped else replay(run.mon.frames, end=cut)
    n_live = sum(1 for t in ctl.trips if t.deadline < cut)
    n_off = sum(1 for t in off.trips if t.deadline < cut)
    res.figures["offline_replay_trips"] = n_off
    res.check(n_off == n_live, f"live emulator tripped {n_live}x, replay of the bus {n_off}x")
    # ... and graded the same: every command a frame gave, at the frame's time.
    live_cmds = frame_commands(ctl.changes, t1=cut)
    off_cmds = frame_commands(off.changes, t1=cut)
    res.figures["emulator_commands"] = share_counts(live_cmds)
    res.check(live_cmds == off_cmds, "live emulator and the replay graded differently: "
                                     f"{first_difference(live_cmds, off_cmds)}")
    res.figures["disturbance_windows"] = [w[2] for w in run.windows]


def share_counts(cmds: list[tuple[float, float]]) -> dict[str, int]:
    """Commands by grade (``release``, ``controlled 30 %``, ``EMERGENCY``), counted."""
    out: dict[str, int] = {}
    for _, share in cmds:
        out[grade_text(share)] = out.get(grade_text(share), 0) + 1
    return out


def first_difference(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> str:
    for i, (x, y) in enumerate(zip(a, b, strict=False)):
        if x != y:
            return f"command {i}: live {x}, replay {y}"
    return f"{len(a)} commands live, {len(b)} in the replay"


def check_candump(run: Run, res: Result) -> None:
    assert run.candump is not None
    path = run.candump.path
    cd, bad = read_candump(path.read_text(errors="replace").splitlines())
    py = list(run.mon.frames)
    window = None
    if len(run.markers) == 2:
        window = (run.markers[0].ts, run.markers[1].ts)
    cc = crosscheck(cd, py, window)
    res.figures.update(cc.figures())
    res.figures["unparsed_lines"] = len(bad)
    res.figures["candump_rc"] = run.candump.proc.returncode
    res.figures["between_markers"] = window is not None
    for fa in cc.only_candump[:3]:
        res.notes.append(f"only candump: {fa.ts:.6f} {fa.can_id:03X}#{fa.data.hex()}")
    for fb in cc.only_pycan[:3]:
        res.notes.append(f"only python-can: {fb.ts:.6f} {fb.can_id:03X}#{fb.data.hex()}")
    res.check(window is not None, "start/stop marker frames missing")
    res.check(cc.ok, "candump and python-can disagree")
    res.check(not bad, f"{len(bad)} candump lines could not be parsed")
    err = run.candump.stderr_text().strip()
    if err:
        res.figures["candump_stderr"] = " | ".join(err.splitlines()[:3])
    res.figures["markers"] = MARKER_ID
    # The graded commands (SLOWING's brake_request 2 among them) are in both records alike.
    if window is not None:
        in_cd = brake_requests(cd, window)
        in_py = brake_requests(py, window)
        res.figures["brake_requests"] = in_cd
        res.check(in_cd == in_py, f"ESTOP_BRAKE brake_requests: candump {in_cd}, python-can "
                                  f"{in_py}")


def brake_requests(frames: list[Frame], window: tuple[float, float]) -> dict[str, int]:
    """ESTOP_BRAKE frames in ``window`` by brake_request (byte 0) name, counted."""
    out: dict[str, int] = {}
    for f in frames:
        if f.can_id == BRAKE_ID and window[0] <= f.ts <= window[1] and f.data:
            name = brake_request_name(f.data[0])
            out[name] = out.get(name, 0) + 1
    return dict(sorted(out.items()))


def check_logs(run: Run, res: Result) -> None:
    total = 0
    bad: list[str] = []
    missing: list[str] = []
    for d in run.daemons:
        total += len(d.lines)
        bad += d.non_json()
        for r in d.events():
            if not isinstance(r.get("t_mono"), int | float) or not isinstance(r.get("event"), str):
                missing.append(json.dumps(r)[:120])
            elif r["event"] == "state" and not all(k in r for k in ("from", "to", "reason",
                                                                   "src", "cause")):
                missing.append(json.dumps(r)[:120])
    res.figures["log_lines"] = total
    res.figures["non_json_lines"] = len(bad)
    res.figures["incomplete_records"] = len(missing)
    for line in (bad + missing)[:3]:
        res.notes.append(f"log: {line[:120]}")
    res.check(total > 0, "the daemon logged nothing")
    res.check(not bad, "log lines that are not JSON objects")
    res.check(not missing, "records without t_mono/event (or state without "
                           "from/to/reason/src/cause)")
    starts = sum(len(d.events("start")) for d in run.daemons)
    res.figures["start_events"] = f"{starts}/{len(run.daemons)}"
    # Every state change seen on the bus has a 'state' log line (per daemon instance), kind
    # by kind (SLOWING's among them), and every line's cause fits its change.
    bus: Counter[str] = Counter()
    logged: Counter[str] = Counter()
    wrong: list[str] = []
    for i, d in enumerate(run.daemons):
        t0 = d.t_start
        t1 = run.daemons[i + 1].t_start if i + 1 < len(run.daemons) else time.time()
        if d.signal_time is not None:  # the last frame after SIGTERM is not a state change
            t1 = min(t1, d.signal_time)
        bus += bus_transitions(run.mon.window(t0, t1))
        # Which lines came before the signal is judged on the daemon's own clock: the
        # harness may read a line written before the signal only after it.
        lines = log_changes(r for r in d.events("state") if d.signal_mono is None
                            or float(r.get("t_mono", 0.0)) < d.signal_mono)
        logged += Counter(f"{c.frm}->{c.to}" for c in lines)
        wrong += [w for w in map(cause_problem, log_changes(d.events("state"))) if w]
    res.figures["state_changes_bus"] = dict(sorted(bus.items()))
    res.figures["state_changes_log"] = dict(sorted(logged.items()))
    res.check(bus == logged, f"{sum(bus.values())} state changes on the bus, "
                             f"{sum(logged.values())} 'state' log lines: {dict(bus - logged)} "
                             f"not logged, {dict(logged - bus)} not on the bus")
    res.figures["causes_wrong"] = len(wrong)
    for w in wrong[:3]:
        res.notes.append(f"log: {w}")
    res.check(not wrong, f"{len(wrong)} state lines whose cause does not fit the change")


GLOBAL: list[Row] = [
    ("bus_integrity", "Whole run: frame checks, gaps, emulator",
     "0 CRC/counter/content errors; no gap >= 50 ms and no lost frames outside the provoked "
     "disturbances; live and offline emulator agree (trips, and every graded command)",
     check_bus),
    ("candump_crosscheck", "candump -L vs python-can",
     "same frames, same timestamps, in the same order CAN ID by CAN ID, between the start and "
     "stop markers (so the same brake_requests, controlled stops too)",
     check_candump),
    ("log_format", "estopd --log-json lines",
     "every line a JSON object with t_mono/event; one state line per state change on the bus, "
     "kind by kind (SLOWING's too); every state line's cause fits its change",
     check_logs),
]

