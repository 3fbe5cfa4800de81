"""The remote's side of a daemon on loopback, for the demo and the benchmarks: raw UDP control
packets (timed to the send) and the TCP stop channel, which is
:class:`estop.client.channel.StopChannel`, the one request/reply client of the project."""

from __future__ import annotations

import socket
import time

from estop.client.channel import ConnectionClosed, ReplyNotAuthentic, StopChannel
from estop.client.identity import Identity
from estop.protocol import tcp, udp
from estop.unit.canlog import DaemonError

__all__ = ["Link"]


class Link:
    """Raw sockets to a daemon on loopback; every send returns time.time() just before it.

    Without a key: 20-byte control packets and 16-byte request frames. With ``key``: the
    60-byte authenticated control packets and 48-byte request frames of spec section 5, under
    ``remote_id``, with one counter that rises with every message; the session is learnt with
    a STATUS request at once, and every reply's tag is verified (a reply that fails raises
    :class:`DaemonError`, as does a connection the daemon closes). Other failures of the stop
    channel raise :class:`~estop.client.channel.StopChannelError` (an OSError).
    """

    def __init__(self, udp_port: int, tcp_port: int, host: str = "127.0.0.1",
                 reply_timeout_s: float = 2.0, *, key: bytes | None = None,
                 remote_id: int = 1) -> None:
        self.addr = (host, udp_port)
        self.identity = Identity(key, remote_id)
        self.channel = StopChannel(host, tcp_port, timeout=reply_timeout_s,
                                   identity=self.identity)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._packets: dict[tuple[float, float, int], bytes] = {}
        self.recording: list[bytes] | None = None  # a list here collects every datagram sent
        try:
            self.channel.connect()
            if self.identity.keyed:
                self.request(tcp.STATUS)  # the reply carries the session
        except BaseException:
            self.close()
            raise

    @property
    def key(self) -> bytes | None:
        return self.identity.key

    @property
    def session(self) -> int:
        """The unit's session, from its latest verified reply (0: not known)."""
        return self.identity.session

    @property
    def counter(self) -> int:
        """The counter of the latest message sent (it rises with every one)."""
        return self.identity.counter.last

    def send_control(self, gas: float = 0.0, steering: float = 0.0,
                     gear: int = udp.Gear.NEUTRAL) -> float:
        if self.identity.keyed:
            made = self.identity.control_packet(udp.ControlPacket(gas, steering, gear))
            if made is None:  # only when a RELEASE was sent and its reply not read yet
                raise RuntimeError("a RELEASE is in flight: read its reply before the next "
                                   "control packet (docs/REMOTE.md section 4)")
            data = made
        else:
            key = (gas, steering, gear)
            cached = self._packets.get(key)
            if cached is None:
                cached = udp.ControlPacket(gas, steering, gear).encode()
                if len(self._packets) < 256:
                    self._packets[key] = cached
            data = cached
        t = time.time()
        self.udp.sendto(data, self.addr)
        if self.recording is not None:
            self.recording.append(data)
        return t

    def send_request(self, msg_id: int) -> tuple[int, float]:
        """Send one request; return (seq, time just before sending)."""
        return self.channel.send(msg_id)

    def read_reply(self, seq: int) -> tcp.Reply:
        try:
            return self.channel.receive(seq)
        except ReplyNotAuthentic as exc:
            raise DaemonError(f"the daemon's reply did not verify: {exc}") from None
        except ConnectionClosed:
            raise DaemonError("the daemon closed the TCP connection") from None

    def request(self, msg_id: int) -> tuple[tcp.Reply, float]:
        seq, t = self.send_request(msg_id)
        return self.read_reply(seq), t

    def close(self) -> None:
        self.udp.close()
        self.channel.close()
