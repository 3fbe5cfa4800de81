"""Live parts of the HIL harness: vcan, candump, the python-can bus monitor with the brake
controller emulator, the daemon under test, and the remote (UDP control, TCP stop channel).

Every wait here is bounded; nothing blocks forever. Wall-clock times (``time.time()``) are used
throughout because SocketCAN stamps frames with CLOCK_REALTIME.
"""

from __future__ import annotations

import bisect
import fcntl
import json
import os
import queue
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from estop.protocol import auth, tcp, udp
from hilcheck import BrakeController, Frame, merge_more, read_stalls, udp_socket_drops

MARKER_ID = 0x7FF  # harness marker frames (lowest priority ID, ignored by the checks)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # root may exceed rmem_max
LAG_MAX_S = 10.0  # how far the bus monitor may fall behind the bus before a wait gives up


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
        self._offsets = [0] * len(self.paths)
        self._merged: list[tuple[float, float]] = []
        self._lock = threading.Lock()

    def intervals(self) -> list[tuple[float, float]]:
        """Union over the CPUs of the intervals in which one could not run (read on from where
        the previous call stopped: a loaded run writes thousands of lines)."""
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
                new += read_stalls(data[:end].decode(errors="replace").splitlines())
            self._merged = merge_more(self._merged, new)
            return self._merged

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
        # A large receive queue: under load this thread may fall seconds behind, and a frame
        # lost here would look like a frame the daemon never sent (candump would disagree).
        sock = getattr(self.bus, "socket", None)
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 8 << 20)
            except OSError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.frames: list[Frame] = []
        self.errors: list[BusError] = []
        self.ctl = BrakeController()
        self._tx: can.BusABC | None = None  # sends the marker frames
        self.max_lag = 0.0  # seconds this thread read a frame after its kernel timestamp
        self.max_lag_at = 0.0
        self.lag_giveups = 0  # waits given up because this thread was LAG_MAX_S behind
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
            batch = [] if msg is None else [msg]
            # Behind the bus (a loaded host): take what is queued in one go, one lock and one
            # wake-up of the waiting scenario for many frames, to catch up sooner.
            while batch and len(batch) < 64 and time.time() - batch[-1].timestamp > 0.05:
                more = self._recv(0.0)
                if more is None:
                    break
                batch.append(more)
            with self.cond:
                for m in batch:
                    lag = time.time() - m.timestamp  # how far behind the bus this thread is
                    if lag > self.max_lag:
                        self.max_lag, self.max_lag_at = lag, m.timestamp
                    fr = Frame(m.timestamp, m.arbitration_id, bytes(m.data))
                    self.frames.append(fr)
                    self.ctl.on_frame(fr)
                if not batch and now is not None:
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
        """First frame from index ``start`` on that satisfies ``pred``, if one is on the bus
        within ``timeout`` seconds from now. "Within" is bus time (kernel timestamps): when
        this thread lags behind the bus (a loaded host), it is waited for, up to LAG_MAX_S
        more, so that a frame that came in time is never missed for being read late."""
        t_bus_end = time.time() + timeout
        end = time.monotonic() + timeout + LAG_MAX_S
        i = start
        with self.cond:
            while True:
                while i < len(self.frames):
                    if pred(self.frames[i]):
                        return self.frames[i]
                    i += 1
                if self.frames and self.frames[-1].ts > t_bus_end:
                    return None  # read past the deadline: none came in time
                left = end - time.monotonic()
                if left <= 0:
                    self.lag_giveups += 1  # not a finding: this thread fell too far behind
                    return None
                self.cond.wait(min(left, 0.05))

    def marker(self, text: bytes) -> Frame:
        """Send a marker frame from a separate socket and wait until it is seen."""
        start = self.index()
        msg = can.Message(arbitration_id=MARKER_ID, data=text[:8], is_extended_id=False)
        for attempt in range(2):
            if self._tx is None:
                self._tx = can.Bus(interface="socketcan", channel=self.iface)
            try:
                self._tx.send(msg)
                break
            except can.CanError:
                # A socket keeps an error of its interface going down (ENETDOWN) for its next
                # send: a fresh socket then.
                self._tx.shutdown()
                self._tx = None
                if attempt:
                    raise
        fr = self.wait_for(lambda f: f.can_id == MARKER_ID and f.data == text[:8], start, 2.0)
        if fr is None:
            raise RigError(f"marker frame {text!r} was not received back on {self.iface}")
        return fr

    def sync(self) -> None:
        """Return once this thread has read every frame sent before now (a marker frame
        behind them: a socket's queue keeps the order)."""
        self.marker(b"HILSYNC")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.shutdown()
        if self._tx is not None:
            self._tx.shutdown()


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
        self.signal_mono: float | None = None  # the daemon's clock (t_mono) at the signal
        self.keyed = "--key-file" in argv  # the unit has a key (spec section 5)
        self.opts: dict[str, str] = {}  # the options a row asked for (Run.want_opts)

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
        self.signal_mono = time.monotonic()  # CLOCK_MONOTONIC, as estopd's t_mono
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
        self.lock = threading.Lock()
        self.last_send: float | None = None  # wall time taken just before the last sendto
        self.keepalive_times: list[float] = []
        self.sent = 0
        self.errors = 0

    def packet(self, body: bytes) -> bytes:
        """The datagram that carries the control body ``body`` (here: the body itself)."""
        return body

    def sent_since(self, t: float) -> int:
        """Keepalive packets sent at or after wall time ``t`` (the list is in time order and
        long: a binary search, as this is polled)."""
        return len(self.keepalive_times) - bisect.bisect_left(self.keepalive_times, t)

    def nth_since(self, t: float, n: int) -> float | None:
        """The send time of the ``n``-th keepalive packet (1: the first) at or after ``t``."""
        i = bisect.bisect_left(self.keepalive_times, t) + n - 1
        return self.keepalive_times[i] if i < len(self.keepalive_times) else None

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
                self.last_send = self.send(self.packet(data))
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
        ts = self.keepalive_times[bisect.bisect_left(self.keepalive_times, t0):
                                  bisect.bisect_right(self.keepalive_times, t1)]
        return max((b - a for a, b in zip(ts, ts[1:], strict=False)), default=0.0)

    def close(self) -> None:
        self.stop()
        self.sock.close()


@dataclass(frozen=True, slots=True)
class Exchange:
    reply: tcp.Reply
    t_send: float  # just before sendall
    t_reply: float  # when the complete reply was read
    auth: auth.AuthReply | None = None  # a 48-byte reply (to a 48-byte request)
    tag_ok: bool | None = None  # its tag verified under the unit's key, for this request
    frame: bytes = b""  # the request as sent


def read_reply(sock: socket.socket, asm: tcp.FrameAssembler, timeout: float,
               what: str) -> tuple[bytes, float]:
    """Reads exactly one reply frame (``asm`` knows its size) within ``timeout`` s: the frame
    and the time it was whole. ``what`` names the request in the errors."""
    end = time.monotonic() + timeout
    while True:
        left = end - time.monotonic()
        if left <= 0:
            raise RigError(f"no reply to {what} within {timeout} s")
        sock.settimeout(left)
        data = sock.recv(128)
        if not data:
            raise RigError(f"connection closed instead of a reply to {what}")
        frames = asm.feed(data)
        if frames:
            t1 = time.time()
            if len(frames) > 1 or asm.pending:
                raise RigError("more than one reply frame to one request")
            return frames[0], t1


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
        raw, t1 = read_reply(self.sock, self.asm, self.timeout, f"msg_id {msg_id:#x}")
        rep = tcp.Reply.decode(raw)
        if rep.seq != self.seq:
            raise RigError(f"reply seq {rep.seq}, request seq {self.seq}")
        return Exchange(rep, t0, t1)

    def stop(self, stop_id: int = tcp.DEFAULT_STOP_ID) -> Exchange:
        return self.request(stop_id)

    def lift(self) -> Exchange:
        return self.request(tcp.LIFT)

    def request_frame(self, msg_id: int, remote_id: int = 0, counter: int = 1) -> Exchange:
        """A 48-byte request frame (spec section 5.2, tag 16 zero bytes, session 0) on this
        connection, whose first 4 bytes tell the unit its form, and its 48-byte reply:
        ``tag_ok`` says whether the reply has the zero tag of a unit without a key and echoes
        the seq and counter."""
        self.seq += 1
        frame = auth.AuthRequest(msg_id, self.seq, remote_id, 0, counter).encode(None)
        t0 = time.time()
        self.sock.sendall(frame)
        raw, t1 = read_reply(self.sock, tcp.FrameAssembler(auth.REPLY_SIZE), self.timeout,
                             "a request frame")
        try:
            rep = auth.AuthReply.decode(raw, None)
        except tcp.FrameError as exc:
            raise RigError(f"bad reply frame {raw.hex(' ')}: {exc}") from exc
        ok = raw[32:] == bytes(16) and rep.seq == self.seq and rep.counter == counter
        return Exchange(rep.reply, t0, t1, rep, ok, frame)

    def status(self) -> Exchange:
        return self.request(tcp.STATUS)

    def release(self) -> Exchange:
        return self.request(tcp.RELEASE)

    def close(self) -> None:
        self.sock.close()


class AuthClient:
    """One TCP connection that speaks 48-byte request and reply frames (spec section 5).

    Requests carry ``remote_id``, the session this client believes in and a counter it raises
    with every request; they are tagged with ``key`` (None: 16 zero bytes). Every reply is
    checked against ``unit_key`` (the key the unit holds, known to the harness) and the
    request's own tag: ``tag_ok`` says whether it verified. A genuine reply teaches the
    client the unit's session. ``sent`` records every request frame as sent (for replays).
    """

    def __init__(self, port: int, key: bytes | None, unit_key: bytes, remote_id: int,
                 timeout: float = 2.0) -> None:
        self.port = port
        self.key = key
        self.unit_key = unit_key
        self.remote_id = remote_id
        self.session = 0
        self.counter = 0
        self.seq = 0
        self.timeout = timeout
        self.sent: list[bytes] = []
        self.sock: socket.socket | None = None
        self.connect()

    def connect(self) -> None:
        self.close()
        self.sock = socket.create_connection(("127.0.0.1", self.port), timeout=self.timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def frame(self, msg_id: int, counter: int | None = None) -> bytes:
        """A new request frame (raising the counter unless ``counter`` is given)."""
        self.seq += 1
        if counter is None:
            self.counter += 1
            counter = self.counter
        return auth.AuthRequest(msg_id, self.seq, self.remote_id, self.session,
                                counter).encode(self.key)

    def exchange(self, frame: bytes) -> Exchange:
        """Send one 48-byte request frame as it is and read its 48-byte reply."""
        assert self.sock is not None
        seq = struct.unpack_from("<I", frame, 8)[0]
        t0 = time.time()
        self.sock.sendall(frame)
        self.sent.append(frame)
        raw, t1 = read_reply(self.sock, tcp.FrameAssembler(auth.REPLY_SIZE), self.timeout,
                             "a request frame")
        tag = auth.request_tag(frame)
        try:
            rep = auth.AuthReply.decode(raw, self.unit_key, tag)
            ok = True
        except auth.TagMismatch:
            rep = auth.AuthReply.decode(raw, None)
            ok = False
        except tcp.FrameError as exc:
            raise RigError(f"bad reply frame {raw.hex(' ')}: {exc}") from exc
        if rep.seq != seq:
            raise RigError(f"reply seq {rep.seq}, request seq {seq}")
        if ok:
            self.session = rep.session
        return Exchange(rep.reply, t0, t1, rep, ok, frame)

    def request(self, msg_id: int, counter: int | None = None) -> Exchange:
        return self.exchange(self.frame(msg_id, counter))

    def status(self) -> Exchange:
        return self.request(tcp.STATUS)

    def release(self) -> Exchange:
        return self.request(tcp.RELEASE)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class AuthRemote(UdpRemote):
    """The key holder's remote: authenticated 60-byte control packets with a rising counter
    (its keepalive thread wraps every body), and an :class:`AuthClient` on the stop channel.
    It learns the unit's session with a STATUS request frame (session 0) and records every
    control packet it sent, with its time, so that an attacker's replay can be staged."""

    def __init__(self, udp_port: int, tcp_port: int, key: bytes, remote_id: int) -> None:
        super().__init__(udp_port)
        self.key = key
        self.remote_id = remote_id
        self.udp_counter = 0
        self.recorded: list[tuple[float, bytes]] = []
        self.tcp = AuthClient(tcp_port, key, key, remote_id)

    @property
    def session(self) -> int:
        return self.tcp.session

    def learn_session(self) -> Exchange:
        """(Re)connect and ask STATUS with session 0, as a remote does after a restart."""
        self.tcp.connect()
        self.tcp.session = 0
        ex = self.tcp.status()
        if not ex.tag_ok:
            raise RigError("the reply to STATUS does not verify under the key")
        return ex

    def packet(self, body: bytes) -> bytes:
        with self.lock:
            self.udp_counter += 1
            pkt = auth.AuthControlPacket(self.remote_id, self.session, self.udp_counter,
                                         udp.decode(body)).encode(self.key)
            self.recorded.append((time.time(), pkt))
        return pkt

    def release(self) -> Exchange:
        return self.tcp.release()

    def close(self) -> None:
        super().close()
        self.tcp.close()


def wrong_key(key: bytes) -> bytes:
    """A key that is not ``key`` (every byte changed)."""
    return bytes(b ^ 0x5A for b in key)


# --------------------------------------------------------------------------- the flooder

class Flooder:
    """``flood.py`` in a process of its own (see there): bursts and floods of invalid UDP."""

    def __init__(self, port: int, rate: float, python: str = sys.executable) -> None:
        script = str(Path(__file__).resolve().parent / "flood.py")
        self.proc = subprocess.Popen([python, "-B", script, str(port), "--rate", str(rate)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     bufsize=1)
        self.t_start = time.time()
        self.t_ready: float | None = None
        self._answers: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, name="flood-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._answers.put(line)

    def _say(self, line: str) -> None:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            raise RigError(f"flooder gone ({exc})") from exc

    def _answer(self, timeout: float) -> dict:
        try:
            rec = json.loads(self._answers.get(timeout=timeout))
        except queue.Empty:
            raise RigError(f"flooder did not answer within {timeout} s "
                           f"(exit code {self.proc.poll()})") from None
        if not isinstance(rec, dict) or "error" in rec:
            raise RigError(f"flooder: {rec}")
        return rec

    def ready(self, timeout: float = 20.0) -> float:
        """Wait for the line the flooder writes once it is up; returns its time."""
        if self.t_ready is None:
            self.t_ready = float(self._answer(timeout)["t"])
        return self.t_ready

    def burst(self, n: int, timeout: float = 10.0) -> dict:
        self._say(f"burst {n}")
        return self._answer(timeout)

    def start(self) -> None:
        self._say("flood")

    def stop(self, timeout: float = 10.0) -> dict:
        self._say("stop")
        return self._answer(timeout)

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self._say("quit")
                self.proc.wait(timeout=3)
            except (RigError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=3)
        self._reader.join(timeout=2)


class QueueWatch:
    """A thread that reads the daemon's UDP receive queue (/proc/net/udp) every ``period`` s:
    how full it got (bytes of the receive buffer in use, the kernel's count)."""

    def __init__(self, port: int, period: float = 0.005) -> None:
        self.port = port
        self.period = period
        self.max_bytes: int | None = None
        self.reads = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="queue-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            got = udp_drops(self.port)
            if got is not None:
                self.reads += 1
                self.max_bytes = max(self.max_bytes or 0, got[0])
            self._stop.wait(self.period)

    def stop(self) -> int | None:
        self._stop.set()
        self._thread.join(timeout=2)
        return self.max_bytes


def udp_drops(port: int) -> tuple[int, int] | None:
    """(rx_queue bytes, kernel drops) of the daemon's UDP socket, from /proc/net/udp (this
    network namespace)."""
    try:
        return udp_socket_drops(Path("/proc/net/udp").read_text(), port)
    except OSError:
        return None


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
