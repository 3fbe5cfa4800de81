"""The load the HIL harness puts on the daemon from processes of its own, and what it watches
of it: the UDP flooder (flood.py), the connect storm (storm.py), the ``estop`` command started
ahead, the daemon's UDP receive queue, and a tap on loopback that times the datagrams a command
sends.
"""

from __future__ import annotations

import ctypes
import json
import os
import queue
import select
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

from estop.unit.udpsocket import udp_socket
from hilrig import RigError


class Helper:
    """A helper script of this folder in a process of its own, started with the run (a Python
    start under TCG on a busy host can take tens of seconds): commands one per line on its
    standard input, every answer one JSON line on its standard output."""

    def __init__(self, script: str, args: list[str], python: str = sys.executable) -> None:
        self.name = Path(script).stem
        path = str(Path(__file__).resolve().parent / script)
        self.proc = subprocess.Popen([python, "-B", path, *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, bufsize=1)
        self.t_start = time.time()
        self.t_ready: float | None = None
        self._answers: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, name=f"{self.name}-out", daemon=True)
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
            raise RigError(f"{self.name} gone ({exc})") from exc

    def _answer(self, timeout: float) -> dict:
        try:
            rec = json.loads(self._answers.get(timeout=timeout))
        except queue.Empty:
            raise RigError(f"{self.name} did not answer within {timeout} s "
                           f"(exit code {self.proc.poll()})") from None
        if not isinstance(rec, dict) or "error" in rec:
            raise RigError(f"{self.name}: {rec}")
        return rec

    def ready(self, timeout: float = 20.0) -> float:
        """Wait for the line the helper writes once it is up; returns its time."""
        if self.t_ready is None:
            self.t_ready = float(self._answer(timeout)["t"])
        return self.t_ready

    def stop(self, timeout: float = 10.0) -> dict:
        """End what runs (a flood, a storm); its answer."""
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


class Flooder(Helper):
    """``flood.py`` (see there): bursts and floods of invalid UDP."""

    def __init__(self, port: int, rate: float, python: str = sys.executable) -> None:
        super().__init__("flood.py", [str(port), "--rate", str(rate)], python)

    def burst(self, n: int, timeout: float = 10.0) -> dict:
        self._say(f"burst {n}")
        return self._answer(timeout)

    def start(self) -> None:
        self._say("flood")


class Storm(Helper):
    """``storm.py`` (see there): busy connections that hold every place of the stop channel
    and a storm of new connections."""

    def __init__(self, port: int, busy: int, busy_ms: float, connect_ms: float,
                 python: str = sys.executable) -> None:
        super().__init__("storm.py", [str(port), "--busy", str(busy), "--busy-ms", str(busy_ms),
                                      "--connect-ms", str(connect_ms)], python)

    def start(self, timeout: float = 10.0) -> dict:
        """Start the storm; returns once every busy connection has had a reply."""
        self._say("storm")
        return self._answer(timeout)


# What the ``estop`` script runs (its console entry point: ``estop.cli.main`` on its
# arguments), once for every line on standard input: the command's code in a process of its
# own, without its interpreter's start and imports inside the row that runs it (the modules
# `estop stop` loads took 60-80 ms natively, 3-8 s in a loaded TCG VM, where nothing is
# compiled ahead; a Python start there takes 10-35 s). It starts niced, not to slow the rows
# running meanwhile, and runs each press at normal priority again, as an operator's would.
LAUNCH = """import os, sys
os.nice(19)
sys.argv[0] = "estop"
from estop.cli import build_parser, main
build_parser()  # what main() imports as it builds its parser, loaded now
import estop.client.keyfile, estop.client.oneshot, estop.client.channel
print("ready", flush=True)
while sys.stdin.readline():
    try:
        os.setpriority(os.PRIO_PROCESS, 0, 0)
    except OSError:
        pass
    code = main()
    print(f"\\n#exit {code}", flush=True)
    os.nice(19)
"""
EXIT_MARK = "#exit "


class EstopCommand:
    """The ``estop`` command with ``args``, in a process of its own started ahead (with the run)
    and run on every :meth:`go` (its output and exit code). Never closed by closing its input
    (that only ends it after a press): :meth:`close` kills it."""

    def __init__(self, args: list[str]) -> None:
        estop = shutil.which("estop")
        if estop is None:
            raise RigError("the estop command is not on PATH (make setup)")
        with open(estop) as f:  # the interpreter the script names (#!)
            first = f.readline()
        python = first[2:].strip() if first.startswith("#!") else sys.executable
        self.args = args
        self.proc = subprocess.Popen([python, "-B", "-c", LAUNCH, *args],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1)
        # its output is read from the descriptor (_line), never through self.proc.stdout
        self.t_go = 0.0
        self.is_ready = False
        self._buf = b""

    def _line(self, end: float) -> str | None:
        """The next line of its output ("" when it ended), or None when none came by ``end``
        (monotonic). Read from the descriptor with a buffer of its own: a buffered reader
        could hold the next line where select() does not see it."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        while b"\n" not in self._buf:
            if not select.select([fd], [], [], max(0.0, end - time.monotonic()))[0]:
                return None
            chunk = os.read(fd, 65536)
            if not chunk:
                rest, self._buf = self._buf, b""
                return rest.decode(errors="replace")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode(errors="replace") + "\n"

    def ready(self, timeout: float) -> None:
        """Wait until its imports are done (bounded)."""
        if self.is_ready:
            return
        line = self._line(time.monotonic() + timeout)
        if line is None or line.strip() != "ready":
            self.close()
            raise RigError(f"estop {' '.join(self.args[:1])} did not start within {timeout:g} s"
                           + (f": {line.strip()[:200]}" if line else ""))
        self.is_ready = True

    def go(self, timeout: float) -> tuple[int | None, str]:
        """Run it once; its exit code and output, or None when it did not end within
        ``timeout`` (then it is killed)."""
        assert self.proc.stdin is not None
        end = time.monotonic() + timeout
        self.t_go = time.time()
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        out: list[str] = []
        while (line := self._line(end)) is not None:
            if not line:  # it ended
                break
            if line.startswith(EXIT_MARK):
                return int(line[len(EXIT_MARK):]), "".join(out).strip()
            out.append(line)
        self.close()
        return None, "".join(out).strip()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=5)
        for f in (self.proc.stdin, self.proc.stdout):
            if f is not None:
                f.close()


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
    network namespace; estop.unit.udpsocket)."""
    sock = udp_socket(port)
    return None if sock is None else (sock.rx_queue, sock.drops)


# --------------------------------------------------------------------------- loopback tap

ETH_P_IP = 0x0800
SO_ATTACH_FILTER = 26
SO_TIMESTAMPNS = 35  # SCM_TIMESTAMPNS: the kernel's time of the packet, a struct timespec
SO_RCVBUFFORCE = 33


class _SockFilter(ctypes.Structure):
    _fields_ = [("code", ctypes.c_uint16), ("jt", ctypes.c_uint8), ("jf", ctypes.c_uint8),
                ("k", ctypes.c_uint32)]


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_uint16), ("filter", ctypes.POINTER(_SockFilter))]


def udp_port_filter(port: int, payload: int) -> list[tuple[int, int, int, int]]:
    """A classic BPF program for a packet socket without link header (SOCK_DGRAM): IPv4 UDP,
    not a fragment, to ``port``, with ``payload`` bytes (as ``tcpdump -dd 'udp dst port P and
    udp[4:2] = 8 + N'`` makes it, less the link layer). The kernel drops everything else, so
    the queue holds only what is looked for (the keepalive's datagrams filled it once)."""
    return [
        (0x30, 0, 0, 9),            # ldb [9]: protocol
        (0x15, 0, 8, 17),           # jeq UDP, else drop
        (0x28, 0, 0, 6),            # ldh [6]: flags and fragment offset
        (0x45, 6, 0, 0x1FFF),       # jset fragment: drop
        (0xB1, 0, 0, 0),            # ldxb 4*([0]&0xf): header length
        (0x48, 0, 0, 2),            # ldh [x+2]: destination port
        (0x15, 0, 3, port),         # jeq port, else drop
        (0x48, 0, 0, 4),            # ldh [x+4]: UDP length
        (0x15, 0, 1, 8 + payload),  # jeq header + payload, else drop
        (0x06, 0, 0, 0xFFFF),       # ret: take it
        (0x06, 0, 0, 0),            # ret: drop
    ]


class UdpTap:
    """A packet socket on ``lo`` that keeps every UDP datagram of ``payload`` bytes to ``port``
    with the kernel's time of it (SO_TIMESTAMPNS, CLOCK_REALTIME as the CAN frames' stamps).
    It sees a datagram as it is sent (and again as it is received): so it tells when another
    process, e.g. the ``estop`` command, sent its first datagram, to the microsecond, without
    touching it."""

    def __init__(self, port: int, payload: int, iface: str = "lo") -> None:
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_DGRAM, socket.htons(ETH_P_IP))
        prog = udp_port_filter(port, payload)
        insns = (_SockFilter * len(prog))(*(_SockFilter(*i) for i in prog))
        fprog = _SockFprog(len(prog), insns)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER,
                             bytes(ctypes.string_at(ctypes.addressof(fprog),
                                                    ctypes.sizeof(fprog))))
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 4 << 20)  # root: past rmem_max
        except OSError:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind((iface, 0))
        self.sock.setblocking(False)

    def read(self) -> list[tuple[float, bytes]]:
        """Every datagram queued so far: (kernel time, UDP payload), in order."""
        out: list[tuple[float, bytes]] = []
        while True:
            try:
                data, anc, _flags, _addr = self.sock.recvmsg(
                    2048, socket.CMSG_SPACE(struct.calcsize("ll")))
            except BlockingIOError:
                return out
            ts = time.time()  # no stamp: the time it was read (later, never earlier)
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = struct.unpack("ll", raw[:struct.calcsize("ll")])
                    ts = sec + nsec / 1e9
            ihl = (data[0] & 0x0F) * 4
            out.append((ts, data[ihl + 8:]))

    def close(self) -> None:
        self.sock.close()
