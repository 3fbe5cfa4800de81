"""The run of the HIL harness: the daemon under test, vcan, the observers and the remote
(:class:`Run`), one row's record (:class:`Result`), the timing profiles (:class:`Limits`) and
the settings every row shares.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import can

from estop.client.keyfile import KeyFileError, load_key_file, write_key_file
from estop.protocol.can import BRAKE_ID, BrakeFrame
from hilbus import BusMonitor, next_frame
from hilclients import NEUTRAL, AuthRemote, StopClient, UdpRemote, connect_retry
from hildaemon import Daemon, sched_text, threads_sched
from hilemu import Frame
from hilload import EstopCommand, Flooder, Storm
from hilrig import Candump, RigError, StallMonitor, cpu_busy_s, cpu_s, free_port, setup_vcan

TIMEOUT_MS = 200
WARN_MS = TIMEOUT_MS / 2
EARLY_TOL_MS = 0.1  # a stop before the deadline is a failure (clock granularity only)
# After a provoked outage, lost-frame counter jumps may still show on the next ESTOP_STATUS
# frame (every 100 ms): the disturbance window ends this long after the first frame back.
RECOVERY_S = 0.15
# A latency sample during which a CPU stood still or the daemon queued STALL_EXCUSE_S (hilcheck)
# is not judged (see hil/mon: stallmon, waitmon); it is still shown, and a row with too few
# judged samples is tried again (scenarios.TRIES).
# The harness's own keepalive (20 ms) must not pause this long where a live link is the test's
# premise; if it did, the test is tried again (scenarios.TRIES).
KEEPALIVE_GAP_S = 0.15
# Valid packets a RELEASE needs (spec section 3: 5), with two to spare.
ARM_PACKETS = 7
# The invalid-UDP flood's target rate (datagrams/s; 0: as fast as it can): the flooder process
# starts with the run (rows_fault.py has the rest of the flood's figures).
FLOOD_RATE = float(os.environ.get("HIL_FLOOD_RATE", "20000"))
# Keyed rows: the remote id of the key holder's remote.
AUTH_REMOTE_ID = 7
# The daemon runs as deployed (deploy/estopd.service.in): SCHED_FIFO at this priority, set
# before it starts with reset-on-fork (chrt -f -R, as systemd's CPUSchedulingResetOnFork=yes),
# asked again with --rt-prio, and --mlock. 0 (--rt-prio 0 of the runner, HIL_RT_PRIO=0): an
# ordinary process (the Python stand-in: at real-time priority it would starve the harness).
RT_PRIO = int(os.environ.get("HIL_RT_PRIO", "50"))
# The connect storm (storm.py, rows_storm.py): busy connections holding every place (the unit
# keeps 8), each with a STATUS every few ms, and a new connection every few ms.
STORM_BUSY = 8
STORM_BUSY_MS = 5.0
STORM_CONNECT_MS = 5.0
STORM_RUNS = 5  # presses of the stop button under the storm (a median of 3 swung on one)
STOP_DEADLINE_MS = 3000  # estop stop's own deadline in those presses (its default)


@dataclass(frozen=True)
class Limits:
    """Pass limits for "at once" (ms). A daemon that acts only on its 10 ms tick shows a median
    near 5 ms more than one that acts at once, so the median limit tells the two apart; the max
    limit leaves room for scheduler hiccups.

    ``strict`` holds on a real kernel (native vcan, or a KVM guest). Under TCG (software CPU
    emulation) every wake-up costs a few ms and stalls of 10-30 ms occur, so the ``tcg``
    profile widens the latency limits, and asks a flood of the rate such a guest reaches beside
    the harness (a sendmmsg flooder: 4,600 to 12,000 datagrams/s in the runs of 2026-12-03,
    against the 10,000 asked before); the spec-level limits (50 ms brake silence, no early
    stop, no lost frames) are the same in both profiles.
    """

    profile: str
    p50: float  # median of an "at once" latency
    max: float  # any single "at once" latency
    emu: float  # the live emulator's own reaction allowance beyond the 50 ms
    # The least rate (invalid datagrams/s) that counts as a flood; at 2,550/s or more every
    # 100-ms ESTOP_STATUS window gets the 255 that saturate it.
    flood: int = 10_000

    @classmethod
    def for_profile(cls, profile: str) -> Limits:
        if profile == "tcg":
            return cls("tcg", 5.0, 25.0, 200.0, 4_000)
        return cls("strict", 2.0, 10.0, 5.0, 10_000)


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
    # The car's roll-outs (hilroll) by label: distances, when braking began, the model's figure.
    rollouts: dict[str, dict[str, object]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    duration_s: float = 0.0
    inconclusive: str | None = None  # the environment spoiled the try: run it once more
    # Latency samples by label, each with whether a stall excuses it: this try's, and those
    # of the earlier tries of the row, which its verdict counts too (hiljudge.judge).
    pool: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)
    earlier: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)
    # The harness itself could not hold the test's conditions (its keepalive paused, its bus
    # monitor fell behind): any failure of this try may be the harness's own.
    spoiled: bool = False

    def check(self, ok: bool, what: str) -> bool:
        """Record a failed sub-check as a note; returns ``ok``."""
        if not ok:
            self.notes.append(f"FAIL: {what}")
        return ok

    def worth_another_try(self) -> bool:
        """Failed and inconclusive, with nothing failed that the environment cannot explain:
        the harness spoiled the whole try, or every failure is "not judged" (one the CPU
        stalls explain). A failure they do not explain decides at once: a second try that
        alone decided could wash it out."""
        if self.passed or not self.inconclusive:
            return False
        fails = [n for n in self.notes if n.startswith("FAIL")]
        return self.spoiled or all("not judged" in n for n in fails)


class Run:
    """One harness run: vcan, observers, the daemon under test and the remote."""

    def __init__(self, args: argparse.Namespace, lim: Limits) -> None:
        self.args = args
        self.lim = lim
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
        # The stall monitors' files and the daemon's pid (for hil/mon/waitmon) in the guest's own
        # memory, not on the host's directory (StallMonitor), copied there at the end.
        shm = Path("/dev/shm")
        self.local = Path(tempfile.mkdtemp(prefix="estop-hil-",
                                           dir=shm if os.access(shm, os.W_OK) else None))
        self.pidfile = self.local / "daemon.pid"  # the running daemon's, for hil/mon/waitmon
        self.want_key = False  # the next daemon gets --key-file (keyed rows) or --no-auth
        self.want_opts: dict[str, str] = {}  # the next daemon's options beyond the defaults
        self.key: bytes | None = None
        self.key_path = self.out / "estopd.key"
        self.aremote: AuthRemote | None = None
        self.aremote_daemon: Daemon | None = None
        self.flooder: Flooder | None = None
        self.storm: Storm | None = None
        self.stop_press: EstopCommand | None = None  # `estop stop`, started ahead
        self.rt_prio: int = getattr(args, "rt_prio", 0)
        self.chrt = shutil.which("chrt") if self.rt_prio else None
        self.scheds: list[str] = []  # how each daemon started was scheduled (threads_sched)
        self.busy0 = cpu_busy_s()  # the guest's busy CPU seconds when the run began
        self.cpu: dict[str, float | None] = {}  # cpu_use() at the teardown

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
        keying = ["--key-file", str(self.key_path)] if self.want_key else ["--no-auth"]
        opts = {"--timeout-ms": str(TIMEOUT_MS), **self.want_opts}
        rt: list[str] = []
        pre: list[str] = []
        if self.rt_prio:
            rt = ["--rt-prio", str(self.rt_prio), "--mlock"]
            if self.chrt is not None:
                pre = [self.chrt, "-f", "-R", str(self.rt_prio)]
        return [*pre, *self.dut, *rt, "--can", self.iface, "--udp-port", str(self.udp_port),
                "--tcp-port", str(self.tcp_port), "--bind", "127.0.0.1",
                *(x for kv in opts.items() for x in kv), "--log-json", *keying]

    def ensure_key(self) -> bytes:
        """The unit's key: a fresh one in the run's output directory (mode 0600)."""
        if self.key is None:
            try:
                self.key = write_key_file(self.key_path)
            except KeyFileError:
                self.key = load_key_file(self.key_path)  # a second runner in the same dir
        return self.key

    def start_daemon(self) -> tuple[Daemon, Frame]:
        """Start the daemon; returns it and its first ESTOP_BRAKE frame."""
        start = self.mon.index()
        if self.want_key:
            self.ensure_key()
        with self.mon.cond:
            self.mon.ctl.expect_new_sender(time.time())
        d = Daemon(self.argv(), self.out / f"estopd-{len(self.daemons) + 1}.log")
        tmp = self.pidfile.with_suffix(".tmp")  # replaced whole: hil/mon/waitmon reads it any time
        tmp.write_text(f"{d.proc.pid}\n")
        tmp.replace(self.pidfile)
        d.keyed = self.want_key
        d.opts = dict(self.want_opts)
        self.daemons.append(d)
        # By time, not only by index: a monitor that lags (a loaded host) may still hold the
        # previous daemon's last frames.
        fr = self.mon.wait_for(lambda f: f.can_id == BRAKE_ID and f.ts >= d.t_start, start, 5.0)
        if fr is None:
            code = d.wait(0.1)
            raise RigError(f"daemon sent no ESTOP_BRAKE frame within 5 s (exit code {code}; "
                           f"log: {' | '.join(ln.raw for ln in d.lines[-3:])})")
        d.sched = threads_sched(d.proc.pid)
        self.scheds.append(sched_text(d.sched))
        log(f"  daemon pid {d.proc.pid}: {self.scheds[-1]}")
        self.reconnect_clients()
        return d, fr

    def reconnect_clients(self) -> None:
        """The harness's 4 stop clients, on fresh connections."""
        for c in self.clients:
            c.close()
        self.clients = [connect_retry(self.tcp_port, 5.0) for _ in range(4)]

    def ensure_daemon(self) -> None:
        if self.daemons and self.daemon.alive and self.daemon.keyed != self.want_key:
            self.restart_daemon("keyed" if self.want_key else "keyless")
        if self.daemons and self.daemon.alive and self.daemon.opts != self.want_opts:
            self.restart_daemon(" ".join(x for kv in self.want_opts.items() for x in kv)
                                or "default options")
        if not self.daemons or not self.daemon.alive:
            t = time.time()
            self.start_daemon()
            self.windows.append((t - 0.2, time.time() + 0.1, "daemon (re)start"))

    def restart_daemon(self, why: str) -> tuple[Daemon, Frame]:
        """SIGTERM for the running daemon, then a new one (keyed as ``want_key`` says)."""
        t = time.time()
        if self.daemons and self.daemon.alive:
            self.daemon.signal(signal.SIGTERM)
            if self.daemon.wait(3.0) is None:
                self.daemon.kill_hard()
        got = self.start_daemon()
        self.windows.append((t - 0.01, time.time() + 0.1, f"restart ({why})"))
        return got

    def estop_stop(self) -> EstopCommand:
        """``estop stop`` against the unit (stop datagram and STOP over TCP, tried again until
        an answer or STOP_DEADLINE_MS): the process started with the run, run once for every
        press (rows_storm); a new one if it is gone."""
        if self.stop_press is None or self.stop_press.proc.poll() is not None:
            self.stop_press = EstopCommand(
                ["stop", "--host", "127.0.0.1", "--tcp-port", str(self.tcp_port),
                 "--udp-port", str(self.udp_port), "--stop-deadline-ms", str(STOP_DEADLINE_MS),
                 "--json"])
        return self.stop_press

    def auth_remote(self) -> AuthRemote:
        """The key holder's remote, knowing the running daemon's session. One object for the
        whole run, so that its counters only ever rise."""
        key = self.ensure_key()
        if self.aremote is None:
            self.aremote = AuthRemote(self.udp_port, self.tcp_port, key, AUTH_REMOTE_ID)
        if self.aremote_daemon is not self.daemon:
            self.aremote.learn_session()
            self.aremote_daemon = self.daemon
        return self.aremote

    def stalls(self) -> list[tuple[float, float]]:
        return self.stallmon.intervals() if self.stallmon is not None else []

    def keepalive_held(self, res: Result, t0: float, t1: float) -> None:
        gap = self.udp.max_gap(t0, t1)
        res.figures["keepalive_max_gap_ms"] = ms(gap)
        if gap >= KEEPALIVE_GAP_S:
            res.inconclusive = (f"the harness's own keepalive paused {ms(gap)} ms "
                                "(the link was not live, as this test needs)")
            res.spoiled = True

    def setup(self) -> None:
        # The daemon as an ordinary process (a TCG run) may wait behind the harness's own
        # processes, which a deployed daemon at SCHED_FIFO 50 never does: those waits are
        # measured (hil/mon/waitmon) and count with the CPU stalls. At real-time priority they
        # don't.
        self.stallmon = StallMonitor(self.out, None if self.rt_prio else self.pidfile,
                                     work=self.local)
        setup_vcan(self.iface)
        self.candump = Candump(self.iface, self.out / "candump.log")
        self.monitor = BusMonitor(self.iface)
        time.sleep(0.3)  # candump has opened its socket by now; the marker proves it later
        self.markers.append(self.mon.marker(b"HILSTART"))
        self.remote = UdpRemote(self.udp_port)
        # The flooder's interpreter starts now, long before its row: under TCG on a busy host
        # a Python start can take tens of seconds.
        self.flooder = Flooder(self.udp_port, FLOOD_RATE)
        self.storm = Storm(self.tcp_port, STORM_BUSY, STORM_BUSY_MS, STORM_CONNECT_MS)
        self.estop_stop()

    def cpu_use(self) -> dict[str, float | None]:
        """CPU seconds used so far by the harness's threads and processes and the daemon running
        now, beside the guest's busy CPU seconds since the run began: where a loaded guest's
        time went (the bus monitor fell seconds behind the bus)."""
        out: dict[str, float | None] = {}
        busy = cpu_busy_s()
        if busy is not None and self.busy0 is not None:
            out["all CPUs busy"] = round(busy - self.busy0, 2)
        out.update({f"harness {t.name}": cpu_s(os.getpid(), t.native_id)
                    for t in threading.enumerate() if t.native_id is not None})
        if self.stallmon is not None:
            out.update({p.stem: cpu_s(proc.pid) for p, proc in
                        zip(self.stallmon.paths, self.stallmon.procs, strict=True)})
        if self.candump is not None:
            out["candump"] = cpu_s(self.candump.proc.pid)
        if self.daemons and self.daemon.alive:
            out[f"daemon #{len(self.daemons)} (the last started)"] = cpu_s(self.daemon.proc.pid)
        return out

    def teardown(self) -> None:
        self.cpu = self.cpu_use()
        self.windows.append((time.time() - 0.01, math.inf, "teardown"))
        if self.remote is not None:
            self.remote.close()
        if self.aremote is not None:
            self.aremote.close()
        if self.flooder is not None:
            self.flooder.close()
        if self.storm is not None:
            self.storm.close()
        if self.stop_press is not None:
            self.stop_press.close()
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
        shutil.rmtree(self.local, ignore_errors=True)

    # ---- helpers used by the scenarios
    def brake_after(self, start: int, pred: Callable[[BrakeFrame], bool],
                    timeout: float, after: float = -math.inf) -> tuple[Frame, BrakeFrame] | None:
        """The first good ESTOP_BRAKE frame from index ``start`` on, stamped after ``after``,
        that satisfies ``pred``, if one is on the bus within ``timeout`` s."""
        def match(f: Frame) -> bool:
            if f.can_id != BRAKE_ID or f.ts <= after or BrakeFrame.check(f.data):
                return False
            return pred(BrakeFrame.parse(f.data))

        fr = self.mon.wait_for(match, start, timeout)
        return None if fr is None else (fr, BrakeFrame.parse(fr.data))

    def next_brake(self, timeout: float) -> BrakeFrame | None:
        """The daemon's next good ESTOP_BRAKE frame from now on, read at once from a socket of
        its own (hilbus.next_frame), not through the bus monitor, which may lag; None when
        none came within ``timeout`` s (a frame that fails its checks is skipped)."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            got = next_frame(self.iface, BRAKE_ID, left)
            if got is None:
                return None
            if not BrakeFrame.check(got[1]):
                return BrakeFrame.parse(got[1])
        return None

    def wait_packets(self, remote: UdpRemote, t0: float, n: int = ARM_PACKETS) -> None:
        """Until the keepalive started at ``t0`` has sent ``n`` packets (bounded: 3 s)."""
        end = time.monotonic() + 3.0
        while remote.sent_since(t0) < n:
            if time.monotonic() > end:
                raise RigError(f"the harness's keepalive sent {remote.sent_since(t0)} packets "
                               f"in 3 s")
            time.sleep(0.005)

    def arm(self, res: Result, client: int = 0,
            remote: UdpRemote | None = None) -> tuple[float, Frame]:
        """Neutral keepalive, enough valid packets, RELEASE -> ARMED. Returns (t_send, frame).
        With an :class:`AuthRemote`, its authenticated packets and RELEASE."""
        rem = remote or self.udp
        for attempt in range(2):
            t0 = time.time()
            rem.start(NEUTRAL)
            self.wait_packets(rem, t0)
            start = self.mon.index()
            if isinstance(rem, AuthRemote):
                ex = rem.release()
                if not ex.tag_ok:
                    raise RigError("the reply to an authenticated RELEASE does not verify")
            else:
                ex = self.clients[client].release()
            if ex.reply.ack and ex.reply.state == 1:
                break
            # Only a pause of the harness's own keepalive excuses a NAK 2 (no live link), or an
            # ACK that found the unit no longer ARMED (its link lost after the RELEASE, seen
            # under a loaded TCG guest: ACK SLOWING): then once more.
            pause = rem.max_gap(t0, time.time())
            excusable = ex.reply.nak_code == 2 or (ex.reply.ack and ex.reply.state != 1)
            if attempt or not excusable or pause < KEEPALIVE_GAP_S:
                raise RigError(f"RELEASE with a live neutral link not accepted: {ex.reply}")
            res.notes.append(f"RELEASE answered {ex.reply} after a {ms(pause)} ms pause of the "
                             "harness's keepalive: armed once more")
            rem.stop()
            self.clients[client].stop()  # from a known state: STOPPED
        # Stamped after the RELEASE: a bus monitor that lags (seen: 1.7 s) still holds ARMED
        # frames of an earlier try past ``start`` (a retried release row took one 1441 ms
        # before its RELEASE).
        got = self.brake_after(start, lambda b: b.state == 1, 1.0, after=ex.t_send)
        if got is None:
            raise RigError("ACK for RELEASE, but no ARMED frame on the bus within 1 s")
        return ex.t_send, got[0]


# One row of the protocol: id, title, criterion (formatted with the profile's limits), check.
Row = tuple[str, str, str, Callable[[Run, Result], None]]
