"""Helpers of the touch remote's browser test (tests/test_touch_browser.py): the remote as a
process, a UDP tap between it and estopd, a TCP relay that can cut the page's WebSocket, and
a phone (a Playwright page with touch emulation) whose fingers are touch events dispatched
through the DevTools protocol."""

from __future__ import annotations

import contextlib
import re
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from estop.protocol import tcp
from estop.protocol.auth import CONTROL_SIZE, REQUEST_SIZE, AuthControlPacket
from net_util import SO_TIMESTAMPNS

LOCAL = "127.0.0.1"


def kind(data: bytes) -> str:
    """What a datagram of the remote is: control, lift, stop or other."""
    if len(data) == CONTROL_SIZE:
        return "control"
    if len(data) == REQUEST_SIZE:
        msg_id = struct.unpack_from("<I", data, 4)[0]
        return "lift" if msg_id == tcp.LIFT else "stop" if msg_id == tcp.DEFAULT_STOP_ID \
            else "other"
    return "other"


class UdpTap:
    """A UDP port on loopback between the remote and estopd: keeps the kernel's receive time
    of every datagram (SO_TIMESTAMPNS, wall clock) and forwards it to the unit at once."""

    def __init__(self, target_port: int) -> None:
        self.target = (LOCAL, target_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.bind((LOCAL, 0))
        self.sock.settimeout(0.02)
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.port: int = self.sock.getsockname()[1]
        self._got: list[tuple[float, bytes]] = []
        # When each went on to the unit (wall clock): after the first stamp and before the second
        # (the tap's thread may be starved between either stamp and the send).
        self.forwarded: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, anc, _, _ = self.sock.recvmsg(2048, socket.CMSG_SPACE(16))
            except TimeoutError:
                continue
            except OSError:
                return
            before = time.time()
            with contextlib.suppress(OSError):
                self.out.sendto(data, self.target)
            forwarded = stamp = time.time()
            for level, typ, raw in anc:
                if level == socket.SOL_SOCKET and typ == SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = struct.unpack("qq", raw[:16])
                    stamp = sec + nsec / 1e9
            with self._lock:
                self._got.append((stamp, data))
                self.forwarded.append((before, forwarded))

    def received(self, after: int = 0) -> list[tuple[float, bytes]]:
        with self._lock:
            return self._got[after:]

    def count(self) -> int:
        with self._lock:
            return len(self._got)

    def last_forwarded(self, what: str) -> tuple[float, float]:
        """When the latest datagram of a kind reached the unit: no earlier than the first and
        no later than the second time. On a loaded machine this tap's thread may forward it
        well after the kernel's stamp (the unit's silence starts from then), or be starved
        between the send and the stamp after it (once 319 ms, in CI)."""
        with self._lock:
            return [f for (_, d), f in zip(self._got, self.forwarded, strict=True)
                    if kind(d) == what][-1]

    def of(self, what: str, after: int = 0) -> list[tuple[float, bytes]]:
        return [(t, d) for t, d in self.received(after) if kind(d) == what]

    def wait(self, what: str, after: int = 0, n: int = 1, timeout: float = 5.0
             ) -> list[tuple[float, bytes]]:
        deadline = time.monotonic() + timeout
        while True:
            got = self.of(what, after)
            if len(got) >= n:
                return got
            assert time.monotonic() < deadline, f"fewer than {n} {what} datagrams in {timeout} s"
            time.sleep(0.002)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()
        self.out.close()


def control_of(data: bytes, key: bytes) -> tuple[float, float]:
    """(steering, gas_brake) of an authenticated control packet."""
    body = AuthControlPacket.decode(data, key).body
    return body.steering, body.gas_brake


class TcpCut:
    """A TCP relay on loopback in front of the remote's page server: the browser connects
    here; :meth:`cut` resets every connection at once (a network gone, as the page and the
    remote see it), and later connections are refused."""

    def __init__(self, target_port: int) -> None:
        self.target = (LOCAL, target_port)
        self.lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind((LOCAL, 0))
        self.lsock.listen(16)
        self.lsock.settimeout(0.05)
        self.port: int = self.lsock.getsockname()[1]
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                a, _ = self.lsock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                b = socket.create_connection(self.target, timeout=5)
            except OSError:
                a.close()
                continue
            with self._lock:
                self._pairs.append((a, b))
            th = threading.Thread(target=self._pump, args=(a, b), daemon=True)
            self._threads.append(th)
            th.start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        peer = {a: b, b: a}
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([a, b], [], [], 0.05)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    peer[s].sendall(data)
        except OSError:
            return
        finally:
            for s in (a, b):
                with contextlib.suppress(OSError):
                    s.close()

    def cut(self) -> float:
        """Reset every connection (RST both ways); returns the wall-clock time of the cut."""
        self._stop.set()
        t = time.time()
        with self._lock:
            for pair in self._pairs:
                for s in pair:
                    with contextlib.suppress(OSError):
                        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                     struct.pack("ii", 1, 0))
                        s.close()
        self.lsock.close()
        return t

    def close(self) -> None:
        if not self._stop.is_set():
            self.cut()
        for th in self._threads:
            th.join(timeout=5)


URL_RE = re.compile(r"open (http://\S+)")


class TouchRemote:
    """``estop remote --touch`` as a process; its output lines are kept as they come."""

    def __init__(self, *args: str, cwd: Path | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "estop", "remote", "--touch", *args],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, cwd=cwd)
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        line = self.wait_line("open http", timeout=15.0)
        m = URL_RE.search(line)
        assert m, line
        self.url = m[1]
        base, _, self.fragment = self.url.partition("#")
        self.base = base

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append(line.rstrip("\n"))

    def wait_line(self, text: str, after: int = 0, timeout: float = 5.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                for line in self.lines[after:]:
                    if text in line:
                        return line
            if self.proc.poll() is not None and not self._reader.is_alive():
                raise AssertionError(f"estop remote --touch exited {self.proc.returncode}: "
                                     f"{self.output()}")
            assert time.monotonic() < deadline, f"no line with {text!r}: {self.output()}"
            time.sleep(0.005)

    def output(self) -> str:
        with self._lock:
            return "\n".join(self.lines)

    def mark(self) -> int:
        with self._lock:
            return len(self.lines)

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._reader.join(timeout=5)
        return self.proc.returncode


class Phone:
    """A Playwright page with touch emulation; fingers are DevTools touch events."""

    def __init__(self, context: Any, page: Any) -> None:
        self.context = context
        self.page = page
        self.cdp = context.new_cdp_session(page)
        self.fingers: dict[int, tuple[float, float]] = {}

    def area(self, selector: str = "#drive") -> dict[str, float]:
        box: dict[str, float] = self.page.locator(selector).bounding_box()
        return box

    def point(self, fx: float, fy: float, selector: str = "#drive") -> tuple[float, float]:
        """The point at fractions (fx, fy) of an element's box (0.5, 0.5: its middle)."""
        box = self.area(selector)
        return box["x"] + fx * box["width"], box["y"] + fy * box["height"]

    def _dispatch(self, kind: str) -> None:
        points = [{"x": x, "y": y, "id": i} for i, (x, y) in self.fingers.items()]
        self.cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})

    def down(self, finger: int, xy: tuple[float, float]) -> None:
        self.fingers[finger] = xy
        self._dispatch("touchStart")

    def move(self, finger: int, xy: tuple[float, float]) -> None:
        self.fingers[finger] = xy
        self._dispatch("touchMove")

    def up(self, finger: int) -> float:
        """Lift one finger; returns the wall-clock time just before the event was sent.
        A touchEnd naming one point releases that one (chromium 156; DevTools' own words
        are that a touchEnd carries none: that form ends them all, for the last finger)."""
        x, y = self.fingers.pop(finger)
        points = [{"x": x, "y": y, "id": finger}] if self.fingers else []
        t = time.time()
        self.cdp.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": points})
        return t

    def cancel(self) -> float:
        """The browser cancels every touch (touchcancel)."""
        self.fingers.clear()
        t = time.time()
        self.cdp.send("Input.dispatchTouchEvent", {"type": "touchCancel", "touchPoints": []})
        return t

    def tap(self, selector: str, finger: int = 9) -> None:
        self.down(finger, self.point(0.5, 0.5, selector))
        self.up(finger)

    def shown(self) -> list[dict[str, Any]]:
        shown: list[dict[str, Any]] = self.page.evaluate("window.estop.shown")
        return shown

    def wait_state(self, state: str, reason: str = "", timeout_s: float = 5.0) -> None:
        self.page.wait_for_function(
            "([s, r]) => window.estop.last && window.estop.last.state === s && "
            "window.estop.last.reason === r", arg=[state, reason], timeout=timeout_s * 1000)

    def wait_shown(self, state: str, timeout_s: float = 5.0) -> None:
        self.page.wait_for_function(
            "(s) => document.getElementById('state').textContent === s", arg=state,
            timeout=timeout_s * 1000)
