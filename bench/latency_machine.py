"""How busy the machine was during a stop-latency run (CPU of other processes, hypervisor
steal), its own timer wake-up latency (the floor no daemon can beat), and busy loops for CPU
contention (--hog). Linux /proc."""

from __future__ import annotations

import contextlib
import ctypes
import os
import subprocess
import sys
import time
from pathlib import Path


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
