"""Loopback helpers for the tool tests: a counting UDP sink, a scripted TCP stop port, and the
polling loops of fake units (datagrams, connections, chunks)."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

LOCAL = "127.0.0.1"


# Linux's SO_TIMESTAMPNS (and SCM_TIMESTAMPNS), which the socket module does not name.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


class UdpSink:
    """A UDP socket on loopback that counts every datagram it receives, on a thread. It keeps
    the kernel's receive time of each (``stamps``, wall-clock seconds): on loopback that is
    when it was sent, whenever the thread got round to reading it."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.bind((LOCAL, 0))
        self.sock.settimeout(0.02)
        self.port: int = self.sock.getsockname()[1]
        self.datagrams: list[bytes] = []
        self.stamps: list[float] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, ancillary, _, _ = self.sock.recvmsg(2048, socket.CMSG_SPACE(16))
            except TimeoutError:
                continue
            except OSError:
                return
            stamp = time.time()
            for level, kind, raw in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = struct.unpack("qq", raw[:16])
                    stamp = sec + nsec / 1e9
            with self._lock:
                self.datagrams.append(data)
                self.stamps.append(stamp)

    def received(self) -> list[tuple[float, bytes]]:
        """(kernel receive time, datagram) of everything so far, in order."""
        with self._lock:
            return list(zip(self.stamps, self.datagrams, strict=True))

    @property
    def count(self) -> int:
        with self._lock:
            return len(self.datagrams)

    def wait_for(self, n: int, timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        while self.count < n and time.monotonic() < deadline:
            time.sleep(0.005)
        return self.count >= n

    def settle(self, expected: int, quiet: float = 0.2) -> int:
        """Wait (up to 10 s) until ``expected`` datagrams are in, then ``quiet`` more seconds
        for any that should not come; return the count."""
        self.wait_for(expected, timeout=10.0)
        time.sleep(quiet)
        return self.count

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def unused_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


class ScriptedStopPort:
    """A TCP stop port on loopback, served by a thread, whose connections behave as told, one
    word per connection in order of arrival (the last word holds for the rest):

    - ``ack``: answer every plain request with ACK (state STOPPED, reason tcp_stop)
    - ``nak``: answer every request with NAK 1 (unknown msg_id)
    - ``close``: read one request and close without a reply (a daemon that restarts)
    - ``silent``: read requests and never answer

    ``drop_all()`` closes every open connection (the daemon went away). What arrived is kept:
    ``requests`` (raw frames, in order), ``accepted_at`` (time.monotonic() of each accept).
    """

    def __init__(self, *behaviour: str) -> None:
        from estop.protocol import tcp

        self._tcp = tcp
        self.behaviour = list(behaviour) or ["ack"]
        self.requests: list[bytes] = []
        self.accepted_at: list[float] = []
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((LOCAL, 0))
        self.sock.listen(16)
        self.sock.settimeout(0.02)
        self.port: int = self.sock.getsockname()[1]
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    @property
    def connections(self) -> int:
        with self._lock:
            return len(self.accepted_at)

    def _accept(self) -> None:
        for conn in connections(self.sock, self._stop):
            with self._lock:
                n = len(self.accepted_at)
                self.accepted_at.append(time.monotonic())
                self._conns.append(conn)
                word = self.behaviour[min(n, len(self.behaviour) - 1)]
            th = threading.Thread(target=self._serve, args=(conn, word), daemon=True)
            self._threads.append(th)
            th.start()

    def _serve(self, conn: socket.socket, word: str) -> None:
        tcp = self._tcp
        asm = tcp.FrameAssembler()
        with conn:
            for chunk in chunks(conn, self._stop, 0.02):
                for frame in asm.feed(chunk):
                    with self._lock:
                        self.requests.append(frame)
                    if word == "close":
                        return
                    if word == "silent":
                        continue
                    req = tcp.Request.decode(frame)
                    if word == "nak":
                        reply = tcp.Reply(False, req.seq, 0, 1, 0, tcp.NakCode.UNKNOWN_MSG_ID)
                    else:
                        reply = tcp.Reply(True, req.seq, 0, 2)
                    try:
                        conn.sendall(reply.encode())
                    except OSError:
                        return

    def drop_all(self) -> None:
        with self._lock:
            for c in self._conns:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        self.drop_all()
        for th in self._threads:
            th.join(timeout=5)
        self.sock.close()


def datagrams(sock: socket.socket, stop: threading.Event) -> Iterator[bytes]:
    """Datagrams arriving on a socket with a timeout, until stop is set or the socket fails."""
    while not stop.is_set():
        try:
            yield sock.recv(2048)
        except TimeoutError:
            continue
        except OSError:
            return


def connections(sock: socket.socket, stop: threading.Event) -> Iterator[socket.socket]:
    """Connections accepted on a listening socket with a timeout, until stop or failure."""
    while not stop.is_set():
        try:
            conn, _ = sock.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        yield conn


def chunks(conn: socket.socket, stop: threading.Event, timeout: float) -> Iterator[bytes]:
    """What a peer sends, chunk by chunk, until it closes, the connection fails or stop."""
    conn.settimeout(timeout)
    while not stop.is_set():
        try:
            chunk = conn.recv(4096)
        except TimeoutError:
            continue
        except OSError:
            return
        if not chunk:
            return
        yield chunk



class FakeUnitPorts:
    """A fake unit's UDP control port and listening TCP stop port on loopback, each served by
    a thread of the subclass (``_udp_loop``, ``_tcp_loop``) until ``close``."""

    def _open_ports(self, timeout: float) -> None:
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind((LOCAL, 0))
        self.udp.settimeout(timeout)
        self.tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.tcp.bind((LOCAL, 0))
        self.tcp.listen(8)
        self.tcp.settimeout(timeout)
        self.udp_port: int = self.udp.getsockname()[1]
        self.tcp_port: int = self.tcp.getsockname()[1]
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._udp_loop, daemon=True),
                         threading.Thread(target=self._tcp_loop, daemon=True)]
        for t in self._threads:
            t.start()

    def _udp_loop(self) -> None:
        raise NotImplementedError

    def _tcp_loop(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        self.udp.close()
        self.tcp.close()

def wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    """A fake unit's threads may lag on a busy machine: wait (bounded) for what must come, then
    a little longer, so that what must not come has had its chance too."""
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
