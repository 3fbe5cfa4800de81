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

Outputs: a Markdown table (printed and saved), JSON with the raw samples, and a PNG histogram,
in bench/out/ by default. Goals are checked and printed; the exit code is 0 unless the bench
could not run (or --strict and a goal failed).

    bench/stop_latency.py [--quick] [--trials N] [--timeout-ms 20] [--flood-rate 80000]
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
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from estop.loopback import Daemon, DaemonError, Link, find_estopd, is_stop_frame, stamp
from estop.protocol import can, tcp, udp

HERE = Path(__file__).resolve().parent
METRICS = ("overshoot", "tcp_stop")
METRIC_TITLES = {"overshoot": "timeout overshoot", "tcp_stop": "TCP stop latency"}
GOAL_FLOOD_RATE = 50_000.0
GOAL_P999_MS = {"idle": 1.0, "flood": 2.0}
GOAL_AHEAD_FACTOR = 5.0
BUSY_CORES = 0.25  # other processes' CPU during a run above which the report warns
BUSY_STEAL = 0.05  # hypervisor steal (cores) above which the report warns


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


def flood_child(ports: list[int], rate: float, max_s: float) -> int:
    """Send invalid datagrams at ``rate``/s to 127.0.0.1:ports[i] until SIGTERM, end of
    stdin, or max_s. A line on stdin holding an index switches the target (the pacing goes
    on without a burst). At the end print one JSON line: per port, packets sent and seconds
    spent on it."""
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
    payloads = FLOOD_PAYLOADS
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
        due = start + total / rate
        if now < due:
            time.sleep(min(due - now, 0.001))
            continue
        for i in range(batch):
            try:
                sock.sendto(payloads[i & 3], addr)
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

    @property
    def rate(self) -> float:
        return self.sent / self.elapsed_s if self.elapsed_s > 0 else 0.0


class Flood:
    """One flooder child aimed at one of several daemons' UDP ports at a time."""

    def __init__(self, ports: list[int], rate: float, max_s: float) -> None:
        self.ports = ports
        self.rate = rate
        self._drops0 = {p: udp_drops(p) for p in ports}
        self._proc: subprocess.Popen[str] = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--flood-child",
             ",".join(map(str, ports)), str(rate), str(max_s)],
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
        stats = {p: FloodStats(self.rate) for p in self.ports}
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

    def add_sample(self, metric: str, value_ms: float) -> None:
        self.samples[metric].append(value_ms)
        self.sample_times[metric].append(round(time.time(), 3))

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


class Trials:
    def __init__(self, daemon: Daemon, link: Link, timeout_ms: int, send_slack_s: float,
                 result: RunResult, seed: int = 1) -> None:
        self.d = daemon
        self.link = link
        self.timeout_s = timeout_ms / 1000.0
        self.slack = send_slack_s
        self.r = result
        self.rng = random.Random(seed)

    def send(self, gas: float, gear: int) -> tuple[float, bool]:
        """Send one control packet; (time before the send, send took <= slack)."""
        t = self.link.send_control(gas, 0.0, gear)
        return t, time.time() - t <= self.slack

    def release(self) -> float | None:
        """Bring the unit to ARMED; time.time() after the ACK, None if it keeps refusing.

        First a random pause of 0..10 ms (one brake period), so that trials do not lock onto
        the phase of the daemon's periodic work (each trial starts right after a stop frame).
        """
        time.sleep(self.rng.uniform(0.0, 0.010))
        for _ in range(50):
            for _ in range(5):
                self.link.send_control(0.0, 0.0, udp.Gear.NEUTRAL)
            time.sleep(0.0005)
            reply, _t = self.link.request(tcp.RELEASE)
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
                if can.StatusFrame.parse(rec.data).invalid_packets == 255:
                    self.r.status_invalid_saturated += 1
            elif is_stop_frame(rec) and stamp(rec) >= after:
                return stamp(rec), can.BrakeFrame.parse(rec.data).reason

    def timeout_trial(self) -> bool:
        """One timeout trial; True when it produced a sample."""
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
        stop = self.wait_stop(t_ack, self.timeout_s + 2.0)
        if stop is None:
            self.r.missed["overshoot"] += 1
            return False
        t_stop, reason = stop
        why = ("late send" if late else "gap between packets" if gap
               else "stop before the last packet" if t_stop < t_last else None)
        if why is not None:
            self.r.discard("overshoot", why)
            return False
        if reason != can.Reason.UDP_TIMEOUT:
            self.r.wrong_reason["overshoot"] += 1
            return False
        self.r.add_sample("overshoot", (t_stop - (t_last + self.timeout_s)) * 1000.0)
        return True

    def tcp_trial(self) -> bool:
        t_ack = self.release()
        if t_ack is None:
            return False
        _t_pkt, quick = self.send(0.3, udp.Gear.DRIVE)
        seq, t_stop = self.link.send_request(tcp.DEFAULT_STOP_ID)
        quick = quick and time.time() - t_stop <= self.slack
        stop = self.wait_stop(t_ack, 2.0)
        self.link.read_reply(seq)
        if stop is None:
            self.r.missed["tcp_stop"] += 1
            return False
        t_frame, reason = stop
        if reason == can.Reason.UDP_TIMEOUT:
            # the link timed out before the STOP was handled (the bench or the daemon was
            # held up, or the kernel dropped the drive packet): a stop, but not the TCP path
            self.r.discard("tcp_stop", "link timed out first")
            return False
        if reason != can.Reason.TCP_STOP:
            self.r.wrong_reason["tcp_stop"] += 1
            return False
        if not quick:
            self.r.discard("tcp_stop", "late send")
            return False
        self.r.add_sample("tcp_stop", (t_frame - t_stop) * 1000.0)
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


def run_load(load: str, daemons: list[tuple[str, list[str]]], args: argparse.Namespace,
             n: int) -> list[RunResult]:
    """All daemons side by side under one load: they run at once, and trials alternate
    between them in blocks, so background load on the machine falls on both alike. The
    flood (one child) is aimed at the daemon whose block is running."""
    t0 = time.monotonic()
    cons = [Contender(name, Daemon(cmd, timeout_ms=args.timeout_ms),
                      RunResult(name, load, args.timeout_ms)) for name, cmd in daemons]
    flood: Flood | None = None
    try:
        for c in cons:
            try:
                c.daemon.start()
                c.link = Link(c.daemon.udp_port, c.daemon.tcp_port)
                c.trials = Trials(c.daemon, c.link, args.timeout_ms,
                                  args.send_slack_ms / 1000.0, c.result)
            except (DaemonError, OSError) as exc:
                c.result.error = str(exc)
        live = [c for c in cons if c.trials is not None]
        if load == "flood" and live:
            flood = Flood([c.daemon.udp_port for c in cons], args.flood_rate,
                          args.max_run_s + 30.0)
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
                    target = min(n, len(c.result.samples["overshoot"]) + args.block)
                    try:
                        c.attempts += c.trials.run(target, deadline, args.block * 3)
                    except (DaemonError, OSError, tcp.FrameError) as exc:
                        c.result.error = str(exc)
                    c.result.add_cpu(meter.finish())
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
    wall = time.monotonic() - t0
    for c in cons:
        c.result.wall_s = wall
    return [c.result for c in cons]


# --------------------------------------------------------------------------------------------
# Reporting


def check_goals(results: list[RunResult]) -> list[tuple[str, bool]]:
    by = {(r.daemon, r.load): r for r in results}
    goals: list[tuple[str, bool]] = []
    for load in ("idle", "flood"):
        e, b = by.get(("estopd", load)), by.get(("baseline", load))
        if e is None:
            continue
        ok_run = e.error is None and len(e.samples["overshoot"]) > 0
        p = summarize(e.samples["overshoot"])["p99.9"]
        lim = GOAL_P999_MS[load]
        goals.append((f"estopd p99.9 timeout overshoot {load}: {fmt_ms(p)} ms < {lim} ms",
                      ok_run and p < lim))
        missing = sum(e.missed.values()) + sum(e.wrong_reason.values())
        goals.append((f"estopd {load}: every trial stopped, with the right reason "
                      f"({missing} missed or wrong)", ok_run and missing == 0))
        if b is not None and b.samples["overshoot"]:
            pb = summarize(b.samples["overshoot"])["p99.9"]
            goals.append((f"estopd p99.9 overshoot {load} at most 1/{GOAL_AHEAD_FACTOR:g} of "
                          f"the baseline's ({fmt_ms(p)} vs {fmt_ms(pb)} ms)",
                          ok_run and p * GOAL_AHEAD_FACTOR <= pb))
        if load == "flood":
            for r in (e, b):
                if r is not None and r.flood is not None:
                    goals.append((f"flood at {r.daemon}: {r.flood.rate:,.0f} packets/s while "
                                  f"aimed at it >= {GOAL_FLOOD_RATE:,.0f}",
                                  r.flood.rate >= GOAL_FLOOD_RATE))
    return goals


def markdown(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> str:
    lines = [
        "# Stop latency: estopd vs asyncio baseline",
        "",
        f"{meta['date']} on {meta['host']} ({meta['cpus']} CPUs, Python {meta['python']}); "
        f"timeout {meta['timeout_ms']} ms; {meta['trials']} trials per cell; flood target "
        f"{meta['flood_rate']:,.0f} invalid packets/s on loopback. All times in ms.",
        "",
        "| daemon | load | metric | n | p50 | p99 | p99.9 | max | early | missed | wrong | "
        "discarded |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in results:
        for m in METRICS:
            s = summarize(r.samples[m])
            early = str(r.early(m)) if m == "overshoot" else "-"
            lines.append(
                f"| {r.daemon} | {r.load} | {METRIC_TITLES[m]} | {s['n']} | {fmt_ms(s['p50'])} |"
                f" {fmt_ms(s['p99'])} | {fmt_ms(s['p99.9'])} | {fmt_ms(s['max'])} | {early} |"
                f" {r.missed[m]} | {r.wrong_reason[m]} | {r.discarded[m]} |")
    floor = meta.get("timer_floor_ms")
    if floor:
        lines += ["", f"Reference, this machine's own timer wake-up latency ({floor['n']} sleeps "
                  f"of {meta['timeout_ms']} ms, timer slack 1 ns, before the daemons start): "
                  f"p50 {fmt_ms(floor['p50'])}, p99 {fmt_ms(floor['p99'])}, p99.9 "
                  f"{fmt_ms(floor['p99.9'])}, max {fmt_ms(floor['max'])} ms (other CPU "
                  f"{meta.get('timer_floor_other_cpu', 'n/a')} cores, steal "
                  f"{meta.get('timer_floor_steal', 'n/a')}). A timeout stop's tail at or below "
                  f"this comes from the machine, not the daemon."]
    lines += ["", "Flood (per run): the sender's count over its own run time; kernel drops: "
              "datagrams the daemon's socket dropped (receive buffer full); STATUS: the "
              "daemon's own ESTOP_STATUS frames whose invalid-packet count (per 100 ms) "
              "saturated at 255, i.e. it saw >= 2,550 invalid packets/s.", ""]
    for r in results:
        if r.flood is not None:
            f = r.flood
            drops = "n/a" if f.kernel_drops is None else f"{f.kernel_drops:,}"
            lines.append(f"- {r.daemon}: {f.sent:,} packets in {f.elapsed_s:.1f} s = "
                         f"{f.rate:,.0f} packets/s; kernel drops {drops}; STATUS saturated "
                         f"{r.status_invalid_saturated} of {r.status_frames}")
    lines += ["", "Per run: wall time of the load (both daemons); CPU that other processes on "
              "this machine used meanwhile (cores, averaged over the daemon's blocks; not the "
              "bench, its daemons or its flooder) and hypervisor "
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
              "discarded = the bench's own send was late (descheduled), or in a TCP trial the "
              "link timed out before the STOP was handled: sample dropped.", ""]
    return "\n".join(lines)


def plot(results: list[RunResult], path: Path, timeout_ms: int,
         floor_samples: Sequence[float] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 0.001
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), squeeze=False)
    colors = {"estopd": "tab:blue", "baseline": "tab:orange"}
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
        return flood_child([int(p) for p in argv[1].split(",")], float(argv[2]),
                           float(argv[3]))
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
                    help="run both daemons under `chrt -f PRIO` (SCHED_FIFO, needs "
                         "CAP_SYS_NICE), as a real-time deployment would; 0 = off")
    ap.add_argument("--estopd", metavar="PATH", help="estopd binary (default: found like "
                    "`estop demo` does)")
    ap.add_argument("--only", choices=("estopd", "baseline"), help="run one daemon only")
    ap.add_argument("--loads", default="idle,flood", help="comma-separated: idle,flood")
    ap.add_argument("--out", type=Path, default=HERE / "out")
    ap.add_argument("--no-floor", action="store_true",
                    help="skip the reference measurement of the machine's timer wake-up")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a goal fails")
    args = ap.parse_args(argv)
    n = 100 if args.quick else args.trials

    daemons: list[tuple[str, list[str]]] = []
    if args.only != "baseline":
        exe = find_estopd(args.estopd)
        if exe is None:
            sys.stderr.write("stop_latency: estopd not found (make setup, or make -C firmware,"
                             " or --estopd PATH)\n")
            return 2
        daemons.append(("estopd", [exe]))
    if args.only != "estopd":
        daemons.append(("baseline", [sys.executable, str(HERE / "baseline_asyncio.py")]))
    loads = [x for x in args.loads.split(",") if x]
    if any(x not in ("idle", "flood") for x in loads):
        ap.error("--loads takes idle and/or flood")

    if args.rt_prio:
        chrt = shutil.which("chrt")
        if chrt is None:
            ap.error("--rt-prio needs chrt (util-linux)")
        daemons = [(name, [chrt, "-f", str(args.rt_prio), *cmd]) for name, cmd in daemons]

    t_start = time.monotonic()
    results: list[RunResult] = []
    floor: dict[str, Any] = {}
    floor_samples: list[float] = []
    if not args.no_floor:
        say(f"reference: this machine's timer wake-up latency, {n} sleeps of "
            f"{args.timeout_ms} ms ...")
        meter = CpuMeter()
        floor_samples = timer_floor(n, args.timeout_ms / 1000.0)
        floor["timer_floor_ms"] = summarize(floor_samples)
        cpu = meter.finish()
        if cpu is not None:
            floor["timer_floor_other_cpu"] = round(cpu[0], 2)
            floor["timer_floor_steal"] = round(cpu[1], 2)
    for load in loads:
        say(f"{load}: {' and '.join(d for d, _ in daemons)} side by side, {n} trials per "
            f"metric each, alternating in blocks of {args.block} ...")
        for r in run_load(load, daemons, args, n):
            results.append(r)
            extra = f", flood {r.flood.rate:,.0f}/s" if r.flood else ""
            err = f", ERROR {r.error}" if r.error else ""
            say(f"  {r.daemon}: {len(r.samples['overshoot'])} + {len(r.samples['tcp_stop'])} "
                f"samples{extra}{err}")
        say(f"  {load} done in {results[-1].wall_s:.1f} s")

    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "host": platform.node(),
            "cpus": os.cpu_count(), "python": platform.python_version(),
            "timeout_ms": args.timeout_ms, "trials": n, "flood_rate": args.flood_rate,
            "send_slack_ms": args.send_slack_ms, "block": args.block,
            "rt_prio": args.rt_prio, "commands": {k: v for k, v in daemons}, **floor,
            "bench_wall_s": round(time.monotonic() - t_start, 1)}
    goals = check_goals(results)
    md = markdown(results, meta, goals)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stop_latency.md").write_text(md)
    runs: list[dict[str, Any]] = []
    doc: dict[str, Any] = {"meta": meta, "runs": runs,
                           "goals": [{"goal": g, "pass": ok} for g, ok in goals]}
    for r in results:
        d = asdict(r)
        d["summary_ms"] = {m: summarize(r.samples[m]) for m in METRICS}
        if r.flood is not None:
            d["flood"]["rate"] = r.flood.rate
        runs.append(d)
    (args.out / "stop_latency.json").write_text(json.dumps(doc, indent=1, allow_nan=True))
    doc["timer_floor_samples_ms"] = floor_samples
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
