"""Live parts of the HIL harness: vcan, candump, the python-can bus monitor with the brake
controller emulator, the daemon under test, and the remote (UDP control, TCP stop channel).

Every wait here is bounded; nothing blocks forever. Wall-clock times (``time.time()``) are used
throughout because SocketCAN stamps frames with CLOCK_REALTIME.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import socket
import struct
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from estop.protocol import tcp, udp
from hilcheck import BrakeController, Frame, merge, read_stalls

MARKER_ID = 0x7FF  # harness marker frames (lowest priority ID, ignored by the checks)


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

class StallMonitor:
    """One ``stallmon.py`` per CPU (real-time priority): when did a CPU not run at all?"""

    def __init__(self, out: Path, python: str) -> None:
        cpus = sorted(os.sched_getaffinity(0))[:8]
        self.paths = [out / f"stalls-cpu{c}.txt" for c in cpus]
        script = str(Path(__file__).resolve().parent / "stallmon.py")
        self.procs = [subprocess.Popen([python, "-B", script, str(c), str(p)],
                                       stdin=subprocess.DEVNULL)
                      for c, p in zip(cpus, self.paths, strict=True)]

    def intervals(self) -> list[tuple[float, float]]:
        """Union over the CPUs of the intervals in which one could not run."""
        found: list[tuple[float, float]] = []
        for p in self.paths:
            try:
                found += read_stalls(p.read_text().splitlines())
            except OSError:
                pass
        return merge(found)

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


# --------------------------------------------------------------------------- bus monitor

@dataclass(frozen=True, slots=True)
class BusError:
    ts: float
    text: str


class BusMonitor:
    """python-can receiver thread: records every frame and drives the brake controller
    emulator in real time (its 50 ms watchdog is checked at least every millisecond)."""

    def __init__(self, iface: str) -> None:
        self.iface = iface
        self.bus = can.Bus(interface="socketcan", channel=iface, receive_own_messages=False)
        self.frames: list[Frame] = []
        self.errors: list[BusError] = []
        self.ctl = BrakeController()
        self.cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bus-monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            # Sleep in recv() until the next frame or the emulator's watchdog deadline.
            with self.cond:
                last, tripped = self.ctl.last_good, self.ctl.tripped
            wait = 0.05
            if last is not None and not tripped:
                wait = min(wait, max(0.0, last + self.ctl.silence_s - time.time()))
            msg = self._recv(wait)
            now = None
            if msg is None:
                # Nothing arrived until ``now``; a frame that slipped in meanwhile still counts
                # by its kernel timestamp, so look once more before declaring silence.
                now = time.time()
                msg = self._recv(0.0)
            with self.cond:
                if msg is not None:
                    fr = Frame(msg.timestamp, msg.arbitration_id, bytes(msg.data))
                    self.frames.append(fr)
                    self.ctl.on_frame(fr)
                elif now is not None:
                    self.ctl.on_tick(now)
                self.cond.notify_all()

    def _recv(self, timeout: float) -> can.Message | None:
        try:
            msg = self.bus.recv(timeout=timeout)
        except can.CanError as exc:  # ENETDOWN once when the link goes down, ...
            with self.cond:
                self.errors.append(BusError(time.time(), str(exc)))
            return None
        if msg is None or msg.is_error_frame or msg.is_remote_frame:
            return None
        return msg

    def index(self) -> int:
        with self.cond:
            return len(self.frames)

    def since(self, start: int) -> list[Frame]:
        with self.cond:
            return self.frames[start:]

    def window(self, t0: float, t1: float) -> list[Frame]:
        with self.cond:
            return [f for f in self.frames if t0 <= f.ts <= t1]

    def wait_for(self, pred: Callable[[Frame], bool], start: int,
                 timeout: float) -> Frame | None:
        """First frame from index ``start`` on that satisfies ``pred``, waiting at most
        ``timeout`` seconds for it."""
        end = time.monotonic() + timeout
        i = start
        with self.cond:
            while True:
                while i < len(self.frames):
                    if pred(self.frames[i]):
                        return self.frames[i]
                    i += 1
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(min(left, 0.05))

    def marker(self, text: bytes) -> Frame:
        """Send a marker frame from a separate socket and wait until it is seen."""
        start = self.index()
        with can.Bus(interface="socketcan", channel=self.iface) as tx:
            tx.send(can.Message(arbitration_id=MARKER_ID, data=text[:8], is_extended_id=False))
        fr = self.wait_for(lambda f: f.can_id == MARKER_ID and f.data == text[:8], start, 2.0)
        if fr is None:
            raise RigError(f"marker frame {text!r} was not received back on {self.iface}")
        return fr

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.shutdown()


# --------------------------------------------------------------------------- the daemon

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

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for raw in self.proc.stderr:
            t = time.time()
            line = raw.rstrip("\n")
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict):
                    rec = None
            except ValueError:
                rec = None
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


# --------------------------------------------------------------------------- the remote

NEUTRAL = udp.ControlPacket(0.0, 0.0, udp.Gear.NEUTRAL).encode()
DRIVE_GAS = udp.ControlPacket(0.3, -0.25, udp.Gear.DRIVE, udp.TurnSignal.LEFT).encode()


class UdpRemote:
    """Control packets to the daemon; a keepalive thread sends one every ``period`` s."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.last_send: float | None = None  # wall time taken just before the last sendto
        self.keepalive_times: list[float] = []
        self.sent = 0
        self.errors = 0

    def send(self, data: bytes) -> float:
        t = time.time()
        try:
            self.sock.send(data)
        except OSError:  # ECONNREFUSED from an earlier datagram while the daemon was down
            self.errors += 1
        self.sent += 1
        return t

    def start(self, data: bytes = NEUTRAL, period: float = 0.02) -> None:
        self.stop()
        self._stop.clear()

        def run() -> None:
            nxt = time.monotonic()
            while not self._stop.is_set():
                self.last_send = self.send(data)
                self.keepalive_times.append(self.last_send)
                nxt += period
                self._stop.wait(max(0.0, nxt - time.monotonic()))

        self._thread = threading.Thread(target=run, name="udp-keepalive", daemon=True)
        self._thread.start()

    def stop(self) -> float | None:
        """Stop the keepalive; returns the time of the last packet it sent."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2)
            if self._thread.is_alive():
                raise RigError("UDP keepalive thread did not stop")
            self._thread = None
        return self.last_send

    def max_gap(self, t0: float, t1: float) -> float:
        """Longest pause between keepalive packets sent in ``[t0, t1]`` (seconds)."""
        ts = [t for t in self.keepalive_times if t0 <= t <= t1]
        return max((b - a for a, b in zip(ts, ts[1:], strict=False)), default=0.0)

    def close(self) -> None:
        self.stop()
        self.sock.close()


@dataclass(frozen=True, slots=True)
class Exchange:
    reply: tcp.Reply
    t_send: float  # just before sendall
    t_reply: float  # when the complete reply was read


class StopClient:
    """One TCP connection of the stop channel."""

    def __init__(self, port: int, timeout: float = 2.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.asm = tcp.FrameAssembler()
        self.timeout = timeout
        self.seq = 0

    def request(self, msg_id: int) -> Exchange:
        self.seq += 1
        req = tcp.Request(msg_id, self.seq)
        t0 = time.time()
        self.sock.sendall(req.encode())
        end = time.monotonic() + self.timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise RigError(f"no reply to msg_id {msg_id:#x} within {self.timeout} s")
            self.sock.settimeout(left)
            data = self.sock.recv(64)
            if not data:
                raise RigError(f"connection closed instead of a reply to msg_id {msg_id:#x}")
            frames = self.asm.feed(data)
            if frames:
                t1 = time.time()
                rep = tcp.Reply.decode(frames[0])
                if rep.seq != self.seq:
                    raise RigError(f"reply seq {rep.seq}, request seq {self.seq}")
                if len(frames) > 1 or self.asm.pending:
                    raise RigError("more than one reply frame to one request")
                return Exchange(rep, t0, t1)

    def stop(self, stop_id: int = tcp.DEFAULT_STOP_ID) -> Exchange:
        return self.request(stop_id)

    def status(self) -> Exchange:
        return self.request(tcp.STATUS)

    def release(self) -> Exchange:
        return self.request(tcp.RELEASE)

    def close(self) -> None:
        self.sock.close()


def connect_retry(port: int, timeout: float) -> StopClient:
    end = time.monotonic() + timeout
    while True:
        try:
            return StopClient(port)
        except OSError as exc:
            if time.monotonic() >= end:
                raise RigError(f"cannot connect to the stop channel on port {port}: {exc}") \
                    from exc
            time.sleep(0.02)


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
