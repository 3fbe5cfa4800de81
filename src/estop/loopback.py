"""Runs ``estopd`` on loopback and talks to it: the part shared by ``estop demo`` and the
stop-latency and memory benchmarks in ``bench/``.

:class:`Daemon` starts the binary with free loopback ports and reads its can-log (stdout) and
its log (stderr) on threads; :class:`Link` is the remote's side (UDP control packets, one TCP
connection for requests).
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

from estop.protocol import can, canlog, tcp, udp

__all__ = [
    "Daemon",
    "DaemonError",
    "Link",
    "find_estopd",
    "is_stop_frame",
    "parse_start_ports",
    "stamp",
]


# --------------------------------------------------------------------------------------------
# Reading the daemon's output


def stamp(rec: canlog.CanLogRecord) -> float:
    """A can-log record's realtime stamp in seconds (comparable with time.time())."""
    return rec.timestamp_us / 1_000_000


def is_stop_frame(rec: canlog.CanLogRecord) -> bool:
    """An ESTOP_BRAKE frame that requests the brake."""
    return rec.can_id == can.BRAKE_ID and len(rec.data) == can.DLC and rec.data[0] == 1


_PORT_RE = {
    kind: re.compile(kind + r"[A-Za-z_]*\"?\s*[=:]\s*\"?(?:[0-9A-Za-z.\[\]:]*:)?(\d{1,5})\b")
    for kind in ("udp", "tcp")
}


def parse_start_ports(line: str) -> tuple[int, int] | None:
    """(udp_port, tcp_port) from a daemon's ``start`` log line, text or JSON; else None.

    Accepts ``udp=5700``, ``udp_port=5700``, ``udp=127.0.0.1:5700``, ``"udp_port": 5700`` ...
    """
    if not re.search(r"\bstart\b", line):
        return None
    found = []
    for kind in ("udp", "tcp"):
        m = _PORT_RE[kind].search(line)
        if m is None:
            return None
        found.append(int(m.group(1)))
    return found[0], found[1]


# --------------------------------------------------------------------------------------------
# Finding and running the daemon


class DaemonError(RuntimeError):
    """The daemon could not be found, started, or it died. ``str()`` is one line."""


def find_estopd(explicit: str | None = None) -> str | None:
    """Path of the estopd binary: ``explicit``, $ESTOPD, beside this Python (the venv's bin),
    on PATH, or the repo's firmware/build/estopd. None when there is none."""
    candidates: list[Path] = []
    for given in (explicit, os.environ.get("ESTOPD")):
        if given:
            return given if Path(given).is_file() or shutil.which(given) else None
    candidates.append(Path(sys.executable).parent / "estopd")
    on_path = shutil.which("estopd")
    if on_path:
        candidates.append(Path(on_path))
    candidates.append(Path(__file__).resolve().parents[2] / "firmware" / "build" / "estopd")
    for cand in candidates:
        if cand.is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


class Daemon:
    """An estopd-compatible daemon on loopback with free ports and its can-log on a pipe.

    ``command`` is the program (and any leading arguments, e.g. ``[python, baseline.py]``).
    Every can-log line arrives as a :class:`canlog.CanLogRecord` on :attr:`frames`; stderr
    lines are kept in :attr:`log_lines`. Use as a context manager: the process is always
    ended. The unit has the key in ``key_file``, or none (``--no-auth``).
    """

    def __init__(self, command: Sequence[str], *, timeout_ms: int = 200,
                 extra_args: Sequence[str] = (), key_file: str | None = None) -> None:
        auth = ["--key-file", key_file] if key_file is not None else ["--no-auth"]
        self.argv = [*command, "--bind", "127.0.0.1", "--udp-port", "0", "--tcp-port", "0",
                     "--timeout-ms", str(timeout_ms), "--can-log", "-", *auth, *extra_args]
        self.timeout_ms = timeout_ms
        self.frames: queue.Queue[canlog.CanLogRecord] = queue.Queue()
        self.log_lines: list[str] = []
        self.udp_port = 0
        self.tcp_port = 0
        self.returncode: int | None = None
        self.bad_lines = 0
        self._proc: subprocess.Popen[str] | None = None
        self._started = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc else None

    def start(self, wait_s: float = 10.0) -> None:
        try:
            self._proc = subprocess.Popen(
                self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE, text=True, bufsize=1)
        except OSError as exc:
            raise DaemonError(f"cannot run {self.argv[0]}: {exc.strerror}") from exc
        assert self._proc.stdout is not None and self._proc.stderr is not None
        for target, stream in ((self._read_frames, self._proc.stdout),
                               (self._read_log, self._proc.stderr)):
            th = threading.Thread(target=target, args=(stream,), daemon=True)
            th.start()
            self._threads.append(th)
        deadline = time.monotonic() + wait_s
        while not self._started.wait(0.05):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                last = self.log_lines[-1] if self.log_lines else "no output"
                raise DaemonError(f"{Path(self.argv[0]).name} did not start ({last})")

    def _read_frames(self, stream: IO[str]) -> None:
        for line in stream:
            try:
                self.frames.put(canlog.parse_line(line))
            except canlog.CanLogError:
                self.bad_lines += 1

    def _read_log(self, stream: IO[str]) -> None:
        for line in stream:
            self.log_lines.append(line.rstrip("\n"))
            if not self._started.is_set():
                ports = parse_start_ports(line)
                if ports is not None:
                    self.udp_port, self.tcp_port = ports
                    self._started.set()

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, wait_s: float = 3.0) -> int | None:
        """SIGTERM, wait (SIGKILL if it hangs), collect the output; return the exit code."""
        proc = self._proc
        if proc is None:
            return None
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(wait_s)
        for th in self._threads:
            th.join(wait_s)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
        self.returncode = proc.returncode
        return self.returncode

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# --------------------------------------------------------------------------------------------
# The remote's side: UDP control packets and the TCP stop channel


class Link:
    """Raw sockets to a daemon on loopback; every send returns time.time() just before it."""

    def __init__(self, udp_port: int, tcp_port: int, host: str = "127.0.0.1",
                 reply_timeout_s: float = 2.0) -> None:
        self.addr = (host, udp_port)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.tcp = socket.create_connection((host, tcp_port), timeout=reply_timeout_s)
        self.tcp.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._asm = tcp.FrameAssembler()
        self._seq = 0
        self._packets: dict[tuple[float, float, int], bytes] = {}

    def send_control(self, gas: float = 0.0, steering: float = 0.0,
                     gear: int = udp.Gear.NEUTRAL) -> float:
        key = (gas, steering, gear)
        data = self._packets.get(key)
        if data is None:
            data = udp.ControlPacket(gas, steering, gear).encode()
            if len(self._packets) < 256:
                self._packets[key] = data
        t = time.time()
        self.udp.sendto(data, self.addr)
        return t

    def send_request(self, msg_id: int) -> tuple[int, float]:
        """Send one request; return (seq, time just before sending)."""
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        data = tcp.Request(msg_id, self._seq).encode()
        t = time.time()
        self.tcp.sendall(data)
        return self._seq, t

    def read_reply(self, seq: int) -> tcp.Reply:
        while True:
            for frame in self._asm.feed(b""):
                reply = tcp.Reply.decode(frame)
                if reply.seq == seq:
                    return reply
            chunk = self.tcp.recv(4096)
            if not chunk:
                raise DaemonError("the daemon closed the TCP connection")
            for frame in self._asm.feed(chunk):
                reply = tcp.Reply.decode(frame)
                if reply.seq == seq:
                    return reply

    def request(self, msg_id: int) -> tuple[tcp.Reply, float]:
        seq, t = self.send_request(msg_id)
        return self.read_reply(seq), t

    def close(self) -> None:
        self.udp.close()
        self.tcp.close()
