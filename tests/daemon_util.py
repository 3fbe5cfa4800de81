"""Runs the real ``estopd`` for the integration tests (tests/test_estopd_*.py).

The daemon is started on loopback with free ports (``--udp-port 0 --tcp-port 0 --bind
127.0.0.1``), its can-log on stdout and its event log on stderr, both redirected to files (a
file never fills up, so the daemon can never block on a test that is busy elsewhere). The
ports come from the ``start`` line. :class:`Daemon` is a context manager that always kills
the process on exit.

Packets and replies go through the Python codecs (``estop.protocol``, via tests/core_util.py),
written apart from the C sources, so the daemon is checked against a second reading of
PROTOCOL.md. The can-log line format is checked here with its own strict pattern.
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import pytest

from core_util import packet, reply_fields, request
from estop.protocol.crc import e2e_crc8

ROOT = Path(__file__).resolve().parents[1]
T = TypeVar("T")


def build_preload_shim(source: Path, out_dir: Path) -> Path:
    """An LD_PRELOAD shim built from one C file: the daemon tests' fault injection (a fake
    SocketCAN, a suspend of the host, a preemption between two clock reads)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.fail("no C compiler: run `make setup` (deps/debian-packages.txt, group build)")
    so = out_dir / f"{source.stem}.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-Wall", "-Wextra", "-Werror", "-o", str(so),
                    str(source), "-ldl"], check=True, timeout=60)
    return so


def first_new_match(items: Callable[[], Sequence[T]], pred: Callable[[T], bool], after: int,
                    timeout: float, where: str) -> T:
    """The first element from index `after` on of a growing list that matches, polled every
    5 ms. Each element is tried once: re-testing all since `after` at every poll made a wait
    cost more the longer a test ran (a daemon logs about 100 frames a second). The list is
    scanned once more after the deadline, so an element that came in while the waiter slept
    through it still counts."""
    deadline = time.monotonic() + timeout
    i = after
    while True:
        seen = items()
        for x in seen[i:]:
            if pred(x):
                return x
        i = max(i, len(seen))
        if time.monotonic() > deadline:
            raise AssertionError(f"no matching {where} in {timeout} s")
        time.sleep(0.005)

STOP_ID = 0xE570E570
MSG_STATUS = 1
MSG_RELEASE = 2
MSG_LIFT = 3
ACK = 0x80
NAK = 0x81
STOPPED, ARMED, SLOWING = 0, 1, 2
R_NONE, R_BOOT, R_TCP_STOP, R_UDP_TIMEOUT, R_FAULT, R_LIFT = range(6)
SLOW_LEVEL = 30  # the default slow level L (PROTOCOL.md 4)
BRAKE_ID = 0x050
STATUS_ID = 0x051
BRAKE_DATA_ID = 0x0E57
STATUS_DATA_ID = 0x0E58

# Text `start ... udp=127.0.0.1:41234 tcp=127.0.0.1:41235 ...` or the JSON form of it.
START_RE = re.compile(r'\bstart\b.*\budp"?[=:]"?(?P<uhost>[\d.]+):(?P<uport>\d+)\b'
                      r'.*\btcp"?[=:]"?(?P<thost>[\d.]+):(?P<tport>\d+)\b')
CANLOG_RE = re.compile(r"^\((?P<sec>\d+)\.(?P<usec>\d{6})\) (?P<iface>\S+) "
                       r"(?P<id>[0-9A-F]{3})#(?P<data>(?:[0-9A-F]{2})*)$")


# ---- encoding (PROTOCOL.md 1, 2, 4) ---------------------------------------------------------

# The daemon tests' names for the shared test-side encoders.
udp_packet = packet
tcp_frame = request


@dataclass(frozen=True)
class Reply:
    msg: int
    seq: int
    state: int
    reason: int
    flags: int
    nak: int


def parse_reply(raw: bytes) -> Reply:
    return Reply(*reply_fields(raw))


@dataclass(frozen=True)
class Frame:
    t: float  # CLOCK_REALTIME seconds
    iface: str
    can_id: int
    data: bytes

    @property
    def state(self) -> int:
        return self.data[2]

    @property
    def reason(self) -> int:
        return self.data[3]

    @property
    def counter(self) -> int:
        return self.data[6] & 0x0F

    def crc_ok(self) -> bool:
        data_id = BRAKE_DATA_ID if self.can_id == BRAKE_ID else STATUS_DATA_ID
        return len(self.data) == 8 and self.data[7] == e2e_crc8(data_id, self.data[:7])

    def is_brake(self) -> bool:
        return self.can_id == BRAKE_ID


def parse_canlog_line(line: str) -> Frame:
    m = CANLOG_RE.match(line)
    assert m is not None, f"not a can-utils log line: {line!r}"
    t = int(m["sec"]) + int(m["usec"]) / 1e6
    return Frame(t, m["iface"], int(m["id"], 16), bytes.fromhex(m["data"]))


def check_frames(frames: list[Frame], slow_level: int = SLOW_LEVEL) -> None:
    """Every frame: DLC 8, good CRC, alive counters 0..14 in sequence per ID, brake layout
    (brake_request and brake_level by state: STOPPED 1/100, ARMED 0/0, SLOWING 2/L)."""
    last: dict[int, int] = {}
    for f in frames:
        assert f.can_id in (BRAKE_ID, STATUS_ID), f
        assert f.crc_ok(), f"bad CRC-8: {f}"
        assert f.data[6] >> 4 == 0 and f.counter <= 14, f
        if f.can_id in last:
            assert f.counter == (last[f.can_id] + 1) % 15, f"counter jump {last[f.can_id]} -> {f}"
        last[f.can_id] = f.counter
        if f.is_brake():
            stopped = f.state == STOPPED
            assert f.state in (STOPPED, ARMED, SLOWING), f
            assert (f.data[0], f.data[1]) == {STOPPED: (1, 100), ARMED: (0, 0),
                                              SLOWING: (2, slow_level)}[f.state], f
            assert f.data[5] == 0, f
            assert (f.reason == R_NONE) == (not stopped), f


# ---- the daemon -----------------------------------------------------------------------------

def locate_estopd() -> str | None:
    """$ESTOPD (nothing else when it is set), the repo's firmware/build/estopd, or estopd on
    PATH; None when there is none. The tests reach it through the ``estopd`` session fixture
    (tests/conftest.py), which skips or fails where it is missing."""
    given = os.environ.get("ESTOPD")
    cands = (given,) if given else (str(ROOT / "firmware" / "build" / "estopd"),
                                    shutil.which("estopd"))
    for cand in cands:
        if cand and os.path.isfile(cand) and os.access(cand, os.X_OK):
            return cand
    return None


def find_estopd() -> str:
    """The estopd binary, for a test that asked for the ``estopd`` fixture (which skipped or
    failed already where there is none)."""
    exe = locate_estopd()
    if exe is None:
        pytest.fail("estopd binary not found, and this test does not ask for the estopd "
                    "fixture (tests/conftest.py), which says what to do")
    return exe


def with_auth(args: Iterable[str]) -> list[str]:
    """args plus --no-auth, unless they choose a key (or no key) themselves."""
    args = list(args)
    return args if {"--key-file", "--no-auth"} & set(args) else [*args, "--no-auth"]


def run_estopd(args: Iterable[str], timeout: float = 10.0,
               auth: bool = True) -> subprocess.CompletedProcess[str]:
    """Runs estopd to completion (for options that end it at once); with `auth`, --no-auth is
    added where the arguments name neither it nor --key-file."""
    argv = with_auth(args) if auth else list(args)
    return subprocess.run([find_estopd(), *argv], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL, check=False)


class _Tail:
    """Complete lines of a file that another process appends to."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._buf = b""
        self._pos = 0
        self.lines: list[str] = []

    def poll(self) -> list[str]:
        with self.path.open("rb") as fh:
            fh.seek(self._pos)
            chunk = fh.read()
        self._pos += len(chunk)
        self._buf += chunk
        *done, self._buf = self._buf.split(b"\n")
        new = [d.decode() for d in done]
        self.lines.extend(new)
        return new


_DAEMON_NUMBERS = itertools.count(1)


class Daemon:
    """One estopd process on loopback; use as a context manager (always killed on exit)."""

    def __init__(self, tmp_path: Path, *extra: str) -> None:
        self.argv = [find_estopd(), *with_auth(["--udp-port", "0", "--tcp-port", "0", "--bind",
                                                "127.0.0.1", "--can-log", "-", *extra])]
        # files of this daemon's own: id(self) comes back once an object is freed, and the
        # files are opened for appending, so a later daemon read its predecessor's start line
        n = next(_DAEMON_NUMBERS)
        self.out_path = tmp_path / f"canlog-{n}.log"
        self.err_path = tmp_path / f"stderr-{n}.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self.udp_port = 0
        self.tcp_port = 0
        self.start_line = ""
        self._out = _Tail(self.out_path)
        self._frames: list[Frame] = []  # self._out's lines parsed so far
        self._err = _Tail(self.err_path)
        self._udp: socket.socket | None = None
        self.env: dict[str, str] = {}  # added to the environment of the process

    # -- life cycle
    def start(self, wait_s: float = 10.0) -> Daemon:
        # append mode: a test may add lines of its own (the dashboard's bad-input test), and
        # O_APPEND keeps each process's whole lines intact
        with self.out_path.open("ab") as out, self.err_path.open("ab") as err:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=out,
                                         stderr=err, env={**os.environ, **self.env})
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            for line in self._err.poll():
                m = START_RE.search(line)
                if m:
                    self.start_line = line
                    self.udp_port, self.tcp_port = int(m["uport"]), int(m["tport"])
                    return self
            if self.proc.poll() is not None:
                raise AssertionError(f"estopd exited {self.proc.returncode}: {self.log()}")
            time.sleep(0.005)
        raise AssertionError(f"estopd printed no start line: {self.log()}")

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.kill()

    def kill(self) -> None:
        if self._udp is not None:
            self._udp.close()
            self._udp = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def signal(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
        """Sends sig and waits for the exit code."""
        assert self.proc is not None
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=timeout)

    # -- output
    def log(self) -> list[str]:
        self._err.poll()
        return list(self._err.lines)

    def frames(self) -> list[Frame]:
        # Each line parsed once: wait_frame polls every 5 ms, and parsing the whole can-log
        # (110 lines a second) at every poll made a wait cost more the longer the test ran.
        self._out.poll()
        lines = self._out.lines
        self._frames.extend(parse_canlog_line(line) for line in lines[len(self._frames):])
        return list(self._frames)

    def wait_log(self, pred: Callable[[str], bool], timeout: float = 5.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            for line in self.log():
                if pred(line):
                    return line
            if time.monotonic() > deadline:
                raise AssertionError(f"no matching log line in {timeout}s: {self.log()}")
            time.sleep(0.005)

    def wait_frame(self, pred: Callable[[Frame], bool], timeout: float = 5.0,
                   after: int = 0) -> Frame:
        """First frame from index `after` on that matches."""
        return first_new_match(self.frames, pred, after, timeout, "frame in the can-log")

    def count_once_armed(self, timeout: float = 5.0) -> int:
        """How many frames the can-log holds once the first ARMED brake frame is in it. The
        daemon writes its can-log from a thread, so a RELEASE's ACK can come before the last
        frames of the boot stop are in the file; a search for a STOPPED frame after a count
        taken too early finds one of those (seen at load 10)."""
        self.wait_frame(lambda f: f.is_brake() and f.state == ARMED, timeout=timeout)
        return len(self.frames())

    # -- inputs
    def send_udp(self, payload: bytes) -> None:
        if self._udp is None:
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.sendto(payload, ("127.0.0.1", self.udp_port))

    def connect(self, timeout: float = 5.0) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.tcp_port), timeout=timeout)

    def request(self, msg_id: int, seq: int, sock: socket.socket | None = None) -> Reply:
        """One request on a connection (a fresh one when sock is None), its reply."""
        own = sock is None
        s = self.connect() if sock is None else sock
        try:
            s.sendall(tcp_frame(msg_id, seq))
            return parse_reply(recv_exact(s, 16))
        finally:
            if own:
                s.close()

    def make_live(self, n: int = 6, gas: float = 0.0) -> None:
        """Enough valid packets, quickly, for the link to count as live."""
        for _ in range(n):
            self.send_udp(udp_packet(gas=gas))

    def arm(self, timeout: float = 5.0) -> Reply:
        """Link live, neutral, RELEASE: the unit goes ARMED. A RELEASE refused for want of a
        live link (NAK 2) is tried again with fresh packets until ``timeout``: on a loaded
        machine this process can stall past the unit's timeout between its packets and its
        RELEASE (seen here at load 10), and the link is then rightly silent."""
        deadline = time.monotonic() + timeout
        while True:
            self.make_live()
            time.sleep(0.01)  # let the packets arrive before the TCP request overtakes them
            reply = self.request(MSG_RELEASE, 1)
            if reply.nak != 2 or time.monotonic() > deadline:
                break
        assert reply.msg == ACK and reply.state == ARMED, reply
        return reply


def recv_exact(s: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            raise ConnectionError(f"closed after {len(buf)} of {n} bytes")
        buf += chunk
    return buf


def state_lines(lines: list[str]) -> list[str]:
    return [line for line in lines if " state " in line]


def udp_reads(lines: list[str]) -> dict[str, int]:
    """The latest udp_reads line's numbers: max_round (the most datagrams read in one loop
    round), budget and deadline_cuts (drains cut short by a silence deadline)."""
    found = [s for s in lines if " udp_reads " in s]
    return {k: int(v) for k, v in (f.split("=") for f in found[-1].split()[3:])} if found else {}
