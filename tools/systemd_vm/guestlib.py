"""What the checks inside the VM share (guest side of `make systemd-vm`; runs on the guest's own
python3, 3.11 on Debian 12 and 3.13 on Debian 13, standard library only): commands, the unit's
properties, the journal, ESTOP_BRAKE frames read from vcan0, and the results file.

Times are the guest's CLOCK_MONOTONIC in seconds: systemd's *TimestampMonotonic properties, the
journal's __MONOTONIC_TIMESTAMP and the frames (kernel stamps) all convert to it.
"""

from __future__ import annotations

import bisect
import dataclasses
import errno
import json
import os
import re
import socket
import struct
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

UNIT = "estopd.service"
IFACE = "vcan0"
BRAKE_ID = 0x050
REASONS = {0: "none", 1: "boot", 2: "tcp_stop", 3: "udp_timeout", 4: "fault", 5: "lift"}
STATES = {0: "STOPPED", 1: "ARMED", 2: "SLOWING"}
# Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS) on x86-64; Python's socket module lacks the name.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


class CheckFailed(Exception):
    """A check's expectation did not hold; the message says what was measured."""


class HostStalled(CheckFailed):
    """A time bound failed while the host froze the whole guest (a busy machine: the guest's
    kernel saw its clock jump): the measurement says nothing of systemd; tried once more."""


def host_stall_s(since: float) -> float:
    """The longest freeze of the whole guest from since on, by its kernel's clocksource
    watchdog ('Long readout interval ... cs_nsec: N'), in seconds; 0 when none."""
    longest = 0.0
    for e in journal(unit=None, since_mono=since, grep="Long readout interval"):
        m = re.search(r"cs_nsec: (\d+)", str(e["MESSAGE"]))
        if m:
            longest = max(longest, int(m[1]) / 1e9)
    return longest


def timing_failed(since: float, message: str) -> CheckFailed:
    """The failure of a time bound: HostStalled where the guest was frozen meanwhile."""
    stall = host_stall_s(since)
    if stall > 0.2:
        return HostStalled(f"{message}; the host froze the guest {stall:.2f} s meanwhile")
    return CheckFailed(message)


def sh(argv: list[str] | str, timeout: float = 60.0, check: bool = True,
       env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Runs a command (a list, or a string for sh -c), output captured as text."""
    args = ["sh", "-c", argv] if isinstance(argv, str) else argv
    res = subprocess.run(args, capture_output=True, text=True, timeout=timeout, check=False,
                         env=env, stdin=subprocess.DEVNULL)
    if check and res.returncode != 0:
        raise CheckFailed(f"{args!r} exited {res.returncode}: "
                          f"{(res.stderr or res.stdout).strip()[-400:]}")
    return res


def now() -> float:
    return time.monotonic()


def show(*props: str, unit: str = UNIT) -> dict[str, str]:
    """systemctl show's properties of the unit."""
    out = sh(["systemctl", "show", unit, *(f"--property={p}" for p in props)]).stdout
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def mono(prop_value: str) -> float:
    """A *TimestampMonotonic property (microseconds) in seconds; 0 when unset."""
    return int(prop_value or 0) / 1e6


def wait_for(what: str, cond: Callable[[], Any], timeout: float, step: float = 0.02) -> Any:
    """Polls cond until it returns something true; CheckFailed after timeout seconds."""
    end = now() + timeout
    while True:
        got = cond()
        if got:
            return got
        if now() > end:
            raise CheckFailed(f"{what}: not within {timeout:.1f} s")
        time.sleep(step)


def main_pid() -> int:
    return int(show("MainPID")["MainPID"])


def active_pid(timeout: float, other_than: int = 0) -> int:
    """The unit's main PID once it is active (running) again, other than a given one."""
    def ready() -> int:
        p = show("ActiveState", "SubState", "MainPID")
        pid = int(p["MainPID"])
        ok = p["ActiveState"] == "active" and p["SubState"] == "running" and pid != other_than
        return pid if ok and pid else 0
    return int(wait_for(f"{UNIT} active (running)", ready, timeout))


# -- the journal ----------------------------------------------------------------------------
def journal(unit: str | None = UNIT, since_mono: float = 0.0, boot: str = "0",
            grep: str | None = None) -> list[dict[str, Any]]:
    """Journal entries (JSON) of this boot, of one unit (its own lines and systemd's about it),
    from a monotonic time on."""
    argv = ["journalctl", "-b", boot, "-o", "json", "--no-pager"]
    if unit:
        argv += ["-u", unit]
    if grep:
        argv += ["-g", grep]
    out = sh(argv, check=False).stdout
    entries = []
    for line in out.splitlines():
        try:
            e = json.loads(line)
        except ValueError:
            continue
        t = int(e.get("__MONOTONIC_TIMESTAMP", 0)) / 1e6
        if t >= since_mono:
            e["t"] = t
            msg = e.get("MESSAGE", "")
            e["MESSAGE"] = bytes(msg).decode(errors="replace") if isinstance(msg, list) else msg
            entries.append(e)
    return entries


def messages(entries: list[dict[str, Any]]) -> list[str]:
    return [str(e["MESSAGE"]) for e in entries]


def first_line(since: float, pattern: str, timeout: float = 10.0) -> float:
    """The time of the first journal line about the unit from since on that matches pattern
    (systemd's 'Scheduled restart job', 'Starting ...', 'Main process exited', ...)."""
    def find() -> float:
        for e in journal(since_mono=since):
            if re.search(pattern, str(e["MESSAGE"])):
                return float(e["t"])
        return 0.0
    return float(wait_for(f"a journal line /{pattern}/", find, timeout, step=0.1))


def estopd_events(entries: list[dict[str, Any]], event: str) -> list[dict[str, Any]]:
    """estopd's JSON log lines of one event (--log-json), each with the journal's time t."""
    out = []
    for e in entries:
        msg = str(e["MESSAGE"])
        if msg.startswith("{") and f'"event":"{event}"' in msg.replace(" ", ""):
            try:
                obj = json.loads(msg)
            except ValueError:
                continue
            obj["t"] = e["t"]
            out.append(obj)
    return out


# -- ESTOP_BRAKE frames on vcan0 --------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Frame:
    t: float  # monotonic seconds (the kernel's receive stamp)
    data: bytes

    @property
    def brakes(self) -> bool:
        return self.data[0] != 0 and self.data[1] == 100

    @property
    def state(self) -> str:
        return STATES.get(self.data[2], f"?{self.data[2]}")

    @property
    def reason(self) -> str:
        return REASONS.get(self.data[3], f"?{self.data[3]}")

    @property
    def counter(self) -> int:
        return self.data[6] & 0x0F

    def __str__(self) -> str:
        return f"{self.data.hex(' ')} ({self.state} {self.reason})"


class BrakeFrames:
    """Every ESTOP_BRAKE frame on vcan0 from start() on, with kernel stamps, through the
    interface going away and coming back (the socket is opened again)."""

    def __init__(self, iface: str = IFACE) -> None:
        self.iface = iface
        self.frames: list[Frame] = []
        self._times: list[float] = []  # the frames' stamps, for bisect
        self.gone: list[float] = []  # times the interface went away
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._offset = time.time() - time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> BrakeFrames:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    # The queries cost what they return, not what was kept: 100 frames a second pile up, and a
    # check that scanned them all at every poll of wait_for (50 a second) took most of the
    # guest's CPU from the command it waited for (a CI run: estop remote's release not seen
    # within 90 s, the guest busy 87 s of 91).
    def since(self, t: float) -> list[Frame]:
        with self._lock:
            return self.frames[bisect.bisect_left(self._times, t):]

    def first_since(self, t: float) -> Frame | None:
        with self._lock:
            i = bisect.bisect_left(self._times, t)
            return self.frames[i] if i < len(self.frames) else None

    def cursor(self, t: float) -> Callable[[], list[Frame]]:
        """A function that returns the frames from t on that it has not returned before (by
        position: a frame put in before one already returned, its stamp out of order, is
        missed and the last one returned again; one socket's kernel stamps come in order)."""
        with self._lock:
            at = bisect.bisect_left(self._times, t)

        def new() -> list[Frame]:
            nonlocal at
            with self._lock:
                got, at = self.frames[at:], len(self.frames)
            return got
        return new

    def _add(self, frame: Frame) -> None:
        with self._lock:  # in time order: at the end, or where a stamp out of order belongs
            i = bisect.bisect_right(self._times, frame.t)
            self._times.insert(i, frame.t)
            self.frames.insert(i, frame)

    def _open(self) -> socket.socket | None:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        try:
            s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            # only ID 0x050 (11-bit): filter id, mask
            s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER,
                         struct.pack("=II", BRAKE_ID, 0x7FF | socket.CAN_EFF_FLAG))
            s.settimeout(0.2)
            s.bind((self.iface,))
            return s
        except OSError:
            s.close()
            return None

    def _run(self) -> None:
        while not self._stop.is_set():
            s = self._open()
            if s is None:
                time.sleep(0.02)
                continue
            with s:
                while not self._stop.is_set():
                    try:
                        data, anc, _flags, _addr = s.recvmsg(16, 64)
                    except TimeoutError:
                        continue
                    except OSError as e:
                        if e.errno in (errno.ENODEV, errno.ENETDOWN, errno.ENXIO):
                            self.gone.append(time.monotonic())
                            break
                        raise
                    t = time.monotonic()
                    for level, kind, raw in anc:
                        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                            sec, nsec = struct.unpack("=qq", raw[:16])
                            t = sec + nsec / 1e9 - self._offset
                    self._add(Frame(t, bytes(data[8:16])))


# -- results ----------------------------------------------------------------------------------
class Results:
    """One JSON line per check in results.jsonl of the output share: name, ok, what was
    measured, and the reason of a failure."""

    def __init__(self, out: Path, system: str, phase: str) -> None:
        self.path = out / "results.jsonl"
        self.system = system
        self.phase = phase
        self.facts: dict[str, Any] = {}

    def record(self, name: str, ok: bool, measured: str, detail: str = "",
               took: tuple[float, float] = (0.0, 0.0)) -> None:
        line = {"system": self.system, "phase": self.phase, "check": name, "ok": ok,
                "measured": measured, "detail": detail, "wall_s": round(took[0], 1),
                "cpu_s": round(took[1], 1)}
        with self.path.open("a") as f:
            f.write(json.dumps(line) + "\n")
            f.flush()
            os.fsync(f.fileno())
        mark = "ok  " if ok else "FAIL"
        print(f"systemd-vm[{self.system}]: {mark} {name}: {measured} {detail}".rstrip(),
              flush=True)

    def fact(self, key: str, value: Any) -> None:
        self.facts[key] = value
        (self.path.parent / f"facts-{self.phase}.json").write_text(
            json.dumps(self.facts, indent=1, sort_keys=True))

    def run(self, name: str, fn: Callable[[], str]) -> bool:
        """Runs one check: fn returns what it measured, or raises CheckFailed (or anything).
        Its wall time and the guest's busy CPU time during it are kept beside."""
        t0, c0 = now(), busy_s()
        try:
            try:
                measured = fn()
            except HostStalled as e:
                measured = fn() + f" (tried twice: {e})"
        except CheckFailed as e:
            self.record(name, False, "", str(e), (now() - t0, busy_s() - c0))
            return False
        except Exception as e:  # a broken check is a failed check, with its reason
            self.record(name, False, "", f"{type(e).__name__}: {e}",
                        (now() - t0, busy_s() - c0))
            return False
        self.record(name, True, measured, took=(now() - t0, busy_s() - c0))
        return True


def busy_s() -> float:
    """The guest's CPU time spent busy so far (all CPUs, /proc/stat), in seconds."""
    fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq = (int(x) for x in fields[:7])
    return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")
