"""Loopback helpers for the tool tests: a counting UDP sink, a scripted TCP stop port."""

from __future__ import annotations

import socket
import threading
import time

LOCAL = "127.0.0.1"


class UdpSink:
    """A UDP socket on loopback that counts every datagram it receives, on a thread."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind((LOCAL, 0))
        self.sock.settimeout(0.02)
        self.port: int = self.sock.getsockname()[1]
        self.datagrams: list[bytes] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self.datagrams.append(data)

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
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
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
        conn.settimeout(0.02)
        with conn:
            while not self._stop.is_set():
                try:
                    chunk = conn.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not chunk:
                    return
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
