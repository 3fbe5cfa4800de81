"""Client side of the TCP stop channel: one connection, requests answered by reply frames.

Used by ``estop stop|release|status`` (one request per connection) and by
:class:`estop.remote.Remote` (one connection kept open, as the tablet does).
"""

from __future__ import annotations

import socket
import threading
import time

from estop.protocol import tcp
from estop.protocol.can import flag_names, reason_name, state_name
from estop.protocol.tcp import FrameAssembler, Reply, Request

__all__ = ["StopChannel", "StopChannelError", "format_reply", "reply_dict"]


class StopChannelError(OSError):
    """Connecting, sending or receiving failed, or the reply was malformed. One-line ``str``."""


def format_reply(reply: Reply) -> str:
    """``ACK seq=1 state=STOPPED reason=tcp_stop flags=0x00`` (+ `` nak=<name>`` for a NAK)."""
    flags = f"flags={reply.flags:#04x}"
    names = flag_names(reply.flags)
    if names:
        flags += "(" + ",".join(names) + ")"
    text = (f"{'ACK' if reply.ack else 'NAK'} seq={reply.seq} state={state_name(reply.state)} "
            f"reason={reason_name(reply.reason)} {flags}")
    if not reply.ack:
        text += f" nak={tcp.NAK_NAMES.get(reply.nak_code, str(reply.nak_code))}"
    return text


def reply_dict(reply: Reply) -> dict[str, object]:
    """The reply as plain JSON-able values (names alongside the numbers)."""
    return {
        "reply": "ACK" if reply.ack else "NAK",
        "seq": reply.seq,
        "state": state_name(reply.state),
        "state_code": reply.state,
        "reason": reason_name(reply.reason),
        "reason_code": reply.reason,
        "flags": reply.flags,
        "link_degraded": bool(reply.flags & 1),
        "nak_code": reply.nak_code,
        "nak": tcp.NAK_NAMES.get(reply.nak_code, str(reply.nak_code)),
    }


class StopChannel:
    """A TCP connection to the unit's stop port. Thread-safe; reconnects lazily after errors.

    ``request()`` sends one frame and waits (at most ``timeout`` seconds) for the reply that
    echoes its seq. Any failure closes the connection and raises :class:`StopChannelError`.
    """

    def __init__(self, host: str, port: int = tcp.DEFAULT_PORT, *, timeout: float = 2.0,
                 stop_id: int = tcp.DEFAULT_STOP_ID, first_seq: int = 1) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        self.stop_id = tcp.check_stop_id(stop_id)
        self._seq = first_seq & 0xFFFFFFFF
        self._sock: socket.socket | None = None
        self._asm = FrameAssembler()
        self._lock = threading.Lock()

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> None:
        with self._lock:
            self._connect()

    def _connect(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        except TimeoutError:
            raise StopChannelError(f"connecting to {self.host}:{self.port} timed out after "
                                   f"{self.timeout:g} s") from None
        except OSError as exc:
            raise StopChannelError(f"cannot connect to {self.host}:{self.port}: "
                                   f"{exc.strerror or exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._asm.reset()
        return sock

    def close(self) -> None:
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._asm.reset()

    def __enter__(self) -> StopChannel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_seq(self) -> int:
        with self._lock:
            return self._seq

    def stop(self, seq: int | None = None) -> Reply:
        return self.request(self.stop_id, seq)

    def release(self, seq: int | None = None) -> Reply:
        return self.request(tcp.RELEASE, seq)

    def status(self, seq: int | None = None) -> Reply:
        return self.request(tcp.STATUS, seq)

    def request(self, msg_id: int, seq: int | None = None) -> Reply:
        """Send ``Request(msg_id, seq)`` (seq: the next of this channel's own counter)."""
        with self._lock:
            if seq is None:
                seq = self._seq
            self._seq = (seq + 1) & 0xFFFFFFFF
            frame = Request(msg_id, seq).encode()
            try:
                sock = self._connect()
                sock.sendall(frame)
                return self._await_reply(sock, seq)
            except StopChannelError:
                self._close()
                raise
            except TimeoutError:
                self._close()
                raise StopChannelError(f"no reply from {self.host}:{self.port} within "
                                       f"{self.timeout:g} s") from None
            except OSError as exc:
                self._close()
                raise StopChannelError(f"connection to {self.host}:{self.port} failed: "
                                       f"{exc.strerror or exc}") from None

    def _await_reply(self, sock: socket.socket, seq: int) -> Reply:
        deadline = time.monotonic() + self.timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            sock.settimeout(left)
            chunk = sock.recv(4096)
            if not chunk:
                raise StopChannelError(f"{self.host}:{self.port} closed the connection "
                                       f"before replying")
            for frame in self._asm.feed(chunk):
                try:
                    reply = Reply.decode(frame)
                except tcp.FrameError as exc:
                    raise StopChannelError(f"bad reply from {self.host}:{self.port}: "
                                           f"{exc}") from None
                if reply.seq != seq:
                    raise StopChannelError(f"reply seq {reply.seq} does not match request "
                                           f"seq {seq}")
                return reply
