"""HIL scenario runner: estopd on a real SocketCAN vcan interface, checked with python-can.

Run by ``hil/run`` (natively, or inside a virtme-ng VM); needs root and a kernel with vcan.
Writes ``results.json`` (and candump.log, estopd-*.log) into ``--out``; ``hilreport.py`` turns
that into the test protocol table and the latency plot.

Each scenario returns a :class:`Result` with pass/fail, measured figures and the criterion it
was judged by. A scenario that raises is a FAIL with the exception as its reason; the runner
goes on with the next one (restarting the daemon if it died) so that the protocol is complete.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shutil
import signal
import socket
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent / "src"))  # estop.protocol when not installed in the venv

import can  # noqa: E402

from estop.protocol.can import BRAKE_ID, STATUS_ID, BrakeFrame, StatusFrame  # noqa: E402
from hilcheck import (  # noqa: E402
    BRAKE_SILENCE_S,
    Frame,
    crosscheck,
    excused,
    frame_gaps,
    in_windows,
    overlap,
    read_candump,
    replay,
    summary,
)
from hilrig import (  # noqa: E402
    DRIVE_GAS,
    MARKER_ID,
    NEUTRAL,
    BusMonitor,
    Candump,
    Daemon,
    RigError,
    StallMonitor,
    StopClient,
    UdpRemote,
    connect_retry,
    free_port,
    iface_stats,
    set_link,
    setup_vcan,
    sh,
)

TIMEOUT_MS = 200
WARN_MS = TIMEOUT_MS / 2
EARLY_TOL_MS = 0.1  # a stop before the deadline is a failure (clock granularity only)
# After a provoked outage, lost-frame counter jumps may still show on the next ESTOP_STATUS
# frame (every 100 ms): the disturbance window ends this long after the first frame back.
RECOVERY_S = 0.15
# A latency sample during which a CPU stood still this long is not judged (see stallmon.py);
# it is still shown, and a run with too few judged samples is repeated once.
STALL_EXCUSE_S = 0.002
# The harness's own keepalive (20 ms) must not pause this long where a live link is the test's
# premise; if it did, the test is repeated once.
KEEPALIVE_GAP_S = 0.15


@dataclass(frozen=True)
class Limits:
    """Pass limits for "at once" (ms). A daemon that acts only on its 10 ms tick shows a median
    near 5 ms more than one that acts at once, so the median limit tells the two apart; the max
    limit leaves room for scheduler hiccups.

    ``strict`` holds on a real kernel (native vcan, or a KVM guest). Under TCG (software CPU
    emulation) every wake-up costs a few ms and stalls of 10-30 ms occur, so the ``tcg``
    profile widens the latency limits; the spec-level limits (50 ms brake silence, no early
    stop, no lost frames) are the same in both profiles.
    """

    profile: str
    p50: float  # median of an "at once" latency
    max: float  # any single "at once" latency
    emu: float  # the live emulator's own reaction allowance beyond the 50 ms

    @classmethod
    def for_profile(cls, profile: str) -> Limits:
        if profile == "tcg":
            return cls("tcg", 5.0, 25.0, 200.0)
        return cls("strict", 2.0, 10.0, 5.0)


LIM = Limits.for_profile("strict")


def log(msg: str) -> None:
    sys.stdout.write(f"[hil {time.strftime('%H:%M:%S')}] {msg}\n")
    sys.stdout.flush()


def ms(x: float) -> float:
    return round(x * 1000.0, 3)


@dataclass
class Result:
    id: str
    title: str
    criterion: str
    passed: bool = False
    figures: dict[str, object] = field(default_factory=dict)
    samples_ms: dict[str, list[float]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    duration_s: float = 0.0
    inconclusive: str | None = None  # the environment spoiled the test: run it once more

    def check(self, ok: bool, what: str) -> bool:
        """Record a failed sub-check as a note; returns ``ok``."""
        if not ok:
            self.notes.append(f"FAIL: {what}")
        return ok


class Run:
    """One harness run: vcan, observers, the daemon under test and the remote."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.iface: str = args.iface
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.dut = args.dut
        self.udp_port = free_port(socket.SOCK_DGRAM)
        self.tcp_port = free_port(socket.SOCK_STREAM)
        self.daemons: list[Daemon] = []
        self.windows: list[tuple[float, float, str]] = []  # disturbances: gaps/jumps allowed
        self.results: list[Result] = []
        self.remote: UdpRemote | None = None
        self.clients: list[StopClient] = []
        self.monitor: BusMonitor | None = None
        self.candump: Candump | None = None
        self.markers: list[Frame] = []
        self.t_closed = math.inf
        self.stallmon: StallMonitor | None = None

    # ---- plumbing
    @property
    def daemon(self) -> Daemon:
        return self.daemons[-1]

    @property
    def mon(self) -> BusMonitor:
        assert self.monitor is not None
        return self.monitor

    @property
    def udp(self) -> UdpRemote:
        assert self.remote is not None
        return self.remote

    def argv(self) -> list[str]:
        return [*self.dut, "--can", self.iface, "--udp-port", str(self.udp_port),
                "--tcp-port", str(self.tcp_port), "--bind", "127.0.0.1",
                "--timeout-ms", str(TIMEOUT_MS), "--log-json", "--no-auth"]

    def start_daemon(self) -> tuple[Daemon, Frame]:
        """Start the daemon; returns it and its first ESTOP_BRAKE frame."""
        self.mon.ctl.expect_new_sender()
        start = self.mon.index()
        d = Daemon(self.argv(), self.out / f"estopd-{len(self.daemons) + 1}.log")
        self.daemons.append(d)
        fr = self.mon.wait_for(lambda f: f.can_id == BRAKE_ID, start, 5.0)
        if fr is None:
            code = d.wait(0.1)
            raise RigError(f"daemon sent no ESTOP_BRAKE frame within 5 s (exit code {code}; "
                           f"log: {' | '.join(ln.raw for ln in d.lines[-3:])})")
        for c in self.clients:
            c.close()
        self.clients = [connect_retry(self.tcp_port, 5.0) for _ in range(4)]
        return d, fr

    def ensure_daemon(self) -> None:
        if not self.daemons or not self.daemon.alive:
            t = time.time()
            self.start_daemon()
            self.windows.append((t - 0.2, time.time() + 0.1, "daemon (re)start"))

    def stalls(self) -> list[tuple[float, float]]:
        return self.stallmon.intervals() if self.stallmon is not None else []

    def keepalive_held(self, res: Result, t0: float, t1: float) -> None:
        gap = self.udp.max_gap(t0, t1)
        res.figures["keepalive_max_gap_ms"] = ms(gap)
        if gap >= KEEPALIVE_GAP_S:
            res.inconclusive = (f"the harness's own keepalive paused {ms(gap)} ms "
                                "(the link was not live, as this test needs)")

    def setup(self) -> None:
        self.stallmon = StallMonitor(self.out, sys.executable)
        setup_vcan(self.iface)
        self.candump = Candump(self.iface, self.out / "candump.log")
        self.monitor = BusMonitor(self.iface)
        time.sleep(0.3)  # candump has opened its socket by now; the marker proves it later
        self.markers.append(self.mon.marker(b"HILSTART"))
        self.remote = UdpRemote(self.udp_port)

    def teardown(self) -> None:
        self.windows.append((time.time() - 0.01, math.inf, "teardown"))
        if self.remote is not None:
            self.remote.close()
        for c in self.clients:
            c.close()
        for d in self.daemons:
            d.kill_hard()
        if self.monitor is not None:
            try:
                self.markers.append(self.mon.marker(b"HILSTOP"))
            except (RigError, can.CanError) as exc:
                log(f"end marker: {exc}")
            time.sleep(0.1)
            self.monitor.close()
            self.t_closed = time.time()
        if self.candump is not None:
            self.candump.stop()
        if self.stallmon is not None:
            self.stallmon.stop()

    # ---- helpers used by the scenarios
    def brake_after(self, start: int, pred: Callable[[BrakeFrame], bool],
                    timeout: float) -> tuple[Frame, BrakeFrame] | None:
        def match(f: Frame) -> bool:
            if f.can_id != BRAKE_ID or BrakeFrame.check(f.data):
                return False
            return pred(BrakeFrame.parse(f.data))

        fr = self.mon.wait_for(match, start, timeout)
        return None if fr is None else (fr, BrakeFrame.parse(fr.data))

    def arm(self, res: Result, client: int = 0) -> tuple[float, Frame]:
        """Neutral keepalive, enough valid packets, RELEASE -> ARMED. Returns (t_send, frame)."""
        self.udp.start(NEUTRAL)
        time.sleep(0.15)  # >= 5 valid packets at 20 ms
        start = self.mon.index()
        ex = self.clients[client].release()
        if not (ex.reply.ack and ex.reply.state == 1):
            raise RigError(f"RELEASE with a live neutral link not accepted: {ex.reply}")
        got = self.brake_after(start, lambda b: b.state == 1, 1.0)
        if got is None:
            raise RigError("ACK for RELEASE, but no ARMED frame on the bus within 1 s")
        return ex.t_send, got[0]


def judge(run: Run, res: Result, key: str, label: str, pairs: list[tuple[float, float]],
          use_median: bool = True, slack_ms: float = 0.0) -> list[float]:
    """Latency samples (reference time, frame time) against the profile's limits.

    Value = frame - reference. A value before its time is never excused; the other limits
    (max: the profile's plus ``slack_ms``) skip samples during which a CPU stood still.
    """
    stalls = run.stalls()
    vals = [ms(b - a) for a, b in pairs]
    judged = [v for (a, b), v in zip(pairs, vals, strict=True)
              if overlap(stalls, a, b) < STALL_EXCUSE_S]
    res.samples_ms[label] = vals
    res.figures[key] = summary(vals) if len(vals) > 1 else (vals[0] if vals else None)
    if len(judged) < len(vals):
        res.figures[f"{key}_not_judged_cpu_stall"] = len(vals) - len(judged)
    if vals:
        res.check(min(vals) >= -EARLY_TOL_MS, f"{label}: {min(vals)} ms, before its time")
    if use_median and len(judged) >= 3:
        res.check(sorted(judged)[len(judged) // 2] <= LIM.p50,
                  f"{label}: median > {LIM.p50} ms (waits for the 10 ms tick?)")
    if judged:
        res.check(max(judged) <= LIM.max + slack_ms,
                  f"{label}: {max(judged)} ms > {LIM.max + slack_ms} ms")
    if vals and len(judged) < (len(vals) + 1) // 2:
        res.inconclusive = f"{len(vals) - len(judged)} of {len(vals)} samples hit a CPU stall"
    return vals


# =========================================================================== scenarios

def sc_boot(run: Run, res: Result) -> None:
    t0 = time.time()
    d, first = run.start_daemon()
    b = BrakeFrame.parse(first.data)
    res.figures["first_frame"] = first.data.hex(" ")
    res.figures["exec_to_first_frame_ms"] = ms(first.ts - t0)
    res.check(first.data == bytes.fromhex("016400010000009C"),
              f"first ESTOP_BRAKE {first.data.hex(' ')} is not the boot frame "
              "01 64 00 01 00 00 00 9c (STOPPED, boot, counter 0)")
    res.check(b.brakes, "first frame does not request the brake")
    ex = run.clients[0].status()
    res.figures["status_reply"] = f"ack={ex.reply.ack} state={ex.reply.state} " \
                                  f"reason={ex.reply.reason}"
    res.check(ex.reply.ack and ex.reply.state == 0 and ex.reply.reason == 1,
              "STATUS does not answer ACK STOPPED boot")
    time.sleep(1.0)
    frames = run.mon.window(first.ts, first.ts + 1.0)
    gaps = [g * 1000 for g in frame_gaps(frames)]
    sgaps = [g * 1000 for g in frame_gaps(frames, STATUS_ID)]
    res.figures["brake_period_ms"] = summary(gaps)
    res.figures["status_period_ms"] = summary(sgaps)
    res.samples_ms["brake period"] = gaps
    res.check(bool(gaps) and abs(sum(gaps) / len(gaps) - 10.0) <= 0.5,
              "mean ESTOP_BRAKE period not 10 +- 0.5 ms")
    res.check(bool(gaps) and max(gaps) < BRAKE_SILENCE_S * 1000,
              "an ESTOP_BRAKE gap reached the brake controller's 50 ms")
    res.check(bool(sgaps) and abs(sum(sgaps) / len(sgaps) - 100.0) <= 5.0,
              "mean ESTOP_STATUS period not 100 +- 5 ms")
    status = [f for f in frames if f.can_id == STATUS_ID]
    res.check(bool(status) and status[0].data[6] & 0x0F == 0,
              "first ESTOP_STATUS counter is not 0")
    bad = [f for f in frames if f.can_id in (BRAKE_ID, STATUS_ID)
           and (BrakeFrame if f.can_id == BRAKE_ID else StatusFrame).check(f.data)]
    res.check(not bad, f"{len(bad)} frames fail the CRC/counter/content checks")
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
    armed = [f for f in run.mon.since(start) if f.can_id == BRAKE_ID and f.data[2] == 1]
    res.check(not armed, "an ARMED frame appeared on the bus")
    res.check(ex.reply.state == 0 and ex2.reply.state == 0, "reply state not STOPPED")


def sc_nak3(run: Run, res: Result) -> None:
    start = run.mon.index()
    run.udp.start(DRIVE_GAS)
    time.sleep(0.2)
    ex = run.clients[2].release()
    run.udp.stop()
    res.figures["gas_0.3"] = f"ack={ex.reply.ack} nak={ex.reply.nak_code}"
    res.check(not ex.reply.ack and ex.reply.nak_code == 3,
              "RELEASE with gas 0.3 in the latest packet: not NAK 3")
    time.sleep(0.05)
    armed = [f for f in run.mon.since(start) if f.can_id == BRAKE_ID and f.data[2] == 1]
    res.check(not armed, "an ARMED frame appeared on the bus")
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
    res.check(run.mon.ctl.braking is False, "brake controller emulator still braking")
    run.udp.stop()
    time.sleep(0.3)


def sc_deadman(run: Run, res: Result) -> None:
    over: list[tuple[float, float]] = []
    flag: list[tuple[float, float]] = []
    phase: list[float] = []
    for i in range(run.args.repeat):
        run.arm(res)
        time.sleep(0.1)
        run.udp.stop()
        # The last packet goes out just after a periodic frame, so the deadline falls just after
        # a 10 ms tick: a daemon that waits for the next tick overshoots by nearly 10 ms.
        tick = run.brake_after(run.mon.index(), lambda b: b.state == 1, 0.5)
        if tick is None:
            res.check(False, f"run {i}: no periodic ARMED frame")
            continue
        start = run.mon.index()
        t_last = run.udp.send(NEUTRAL)
        phase.append(ms(t_last - tick[0].ts))
        got = run.brake_after(start, lambda b: b.state == 0, 1.0)
        if got is None:
            res.check(False, f"run {i}: no STOPPED frame within 1 s of the last packet")
            continue
        fr, b = got
        res.check(b.reason == 3, f"run {i}: stop reason {b.reason}, want 3 udp timeout")
        over.append((t_last + TIMEOUT_MS / 1000, fr.ts))
        frames = run.mon.since(start)
        degraded = [f for f in frames if f.can_id == BRAKE_ID and f.data[2] == 1
                    and f.data[4] & 1 and f.ts < fr.ts]
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
    res.check(len(over) == run.args.repeat, "not every run stopped")


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
        got = run.brake_after(start, lambda b: b.state == 0, 1.0)
        run.udp.stop()
        if run.udp.max_gap(t_arm, ex.t_send) >= KEEPALIVE_GAP_S and ex.reply.reason == 3:
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
    if spoiled:
        res.figures["samples_spoiled_by_keepalive_pause"] = spoiled
        if spoiled > n // 2:
            res.inconclusive = f"{spoiled} of {n} samples: the harness's keepalive paused"
    res.check(len(lat) == n - spoiled, "not every STOP showed on the bus")
    time.sleep(0.25)


INVALID_PACKETS: list[bytes] = [
    b"",
    bytes(19),
    bytes(21),
    struct.pack("<ffiii", math.nan, 0.0, 4, 0, 0),
    struct.pack("<ffiii", 0.0, math.inf, 4, 0, 0),
    struct.pack("<ffiii", 1.5, 0.0, 4, 0, 0),
    struct.pack("<ffiii", 0.0, 0.0, 3, 0, 0),
    struct.pack("<ffiii", 0.0, 0.0, 4, 4, 0),
    struct.pack("<ffiii", 0.0, 0.0, 4, 0, 2),
    struct.pack("<ffii", 0.0, 0.0, 0, 0),
    struct.pack("<ffiii", -1.0000001, 0.0, 4, 0, 0),
    NEUTRAL + b"\x00",
]


def sc_invalid_flood(run: Run, res: Result) -> None:
    d = run.daemon
    run.arm(res)
    time.sleep(0.1)
    start = run.mon.index()
    stop_flood = threading.Event()
    sent = [0]

    def flood() -> None:
        i = 0
        while not stop_flood.is_set():
            run.udp.send(INVALID_PACKETS[i % len(INVALID_PACKETS)])
            sent[0] += 1
            i += 1
            time.sleep(0.001)

    th = threading.Thread(target=flood, daemon=True)
    t_last = run.udp.stop()
    assert t_last is not None
    t_flood = time.time()
    th.start()
    got = run.brake_after(start, lambda b: b.state == 0, 1.0)
    time.sleep(0.05)
    ex = run.clients[0].release()  # only invalid packets arrive: no live link
    time.sleep(0.1)
    stop_flood.set()
    th.join(timeout=2)
    t_end = time.time()
    time.sleep(0.25)
    res.figures["invalid_sent"] = sent[0]
    res.figures["flood_rate_per_s"] = round(sent[0] / max(t_end - t_flood, 1e-6))
    if got is None:
        res.check(False, "still ARMED 1 s after the last valid packet (flood keeps it alive)")
    else:
        fr, b = got
        judge(run, res, "overshoot_ms", "overshoot under invalid flood",
              [(t_last + TIMEOUT_MS / 1000, fr.ts)], use_median=False)
        res.check(b.reason == 3, f"stop reason {b.reason}, want 3 udp timeout")
    res.figures["release_during_flood"] = f"ack={ex.reply.ack} nak={ex.reply.nak_code}"
    res.check(not ex.reply.ack and ex.reply.nak_code == 2,
              "RELEASE while only invalid packets arrive: not NAK 2")
    status = [f for f in run.mon.window(t_flood, t_end + 0.25)
              if f.can_id == STATUS_ID and not StatusFrame.check(f.data)]
    counted = sum(StatusFrame.parse(f.data).invalid_packets for f in status)
    res.figures["invalid_counted_in_ESTOP_STATUS"] = counted
    res.check(counted == sent[0], f"ESTOP_STATUS counted {counted} invalid packets, "
                                  f"{sent[0]} were sent")
    res.check(d.alive, "daemon exited")


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
    first = run.brake_after(start, lambda _b: True, 1.0)
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
        res.check(fr.ts - t_up <= 0.05, "frames resumed more than 50 ms after link up")
        res.check(b.brakes and b.state == 0 and b.reason == 4,
                  "first frame after link up is not STOPPED reason fault with the brake on")
        after = [f for f in run.mon.window(t_up, t_up + 0.3) if f.can_id == BRAKE_ID]
        res.figures["frames_in_300ms_after_up"] = len(after)
        res.check(len(after) >= 20, "periodic frames did not resume after link up")
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
        res.figures["status_reply_during_full_queue_ms"] = ms(ex_mid.t_reply - ex_mid.t_send)
        res.check(ex_mid.t_reply - ex_mid.t_send < 0.1,
                  "STATUS took >= 100 ms while the queue was full (blocked event loop?)")
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
        res.figures["drain_to_first_frame_ms"] = ms(fr.ts - t_clear)
        res.check(fr.ts - t_clear <= 0.05, "frames resumed more than 50 ms after the drain")
        res.check(b.brakes and b.state == 0 and b.reason == 4,
                  f"after the queue drained: {fr.data.hex(' ')}, want STOPPED reason fault")
        after = [f for f in run.mon.window(t_clear, t_clear + 0.3) if f.can_id == BRAKE_ID]
        res.check(len(after) >= 20, "periodic frames did not resume after the queue drained")
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
        res.figures["live_emulator_braked_after_ms"] = ms(react)
        res.samples_ms["SIGKILL: last frame -> brake"] = [ms(react)]
        res.check(react <= BRAKE_SILENCE_S + LIM.emu / 1000,
                  f"live emulator braked {ms(react)} ms after the last frame "
                  f"(> 50 + {LIM.emu} ms)")
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


SCENARIOS: list[tuple[str, str, str, Callable[[Run, Result], None]]] = [
    ("boot", "Boot: first frame, periods, STATUS",
     "boot frame 01 64 00 01 00 00 00 9c; STATUS ACK STOPPED boot; period 10+-0.5 ms, "
     "max gap < 50 ms; STATUS period 100+-5 ms", sc_boot),
    ("nak2", "RELEASE refused, no live link",
     "NAK 2 with no packets and with 3 (<5) packets; no ARMED frame", sc_nak2),
    ("nak3", "RELEASE refused, not neutral",
     "NAK 3 with gas 0.3; no ARMED frame", sc_nak3),
    ("release", "RELEASE accepted",
     "ACK ARMED, ARMED frame <= {max} ms, log STOPPED->ARMED", sc_release),
    ("deadman", "Dead-man timeout (200 ms)",
     f"reason udp_timeout; overshoot >= -{EARLY_TOL_MS}, " "p50 <= {p50}, max <= {max} ms; "
     "degraded flag >= 100 ms after the last packet, <= 110 + {max} ms", sc_deadman),
    ("tcp_stop", "TCP STOP latency (4 clients)",
     "ACK STOPPED tcp_stop; stop frame p50 <= {p50}, max <= {max} ms",
     sc_tcp_stop),
    ("invalid_flood", "Invalid UDP flood while ARMED",
     "stops at last valid + 200 ms (overshoot <= {max} ms, reason udp_timeout); RELEASE NAK 2; "
     "ESTOP_STATUS counts every invalid packet", sc_invalid_flood),
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


# =========================================================================== global checks

def check_bus(run: Run, res: Result) -> None:
    ctl = run.mon.ctl
    wins = [(a, b) for a, b, _ in run.windows]
    frames = [f for f in run.mon.frames if f.can_id in (BRAKE_ID, STATUS_ID)]
    res.figures["brake_frames_good"] = ctl.good
    res.figures["status_frames_good"] = ctl.status_good
    kinds: dict[str, int] = {}
    for iss in ctl.issues:
        kinds[iss.kind] = kinds.get(iss.kind, 0) + 1
    res.figures["issues"] = kinds
    lossy = ("jump", "resync")  # frames lost: allowed only in provoked disturbances
    hard = [i for i in ctl.issues if i.kind not in lossy]
    for i in hard[:5]:
        res.notes.append(f"{i.kind} at {i.ts:.6f} id {i.can_id:#05x}: {i.detail}")
    res.check(not hard, f"{len(hard)} frames failed CRC/length/counter/content checks")
    jumps = [i for i in ctl.issues if i.kind in lossy and not in_windows(i.ts, wins)]
    for i in jumps[:3]:
        res.notes.append(f"{i.kind} at {i.ts:.6f} id {i.can_id:#05x}: {i.detail}")
    res.check(not jumps, f"{len(jumps)} counter jumps (lost frames) outside disturbances")
    gaps = []
    excuses: list[str] = []
    stalls = run.stalls()
    brake = [f for f in frames if f.can_id == BRAKE_ID]
    for a, b in zip(brake, brake[1:], strict=False):
        if in_windows(a.ts, wins) or in_windows(b.ts, wins):
            continue
        if b.ts - a.ts >= BRAKE_SILENCE_S:
            stall = excused(a.ts, b.ts, stalls)
            if stall is not None:
                excuses.append(f"{ms(b.ts - a.ts)} ms gap at {a.ts:.3f}: a CPU stood still "
                               f"{ms(stall)} ms of it")
                wins.append((a.ts, b.ts))  # the trip it caused is excused as well
                continue
        gaps.append((b.ts - a.ts) * 1000)
    res.figures["brake_gap_ms_outside_disturbances"] = summary(gaps)
    long_stalls = [b - a for a, b in stalls if b - a >= 0.010]
    res.figures["cpu_stalls_10ms_or_more"] = (
        f"{len(long_stalls)}, max {ms(max(long_stalls))} ms" if long_stalls else 0)
    res.figures["stall_monitor_realtime"] = run.stallmon.realtime() if run.stallmon else None
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
    cut = run.t_closed - 0.1
    off = replay(run.mon.frames, end=cut)
    n_live = sum(1 for t in ctl.trips if t.deadline < cut)
    n_off = sum(1 for t in off.trips if t.deadline < cut)
    res.figures["offline_replay_trips"] = n_off
    res.check(n_off == n_live, f"live emulator tripped {n_live}x, replay of the bus {n_off}x")
    res.figures["disturbance_windows"] = [w[2] for w in run.windows]


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
                                                                   "src")):
                missing.append(json.dumps(r)[:120])
    res.figures["log_lines"] = total
    res.figures["non_json_lines"] = len(bad)
    res.figures["incomplete_records"] = len(missing)
    for line in (bad + missing)[:3]:
        res.notes.append(f"log: {line[:120]}")
    res.check(total > 0, "the daemon logged nothing")
    res.check(not bad, "log lines that are not JSON objects")
    res.check(not missing, "records without t_mono/event (or state without from/to/reason/src)")
    starts = sum(len(d.events("start")) for d in run.daemons)
    res.figures["start_events"] = f"{starts}/{len(run.daemons)}"
    # Every state change seen on the bus has a 'state' log line (per daemon instance).
    bus_changes = 0
    log_changes = 0
    for i, d in enumerate(run.daemons):
        t0 = d.t_start
        t1 = run.daemons[i + 1].t_start if i + 1 < len(run.daemons) else time.time()
        if d.signal_time is not None:  # the last frame after SIGTERM is not a state change
            t1 = min(t1, d.signal_time)
        prev = None
        for f in run.mon.window(t0, t1):
            if f.can_id != BRAKE_ID or BrakeFrame.check(f.data):
                continue
            st = f.data[2]
            if prev is not None and st != prev:
                bus_changes += 1
            prev = st
        with d.lock:
            log_changes += sum(1 for ln in d.lines if ln.rec is not None
                               and ln.rec.get("event") == "state"
                               and (d.signal_time is None or ln.t_wall < d.signal_time))
    res.figures["state_changes_bus"] = bus_changes
    res.figures["state_changes_log"] = log_changes
    res.check(bus_changes == log_changes,
              f"{bus_changes} state changes on the bus, {log_changes} 'state' log lines")


GLOBAL: list[tuple[str, str, str, Callable[[Run, Result], None]]] = [
    ("bus_integrity", "Whole run: frame checks, gaps, emulator",
     "0 CRC/counter/content errors; no gap >= 50 ms and no lost frames outside the provoked "
     "disturbances; live and offline emulator agree", check_bus),
    ("candump_crosscheck", "candump -L vs python-can",
     "same frames, same order, same timestamps between the start and stop markers",
     check_candump),
    ("log_format", "estopd --log-json lines",
     "every line a JSON object with t_mono/event; one state line per state change on the bus",
     check_logs),
]


# =========================================================================== main

# Scenarios that start from any state and may run again when the environment spoiled them.
RETRYABLE = {"release", "deadman", "tcp_stop", "invalid_flood", "iface_down", "txqueue_full"}


def run_one(run: Run, sid: str, res: Result, fn: Callable[[Run, Result], None]) -> None:
    t0 = time.monotonic()
    try:
        if sid not in ("boot", "restart"):
            run.ensure_daemon()
        fn(run, res)
        res.passed = not any(n.startswith("FAIL") for n in res.notes)
    except Exception as exc:  # noqa: BLE001 - any error is a FAIL with its reason
        res.passed = False
        res.notes.append(f"FAIL: {type(exc).__name__}: {exc}")
        res.notes.append(traceback.format_exc().strip().splitlines()[-2][:200])
        if run.remote is not None:
            run.remote.stop()
        run.windows.append((time.time() - 2.0, time.time() + 0.5, f"error in {sid}"))
    res.duration_s = round(time.monotonic() - t0, 2)
    log(f"  -> {'PASS' if res.passed else 'FAIL'} {json.dumps(res.figures)[:300]}")
    for n in res.notes:
        log(f"     {n}")


def run_all(run: Run, only: set[str] | None, budget_s: float) -> None:
    t_begin = time.monotonic()
    for sid, title, crit, fn in SCENARIOS:
        res = Result(sid, title, crit.format(**asdict(LIM)))
        if only is not None and sid not in only and sid != "boot":
            continue
        if time.monotonic() - t_begin > budget_s:
            res.notes.append(f"FAIL: not run, the {budget_s:.0f} s budget was used up")
            run.results.append(res)
            continue
        log(f"scenario {sid}: {title}")
        run_one(run, sid, res, fn)
        if not res.passed and res.inconclusive and sid in RETRYABLE:
            # The environment, not the daemon, spoiled this run (see the note): once more.
            # The first try stays on record in the notes; the second one decides.
            first = res
            log(f"  inconclusive ({first.inconclusive}): running {sid} once more")
            res = Result(sid, title, first.criterion)
            res.notes.append(f"second try; the first was inconclusive: {first.inconclusive} "
                             f"[{'; '.join(first.notes)[:300]}]")
            run_one(run, sid, res, fn)
            if res.inconclusive:
                res.check(False, f"inconclusive twice: {res.inconclusive}")
                res.passed = False
        run.results.append(res)


def sha256(path: str) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--iface", default="vcan0")
    p.add_argument("--dut", default="estopd",
                   help="daemon command (default: estopd on PATH); split on spaces")
    p.add_argument("--only", help="comma-separated scenario ids (boot always runs)")
    p.add_argument("--repeat", type=int, default=8, help="samples for latency scenarios")
    p.add_argument("--budget", type=float, default=240.0, help="seconds for all scenarios")
    args = p.parse_args(argv)
    sys.setswitchinterval(0.0005)  # short GIL slices: threads react within ~1 ms
    global LIM
    mode = os.environ.get("HIL_MODE", "native")
    LIM = Limits.for_profile(os.environ.get("HIL_TIMING") or ("tcg" if "tcg" in mode else
                                                               "strict"))
    dut = args.dut.split()
    exe = shutil.which(dut[0])
    args.dut = [exe or dut[0], *dut[1:]]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta: dict[str, object] = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "mode": mode,
        "timing_profile": asdict(LIM),
        "host": platform.node(),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "python_can": can.__version__,
        "dut": " ".join(args.dut),
        "dut_sha256": sha256(args.dut[0]) if exe else None,
        "iface": args.iface,
        "timeout_ms": TIMEOUT_MS,
        "repeat": args.repeat,
    }
    try:
        meta["guest_uptime_at_start_s"] = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        pass
    t0 = time.monotonic()
    run = Run(args)
    fatal: str | None = None
    if exe is None:
        fatal = f"daemon {dut[0]!r} not found on PATH (run 'make setup')"
    else:
        try:
            run.setup()
            run_all(run, set(args.only.split(",")) if args.only else None, args.budget)
        except Exception as exc:  # noqa: BLE001
            fatal = f"{type(exc).__name__}: {exc}"
            log(traceback.format_exc())
        finally:
            run.teardown()
        if run.monitor is not None and fatal is None:
            for gid, title, crit, fn in GLOBAL:
                res = Result(gid, title, crit)
                try:
                    fn(run, res)
                    res.passed = not any(n.startswith("FAIL") for n in res.notes)
                except Exception as exc:  # noqa: BLE001
                    res.notes.append(f"FAIL: {type(exc).__name__}: {exc}")
                log(f"check {gid}: {'PASS' if res.passed else 'FAIL'} "
                    f"{json.dumps(res.figures)[:300]}")
                for n in res.notes:
                    log(f"     {n}")
                run.results.append(res)
    meta["runtime_s"] = round(time.monotonic() - t0, 2)
    passed = fatal is None and bool(run.results) and all(r.passed for r in run.results)
    doc = {"meta": meta, "fatal": fatal, "passed": passed,
           "results": [asdict(r) for r in run.results]}
    (out / "results.json").write_text(json.dumps(doc, indent=1) + "\n")
    if fatal:
        log(f"FATAL: {fatal}")
    log(f"{'PASSED' if passed else 'FAILED'}: {sum(r.passed for r in run.results)}/"
        f"{len(run.results)} rows passed; results in {out}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
