"""The fault rows: an invalid-UDP flood, the CAN link down, a full transmit queue, the daemon
killed, restarted, terminated.
"""

from __future__ import annotations

import signal
import threading
import time

import can

from estop.protocol.can import BRAKE_ID, STATUS_ID, BrakeFrame
from hilclients import NEUTRAL
from hilemu import BRAKE_SILENCE_S, replay
from hiljudge import frame_gap_check, judge, judge_frames, judge_late, show_ex, windows_in
from hilload import Flooder, QueueWatch, udp_drops
from hilrig import RigError, iface_stats, set_link, sh
from hilrun import FLOOD_RATE, RECOVERY_S, TIMEOUT_MS, Result, Row, Run, ms
from hilstalls import judge_drops, overlap
from hilstats import sent_between

# The invalid-UDP flood (its target rate is hilrun.FLOOD_RATE; the least rate that counts as
# a flood is the timing profile's, Limits.flood): how long it lasts, and the exactly counted
# burst before it.
FLOOD_S = 0.7
FLOOD_BURST = 120
DRAIN_MAX_S = 10.0  # after the flood's checks, the daemon has read its receive queue empty


def sc_invalid_flood(run: Run, res: Result) -> None:
    """Invalid UDP from a flooder process of its own (flood.py, sendmmsg) after the last valid
    packet: first an exactly counted burst (ESTOP_STATUS must count every packet of it), then
    a flood of Limits.flood packets/s or more across the deadline. The stop must come at the
    deadline all the same. The daemon's receive buffer (8 MiB, its start line's udp_rcvbuf) has
    room for the whole flood, so the kernel must drop nothing (/proc/net/udp): a drop while a
    CPU stood still is inconclusive (the daemon may not have run), never a pass."""
    d = run.daemon
    starts = d.events("start")
    res.figures["udp_rcvbuf"] = starts[0].get("udp_rcvbuf") if starts else None
    if run.flooder is None or run.flooder.proc.poll() is not None:
        run.flooder = Flooder(run.udp_port, FLOOD_RATE)
    fl = run.flooder
    watch: QueueWatch | None = None
    try:
        t_up = fl.ready(60.0)
        res.figures["flooder_up_s"] = round(t_up - fl.t_start, 2)
        run.arm(res)
        time.sleep(0.1)
        # 1. The burst, while the keepalive still holds the link: counted exactly (no window
        #    can saturate: fewer than 255 packets in all).
        drops0 = udp_drops(run.udp_port)
        burst = fl.burst(FLOOD_BURST)
        time.sleep(0.25)  # two ESTOP_STATUS frames after it
        drops1 = udp_drops(run.udp_port)
        bw = windows_in(run, burst["t0"], time.time())
        counted = sum(w.invalid for w in bw)
        lost = (drops1[1] - drops0[1]) if drops0 and drops1 else None
        res.figures["burst"] = {"sent": burst["sent"], "counted": counted, "kernel_drops": lost,
                                "windows": [w.invalid for w in bw]}
        res.check(burst["sent"] == FLOOD_BURST, f"the flooder sent {burst['sent']} of the "
                                                f"{FLOOD_BURST} burst packets")
        res.check(lost is not None, "no daemon socket in /proc/net/udp")
        res.check(lost == 0, f"the kernel dropped {lost} of a burst of {burst['sent']}")
        res.check(counted + (lost or 0) == burst["sent"],
                  f"ESTOP_STATUS counted {counted} of a burst of {burst['sent']} invalid packets "
                  f"({lost} dropped by the kernel)")
        # 2. The flood, from just after the last valid packet until well after the deadline.
        start = run.mon.index()
        t_last = run.udp.stop()
        assert t_last is not None
        fl.start()
        watch = QueueWatch(run.udp_port)
        got = run.brake_after(start, lambda b: b.state == 0, 1.0, after=t_last)
        time.sleep(0.05)
        ex = run.clients[0].release()  # only invalid packets arrive: no live link
        time.sleep(max(0.0, t_last + FLOOD_S - time.time()))
        flood = fl.stop()
        drops2 = udp_drops(run.udp_port)
    except RigError:
        fl.close()  # in an unknown state: a new one for a second try
        raise
    finally:
        rxq_max = watch.stop() if watch is not None else None
    time.sleep(0.25)  # the ESTOP_STATUS frames that count the flood's tail
    t0, t1, sent = flood["t0"], flood["t1"], flood["sent"]
    rate = sent / max(t1 - t0, 1e-6)
    dropped = (drops2[1] - drops1[1]) if drops1 and drops2 else None
    figs: dict[str, object] = {"sent": sent, "s": round(t1 - t0, 3), "rate_per_s": round(rate),
                               "kernel_drops": dropped, "send_errors": flood["errors"],
                               "started_after_last_valid_ms": ms(t0 - t_last)}
    if dropped is not None:
        figs["handled_per_s"] = round((sent - dropped) / max(t1 - t0, 1e-6))
    res.figures["flood"] = figs
    rcvbuf = res.figures["udp_rcvbuf"]
    res.figures["rx_queue_max"] = {"bytes": rxq_max, "reads": watch.reads if watch else 0} | (
        {"of_rcvbuf_pct": round(100 * rxq_max / rcvbuf, 2)}
        if isinstance(rcvbuf, int) and rcvbuf > 0 and rxq_max is not None else {})
    drops = judge_drops(dropped, overlap(run.stalls(), t0, t1), f"the flood (receive buffer "
                                                                 f"{rcvbuf} bytes)")
    for f in drops.fails:
        res.check(False, f)
    if drops.inconclusive:
        res.inconclusive = drops.inconclusive
    if rate < run.lim.flood:
        res.inconclusive = f"the flooder reached {round(rate)} packets/s only"
        res.check(False, f"not judged: not a flood: {round(rate)} < {run.lim.flood} packets/s")
    if t0 > t_last + TIMEOUT_MS / 2000:
        res.inconclusive = f"the flood began {ms(t0 - t_last)} ms after the last valid packet"
        res.check(False, "not judged: the flood began after half the timeout")
    if got is None:
        res.check(False, "still ARMED 1 s after the last valid packet (flood keeps it alive)")
    else:
        fr, b = got
        judge(run, res, "overshoot_ms", "overshoot under invalid flood",
              [(t_last + TIMEOUT_MS / 1000, fr.ts)], use_median=False)
        res.check(b.reason == 3, f"stop reason {b.reason}, want 3 udp timeout")
    res.figures["release_during_flood"] = show_ex(ex)
    res.check(not ex.reply.ack and ex.reply.nak_code == 2,
              "RELEASE while only invalid packets arrive: not NAK 2")
    # 3. ESTOP_STATUS during the flood: every window wholly inside it in which 255 or more
    #    were sent is saturated (255; at 10000/s a window gets 1000), none counts an
    #    authentication failure (no key), and in all it never counts more than was sent.
    fw = windows_in(run, t0, t1 + 0.25)
    inside = [w for w in fw if w.start >= t0 and w.end <= t1]
    res.figures["status_invalid_per_window"] = [w.invalid for w in fw]
    sent_in = [sent_between(flood["series"], w.start, w.end)[0] for w in inside]
    res.figures["sent_per_window_inside"] = sent_in
    res.check(len(inside) >= 3, f"only {len(inside)} ESTOP_STATUS windows inside the flood")
    # A window must saturate where the flooder sent at least 255 in it. One where it sent fewer
    # (held back by the CPU: a TCG guest's flood is uneven) is not judged: a run of 2026-12-03
    # at 4,625 packets/s failed on a window that counted 208 of it.
    low = [w.invalid for w, n in zip(inside, sent_in, strict=True) if w.invalid < 255 <= n]
    res.check(not low, f"ESTOP_STATUS windows inside the flood below saturation: {low}")
    judged = sum(1 for n in sent_in if n >= 255)
    if judged < len(inside):
        res.figures["windows_not_judged_fewer_than_255_sent"] = len(inside) - judged
    if inside and not judged:
        res.inconclusive = "no ESTOP_STATUS window of the flood had 255 packets sent in it"
        res.check(False, f"not judged: {res.inconclusive}")
    res.check(all(w.auth_failures == 0 for w in fw),
              "ESTOP_STATUS counted authentication failures on a unit without a key")
    res.check(sum(w.invalid for w in fw) <= sent, "ESTOP_STATUS counted more than was sent")
    frame_gap_check(run, res, "brake_max_gap_during_flood_ms", t0 - 0.02, t1 + 0.05)
    # The next rows need the control socket read up to date: a daemon that could not keep up
    # with the flood still holds its backlog (the stand-in does, for a second or two).
    waited, left = drained(run.udp_port, DRAIN_MAX_S)
    res.figures["waited_for_empty_receive_queue_ms"] = ms(waited)
    res.check(left == 0, f"the daemon's receive queue still held {left} bytes "
                         f"{DRAIN_MAX_S:g} s after the checks of the flood")
    res.check(d.alive, "daemon exited")


def drained(port: int, limit_s: float) -> tuple[float, int | None]:
    """Wait (at most ``limit_s``) until the daemon's UDP receive queue is empty; returns how
    long that took and the bytes still queued (0: empty; None: no socket)."""
    t0 = time.monotonic()
    while True:
        got = udp_drops(port)
        if got is None or got[0] == 0 or time.monotonic() - t0 >= limit_s:
            return time.monotonic() - t0, None if got is None else got[0]
        time.sleep(0.01)


def sc_iface_down(run: Run, res: Result) -> None:
    d = run.daemon
    run.arm(res)  # keepalive stays on: only a fault can stop it
    time.sleep(0.1)
    since = time.time()
    t_down, _ = set_link(run.iface, up=False)
    time.sleep(0.3)
    res.check(d.alive, "daemon exited while the link was down")
    start = run.mon.index()
    t_up0, t_up = set_link(run.iface, up=True)
    first = run.brake_after(start, lambda _b: True, 1.0, after=t_down)
    time.sleep(0.3)
    run.keepalive_held(res, since, t_up)
    run.windows.append((t_down - 0.01, (first[0].ts if first else t_up) + RECOVERY_S,
                        "link down"))
    ev = d.events(since=since)
    errs = [r for r in ev if r.get("event") in ("can_error", "fault")]
    res.figures["log_events_while_down"] = sorted({str(r.get("event")) for r in errs})
    res.check(bool(errs), "no can_error/fault log event while the link was down")
    st = [r for r in ev if r.get("event") == "state"]
    res.figures["log_state"] = [f"{r.get('from')}->{r.get('to')} {r.get('reason')}" for r in st]
    res.check(any(r.get("to") == "STOPPED" and r.get("reason") == "fault" for r in st),
              "no log line 'state ARMED->STOPPED reason=fault'")
    if first is None:
        res.check(False, "no ESTOP_BRAKE frame within 1 s after the link came up")
    else:
        fr, b = first
        res.figures["up_to_first_frame_ms"] = ms(fr.ts - t_up0)
        res.figures["first_frame_after_up"] = fr.data.hex(" ")
        judge_late(run, res, "up_done_to_first_frame_ms", "first frame after link up", t_up,
                   fr.ts, 0.05)
        res.check(b.brakes and b.state == 0 and b.reason == 4,
                  "first frame after link up is not STOPPED reason fault with the brake on")
        judge_frames(run, res, "frames_in_300ms_after_up",
                     "periodic frames in the 300 ms after link up", t_up, t_up + 0.3, 20)
    run.mon.sync()
    trips = [t for t in run.mon.ctl.trips if t.detected >= t_down]
    res.figures["emulator_braked_after_down_ms"] = \
        ms(trips[0].detected - trips[0].last_good) if trips else None
    res.check(bool(trips), "brake controller emulator did not notice the silence")
    ex = run.clients[0].status()
    res.figures["status_reply"] = f"state={ex.reply.state} reason={ex.reply.reason}"
    res.check(ex.reply.state == 0 and ex.reply.reason == 4, "STATUS is not STOPPED fault")
    res.check(d.alive, "daemon exited")
    res.check(run.candump is not None and run.candump.proc.poll() is None,
              "candump died with the link (observer lost)")
    run.udp.stop()
    time.sleep(0.25)


def sc_txqueue_full(run: Run, res: Result) -> None:
    """vcan has no queue of its own (qdisc noqueue, txqueuelen is ignored): a tbf qdisc with a
    tiny rate and a 10-frame limit makes a real full transmit queue, which a flood of
    low-priority frames from another socket keeps full. Sends then fail with ENOBUFS, as on a
    real controller whose queue does not drain."""
    d = run.daemon
    run.arm(res)  # keepalive stays on
    time.sleep(0.1)
    since = time.time()
    stats0 = iface_stats(run.iface)
    stop = threading.Event()
    counts = {"sent": 0, "enobufs": 0, "other": 0}

    def flood() -> None:
        with can.Bus(interface="socketcan", channel=run.iface) as bus:
            msg = can.Message(arbitration_id=0x7FE, data=b"FLOODING", is_extended_id=False)
            while not stop.is_set():
                try:
                    bus.send(msg, timeout=0)
                    counts["sent"] += 1
                except can.CanError as exc:
                    key = "enobufs" if "No buffer space" in str(exc) or "105" in str(exc) \
                        else "other"
                    counts[key] += 1
                time.sleep(0.0005)

    t_qdisc = time.time()
    sh(["tc", "qdisc", "add", "dev", run.iface, "root", "tbf", "rate", "1kbit",
        "burst", "160", "limit", "160"])
    th = threading.Thread(target=flood, daemon=True)
    th.start()
    t_wait = time.monotonic() + 2.0
    while counts["enobufs"] == 0 and time.monotonic() < t_wait:
        time.sleep(0.001)
    t_full = time.time()  # the queue is full now: the flood's sends fail
    time.sleep(0.3)
    # The event loop must not be stuck in a blocking send: STATUS is answered meanwhile.
    try:
        ex_mid = run.clients[1].status()
        judge_late(run, res, "status_reply_during_full_queue_ms",
                   "STATUS reply while the queue was full (blocked event loop?)", ex_mid.t_send,
                   ex_mid.t_reply, 0.1)
    except (RigError, OSError) as exc:
        res.check(False, f"no STATUS reply while the queue was full: {exc}")
    time.sleep(0.3)
    qstat = sh(["tc", "-s", "qdisc", "show", "dev", run.iface], check=False).stdout
    stop.set()
    th.join(timeout=2)
    sh(["tc", "qdisc", "del", "dev", run.iface, "root"])
    t_clear = time.time()  # ``tc`` has returned: the queue is gone (spawning tc is slow in TCG)
    run.keepalive_held(res, since, t_clear)
    first = run.mon.wait_for(lambda f: f.can_id == BRAKE_ID and f.ts > t_clear, 0, 1.0)
    time.sleep(0.3)
    run.windows.append((t_qdisc - 0.01, (first.ts if first else t_clear) + RECOVERY_S,
                        "tx queue full"))
    stats1 = iface_stats(run.iface)
    res.figures["flood"] = dict(counts)
    res.figures["qdisc"] = " ".join(qstat.split())[:160]
    res.figures["iface_tx_dropped"] = stats1.get("tx_dropped", 0) - stats0.get("tx_dropped", 0)
    res.check(counts["enobufs"] > 0, "the flood never saw ENOBUFS: the queue was not full")
    ev = d.events(since=since)
    errs = [r for r in ev if r.get("event") in ("can_error", "fault")]
    res.figures["log_events"] = sorted({str(r.get("event")) for r in errs})
    if errs:
        res.figures["first_error_log_after_ms"] = ms(
            min(ln.t_wall for ln in d.lines if ln.rec in errs) - t_full)
    res.check(bool(errs), "no can_error/fault log event while the queue was full")
    st = [r for r in ev if r.get("event") == "state"]
    res.figures["log_state"] = [f"{r.get('from')}->{r.get('to')} {r.get('reason')}" for r in st]
    res.check(any(r.get("to") == "STOPPED" and r.get("reason") == "fault" for r in st),
              "no log line 'state ARMED->STOPPED reason=fault' (silent stop or none)")
    res.check(d.alive, "daemon crashed or exited")
    if first is None:
        res.check(False, "no ESTOP_BRAKE frame within 1 s after the queue drained")
    else:
        fr, b = first, BrakeFrame.parse(first.data)
        judge_late(run, res, "drain_to_first_frame_ms", "first frame after the drain", t_clear,
                   fr.ts, 0.05)
        res.check(b.brakes and b.state == 0 and b.reason == 4,
                  f"after the queue drained: {fr.data.hex(' ')}, want STOPPED reason fault")
        judge_frames(run, res, "frames_in_300ms_after_drain",
                     "periodic frames in the 300 ms after the drain", t_clear, t_clear + 0.3, 20)
    ex = run.clients[0].status()
    res.figures["status_reply"] = f"state={ex.reply.state} reason={ex.reply.reason}"
    res.check(ex.reply.state == 0 and ex.reply.reason == 4, "STATUS is not STOPPED fault")
    run.udp.stop()
    time.sleep(0.25)


def sc_sigkill(run: Run, res: Result) -> None:
    d = run.daemon
    run.arm(res)  # ARMED: the last frames release the brake; only the silence can brake
    time.sleep(0.2)
    t_kill = d.signal(signal.SIGKILL)
    code = d.wait(2.0)
    t_dead = time.time()  # reaped: the process is gone
    time.sleep(0.2)
    run.windows.append((t_kill - 0.01, time.time() + 3.0, "killed, restarting"))
    res.figures["exit"] = code
    res.check(code == -signal.SIGKILL, f"exit status {code}, want killed by SIGKILL")
    run.mon.sync()
    unit = [f for f in run.mon.window(t_kill - 1.0, time.time())
            if f.can_id in (BRAKE_ID, STATUS_ID)]
    brake = [f for f in unit if f.can_id == BRAKE_ID and f.ts <= t_dead]
    late = [f for f in unit if f.ts > t_dead]
    res.figures["frames_between_kill_and_reap"] = sum(1 for f in unit if t_kill < f.ts <= t_dead)
    res.figures["frames_after_exit"] = len(late)
    res.check(not late, f"{len(late)} frames from the unit after its process was gone")
    if not brake:
        res.check(False, "no ESTOP_BRAKE frame in the second before the kill")
        return
    last = brake[-1]
    res.figures["last_frame"] = last.data.hex(" ")
    res.figures["last_frame_to_kill_ms"] = ms(t_kill - last.ts)
    res.check(not BrakeFrame.check(last.data), "the last frame fails the frame checks")
    res.check(last.data[0] == 0, "unit was not ARMED before the kill (test set-up)")
    # On the bus (kernel timestamps): the brake controller brakes at last good frame + 50 ms.
    off = replay(run.mon.window(last.ts - 0.5, time.time()), end=time.time())
    trips = [t for t in off.trips if t.last_good >= last.ts - 1e-6]
    res.check(bool(trips) and trips[0].last_good == last.ts and off.braking,
              "the brake controller (replayed on the bus record) does not brake 50 ms after "
              "the last frame")
    live = [t for t in run.mon.ctl.trips if t.last_good >= last.ts - 1e-6]
    if not live:
        res.check(False, "live brake controller emulator did not brake")
    else:
        react = live[0].detected - live[0].last_good
        res.samples_ms["SIGKILL: last frame -> brake"] = [ms(react)]
        judge_late(run, res, "live_emulator_braked_after_ms",
                   "live emulator braked after the last frame", live[0].last_good,
                   live[0].detected, BRAKE_SILENCE_S + run.lim.emu / 1000)
    res.check(run.mon.ctl.braking, "brake controller emulator is not braking")
    run.udp.start(NEUTRAL)  # a live neutral link for the restart scenario


def sc_restart(run: Run, res: Result) -> None:
    if run.daemons and run.daemon.alive:
        res.check(False, "the previous daemon was still running (killed hard now)")
        run.daemon.kill_hard()
    t0 = time.time()
    d, first = run.start_daemon()
    res.figures["exec_to_first_frame_ms"] = ms(first.ts - t0)
    res.figures["first_frame"] = first.data.hex(" ")
    res.check(first.data == bytes.fromhex("016400010000009C"),
              "first frame after restart is not the boot frame (STOPPED, boot, counter 0)")
    time.sleep(0.3)  # a live neutral link all along: still STOPPED (latched)
    run.mon.sync()
    armed = [f for f in run.mon.window(first.ts, time.time())
             if f.can_id == BRAKE_ID and f.data[2] != 0]
    res.check(not armed, "left STOPPED without a RELEASE")
    ex = run.clients[0].status()
    res.figures["status_reply"] = f"state={ex.reply.state} reason={ex.reply.reason}"
    res.check(ex.reply.state == 0 and ex.reply.reason == 1, "STATUS is not STOPPED boot")
    res.check(d.alive, "daemon exited")
    run.udp.stop()


def sc_sigterm(run: Run, res: Result) -> None:
    d = run.daemon
    run.arm(res)
    time.sleep(0.1)
    t_term = d.signal(signal.SIGTERM)
    code = d.wait(2.0)
    t_exit = time.time()
    run.udp.stop()
    time.sleep(0.1)
    run.windows.append((t_term - 0.01, time.time() + 3.0, "SIGTERM, restarting"))
    res.figures["exit_code"] = code
    res.check(code == 0, f"exit code {code} after SIGTERM, want 0")
    run.mon.sync()
    frames = [f for f in run.mon.window(t_term, t_exit + 0.1) if f.can_id == BRAKE_ID]
    if not frames:
        res.check(False, "no ESTOP_BRAKE frame after SIGTERM")
    else:
        last = frames[-1]
        res.figures["last_frame"] = last.data.hex(" ")
        res.figures["sigterm_to_last_frame_ms"] = ms(last.ts - t_term)
        res.check(last.data[0] == 1, "last frame before exit does not request the brake")
        res.check(not BrakeFrame.check(last.data), "last frame fails the frame checks")
    res.figures["exit_events"] = len(d.events("exit"))


ROWS: list[Row] = [
    ("invalid_flood", "Invalid UDP flood while ARMED",
     f"a burst of {FLOOD_BURST} counted exactly; then >= " "{flood} packets/s from a "
     "flooder process: stops at last valid + 200 ms (overshoot <= {max} ms, reason "
     "udp_timeout); RELEASE NAK 2; ESTOP_STATUS windows inside the flood saturated (255) where "
     "255 were sent; "
     "no ESTOP_BRAKE gap of 50 ms; 0 kernel drops (burst and flood); daemon alive",
     sc_invalid_flood),
    ("iface_down", "CAN link down 300 ms, then up",
     "can_error/fault logged; STOPPED fault; frames resume <= 50 ms after up", sc_iface_down),
    ("txqueue_full", "Transmit queue full (tbf qdisc + flood)",
     "ENOBUFS seen; fault logged, STOPPED fault on the bus after drain; no crash; "
     "STATUS answered < 100 ms meanwhile", sc_txqueue_full),
    ("sigkill", "estopd killed (SIGKILL)",
     "no frames once the process is gone; last frame good; brake controller brakes 50 ms "
     "after the last frame (bus record); live emulator <= 50 + {emu} ms", sc_sigkill),
    ("restart", "Restart boots STOPPED",
     "boot frame first; stays STOPPED with a live neutral link; STATUS STOPPED boot",
     sc_restart),
    ("sigterm", "SIGTERM: last frame brakes",
     "last ESTOP_BRAKE frame has brake_request 1; exit code 0", sc_sigterm),
]
