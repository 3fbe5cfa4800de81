"""The demo's attacker: someone on the car's network without the key, who has recorded the
operator's packets. It sends plain heartbeats, heartbeats under a wrong key and replays of the
recording (none may keep the unit alive or bring it back from SLOWING), a forged RELEASE (NAK
4) and a stop datagram with a garbage tag (it stops the car: anyone may stop)."""

from __future__ import annotations

import secrets
import socket
import time
from collections.abc import Sequence

from estop.protocol import auth, tcp, udp
from estop.unit.canlog import DaemonError

__all__ = ["Attacker"]


class Attacker:
    """Sends to the unit at ``udp_port``/``tcp_port`` on loopback; counts what it sent."""

    def __init__(self, udp_port: int, tcp_port: int, session: int,
                 recording: Sequence[bytes]) -> None:
        if not recording:
            raise ValueError("the attacker needs a recording of the operator's packets")
        self.addr = ("127.0.0.1", udp_port)
        self.tcp_port = tcp_port
        self.session = session  # no secret: every reply carries it
        self.recording = list(recording)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.wrong_key = secrets.token_bytes(auth.KEY_SIZE)
        self.counter = 1 << 62  # far above the operator's: only the tag can refuse it
        self.sent = {"plain": 0, "wrong key": 0, "replayed": 0}

    def keep_alive(self) -> None:
        """One round of heartbeats the unit must not count (called every 10 ms)."""
        self.counter += 1
        body = udp.ControlPacket(0.2, 0.0, udp.Gear.DRIVE)
        forged = auth.AuthControlPacket(1, self.session, self.counter, body).encode(self.wrong_key)
        replay = self.recording[self.sent["replayed"] % len(self.recording)]
        for kind, data in (("plain", body.encode()), ("wrong key", forged), ("replayed", replay)):
            self.udp.sendto(data, self.addr)
            self.sent[kind] += 1

    def sent_text(self) -> str:
        """``12 plain, 12 wrong key, 12 replayed``."""
        return ", ".join(f"{n} {kind}" for kind, n in self.sent.items())

    def forged_release(self) -> auth.AuthReply:
        """A RELEASE request frame under the wrong key; the unit answers it all the same."""
        self.counter += 1
        frame = auth.AuthRequest(tcp.RELEASE, 1, 1, self.session, self.counter).encode(
            self.wrong_key)
        with socket.create_connection(("127.0.0.1", self.tcp_port), timeout=2.0) as s:
            s.sendall(frame)
            raw = b""
            while len(raw) < auth.REPLY_SIZE:
                chunk = s.recv(auth.REPLY_SIZE - len(raw))
                if not chunk:
                    raise DaemonError("the daemon closed the attacker's connection")
                raw += chunk
        # The attacker cannot verify the tag (no key); it reads the fields.
        return auth.AuthReply.decode(raw, None, strict=False)

    def stop_datagram(self) -> float:
        """A stop datagram with a garbage tag; returns the time just before sending it."""
        data = auth.stop_datagram(1, 0)[:32] + secrets.token_bytes(auth.TAG_SIZE)
        t = time.time()
        self.udp.sendto(data, self.addr)
        return t

    def close(self) -> None:
        self.udp.close()
