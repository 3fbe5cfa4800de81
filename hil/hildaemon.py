"""The daemon under test as the HIL harness runs it: its process, its JSON log (stderr) read
by a thread, and the scheduling the kernel gives its threads (``--rt-prio``, as deployed).
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from estop.unit import events


@dataclass
class LogLine:
    t_wall: float  # when the harness read it
    raw: str
    rec: dict | None


class Daemon:
    """The daemon under test, with its JSON log (stderr) read by a thread."""

    def __init__(self, argv: list[str], log_path: Path) -> None:
        self.argv = argv
        self.log_path = log_path
        self.lines: list[LogLine] = []
        self.lock = threading.Lock()
        self._log = open(log_path, "a")  # noqa: SIM115 - closed by the reader thread
        self._log.write(f"# {' '.join(argv)}\n")
        self._log.flush()
        self.t_start = time.time()
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, name="daemon-log", daemon=True)
        self._reader.start()
        self.signal_time: float | None = None
        self.signal_mono: float | None = None  # the daemon's clock (t_mono) at the signal
        self.keyed = "--key-file" in argv  # the unit has a key (spec section 5)
        self.opts: dict[str, str] = {}  # the options a row asked for (Run.want_opts)
        self.sched: list[ThreadSched] = []  # its threads' scheduling once it ran (Run)

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for raw in self.proc.stderr:
            t = time.time()
            line = raw.rstrip("\n")
            ev = events.parse(line)  # the package's reader of estopd's log
            rec = dict(ev.fields) if ev is not None and ev.json else None
            with self.lock:
                self.lines.append(LogLine(t, line, rec))
            self._log.write(f"{t:.6f} {line}\n")
            self._log.flush()
        self._log.close()

    def events(self, name: str | None = None, since: float = 0.0) -> list[dict]:
        with self.lock:
            return [ln.rec for ln in self.lines if ln.rec is not None and ln.t_wall >= since
                    and (name is None or ln.rec.get("event") == name)]

    def non_json(self) -> list[str]:
        with self.lock:
            return [ln.raw for ln in self.lines if ln.rec is None]

    def wait_event(self, pred: Callable[[dict], bool], since: float,
                   timeout: float) -> dict | None:
        end = time.monotonic() + timeout
        while True:
            for rec in self.events(since=since):
                if pred(rec):
                    return rec
            if time.monotonic() >= end:
                return None
            time.sleep(0.005)

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def signal(self, sig: int) -> float:
        t = time.time()
        self.signal_mono = time.clock_gettime(time.CLOCK_BOOTTIME)  # estopd's t_mono clock
        self.proc.send_signal(sig)
        self.signal_time = t
        return t

    def wait(self, timeout: float) -> int | None:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def kill_hard(self) -> None:
        if self.alive:
            self.proc.kill()
            self.proc.wait(timeout=5)
        self._reader.join(timeout=2)


# --------------------------------------------------------------------------- its scheduling

SCHED_RESET_ON_FORK = 0x40000000  # or'ed into the policy sched_getscheduler(2) returns
POLICY_NAMES = {os.SCHED_OTHER: "OTHER", os.SCHED_FIFO: "FIFO", os.SCHED_RR: "RR",
                os.SCHED_BATCH: "BATCH", os.SCHED_IDLE: "IDLE"}


@dataclass(frozen=True, slots=True)
class ThreadSched:
    """How the kernel schedules one thread of a process."""

    tid: int
    name: str
    policy: str  # FIFO, RR, OTHER, ...
    priority: int  # the real-time priority (0 for OTHER)
    reset_on_fork: bool
    nice: int = 0

    def text(self) -> str:
        prio = f" {self.priority}" if self.policy in ("FIFO", "RR") else ""
        if self.policy == "OTHER" and self.nice:
            prio = f" nice {self.nice}"
        return f"{self.policy}{prio}{' reset-on-fork' if self.reset_on_fork else ''}"


def threads_sched(pid: int) -> list[ThreadSched]:
    """Every thread of ``pid`` (the main thread first) as the kernel schedules it now."""
    out: list[ThreadSched] = []
    try:
        tids = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return out
    for tid in sorted(tids, key=lambda t: t != pid):
        try:
            raw = os.sched_getscheduler(tid)
            prio = os.sched_getparam(tid).sched_priority
            nice = os.getpriority(os.PRIO_PROCESS, tid)
            name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
        except OSError:
            continue  # the thread ended meanwhile
        policy = raw & ~SCHED_RESET_ON_FORK
        out.append(ThreadSched(tid, name, POLICY_NAMES.get(policy, str(policy)), prio,
                               bool(raw & SCHED_RESET_ON_FORK), nice))
    return out


def sched_text(threads: list[ThreadSched]) -> str:
    """``loop FIFO 50 reset-on-fork; 2 other threads OTHER`` (the main thread, the loop, first;
    the others grouped by what they run with)."""
    if not threads:
        return "unknown (process gone)"
    main, rest = threads[0], threads[1:]
    groups: dict[str, int] = {}
    for t in rest:
        groups[t.text()] = groups.get(t.text(), 0) + 1
    more = "; ".join(f"{n} other thread{'s' if n > 1 else ''} {g}" for g, n in groups.items())
    return f"loop {main.text()}" + (f"; {more}" if more else "")
