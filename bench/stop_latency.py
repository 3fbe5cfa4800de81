"""Stop latency of estopd against a plain asyncio baseline, idle and under a UDP flood.

Two measurements, each over many quick trials, for each daemon (estopd and
``bench/baseline_asyncio.py``), each at idle and while another process floods the daemon's UDP
port with invalid packets (loopback only, bounded in time). Both daemons run at once and the
trials alternate between them in blocks (--block), so background load on the machine falls on
both alike; the one flooder is aimed at the daemon whose block runs. The report also gives the
CPU other processes used meanwhile, hypervisor steal, and a reference measurement of this
machine's own timer wake-up latency, so that a tail can be told apart from the machine's.

- timeout overshoot = first stop frame - (last valid packet sent + timeout)
- TCP stop latency  = first stop frame (brake_request 1) - STOP sent

A trial: pause a random 0..10 ms, send 5 neutral valid packets, RELEASE over TCP (retried
if refused), then either drive 3 packets 1 ms apart and go silent (timeout trial), or drive 1
packet and send STOP (TCP trial). Frame times are the daemon's own can-log stamps
(CLOCK_REALTIME); send times are time.time() taken just before the send call (same clock).
A trial whose send call itself took longer than --send-slack-ms (the bench was descheduled,
so the send time is uncertain), whose packets left gaps over half the timeout, or (TCP trial)
whose link timed out before the STOP was handled is discarded, counted and its reason
reported. Stops with the wrong reason, missing stops and early stops (overshoot < 0) are
counted and reported, never dropped.

Lost log lines (issue 11): the daemon writes its can-log through a queue and drops lines when
its reader is slow, so a lost first stop frame would make the next one look like a late stop.
A trial is discarded with the reason "log lines lost" when the alive counters of ESTOP_BRAKE
or ESTOP_STATUS jump between RELEASE and the stop frame, or when the daemon's own
``output_dropped`` report (up to a second late) covers the trial: samples stay provisional
and are checked again after every block and once the daemon has exited.

Options for the closing notes (``bench/latency_tables.py`` runs them all):

- ``--rt-prio N``: estopd's own ``--rt-prio N`` (SCHED_FIFO for its loop; its output threads
  stay at normal priority), the baseline under ``chrt -f N``; the bench's sender and can-log
  readers then run under SCHED_FIFO too, a little below (``--bench-rt-prio``, default N - 10;
  0 keeps the bench at normal priority);
- ``--hog N``: N busy-loop processes at normal priority for the whole run (CPU contention);
- ``--auth``: estopd with a fresh key (``--key-file``, mode 0600, in a temporary directory)
  against estopd without one; the bench's link sends authenticated packets and request frames
  (learning the session with a STATUS), and the flood is forged authenticated packets (right
  session, valid body, wrong tag), each costing the keyed daemon a BLAKE2s.

Outputs: a Markdown table (printed and saved), JSON with the raw samples, and a PNG histogram,
in bench/out/ by default. Goals are checked and printed; the exit code is 0 unless the bench
could not run (or --strict and a goal failed).

    bench/stop_latency.py [--quick] [--trials N] [--timeout-ms 20] [--flood-rate 80000]
                          [--rt-prio N [--bench-rt-prio M]] [--hog N] [--auth]
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import json
import math
import os
import platform
import queue
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from estop.loopback import (
    Daemon,
    DaemonError,
    Link,
    find_estopd,
    is_stop_frame,
    set_realtime,
    stamp,
)
from estop.protocol import auth, can, tcp, udp

HERE = Path(__file__).resolve().parent
METRICS = ("overshoot", "tcp_stop")
METRIC_TITLES = {"overshoot": "timeout overshoot", "tcp_stop": "TCP stop latency"}
GOAL_FLOOD_RATE = 50_000.0
GOAL_P999_MS = {"idle": 1.0, "flood": 2.0}
GOAL_AHEAD_FACTOR = 5.0
BUSY_CORES = 0.25  # other processes' CPU during a run above which the report warns
BUSY_STEAL = 0.05  # hypervisor steal (cores) above which the report warns
LOST_LINES = "log lines lost"  # the discard reason of issue 11
BENCH_BELOW_DAEMON = 10  # default real-time priority of the bench: this far below the daemon's
KEYED, KEYLESS = "estopd+key", "estopd"  # the two daemons of --auth


# --------------------------------------------------------------------------------------------
# Statistics (pure; exercised on synthetic data by tests/test_bench_smoke.py)


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) of already sorted values, linear between closest ranks
    (numpy's default method). NaN for no values."""
    if not sorted_values:
        return math.nan
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile must be 0..100, got {q}")
    pos = (len(sorted_values) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    frac = pos - lo
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * frac


def summarize(values: Sequence[float]) -> dict[str, float]:
    """n, min, p50, p99, p99.9, max and mean of values (in their own unit)."""
    s = sorted(values)
    if not s:
        nan = math.nan
        return {"n": 0, "min": nan, "p50": nan, "p99": nan, "p99.9": nan, "max": nan,
                "mean": nan}
    return {"n": len(s), "min": s[0], "p50": percentile(s, 50.0), "p99": percentile(s, 99.0),
            "p99.9": percentile(s, 99.9), "max": s[-1], "mean": math.fsum(s) / len(s)}


def log_bins(values: Sequence[float], floor: float, n_bins: int = 60) -> list[float]:
    """Log-spaced histogram edges from ``floor`` to just above the largest value."""
    if floor <= 0:
        raise ValueError("floor must be > 0")
    top = max([floor * 10.0, *values]) * 1.05
    lo, hi = math.log10(floor), math.log10(top)
    return [10 ** (lo + (hi - lo) * i / n_bins) for i in range(n_bins + 1)]


def say(text: str = "") -> None:
    """Output for the person running the bench."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def fmt_ms(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.3f}"


# --------------------------------------------------------------------------------------------
# The flood: a child process sending invalid packets at a paced rate for a bounded time

FLOOD_PAYLOADS = (
    b"\x00" * 7,                                        # wrong length
    b"\x00\x00\xc0\x7f" + b"\x00" * 4 + b"\x08\x00\x00\x00" + b"\x00" * 8,  # gas NaN
    b"\x00" * 8 + b"\x03\x00\x00\x00" + b"\x00" * 8,    # gear 3 unknown
    b"\xff" * 24,                                       # wrong length
)


FORGED_REMOTE_ID = 1  # half the forgeries claim the bench's own remote id


def forged_packets(session: int, n: int = 64) -> list[bytes]:
    """Forged authenticated control packets (spec 5.1) for a unit with ``session``: valid
    bodies, the right session, high counters, but a tag not made with the key, so each one
    costs a keyed unit a BLAKE2s before it is refused. Half claim the bench's remote id."""
    rng = random.Random(session)
    out = []
    for i in range(n):
        body = udp.ControlPacket(round(rng.uniform(-1.0, 1.0), 3),
                                 round(rng.uniform(-1.0, 1.0), 3),
                                 rng.choice((udp.Gear.NEUTRAL, udp.Gear.DRIVE)))
        remote = FORGED_REMOTE_ID if i % 2 == 0 else rng.getrandbits(32)
        signed = auth.AuthControlPacket(remote, session, 2**40 + i, body).encode(None)[:44]
        out.append(signed + rng.randbytes(auth.TAG_SIZE))
    return out


def flood_child(ports: list[int], rate: float, max_s: float,
                sessions: list[int] | None = None) -> int:
    """Send invalid datagrams at ``rate``/s to 127.0.0.1:ports[i] until SIGTERM, end of
    stdin, or max_s: the plain invalid packets of FLOOD_PAYLOADS, or with ``sessions`` (one
    per port) forged authenticated packets for that port's unit. A line on stdin holding an
    index switches the target (the pacing goes on without a burst). At the end print one JSON
    line: per port, packets sent and seconds spent on it."""
    stop = False

    def on_term(_sig: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_term)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    sent = [0] * len(ports)
    busy_s = [0.0] * len(ports)
    errors = 0
    target = 0
    addr = ("127.0.0.1", ports[target])
    pools = ([forged_packets(sess) for sess in sessions] if sessions
             else [list(FLOOD_PAYLOADS)] * len(ports))
    payloads = pools[target]
    batch = 25
    total = 0
    start = time.monotonic()
    since = start
    end = start + max_s
    poller = select.poll()
    poller.register(sys.stdin.fileno(), select.POLLIN)
    while not stop:
        now = time.monotonic()
        if now >= end:
            break
        if poller.poll(0):
            line = sys.stdin.readline()
            if not line:
                break
            busy_s[target] += now - since
            since = now
            target = int(line) % len(ports)
            addr = ("127.0.0.1", ports[target])
            payloads = pools[target]
        due = start + total / rate
        if now < due:
            time.sleep(min(due - now, 0.001))
            continue
        n_pool = len(payloads)
        for i in range(batch):
            try:
                sock.sendto(payloads[(total + i) % n_pool], addr)
                sent[target] += 1
            except (BlockingIOError, ConnectionRefusedError):
                errors += 1
        total += batch
    busy_s[target] += time.monotonic() - since
    sys.stdout.write(json.dumps({"ports": ports, "sent": sent, "seconds": busy_s,
                                 "errors": errors}) + "\n")
    return 0


def udp_drops(port: int) -> int | None:
    """Kernel receive drops of the loopback UDP socket bound to ``port`` (/proc/net/udp)."""
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return None
    for line in lines:
        f = line.split()
        if len(f) >= 13 and int(f[1].split(":")[1], 16) == port:
            return int(f[-1])
    return None


@dataclass
class FloodStats:
    target_rate: float
    sent: int = 0
    errors: int = 0
    elapsed_s: float = 0.0
    kernel_drops: int | None = None
    forged: bool = False  # forged authenticated packets (--auth), not plain invalid ones

    @property
    def rate(self) -> float:
        return self.sent / self.elapsed_s if self.elapsed_s > 0 else 0.0


class Flood:
    """One flooder child aimed at one of several daemons' UDP ports at a time."""

    def __init__(self, ports: list[int], rate: float, max_s: float,
                 sessions: list[int] | None = None) -> None:
        self.ports = ports
        self.rate = rate
        self.forged = sessions is not None
        self._drops0 = {p: udp_drops(p) for p in ports}
        extra = [",".join(f"{s:x}" for s in sessions)] if sessions is not None else []
        self._proc: subprocess.Popen[str] = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--flood-child",
             ",".join(map(str, ports)), str(rate), str(max_s), *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    @property
    def pid(self) -> int:
        return self._proc.pid

    def aim(self, index: int) -> None:
        """Send the flood to ports[index] from now on."""
        assert self._proc.stdin is not None
        self._proc.stdin.write(f"{index}\n")
        self._proc.stdin.flush()

    def stop(self) -> dict[int, FloodStats]:
        """End the child; per port: packets sent to it over the time it was the target."""
        if self._proc.poll() is None:
            self._proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self._proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            out, _ = self._proc.communicate()
        stats = {p: FloodStats(self.rate, forged=self.forged) for p in self.ports}
        for line in out.splitlines():
            if line.startswith("{"):
                d = json.loads(line)
                for i, p in enumerate(d["ports"]):
                    stats[p].sent, stats[p].elapsed_s = d["sent"][i], d["seconds"][i]
                    stats[p].errors = d["errors"]
        for p, st in stats.items():
            d0, d1 = self._drops0[p], udp_drops(p)
            if d0 is not None and d1 is not None:
                st.kernel_drops = d1 - d0
        return stats


# --------------------------------------------------------------------------------------------
# How busy the machine was with other work during a run


def _cpu_jiffies() -> tuple[int, int, int] | None:
    """(busy, steal, total) jiffies of all CPUs from /proc/stat."""
    try:
        first = Path("/proc/stat").read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    v = [int(x) for x in first[1:9]]  # user nice system idle iowait irq softirq steal
    total = sum(v)
    return total - v[3] - v[4], v[7], total


def _proc_jiffies(pid: int | None) -> int:
    """utime + stime of a process (all its threads); 0 when it is gone."""
    if pid is None:
        return 0
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0
    f = stat.rsplit(")", 1)[1].split()
    return int(f[11]) + int(f[12])


class CpuMeter:
    """CPU used during a run by processes other than the bench, its daemon and its flooder
    (in cores, averaged), and the hypervisor's steal. Linux /proc only; None elsewhere."""

    def __init__(self) -> None:
        self.tck = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self.start = _cpu_jiffies()
        self.own_start = _proc_jiffies(os.getpid())
        self.pids: dict[int, int] = {}  # pid -> jiffies when first seen

    def watch(self, pid: int | None) -> None:
        if pid is not None and pid not in self.pids:
            self.pids[pid] = _proc_jiffies(pid)

    def sample_children(self) -> int:
        return sum(_proc_jiffies(p) - j0 for p, j0 in self.pids.items())

    def finish(self, children_used: int | None = None) -> tuple[float, float, float] | None:
        """(other, steal, seconds): cores used by other processes and stolen by the
        hypervisor, averaged over the seconds measured. None without /proc."""
        end = _cpu_jiffies()
        if self.start is None or end is None or end[2] <= self.start[2]:
            return None
        if children_used is None:
            children_used = self.sample_children()
        ncpu = os.cpu_count() or 1
        span = (end[2] - self.start[2]) / ncpu  # wall jiffies
        own = _proc_jiffies(os.getpid()) - self.own_start + children_used
        other = max(0.0, (end[0] - self.start[0] - own) / span)
        steal = (end[1] - self.start[1]) / span
        return other, steal, span / self.tck


def timer_floor(n: int, period_s: float) -> list[float]:
    """This machine's own timer wake-up latency (ms): n sleeps of period_s, with the timer
    slack set to 1 ns where prctl allows. A floor no daemon on this machine can beat."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, ctypes.c_ulong(1), 0, 0, 0)  # PR_SET_TIMERSLACK, 1 ns
    out = []
    for _ in range(n):
        deadline = time.monotonic() + period_s
        time.sleep(period_s)
        out.append((time.monotonic() - deadline) * 1000.0)
    return out


# --------------------------------------------------------------------------------------------
# Trials


@dataclass
class RunResult:
    daemon: str
    load: str
    timeout_ms: int
    samples: dict[str, list[float]] = field(default_factory=lambda: {m: [] for m in METRICS})
    missed: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    wrong_reason: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    discarded: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    release_failures: int = 0
    release_naks: int = 0
    discard_reasons: dict[str, int] = field(default_factory=dict)
    sample_times: dict[str, list[float]] = field(default_factory=lambda: {m: [] for m in METRICS})
    blocks: list[dict[str, float]] = field(default_factory=list)  # per block: t, s, other, steal
    status_frames: int = 0
    status_invalid_saturated: int = 0  # STATUS frames counting >= 255 invalid packets / 100 ms
    status_auth_saturated: int = 0  # ... >= 255 authentication failures / 100 ms
    # per sample: ((first, last) realtime, (first, last) monotonic) of its trial, so that a
    # loss found later (a counter, the daemon's report) can still discard it
    spans: dict[str, list[tuple[tuple[float, float], tuple[float, float]]]] = field(
        default_factory=lambda: {m: [] for m in METRICS})
    log_frames: int = 0  # can-log frames whose alive counters were followed
    log_gaps: int = 0  # counter jumps among them
    log_gap_lines: int = 0  # frames missing by the counters
    daemon_dropped: int = 0  # can-log lines the daemon reported dropped (its total)
    wall_s: float = 0.0
    flood: FloodStats | None = None
    other_cpu: float | None = None  # cores used by other processes during the run
    steal_cpu: float | None = None  # cores stolen by the hypervisor during the run
    metered_s: float = 0.0
    error: str | None = None

    def early(self, metric: str) -> int:
        return sum(1 for v in self.samples[metric] if v < 0)

    def discard(self, metric: str, why: str) -> None:
        self.discarded[metric] += 1
        key = f"{METRIC_TITLES[metric]}: {why}"
        self.discard_reasons[key] = self.discard_reasons.get(key, 0) + 1

    def lost_discards(self, metric: str) -> int:
        return self.discard_reasons.get(f"{METRIC_TITLES[metric]}: {LOST_LINES}", 0)

    def add_sample(self, metric: str, value_ms: float,
                   span: tuple[tuple[float, float], tuple[float, float]] | None = None) -> None:
        self.samples[metric].append(value_ms)
        self.sample_times[metric].append(round(time.time(), 3))
        if span is not None:
            self.spans[metric].append(span)

    def settle(self, lines_lost: Callable[[tuple[float, float], tuple[float, float]], int]
               ) -> int:
        """Discard, as "log lines lost", every sample whose trial has lost lines by what is
        known now (``lines_lost(real, mono)``, e.g. :meth:`Daemon.lines_lost`); return how
        many. Called after every block and once the daemon has exited."""
        moved = 0
        for m in METRICS:
            spans = self.spans[m]
            if len(spans) != len(self.samples[m]):
                continue  # samples made without spans (synthetic runs): nothing to check
            keep = [i for i, (real, mono) in enumerate(spans) if not lines_lost(real, mono)]
            if len(keep) == len(spans):
                continue
            for _ in range(len(spans) - len(keep)):
                self.discard(m, LOST_LINES)
                moved += 1
            times = self.sample_times[m]
            self.samples[m] = [self.samples[m][i] for i in keep]
            if len(times) == len(spans):
                self.sample_times[m] = [times[i] for i in keep]
            self.spans[m] = [spans[i] for i in keep]
        return moved

    def add_cpu(self, measured: tuple[float, float, float] | None) -> None:
        """Fold one block's (other, steal, seconds) into the run's time-weighted means."""
        if measured is None:
            return
        other, steal, secs = measured
        self.blocks.append({"t_end": round(time.time(), 3), "seconds": round(secs, 2),
                            "other": round(other, 3), "steal": round(steal, 3)})
        total = self.metered_s + secs
        if total <= 0:
            return
        self.other_cpu = ((self.other_cpu or 0.0) * self.metered_s + other * secs) / total
        self.steal_cpu = ((self.steal_cpu or 0.0) * self.metered_s + steal * secs) / total
        self.metered_s = total


@dataclass(frozen=True)
class TimeoutSent:
    """What a timeout trial sent: the bench's time.monotonic() when it began, time.time()
    after the RELEASE ACK and before the last packet, and whether a send call was late or the
    packets left a gap."""

    mono: float
    t_ack: float
    t_last: float
    late: bool = False
    gap: bool = False


@dataclass(frozen=True)
class TcpSent:
    """What a TCP trial sent: as :class:`TimeoutSent`, with the time before the STOP."""

    mono: float
    t_ack: float
    t_stop: float
    quick: bool = True


class Trials:
    """Drives trials against one daemon (``link``) and measures them from its can-log
    (``daemon.frames``, checked with ``daemon.lines_lost``). The measuring half
    (:meth:`judge_timeout`, :meth:`judge_tcp`) needs no link: it can be fed recorded lines."""

    def __init__(self, daemon: Daemon, link: Link | None, timeout_ms: int, send_slack_s: float,
                 result: RunResult, seed: int = 1) -> None:
        self.d = daemon
        self.link = link
        self.timeout_s = timeout_ms / 1000.0
        self.slack = send_slack_s
        self.r = result
        self.rng = random.Random(seed)

    @property
    def _link(self) -> Link:
        if self.link is None:
            raise DaemonError("no link to drive trials with")
        return self.link

    def send(self, gas: float, gear: int) -> tuple[float, bool]:
        """Send one control packet; (time before the send, send took <= slack)."""
        t = self._link.send_control(gas, 0.0, gear)
        return t, time.time() - t <= self.slack

    def release(self) -> float | None:
        """Bring the unit to ARMED; time.time() after the ACK, None if it keeps refusing.

        First a random pause of 0..10 ms (one brake period), so that trials do not lock onto
        the phase of the daemon's periodic work (each trial starts right after a stop frame).
        """
        time.sleep(self.rng.uniform(0.0, 0.010))
        link = self._link
        for _ in range(50):
            for _ in range(5):
                link.send_control(0.0, 0.0, udp.Gear.NEUTRAL)
            time.sleep(0.0005)
            reply, _t = link.request(tcp.RELEASE)
            if reply.ack and reply.state == 1:
                return time.time()
            self.r.release_naks += 1
            time.sleep(0.002)
        self.r.release_failures += 1
        return None

    def wait_stop(self, after: float, max_s: float) -> tuple[float, int] | None:
        """(stamp, reason) of the first brake frame with brake_request 1 stamped at or after
        ``after``; None if none comes within max_s."""
        deadline = time.monotonic() + max_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                rec = self.d.frames.get(timeout=min(left, 0.1))
            except queue.Empty:
                if not self.d.alive():
                    raise DaemonError("the daemon died") from None
                continue
            if rec.can_id == can.STATUS_ID and len(rec.data) == can.DLC:
                self.r.status_frames += 1
                st = can.StatusFrame.parse(rec.data)
                self.r.status_invalid_saturated += st.invalid_packets == 255
                self.r.status_auth_saturated += st.auth_failures == 255
            elif is_stop_frame(rec) and stamp(rec) >= after:
                return stamp(rec), can.BrakeFrame.parse(rec.data).reason

    def timeout_trial(self) -> bool:
        """One timeout trial; True when it produced a sample."""
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        prev, late, gap = t_ack, False, False
        t_last = t_ack
        for i in range(3):
            if i:
                time.sleep(0.001)
            t_last, quick = self.send(0.3, udp.Gear.DRIVE)
            late = late or not quick
            gap = gap or t_last - prev >= self.timeout_s / 2
            prev = t_last
        return self.judge_timeout(TimeoutSent(mono, t_ack, t_last, late, gap))

    def judge_timeout(self, sent: TimeoutSent) -> bool:
        """Find the timeout stop in the can-log and count it: a sample, a discard (with its
        reason), a miss or a wrong reason. True when it produced a sample."""
        stop = self.wait_stop(sent.t_ack, self.timeout_s + 2.0)
        if stop is None:
            self.r.missed["overshoot"] += 1
            return False
        t_stop, reason = stop
        span = ((sent.t_ack, t_stop), (sent.mono, time.monotonic()))
        why = (LOST_LINES if self.d.lines_lost(*span) else "late send" if sent.late
               else "gap between packets" if sent.gap
               else "stop before the last packet" if t_stop < sent.t_last else None)
        if why is not None:
            self.r.discard("overshoot", why)
            return False
        if reason != can.Reason.UDP_TIMEOUT:
            self.r.wrong_reason["overshoot"] += 1
            return False
        self.r.add_sample("overshoot", (t_stop - (sent.t_last + self.timeout_s)) * 1000.0, span)
        return True

    def tcp_trial(self) -> bool:
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        _t_pkt, quick = self.send(0.3, udp.Gear.DRIVE)
        seq, t_stop = self._link.send_request(tcp.DEFAULT_STOP_ID)
        quick = quick and time.time() - t_stop <= self.slack
        took = self.judge_tcp(TcpSent(mono, t_ack, t_stop, quick))
        self._link.read_reply(seq)
        return took

    def judge_tcp(self, sent: TcpSent) -> bool:
        """Find the STOP's stop frame in the can-log and count it (see judge_timeout)."""
        stop = self.wait_stop(sent.t_ack, 2.0)
        if stop is None:
            self.r.missed["tcp_stop"] += 1
            return False
        t_frame, reason = stop
        span = ((sent.t_ack, t_frame), (sent.mono, time.monotonic()))
        if reason == can.Reason.UDP_TIMEOUT:
            # the link timed out before the STOP was handled (the bench or the daemon was
            # held up, or the kernel dropped the drive packet): a stop, but not the TCP path
            self.r.discard("tcp_stop", "link timed out first")
            return False
        if reason != can.Reason.TCP_STOP:
            self.r.wrong_reason["tcp_stop"] += 1
            return False
        why = (LOST_LINES if self.d.lines_lost(*span) else None if sent.quick
               else "late send")
        if why is not None:
            self.r.discard("tcp_stop", why)
            return False
        self.r.add_sample("tcp_stop", (t_frame - sent.t_stop) * 1000.0, span)
        return True

    def run(self, n: int, deadline: float, max_attempts: int) -> int:
        """Trials until each metric has n samples, the monotonic deadline passes, or
        max_attempts trial pairs were tried; returns the attempts made."""
        attempts = 0
        while attempts < max_attempts and time.monotonic() < deadline:
            need = [len(self.r.samples[m]) < n for m in METRICS]
            if not any(need):
                break
            attempts += 1
            if need[0]:
                self.timeout_trial()
            if need[1]:
                self.tcp_trial()
        return attempts


@dataclass
class Contender:
    name: str
    daemon: Daemon
    result: RunResult
    link: Link | None = None
    trials: Trials | None = None
    attempts: int = 0


def _drain(daemon: Daemon) -> None:
    while True:
        try:
            daemon.frames.get_nowait()
        except queue.Empty:
            return


@dataclass
class DaemonSpec:
    """One daemon of a run: its name in the report, its command, its key (None: --no-auth)
    and extra options."""

    name: str
    command: list[str]
    key: bytes | None = None
    key_file: str | None = None
    extra: list[str] = field(default_factory=list)


def run_load(load: str, daemons: list[DaemonSpec], args: argparse.Namespace, n: int,
             watch_pids: Sequence[int] = ()) -> list[RunResult]:
    """All daemons side by side under one load: they run at once, and trials alternate
    between them in blocks, so background load on the machine falls on both alike. The
    flood (one child) is aimed at the daemon whose block is running. ``watch_pids`` (the
    hogs) count as the bench's own processes in the CPU meter."""
    t0 = time.monotonic()
    cons = [Contender(d.name, Daemon(d.command, timeout_ms=args.timeout_ms, extra_args=d.extra,
                                     key_file=d.key_file, reader_rt_prio=args.bench_rt_prio),
                      RunResult(d.name, load, args.timeout_ms)) for d in daemons]
    flood: Flood | None = None
    try:
        for c, spec in zip(cons, daemons, strict=True):
            try:
                c.daemon.start()
                c.link = Link(c.daemon.udp_port, c.daemon.tcp_port, key=spec.key)
                c.trials = Trials(c.daemon, c.link, args.timeout_ms,
                                  args.send_slack_ms / 1000.0, c.result)
            except (DaemonError, OSError, tcp.FrameError) as exc:
                c.result.error = str(exc)
        live = [c for c in cons if c.trials is not None]
        if load == "flood" and live:
            sessions = None
            if args.auth:  # each unit's own session: forgeries that get as far as the tag
                sessions = [(c.link.session if c.link is not None and c.link.session else
                             c.daemon.session or 1) for c in cons]
            flood = Flood([c.daemon.udp_port for c in cons], args.flood_rate,
                          args.max_run_s + 30.0, sessions)
        deadline = time.monotonic() + args.max_run_s
        gc.collect()
        gc.disable()
        try:
            while live and time.monotonic() < deadline:
                for c in list(live):
                    assert c.trials is not None
                    if flood is not None:
                        flood.aim(cons.index(c))
                        time.sleep(0.1)  # the daemon under test is in the flood for a while
                    _drain(c.daemon)  # frames logged while the other daemon was tested
                    meter = CpuMeter()
                    for other in cons:
                        meter.watch(other.daemon.pid)
                    if flood is not None:
                        meter.watch(flood.pid)
                    for pid in watch_pids:
                        meter.watch(pid)
                    target = min(n, len(c.result.samples["overshoot"]) + args.block)
                    try:
                        c.attempts += c.trials.run(target, deadline, args.block * 3)
                    except (DaemonError, OSError, tcp.FrameError) as exc:
                        c.result.error = str(exc)
                    c.result.add_cpu(meter.finish())
                    c.result.settle(c.daemon.lines_lost)  # losses found since
                    done = all(len(c.result.samples[m]) >= n for m in METRICS)
                    if done or c.result.error or c.attempts > 3 * n:
                        live.remove(c)
        finally:
            gc.enable()
    finally:
        if flood is not None:
            stats = flood.stop()
            for c in cons:
                c.result.flood = stats.get(c.daemon.udp_port)
        for c in cons:
            if c.link is not None:
                c.link.close()
            c.daemon.stop()
            # every line and every drop report is in now: the final word on lost lines
            c.result.settle(c.daemon.lines_lost)
            c.result.log_frames = c.daemon.loss.frames
            c.result.log_gaps = len(c.daemon.loss.gaps)
            c.result.log_gap_lines = c.daemon.loss.lines_lost
            c.result.daemon_dropped = c.daemon.dropped_total
    wall = time.monotonic() - t0
    for c in cons:
        c.result.wall_s = wall
    return [c.result for c in cons]


# --------------------------------------------------------------------------------------------
# CPU contention: busy loops at normal priority


class Hogs:
    """``n`` busy-loop processes at normal priority (nice 0, SCHED_OTHER), one per core on a
    machine with n cores: the contention of issue 11. Ended by :meth:`stop`."""

    def __init__(self, n: int) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        self._t0 = time.monotonic()
        for _ in range(n):
            self.procs.append(subprocess.Popen(
                [sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL))
        self.pids = [p.pid for p in self.procs]
        self.cpu_cores: float | None = None  # cores the hogs used on average

    def stop(self) -> None:
        tck = os.sysconf("SC_CLK_TCK")
        used = sum(_proc_jiffies(p) for p in self.pids)
        secs = time.monotonic() - self._t0
        if self.procs and secs > 0:
            self.cpu_cores = used / tck / secs
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def make_key_file(directory: Path) -> tuple[bytes, str]:
    """A fresh key in ``directory``/estopd.key, mode 0600 from the start."""
    key = os.urandom(auth.KEY_SIZE)
    path = directory / "estopd.key"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(auth.format_key(key))
    return key, str(path)


# --------------------------------------------------------------------------------------------
# Reporting


def check_goals(results: list[RunResult], auth: bool = False) -> list[tuple[str, bool]]:
    """Goals of the run. Plain: estopd's p99.9 overshoot (idle < 1 ms, flood < 2 ms), every
    trial stopped with the right reason, 5x ahead of the baseline, the flood fast enough.
    --auth (issue 8): the keyed estopd under the forged flood, p99.9 < 2 ms, no kernel drops,
    and the release/heartbeat path still working (every trial armed)."""
    by = {(r.daemon, r.load): r for r in results}
    main_name = KEYED if auth else "estopd"
    goals: list[tuple[str, bool]] = []
    for load in ("idle", "flood"):
        e, b = by.get((main_name, load)), by.get(("baseline", load))
        if e is None:
            continue
        ok_run = e.error is None and len(e.samples["overshoot"]) > 0
        p = summarize(e.samples["overshoot"])["p99.9"]
        lim = GOAL_P999_MS[load]
        goals.append((f"{main_name} p99.9 timeout overshoot {load}: {fmt_ms(p)} ms < {lim} ms",
                      ok_run and p < lim))
        missing = sum(e.missed.values()) + sum(e.wrong_reason.values())
        goals.append((f"{main_name} {load}: every trial stopped, with the right reason "
                      f"({missing} missed or wrong)", ok_run and missing == 0))
        if auth:
            goals.append((f"{main_name} {load}: the release/heartbeat path works (every trial "
                          f"armed: {e.release_failures} release failures, {e.release_naks} "
                          f"NAKs retried)", ok_run and e.release_failures == 0))
        if b is not None and b.samples["overshoot"]:
            pb = summarize(b.samples["overshoot"])["p99.9"]
            goals.append((f"estopd p99.9 overshoot {load} at most 1/{GOAL_AHEAD_FACTOR:g} of "
                          f"the baseline's ({fmt_ms(p)} vs {fmt_ms(pb)} ms)",
                          ok_run and p * GOAL_AHEAD_FACTOR <= pb))
        if load == "flood":
            if auth and e.flood is not None:
                kd = e.flood.kernel_drops
                goals.append((f"{main_name} under the forged flood: no kernel drops "
                              f"({'n/a' if kd is None else f'{kd:,}'})", kd == 0))
            for r in (e, b):
                if r is not None and r.flood is not None:
                    goals.append((f"flood at {r.daemon}: {r.flood.rate:,.0f} packets/s while "
                                  f"aimed at it >= {GOAL_FLOOD_RATE:,.0f}",
                                  r.flood.rate >= GOAL_FLOOD_RATE))
    return goals


def markdown(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> str:
    auth_mode = bool(meta.get("auth"))
    title = ("Stop latency: estopd with a key vs without" if auth_mode
             else "Stop latency: estopd vs asyncio baseline"
             if any(r.daemon == "baseline" for r in results) else "Stop latency: estopd")
    flood_kind = ("forged authenticated packets/s (60 bytes, right session, wrong tag)"
                  if auth_mode else "invalid packets/s")
    lines = [
        f"# {title}",
        "",
        f"{meta['date']} on {meta['host']} ({meta['cpus']} CPUs, Python {meta['python']}); "
        f"timeout {meta['timeout_ms']} ms; {meta['trials']} trials per cell; flood target "
        f"{meta['flood_rate']:,.0f} {flood_kind} on loopback. All times in ms.",
    ]
    if meta.get("priorities"):
        lines += ["", f"Priorities: {meta['priorities']}."]
    if meta.get("hog"):
        used = meta.get("hog_cpu_cores")
        lines += ["", f"CPU contention: {meta['hog']} busy-loop processes at normal priority "
                  f"ran throughout" + (f" (they used {used:.2f} cores)" if used is not None
                                       else "") + "."]
    if auth_mode:
        lines += ["", f"{KEYED}: estopd --key-file (a fresh key, mode 0600); the bench's link "
                  f"sends authenticated 60-byte packets and 48-byte request frames (session "
                  f"learnt with a STATUS, rising counters) and verifies every reply. "
                  f"{KEYLESS}: estopd --no-auth, plain link, the same flood (to it the forged "
                  f"packets are merely invalid)."]
    lines += [
        "",
        "| daemon | load | metric | n | p50 | p99 | p99.9 | max | early | missed | wrong | "
        "discarded | lines lost |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
        "---: |",
    ]
    for r in results:
        for m in METRICS:
            s = summarize(r.samples[m])
            early = str(r.early(m)) if m == "overshoot" else "-"
            lines.append(
                f"| {r.daemon} | {r.load} | {METRIC_TITLES[m]} | {s['n']} | {fmt_ms(s['p50'])} |"
                f" {fmt_ms(s['p99'])} | {fmt_ms(s['p99.9'])} | {fmt_ms(s['max'])} | {early} |"
                f" {r.missed[m]} | {r.wrong_reason[m]} | {r.discarded[m]} |"
                f" {r.lost_discards(m)} |")
    floor = meta.get("timer_floor_ms")
    if floor:
        prio = meta.get("timer_floor_prio")
        at = f", SCHED_FIFO {prio}" if prio else ""
        lines += ["", f"Reference, this machine's own timer wake-up latency ({floor['n']} sleeps "
                  f"of {meta['timeout_ms']} ms, timer slack 1 ns{at}, before the daemons "
                  f"start): p50 {fmt_ms(floor['p50'])}, p99 {fmt_ms(floor['p99'])}, p99.9 "
                  f"{fmt_ms(floor['p99.9'])}, max {fmt_ms(floor['max'])} ms (other CPU "
                  f"{meta.get('timer_floor_other_cpu', 'n/a')} cores, steal "
                  f"{meta.get('timer_floor_steal', 'n/a')}). A timeout stop's tail at or below "
                  f"this comes from the machine, not the daemon."]
    lines += ["", "Flood (per run): the sender's count over its own run time; kernel drops: "
              "datagrams the daemon's socket dropped (receive buffer full, /proc/net/udp); "
              "STATUS: the daemon's own ESTOP_STATUS frames whose invalid-packet (or "
              "authentication-failure) count per 100 ms saturated at 255, i.e. it saw >= 2,550 "
              "such packets/s.", ""]
    for r in results:
        if r.flood is not None:
            f = r.flood
            drops = "n/a" if f.kernel_drops is None else f"{f.kernel_drops:,}"
            kind = "forged" if f.forged else "invalid"
            lines.append(f"- {r.daemon}: {f.sent:,} {kind} packets in {f.elapsed_s:.1f} s = "
                         f"{f.rate:,.0f} packets/s; kernel drops {drops}; STATUS saturated "
                         f"{r.status_invalid_saturated} (invalid), {r.status_auth_saturated} "
                         f"(auth failures) of {r.status_frames}")
    lines += ["", "Can-log lines lost (issue 11): frames whose alive counters were followed, "
              "counter jumps (frames missing), and the lines the daemon itself reported "
              "dropped (output_dropped). A trial that lost lines between RELEASE and its stop "
              "frame is discarded, never timed (column 'lines lost').", ""]
    for r in results:
        lines.append(f"- {r.daemon} {r.load}: {r.log_frames:,} frames followed, {r.log_gaps} "
                     f"jumps ({r.log_gap_lines} frames missing), daemon reported "
                     f"{r.daemon_dropped} dropped")
    lines += ["", "Per run: wall time of the load (both daemons); CPU that other processes on "
              "this machine used meanwhile (cores, averaged over the daemon's blocks; not the "
              "bench, its daemons, its flooder or its busy loops) and hypervisor "
              "steal: numbers taken on a busy machine have fatter tails; RELEASE refusals "
              "(retried) and failures; errors.", ""]
    for r in results:
        err = f"; ERROR {r.error}" if r.error else ""
        other = "n/a" if r.other_cpu is None else f"{r.other_cpu:.2f}"
        steal = "n/a" if r.steal_cpu is None else f"{r.steal_cpu:.2f}"
        peak = max((b["other"] + b["steal"] for b in r.blocks), default=math.nan)
        lines.append(f"- {r.daemon} {r.load}: {r.wall_s:.1f} s; other CPU {other} cores, "
                     f"steal {steal} (busiest block: {fmt_ms(peak)} cores); RELEASE NAKs "
                     f"{r.release_naks}, release failures {r.release_failures}{err}")
        if r.discard_reasons:
            lines.append("  - discarded: " + ", ".join(
                f"{k} {v}" for k, v in sorted(r.discard_reasons.items())))
    busy = [r for r in results if (r.other_cpu or 0.0) > BUSY_CORES
             or (r.steal_cpu or 0.0) > BUSY_STEAL]
    if busy:
        lines += ["", "WARNING: the machine was busy with other work (or the hypervisor stole "
                  "CPU) during " + ", ".join(f"{r.daemon} {r.load} (other {r.other_cpu or 0:.2f}"
                                             f", steal {r.steal_cpu or 0:.2f} cores)"
                                             for r in busy)
                  + ": their tails show that load as much as the daemon under test; rerun on "
                  "a quiet machine for numbers to compare against the goals."]
    lines += ["", "Goals:", ""]
    lines += [f"- {'PASS' if ok else 'FAIL'}: {text}" for text, ok in goals]
    lines += ["", "Columns: early = stop frame before last packet + timeout (safe, but the "
              "daemon's deadline did not come from our last packet: e.g. it was dropped); "
              "missed = no stop frame within 2 s; wrong = stopped for another reason; "
              "discarded = the bench's own send was late (descheduled), in a TCP trial the "
              "link timed out before the STOP was handled, or can-log lines were lost: sample "
              "dropped; lines lost = of those, the trials discarded because can-log lines "
              "were lost (the first stop frame seen may not have been the first sent).", ""]
    return "\n".join(lines)


def document(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> dict[str, Any]:
    """The JSON report: meta, goals, and per run its raw data and summaries (what
    bench/latency_tables.py reads)."""
    runs: list[dict[str, Any]] = []
    for r in results:
        d = asdict(r)
        d["summary_ms"] = {m: summarize(r.samples[m]) for m in METRICS}
        if r.flood is not None:
            d["flood"]["rate"] = r.flood.rate
        runs.append(d)
    return {"meta": meta, "runs": runs, "goals": [{"goal": g, "pass": ok} for g, ok in goals]}


def plot(results: list[RunResult], path: Path, timeout_ms: int,
         floor_samples: Sequence[float] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 0.001
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), squeeze=False)
    colors = {"estopd": "tab:blue", "baseline": "tab:orange", KEYED: "tab:green"}
    for row, m in enumerate(METRICS):
        for col, load in enumerate(("idle", "flood")):
            ax = axes[row][col]
            runs = [r for r in results if r.load == load and r.samples[m]]
            allv = [max(v, floor) for r in runs for v in r.samples[m]]
            if m == "overshoot" and load == "idle" and allv:
                allv += [max(v, floor) for v in floor_samples]
            if not allv:
                ax.set_axis_off()
                continue
            bins = log_bins(allv, floor)
            for r in runs:
                vals = [max(v, floor) for v in r.samples[m]]
                s = summarize(r.samples[m])
                ax.hist(vals, bins=bins, alpha=0.6, color=colors.get(r.daemon),
                        label=f"{r.daemon} (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if m == "overshoot" and load == "idle" and floor_samples:
                s = summarize(floor_samples)
                ax.hist([max(v, floor) for v in floor_samples], bins=bins, histtype="step",
                        color="k", lw=1,
                        label=f"machine timer wake (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if m == "overshoot":
                ax.axvline(GOAL_P999_MS[load], color="k", ls="--", lw=1,
                           label=f"goal p99.9 < {GOAL_P999_MS[load]:g} ms")
            ax.set_xscale("log")
            ax.set_xlabel("ms (log; values <= 0.001 ms drawn at 0.001)")
            ax.set_ylabel("trials")
            ax.set_title(f"{METRIC_TITLES[m]}, {load}")
            ax.legend(fontsize=8)
    fig.suptitle(f"estop stop latency, timeout {timeout_ms} ms")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--flood-child"]:
        sessions = [int(x, 16) for x in argv[4].split(",")] if len(argv) > 4 else None
        return flood_child([int(p) for p in argv[1].split(",")], float(argv[2]),
                           float(argv[3]), sessions)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000, help="trials per metric and run")
    ap.add_argument("--quick", action="store_true", help="smoke run: 100 trials")
    ap.add_argument("--timeout-ms", type=int, default=20)
    ap.add_argument("--flood-rate", type=float, default=80_000.0,
                    help="invalid packets/s sent during the flood runs (goal: >= 50,000)")
    ap.add_argument("--send-slack-ms", type=float, default=0.25,
                    help="discard a trial whose send call took longer than this")
    ap.add_argument("--block", type=int, default=50,
                    help="trials per daemon before switching to the other one")
    ap.add_argument("--max-run-s", type=float, default=300.0,
                    help="time limit of one load (both daemons)")
    ap.add_argument("--rt-prio", type=int, default=0, metavar="PRIO",
                    help="real-time daemons, as a deployment would run them: estopd with its "
                         "own --rt-prio PRIO (SCHED_FIFO loop, output threads normal), the "
                         "baseline under `chrt -f PRIO` (needs CAP_SYS_NICE); 0 = off")
    ap.add_argument("--bench-rt-prio", type=int, default=None, metavar="PRIO",
                    help="SCHED_FIFO priority of the bench's sender and can-log readers "
                         f"(default: --rt-prio minus {BENCH_BELOW_DAEMON}, at least 1, when "
                         "--rt-prio is set; 0 = normal priority)")
    ap.add_argument("--hog", type=int, default=0, metavar="N",
                    help="run N busy-loop processes at normal priority throughout (CPU "
                         "contention; 2 = one per core here)")
    ap.add_argument("--auth", action="store_true",
                    help="estopd with a fresh key (--key-file) against estopd without one; "
                         "authenticated link, flood of forged authenticated packets")
    ap.add_argument("--estopd", metavar="PATH", help="estopd binary (default: found like "
                    "`estop demo` does)")
    ap.add_argument("--only", choices=("estopd", "baseline"), help="run one daemon only "
                    "(with --auth: estopd = the keyed one)")
    ap.add_argument("--loads", default="idle,flood", help="comma-separated: idle,flood")
    ap.add_argument("--out", type=Path, default=HERE / "out")
    ap.add_argument("--no-floor", action="store_true",
                    help="skip the reference measurement of the machine's timer wake-up")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a goal fails")
    args = ap.parse_args(argv)
    n = 100 if args.quick else args.trials
    if not 0 <= args.rt_prio <= 99:
        ap.error("--rt-prio takes 1..99 (0 = off)")
    if args.bench_rt_prio is None:
        args.bench_rt_prio = max(1, args.rt_prio - BENCH_BELOW_DAEMON) if args.rt_prio else 0
    if not 0 <= args.bench_rt_prio <= 99:
        ap.error("--bench-rt-prio takes 1..99 (0 = normal priority)")
    if args.hog < 0:
        ap.error("--hog takes a number of busy loops >= 0")
    if args.auth and args.only == "baseline":
        ap.error("--auth compares estopd with and without a key; the baseline has no key")
    loads = [x for x in args.loads.split(",") if x]
    if any(x not in ("idle", "flood") for x in loads):
        ap.error("--loads takes idle and/or flood")

    exe = None
    if args.only != "baseline":
        exe = find_estopd(args.estopd)
        if exe is None:
            sys.stderr.write("stop_latency: estopd not found (make setup, or make -C firmware,"
                             " or --estopd PATH)\n")
            return 2
    estopd_extra = ["--rt-prio", str(args.rt_prio)] if args.rt_prio else []
    chrt: list[str] = []
    if args.rt_prio and args.only != "estopd" and not args.auth:
        found = shutil.which("chrt")
        if found is None:
            ap.error("--rt-prio needs chrt (util-linux) for the baseline")
        chrt = [found, "-f", str(args.rt_prio)]

    with tempfile.TemporaryDirectory(prefix="estop-bench-") as tmp:
        daemons: list[DaemonSpec] = []
        if args.auth:
            assert exe is not None
            key, key_file = make_key_file(Path(tmp))
            daemons.append(DaemonSpec(KEYED, [exe], key, key_file, estopd_extra))
            if args.only is None:
                daemons.append(DaemonSpec(KEYLESS, [exe], extra=estopd_extra))
        else:
            if exe is not None:
                daemons.append(DaemonSpec("estopd", [exe], extra=estopd_extra))
            if args.only != "estopd":
                daemons.append(DaemonSpec("baseline", [*chrt, sys.executable,
                                                       str(HERE / "baseline_asyncio.py")]))
        return _run(args, n, loads, daemons)


def priorities(args: argparse.Namespace, names: Sequence[str] = ()) -> str:
    """One sentence on who ran at which priority, for the report."""
    if args.rt_prio:
        base = "; the baseline under chrt -f" if "baseline" in names else ""
        daemon = (f"daemons SCHED_FIFO {args.rt_prio} (estopd: its own --rt-prio {args.rt_prio}"
                  f", its loop only, its output threads at normal priority{base})")
    else:
        daemon = "daemons at normal priority"
    if args.bench_rt_prio:
        bench = (f"the bench's sender and can-log readers SCHED_FIFO {args.bench_rt_prio}"
                 + (" (below the daemons, so the reader keeps up on a busy machine)"
                    if args.rt_prio else ""))
    else:
        bench = "the bench (sender and can-log readers) at normal priority"
    return f"{daemon}; {bench}"


class PrioError(Exception):
    """The bench could not change its own scheduling. ``str()`` is one line."""


def _prio(prio: int) -> None:
    """The calling thread to SCHED_FIFO ``prio`` (0: normal priority)."""
    try:
        set_realtime(prio)
    except OSError as exc:
        raise PrioError(f"cannot run the bench at real-time priority {prio} ({exc.strerror}; "
                        f"needs CAP_SYS_NICE or RLIMIT_RTPRIO)") from None


def _run(args: argparse.Namespace, n: int, loads: list[str], daemons: list[DaemonSpec]) -> int:
    t_start = time.monotonic()
    hogs = Hogs(args.hog) if args.hog else None
    results: list[RunResult] = []
    floor: dict[str, Any] = {}
    floor_samples: list[float] = []
    try:
        if not args.no_floor:
            say(f"reference: this machine's timer wake-up latency, {n} sleeps of "
                f"{args.timeout_ms} ms ...")
            meter = CpuMeter()
            for pid in hogs.pids if hogs else ():
                meter.watch(pid)
            if args.rt_prio:  # the floor a daemon at its priority could reach
                _prio(args.rt_prio)
            floor_samples = timer_floor(n, args.timeout_ms / 1000.0)
            _prio(0)
            floor["timer_floor_ms"] = summarize(floor_samples)
            floor["timer_floor_prio"] = args.rt_prio
            cpu = meter.finish()
            if cpu is not None:
                floor["timer_floor_other_cpu"] = round(cpu[0], 2)
                floor["timer_floor_steal"] = round(cpu[1], 2)
        if args.bench_rt_prio:
            _prio(args.bench_rt_prio)  # reset on fork: daemons, flood, hogs stay normal
        names = [d.name for d in daemons]
        say(f"priorities: {priorities(args, names)}"
            + (f"; {args.hog} busy loops" if hogs else ""))
        for load in loads:
            say(f"{load}: {' and '.join(d.name for d in daemons)} side by side, {n} trials per "
                f"metric each, alternating in blocks of {args.block} ...")
            for r in run_load(load, daemons, args, n, hogs.pids if hogs else ()):
                results.append(r)
                extra = f", flood {r.flood.rate:,.0f}/s" if r.flood else ""
                err = f", ERROR {r.error}" if r.error else ""
                lost = sum(r.lost_discards(m) for m in METRICS)
                say(f"  {r.daemon}: {len(r.samples['overshoot'])} + "
                    f"{len(r.samples['tcp_stop'])} samples, {lost} trials with log lines "
                    f"lost{extra}{err}")
            say(f"  {load} done in {results[-1].wall_s:.1f} s")
    except PrioError as exc:
        sys.stderr.write(f"stop_latency: {exc}\n")
        return 2
    finally:
        if hogs is not None:
            hogs.stop()
        with contextlib.suppress(OSError):
            set_realtime(0)

    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "host": platform.node(),
            "cpus": os.cpu_count(), "python": platform.python_version(),
            "timeout_ms": args.timeout_ms, "trials": n, "flood_rate": args.flood_rate,
            "send_slack_ms": args.send_slack_ms, "block": args.block,
            "rt_prio": args.rt_prio, "bench_rt_prio": args.bench_rt_prio,
            "priorities": priorities(args, [d.name for d in daemons]), "hog": args.hog,
            "hog_cpu_cores": None if hogs is None or hogs.cpu_cores is None
            else round(hogs.cpu_cores, 2),
            "auth": args.auth, "argv": sys.argv[1:],
            "commands": {d.name: Daemon(d.command, timeout_ms=args.timeout_ms,
                                        extra_args=d.extra, key_file=d.key_file).argv
                         for d in daemons},
            **floor, "bench_wall_s": round(time.monotonic() - t_start, 1)}
    goals = check_goals(results, auth=args.auth)
    md = markdown(results, meta, goals)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stop_latency.md").write_text(md)
    doc = document(results, meta, goals)
    doc["timer_floor_samples_ms"] = floor_samples
    (args.out / "stop_latency.json").write_text(json.dumps(doc, indent=1, allow_nan=True))
    plot(results, args.out / "stop_latency.png", args.timeout_ms, floor_samples)
    say()
    say(md)
    say(f"bench wall time {meta['bench_wall_s']} s; wrote {args.out}/stop_latency.md, "
        f".json, .png")
    if args.strict and not all(ok for _, ok in goals):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
