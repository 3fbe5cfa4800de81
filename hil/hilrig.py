"""The HIL rig's set-up: vcan (and its link switched in-process), ports, candump (the
independent observer), the per-CPU stall monitors, the interface's counters.

Every wait here is bounded; nothing blocks forever. Wall-clock times (``time.time()``) are used
throughout because SocketCAN stamps frames with CLOCK_REALTIME.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import socket
import struct
import subprocess
import threading
import time
from pathlib import Path

from hilstalls import merge_more, read_stalls


class RigError(RuntimeError):
    """The rig itself could not do something (not a finding about the daemon)."""


def sh(cmd: list[str], timeout: float = 10.0, check: bool = True) -> subprocess.CompletedProcess:
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if check and res.returncode != 0:
        raise RigError(f"{' '.join(cmd)} failed ({res.returncode}): "
                       f"{(res.stderr or res.stdout).strip()}")
    return res


def setup_vcan(iface: str) -> None:
    sh(["modprobe", "vcan"], check=False)  # may be built in or loaded already
    if sh(["ip", "link", "show", iface], check=False).returncode == 0:
        sh(["ip", "link", "del", "dev", iface])
    sh(["ip", "link", "add", "dev", iface, "type", "vcan"])
    sh(["ip", "link", "set", "up", iface])


SIOCGIFFLAGS = 0x8913
SIOCSIFFLAGS = 0x8914
IFF_UP = 0x1


def set_link(iface: str, up: bool) -> tuple[float, float]:
    """``ip link set IFACE up|down`` done in-process (ioctl), so that the time it takes effect
    is known to well under a millisecond (spawning ``ip`` can take 100s of ms in a TCG VM).
    Returns the wall times just before and just after the change."""
    name = iface.encode()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        ifr = fcntl.ioctl(s, SIOCGIFFLAGS, struct.pack("16sH14x", name, 0))
        flags = struct.unpack("16sH14x", ifr)[1]
        flags = flags | IFF_UP if up else flags & ~IFF_UP
        t0 = time.time()
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sH14x", name, flags))
        return t0, time.time()


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- candump

class Candump:
    """``candump -L -D IFACE`` writing the whole bus to a file (the independent observer)."""

    def __init__(self, iface: str, path: Path) -> None:
        self.path = path
        self._out = open(path, "w")  # noqa: SIM115 - closed in stop()
        self._err_path = path.with_suffix(".stderr")
        self._err = open(self._err_path, "w")  # noqa: SIM115
        self.proc = subprocess.Popen(["candump", "-L", "-D", iface], stdout=self._out,
                                     stderr=self._err, stdin=subprocess.DEVNULL)

    def stop(self) -> int | None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self._out.close()
        self._err.close()
        return self.proc.returncode

    def stderr_text(self) -> str:
        return self._err_path.read_text(errors="replace")


# --------------------------------------------------------------------------- stall monitor

MON_BIN = Path(__file__).resolve().parent / "mon" / "build"  # hil/mon's make (hil/run)


class StallMonitor:
    """One ``stallmon`` per CPU (hil/mon, real-time priority): when did a CPU not run at all?
    With ``daemon_pidfile`` (the daemon an ordinary process: a TCG run), ``waitmon`` as well:
    when did the daemon wait on a run queue behind the harness's processes?"""

    def __init__(self, out: Path, daemon_pidfile: Path | None = None,
                 work: Path | None = None, bindir: Path = MON_BIN) -> None:
        """The monitors write into ``work`` (default ``out``), copied into ``out`` at stop():
        in a TCG guest ``out`` is the host's directory, each line written a round trip to the
        host, and the monitors wake 1,500 times a second at real-time priority (a local run
        measured 183 of the guest's 341 busy CPU seconds in their Python versions, writing
        there; hilrun puts ``work`` in /dev/shm)."""
        cpus = sorted(os.sched_getaffinity(0))[:8]
        for exe in ("stallmon", "waitmon"):
            if not os.access(bindir / exe, os.X_OK):
                raise RigError(f"no {bindir / exe}: build the monitors (make -C hil/mon)")
        self.out = out
        work = work or out
        work.mkdir(parents=True, exist_ok=True)
        self.paths = [work / f"stalls-cpu{c}.txt" for c in cpus]
        argvs = [[str(bindir / "stallmon"), str(c), str(p)]
                 for c, p in zip(cpus, self.paths, strict=True)]
        self.wait_path: Path | None = None
        if daemon_pidfile is not None:
            self.wait_path = work / "daemon-waits.txt"
            self.paths.append(self.wait_path)
            argvs.append([str(bindir / "waitmon"), str(daemon_pidfile), str(self.wait_path)])
        self.procs = [subprocess.Popen(a, stdin=subprocess.DEVNULL) for a in argvs]
        self._offsets = [0] * len(self.paths)
        self._merged: list[tuple[float, float]] = []
        self._waits: list[tuple[float, float]] = []
        self._lock = threading.Lock()

    def intervals(self) -> list[tuple[float, float]]:
        """Union of the intervals in which a CPU could not run, or the daemon waited for one
        (read on from where the previous call stopped: a loaded run writes thousands of lines)."""
        with self._lock:
            new: list[tuple[float, float]] = []
            for i, p in enumerate(self.paths):
                try:
                    with open(p, "rb") as f:
                        f.seek(self._offsets[i])
                        data = f.read()
                except OSError:
                    continue
                end = data.rfind(b"\n") + 1  # complete lines only
                self._offsets[i] += end
                got = read_stalls(data[:end].decode(errors="replace").splitlines())
                if p == self.wait_path:
                    self._waits = merge_more(self._waits, got)
                new += got
            self._merged = merge_more(self._merged, new)
            return self._merged

    def waits(self) -> list[tuple[float, float]]:
        """The daemon's waits on a run queue alone (none unless monitored), merged."""
        self.intervals()
        with self._lock:
            return self._waits

    def realtime(self) -> bool:
        try:
            return all(" rt 1 " in p.read_text().splitlines()[0] for p in self.paths)
        except (OSError, IndexError):
            return False

    def stop(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=3)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=3)
        for p in self.paths:
            if p.parent != self.out and p.exists():
                shutil.copyfile(p, self.out / p.name)


def cpu_s(pid: int, tid: int | None = None) -> float | None:
    """CPU seconds (user and system) a process, or one of its threads, has used; None if gone."""
    path = f"/proc/{pid}/task/{tid}/stat" if tid is not None else f"/proc/{pid}/stat"
    try:
        fields = Path(path).read_text().rsplit(")", 1)[1].split()
        return round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 2)
    except (OSError, IndexError, ValueError):
        return None


def cpu_busy_s() -> float | None:
    """CPU seconds all CPUs have spent busy (not idle, not waiting for I/O) since boot."""
    try:
        f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return round((sum(f[:8]) - f[3] - f[4]) / os.sysconf("SC_CLK_TCK"), 2)
    except (OSError, ValueError, IndexError):
        return None


def iface_stats(iface: str) -> dict[str, int]:
    base = Path("/sys/class/net") / iface / "statistics"
    out: dict[str, int] = {}
    for name in ("tx_packets", "tx_dropped", "tx_errors", "rx_packets"):
        try:
            out[name] = int((base / name).read_text())
        except OSError:
            pass
    return out


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
