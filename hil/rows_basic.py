"""The basic rows: boot, RELEASE refused and accepted, the dead-man timeout, TCP STOP."""

from __future__ import annotations

import signal
import time

from estop.protocol.can import BRAKE_ID, STATUS_ID, BrakeFrame, StatusFrame
from hilclients import DRIVE_GAS, NEUTRAL
from hilemu import BRAKE_SILENCE_S, Frame
from hiljudge import (
    apply_gaps,
    judge,
    judge_rolls,
    judge_sched,
    judge_spoiled,
    last_packet,
    link_died_first,
    no_armed_frame,
)
from hilroll import MODEL_TEXT, Roll, roll, single_stage_distance
from hilrun import EARLY_TOL_MS, TIMEOUT_MS, WARN_MS, Result, Row, Run, ms
from hilstalls import judge_gaps, periods
from hilstats import summary

# Boot: the periods are those of the grid fitted under the frames (hilstalls.periods,
# grid_period); the daemon is watched for at least 1 s, longer (up to
# BOOT_WATCH_MAX_S) until the fit rests on this many gaps.
BOOT_MIN_BRAKE_GAPS = 20
BOOT_MIN_STATUS_GAPS = 3
BOOT_WATCH_MAX_S = 4.0


def judge_boot_frames(res: Result, frames: list[Frame], stalls: list[tuple[float, float]],
                      watched_s: float) -> None:
    """The boot row's verdict on the frames watched after the first one: the grid periods, no
    ESTOP_BRAKE gap of 50 ms, the first STATUS counter, every frame's checks."""
    brake_ts = [f.ts for f in frames if f.can_id == BRAKE_ID]
    bp = periods(brake_ts, stalls, 0.010)
    sp = periods([f.ts for f in frames if f.can_id == STATUS_ID], stalls, 0.100)
    gaps = [g * 1000 for g in bp.gaps]
    res.figures["watched_s"] = watched_s
    res.figures["brake_period_ms"] = summary(gaps)
    res.figures["status_period_ms"] = summary([g * 1000 for g in sp.gaps])
    res.samples_ms["brake period"] = gaps
    for name, pr, nominal, tol, least in (("ESTOP_BRAKE", bp, 10.0, 0.5, BOOT_MIN_BRAKE_GAPS),
                                          ("ESTOP_STATUS", sp, 100.0, 5.0,
                                           BOOT_MIN_STATUS_GAPS)):
        key = "brake" if name == "ESTOP_BRAKE" else "status"
        mean = pr.mean_judged
        res.figures[f"{key}_period_stall_free"] = {
            "n": len(pr.judged), "stretches": pr.stretches,
            "mean": None if mean is None else round(mean * 1000, 3)}
        res.figures[f"{key}_gaps_left_out"] = pr.left_out_text()
        # Judged: the grid's period (hilstalls.grid_period), not the stretches' mean gap,
        # which a first frame delayed unseen shortens (9.22 ms in a TCG run, grid 10.01 ms).
        res.figures[f"{key}_grid_period"] = {
            "gaps": pr.grid_gaps, "ms": None if pr.grid is None else round(pr.grid * 1000, 3)}
        if pr.grid is None or pr.grid_gaps < least:
            res.inconclusive = (f"{name}: only {pr.grid_gaps} gaps in runs of 3 frames "
                                f"in {res.figures['watched_s']} s")
            res.check(False, f"{name} period not judged: {pr.grid_gaps} < {least} gaps "
                             "in runs of 3 frames")
        else:
            res.check(abs(pr.grid * 1000 - nominal) <= tol,
                      f"{name} grid period {round(pr.grid * 1000, 3)} ms (fitted under the "
                      f"frames) not {nominal:g} +- {tol:g} ms")
    # Spec section 4: no gap of 50 ms at all. One that the CPU stalls explain is not a pass
    # either: the row is inconclusive and boots the daemon once more; the second boot decides
    # (a fresh-machine run of a87f13b failed here on gaps of 65.8 and 54.0 ms inside vCPU
    # stalls of 65.8 and 54.0 ms, the grid 10.014 ms: tests/harness/test_hil_gaps.py).
    res.check(bool(gaps), "no ESTOP_BRAKE gap to judge")
    apply_gaps(res, judge_gaps(brake_ts, stalls, BRAKE_SILENCE_S))
    status = [f for f in frames if f.can_id == STATUS_ID]
    res.check(bool(status) and status[0].data[6] & 0x0F == 0,
              "first ESTOP_STATUS counter is not 0")
    bad = [f for f in frames if f.can_id in (BRAKE_ID, STATUS_ID)
           and (BrakeFrame if f.can_id == BRAKE_ID else StatusFrame).check(f.data)]
    res.check(not bad, f"{len(bad)} frames fail the CRC/counter/content checks")


def sc_boot(run: Run, res: Result) -> None:
    t_again = None
    if run.daemons and run.daemon.alive:  # a second try: a fresh boot again
        t_again = time.time()
        run.daemon.signal(signal.SIGTERM)
        if run.daemon.wait(3.0) is None:
            run.daemon.kill_hard()
    t0 = time.time()
    d, first = run.start_daemon()
    if t_again is not None:
        run.windows.append((t_again - 0.01, first.ts + 0.1, "boot once more"))
    b = BrakeFrame.parse(first.data)
    res.figures["first_frame"] = first.data.hex(" ")
    res.figures["exec_to_first_frame_ms"] = ms(first.ts - t0)
    res.check(first.data == bytes.fromhex("016400010000009C"),
              f"first ESTOP_BRAKE {first.data.hex(' ')} is not the boot frame "
              "01 64 00 01 00 00 00 9c (STOPPED, boot, counter 0)")
    res.check(b.brakes, "first frame does not request the brake")
    judge_sched(run, res, d)
    ex = run.clients[0].status()
    res.figures["status_reply"] = f"ack={ex.reply.ack} state={ex.reply.state} " \
                                  f"reason={ex.reply.reason}"
    res.check(ex.reply.ack and ex.reply.state == 0 and ex.reply.reason == 1,
              "STATUS does not answer ACK STOPPED boot")
    # The periods are the grid's, fitted under the frames (hilstalls.periods): watch for
    # 1 s, and on (at most BOOT_WATCH_MAX_S) until the fit rests on enough gaps.
    end = first.ts + 1.0
    while True:
        time.sleep(max(0.0, end + 0.02 - time.time()))
        run.mon.sync()
        frames = run.mon.window(first.ts, end)
        stalls = run.stalls()
        bp = periods([f.ts for f in frames if f.can_id == BRAKE_ID], stalls, 0.010)
        sp = periods([f.ts for f in frames if f.can_id == STATUS_ID], stalls, 0.100)
        if (bp.grid_gaps >= BOOT_MIN_BRAKE_GAPS and sp.grid_gaps >= BOOT_MIN_STATUS_GAPS) \
                or end - first.ts >= BOOT_WATCH_MAX_S - 1e-6:
            break
        end += 1.0
    judge_boot_frames(res, frames, stalls, round(end - first.ts, 1))
    res.check(d.alive, "daemon exited")


def sc_nak2(run: Run, res: Result) -> None:
    start = run.mon.index()
    ex = run.clients[1].release()
    res.figures["no_packets"] = f"ack={ex.reply.ack} nak={ex.reply.nak_code}"
    res.check(not ex.reply.ack and ex.reply.nak_code == 2,
              "RELEASE with no control packets ever: not NAK 2")
    for _ in range(3):
        run.udp.send(NEUTRAL)
        time.sleep(0.02)
    ex2 = run.clients[1].release()
    res.figures["3_packets"] = f"ack={ex2.reply.ack} nak={ex2.reply.nak_code}"
    res.check(not ex2.reply.ack and ex2.reply.nak_code == 2,
              "RELEASE after only 3 valid packets (5 needed): not NAK 2")
    time.sleep(0.1)
    no_armed_frame(run, res, start)
    res.check(ex.reply.state == 0 and ex2.reply.state == 0, "reply state not STOPPED")


def sc_nak3(run: Run, res: Result) -> None:
    start = run.mon.index()
    t0 = time.time()
    run.udp.start(DRIVE_GAS)
    run.wait_packets(run.udp, t0)
    ex = run.clients[2].release()
    run.udp.stop()
    res.figures["gas_0.3"] = f"ack={ex.reply.ack} nak={ex.reply.nak_code}"
    res.check(not ex.reply.ack and ex.reply.nak_code == 3,
              "RELEASE with gas 0.3 in the latest packet: not NAK 3")
    time.sleep(0.05)
    no_armed_frame(run, res, start)
    time.sleep(0.25)  # let the link die before the next scenario


def sc_release(run: Run, res: Result) -> None:
    d = run.daemon
    since = time.time()
    t_send, fr = run.arm(res, client=3)
    judge(run, res, "release_to_armed_frame_ms", "release -> ARMED frame", [(t_send, fr.ts)],
          use_median=False)
    b = BrakeFrame.parse(fr.data)
    res.figures["armed_frame"] = fr.data.hex(" ")
    res.check(not b.brakes and b.brake_level == 0 and b.reason == 0,
              "ARMED frame does not release the brake")
    ev = d.wait_event(lambda r: r.get("event") == "state" and r.get("to") == "ARMED", since, 1.0)
    res.figures["log_state_event"] = None if ev is None else \
        f"{ev.get('from')}->{ev.get('to')} reason={ev.get('reason')} src={ev.get('src')}"
    res.check(ev is not None and ev.get("from") == "STOPPED",
              "no log line 'state STOPPED->ARMED'")
    ex = run.clients[0].release()
    res.check(ex.reply.ack and ex.reply.state == 1, "RELEASE while ARMED: not ACK ARMED")
    time.sleep(0.1)
    run.mon.sync()
    res.check(run.mon.ctl.braking is False, "brake controller emulator still braking")
    run.udp.stop()
    time.sleep(0.3)


def sc_deadman(run: Run, res: Result) -> None:
    over: list[tuple[float, float]] = []
    flag: list[tuple[float, float]] = []
    phase: list[float] = []
    rolls: list[Roll] = []
    spoiled = 0
    for i in range(run.args.repeat):
        run.arm(res)
        time.sleep(0.1)
        start = run.mon.index()
        t_last = last_packet(run, res, run.udp, i)
        if t_last is None:
            spoiled += 1
            time.sleep(0.3)
            continue
        tick = run.brake_after(start, lambda b: b.state == 1, 0.1)
        if tick is not None:
            phase.append(ms(t_last - tick[0].ts))
        # Stamped after the last packet: the bus monitor may still be reading frames of the
        # sample before (a local run under load: a degraded flag 2.2 s "before its time").
        got = run.brake_after(start, lambda b: b.state == 0, 1.0, after=t_last)
        if got is None:
            res.check(False, f"run {i}: no STOPPED frame within 1 s of the last packet")
            continue
        fr, b = got
        res.check(b.reason == 3, f"run {i}: stop reason {b.reason}, want 3 udp timeout")
        over.append((t_last + TIMEOUT_MS / 1000, fr.ts))
        rolls.append(roll(run.mon.window(t_last - 1.0, fr.ts + 0.05), t_last))
        frames = run.mon.since(start)
        degraded = [f for f in frames if f.can_id == BRAKE_ID and f.data[2] == 1
                    and f.data[4] & 1 and t_last < f.ts < fr.ts]
        if degraded:
            flag.append((t_last + WARN_MS / 1000, degraded[0].ts))
        else:
            res.check(False, f"run {i}: no ARMED frame with the link-degraded flag before "
                             "the stop")
        if i == 0:  # a STOP while stopped keeps the first reason
            ex = run.clients[1].stop()
            res.check(ex.reply.ack and ex.reply.reason == 3,
                      "STOP after a udp timeout: reply is not ACK with reason udp_timeout")
            time.sleep(0.03)
            b2 = run.brake_after(run.mon.index() - 1, lambda _b: True, 0.5)
            res.check(b2 is not None and b2[1].reason == 3,
                      "STOP after a udp timeout changed the reason on the bus")
    judge(run, res, "overshoot_ms", "dead-man overshoot", over)
    # The flag may wait for the next periodic frame: up to 10 ms after the warn time.
    judge(run, res, "degraded_flag_after_warn_ms", "degraded flag after warn time", flag,
          use_median=False, slack_ms=10.0)
    res.figures["last_packet_after_tick_ms"] = summary(phase)
    # Without a lift the car rolls the whole timeout before braking even starts.
    judge_rolls(res, "distance_from_last_packet_m", "dead-man (T 200 ms), from the last packet",
                rolls, single_stage_distance(TIMEOUT_MS / 1000), "full braking at T")
    res.figures["car"] = MODEL_TEXT
    judge_spoiled(res, spoiled, run.args.repeat, len(over), "not every run stopped",
                  keepalive=False)


def sc_tcp_stop(run: Run, res: Result) -> None:
    lat: list[tuple[float, float]] = []
    rep: list[float] = []
    spoiled = 0
    n = run.args.repeat + 4
    for i in range(n):
        t_arm = time.time()
        run.arm(res)
        time.sleep(0.05)
        k = i % len(run.clients)
        start = run.mon.index()
        ex = run.clients[k].stop()
        got = run.brake_after(start, lambda b: b.state == 0, 1.0, after=ex.t_send)
        run.udp.stop()
        if link_died_first(run.udp, t_arm, ex.t_send, ex.reply.reason):
            spoiled += 1  # the harness let the link die before its STOP: not a sample
            continue
        res.check(ex.reply.ack and ex.reply.state == 0 and ex.reply.reason == 2,
                  f"run {i} (client {k}): reply not ACK STOPPED tcp_stop: {ex.reply}")
        rep.append(ms(ex.t_reply - ex.t_send))
        if got is None:
            res.check(False, f"run {i}: no STOPPED frame within 1 s of the STOP")
            continue
        fr, b = got
        res.check(b.reason == 2, f"run {i}: bus reason {b.reason}, want 2 tcp stop")
        lat.append((ex.t_send, fr.ts))
    judge(run, res, "stop_frame_latency_ms", "TCP STOP -> stop frame", lat)
    res.samples_ms["TCP STOP -> reply"] = rep
    res.figures["reply_latency_ms"] = summary(rep)
    res.figures["clients"] = len(run.clients)
    judge_spoiled(res, spoiled, n, len(lat), "not every STOP showed on the bus", keepalive=True)
    time.sleep(0.25)


ROWS: list[Row] = [
    ("boot", "Boot: first frame, periods, STATUS",
     "boot frame 01 64 00 01 00 00 00 9c; STATUS ACK STOPPED boot; grid periods fitted under "
     f"the frames (>= {BOOT_MIN_BRAKE_GAPS} / {BOOT_MIN_STATUS_GAPS} gaps): "
     "ESTOP_BRAKE 10+-0.5 "
     "ms, ESTOP_STATUS 100+-5 ms; no ESTOP_BRAKE gap >= 50 ms at all", sc_boot),
    ("nak2", "RELEASE refused, no live link",
     "NAK 2 with no packets and with 3 (<5) packets; no ARMED frame", sc_nak2),
    ("nak3", "RELEASE refused, not neutral",
     "NAK 3 with gas 0.3; no ARMED frame", sc_nak3),
    ("release", "RELEASE accepted",
     "ACK ARMED, ARMED frame <= {max} ms, log STOPPED->ARMED", sc_release),
    ("deadman", "Dead-man timeout (200 ms)",
     f"reason udp_timeout; overshoot >= -{EARLY_TOL_MS}, " "p50 <= {p50}, max <= {max} ms; "
     "degraded flag >= 100 ms after the last packet, <= 110 + {max} ms; the car's roll-out "
     "from the last packet", sc_deadman),
    ("tcp_stop", "TCP STOP latency (4 clients)",
     "ACK STOPPED tcp_stop; stop frame p50 <= {p50}, max <= {max} ms",
     sc_tcp_stop),
]
