"""The demo's version-2 unit: a second estopd on loopback that answers silence as version 2
did, to show what the lift saves.

It is the same estopd with one stage, the slow time equal to the timeout (spec section 3: then
the unit never enters SLOWING and behaves as in version 2), at version 2's timeout of 200 ms,
with the same key. It gets the operator's control packets (each one the link delivers to the
demo's unit is sent on to it, re-made under its own session) and never a lift datagram, which
a version-2 unit would not know: after the lift it waits for its timeout.
"""

from __future__ import annotations

import queue
import threading

from estop.demo.bus import BusWatch, Change
from estop.protocol import auth, tcp
from estop.unit.daemon import Daemon
from estop.unit.looplink import Link

__all__ = ["V2_TIMEOUT_MS", "V2Twin"]

V2_TIMEOUT_MS = 200  # version 2's default timeout, the issue's "200 ms before braking starts"


class V2Twin:
    """Start with :meth:`start`, feed with :meth:`forward` (from any thread), end with
    :meth:`stop` (always; also after a failed start)."""

    def __init__(self, exe: str, key_file: str, key: bytes,
                 timeout_ms: int = V2_TIMEOUT_MS) -> None:
        self.timeout_ms = timeout_ms
        self.key = key
        self.daemon = Daemon([exe], timeout_ms=timeout_ms, key_file=key_file)
        self.watch = BusWatch()
        self._link: Link | None = None
        self._lock = threading.Lock()
        self.forwarded = 0

    def start(self) -> None:
        self.daemon.start()
        link = Link(self.daemon.udp_port, self.daemon.tcp_port, key=self.key)
        with self._lock:
            self._link = link

    def forward(self, packet: bytes) -> None:
        """The operator's 60-byte control packet, as the demo's unit got it: its body goes on
        to the twin under the twin's session. Never raises (it runs on the remote's sender
        thread): once the twin is stopped, nothing is sent."""
        try:
            body = auth.AuthControlPacket.decode(packet, self.key).body
        except ValueError:  # not a good control packet (auth.AuthError, InvalidPacket)
            return
        with self._lock:
            if self._link is None:
                return
            try:
                self._link.send_control(body.gas_brake, body.steering, body.gear)
                self.forwarded += 1
            except OSError:
                pass

    def release(self) -> tcp.Reply:
        with self._lock:
            if self._link is None:
                raise OSError("the version-2 unit is not running")
            reply, _t = self._link.request(tcp.RELEASE)
            return reply

    def drain(self) -> list[Change]:
        """Take the frames logged so far; the changes they show."""
        out: list[Change] = []
        while True:
            try:
                rec = self.daemon.frames.get_nowait()
            except queue.Empty:
                return out
            change = self.watch.take(rec)
            if change is not None:
                out.append(change)

    def stop(self) -> int | None:
        """Stop feeding it, end the daemon, take its last frames; its exit code."""
        with self._lock:
            link, self._link = self._link, None
        if link is not None:
            link.close()
        rc = self.daemon.stop()
        self.drain()
        return rc

    @property
    def running(self) -> bool:
        return self._link is not None
