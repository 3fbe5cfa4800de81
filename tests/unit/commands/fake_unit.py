"""A small fake unit for the command-line tests: a UDP port recording control packets and a
TCP stop port answering per spec section 3 (conftest.py beside it makes one per test).
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass, field

from estop.protocol import auth, tcp, udp
from estop.protocol.tcp import FrameAssembler, Reply, Request
from estop.protocol.udp import ControlPacket
from net_util import LOCAL, FakeUnitPorts, chunks, connections, datagrams

# --------------------------------------------------------------------------- a fake unit

@dataclass
class FakeUnit(FakeUnitPorts):
    """Just enough of the unit for the CLI: a UDP port recording control packets (and stop and
    lift datagrams, which stop it) and a TCP stop port answering per spec section 3 (STOPPED
    latched, RELEASE needs a live, neutral link of >= 5 valid packets, udp timeout 200 ms).
    ``mode`` breaks the replies on purpose: ``silent`` (no reply), ``close`` (hang up),
    ``badcrc``, ``wrongseq``, ``split`` (reply in two pieces)."""

    mode: str = "normal"
    timeout: float = 0.2
    stop_id: int = tcp.DEFAULT_STOP_ID
    packets: list[tuple[float, bytes]] = field(default_factory=list)
    stop_datagrams: list[bytes] = field(default_factory=list)
    requests: list[Request] = field(default_factory=list)
    raw_requests: list[bytes] = field(default_factory=list)
    state: int = 0
    reason: int = 1
    valid_run: int = 0
    last_valid: ControlPacket | None = None
    last_valid_t: float = -1e9

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self._open_ports(0.05)

    # UDP side
    def _udp_loop(self) -> None:
        for data in datagrams(self.udp, self._stop):
            now = time.monotonic()
            with self.lock:
                if len(data) == auth.REQUEST_SIZE and data[:4] == auth.REQUEST_MAGIC:
                    self.stop_datagrams.append(data)
                    kind = auth.AuthRequest.decode(data, None).kind(self.stop_id)
                    if kind in ("stop", "lift"):
                        self._enter_stop(2 if kind == "stop" else 5)
                    continue
                self.packets.append((now, data))
                self._expire(now)
                if udp.is_valid(data):
                    self.last_valid = udp.decode(data)
                    self.last_valid_t = now
                    if self.state == 0:
                        self.valid_run += 1

    def _expire(self, now: float) -> None:
        if self.state == 1 and now - self.last_valid_t >= self.timeout:
            self._enter_stop(3)

    def _enter_stop(self, reason: int) -> None:
        if self.state == 1:
            self.state, self.reason = 0, reason
        self.valid_run = 0

    # TCP side
    def _tcp_loop(self) -> None:
        for conn in connections(self.tcp, self._stop):
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        asm = FrameAssembler()
        with conn:
            for chunk in chunks(conn, self._stop, 0.05):
                for frame in asm.feed(chunk):
                    self.raw_requests.append(frame)
                    try:
                        req = Request.decode(frame)
                    except tcp.CrcMismatch:
                        return
                    self.requests.append(req)
                    if self.mode == "silent":
                        continue
                    if self.mode == "close":
                        return
                    data = self.answer(req).encode()
                    if self.mode == "badcrc":
                        data = data[:12] + bytes(4)
                    if self.mode == "wrongseq":
                        data = Reply(True, req.seq + 1, self.state, self.reason).encode()
                    if self.mode == "split":
                        conn.sendall(data[:5])
                        time.sleep(0.05)
                        conn.sendall(data[5:])
                    else:
                        conn.sendall(data)

    def answer(self, req: Request) -> Reply:
        now = time.monotonic()
        with self.lock:
            self._expire(now)
            kind = req.kind(self.stop_id)
            nak = 0
            if kind in ("stop", "lift"):
                self._enter_stop(2 if kind == "stop" else 5)
            elif kind == "release" and self.state == 0:
                live = now - self.last_valid_t < self.timeout and self.valid_run >= 5
                if not live:
                    nak = tcp.NakCode.NO_LIVE_LINK
                elif self.last_valid is None or not self.last_valid.is_neutral:
                    nak = tcp.NakCode.NOT_NEUTRAL
                else:
                    self.state, self.reason = 1, 0
            elif kind == "unknown":
                nak = tcp.NakCode.UNKNOWN_MSG_ID
            return Reply(nak == 0, req.seq, self.state, self.reason, 0, nak)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])
