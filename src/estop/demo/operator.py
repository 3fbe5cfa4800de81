"""The demo's operator: the tablet (the real :class:`estop.client.sender.Remote`, with the key)
and its Wi-Fi link (:mod:`estop.model.wifi`), which the story can take down (every packet lost:
a burst, a dead Wi-Fi) and bring back.

It notes when each control packet got through (realtime), keeps the latest ones (the
attacker's recording) and sends each on to the version-2 unit, when there is one.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque

from estop.client.sender import Remote
from estop.demo.twin import V2Twin
from estop.model.wifi import IDEAL, LinkConfig, LinkModel
from estop.protocol import udp

__all__ = ["DEAD_LINK", "Operator"]

DEAD_LINK = LinkConfig(loss=1.0)  # the link model losing every packet
Control = tuple[float, float, int]  # gas_brake, steering, gear


def drive_control(t: float) -> Control:
    """The operator's drive, ``t`` seconds in: gas up to 0.4, a gentle weave."""
    return round(min(0.4, 0.4 * t), 2), round(0.3 * math.sin(2.0 * t), 2), udp.Gear.DRIVE


class Operator:
    """The tablet against the unit at ``udp_port``/``tcp_port`` on loopback; :meth:`close`
    always."""

    def __init__(self, udp_port: int, tcp_port: int, key: bytes,
                 twin: V2Twin | None = None) -> None:
        self.twin = twin
        self.clock = time.time() - time.monotonic()  # realtime = monotonic + clock
        self.remote = Remote("127.0.0.1", udp_port, tcp_port, key=key,
                             on_packet=self._on_packet)
        self._lock = threading.Lock()
        self._delivered: deque[float] = deque(maxlen=2000)  # realtime of delivered packets
        self._recording: deque[bytes] = deque(maxlen=200)  # the latest delivered packets
        self._drive_from: float | None = None  # monotonic start of the drive
        self._control: Control | None = None
        self._dead: LinkModel | None = None  # the link model while the link is down

    def _on_packet(self, t_send: float, data: bytes, t_deliver: float | None) -> None:
        """Every control packet, from the remote's sender thread (times monotonic)."""
        if t_deliver is None:
            return
        with self._lock:
            self._delivered.append(t_deliver + self.clock)
            self._recording.append(data)
        if self.twin is not None:
            self.twin.forward(data)

    @property
    def last_delivered(self) -> float:
        """When the latest packet got through (realtime; -inf before any)."""
        with self._lock:
            return self._delivered[-1] if self._delivered else -math.inf

    def first_delivered(self, after: float) -> float | None:
        with self._lock:
            return next((t for t in self._delivered if t >= after), None)

    def recording(self) -> list[bytes]:
        """The latest packets that got through, as someone on the network recorded them."""
        with self._lock:
            return list(self._recording)

    # --------------------------------------------------------------------------- the hand

    def drive(self) -> None:
        """Start driving: from now the packets follow :func:`drive_control`."""
        self._drive_from = time.monotonic()

    def steer(self, now: float) -> None:
        """Follow the drive (call often; ``now`` monotonic)."""
        if self._drive_from is None:
            return
        control = drive_control(now - self._drive_from)
        if control != self._control:
            gas, steering, gear = control
            self.remote.set_control(gas_brake=gas, steering=steering, gear=gear)
            self._control = control

    def neutral(self) -> None:
        """Stop driving: neutral, no gas."""
        self.hands_off()
        self.remote.set_control(gas_brake=0.0, steering=0.0, gear=udp.Gear.NEUTRAL)

    def hands_off(self) -> None:
        """The packets keep what they say now."""
        self._drive_from = None
        self._control = None

    # --------------------------------------------------------------------------- the link

    def link_down(self) -> None:
        """Every packet lost from now on (one being handed over may still get through)."""
        self._dead = LinkModel(DEAD_LINK)
        self.remote.link = self._dead

    def link_up(self) -> int:
        """The link delivers again; returns the packets lost while it was down."""
        self.remote.link = LinkModel(IDEAL)
        lost = self._dead.stats.lost if self._dead is not None else 0
        self._dead = None
        return lost

    def text(self) -> str:
        """For the live view: ``held, gas +0.40 steer -0.12 drive, link DOWN (12 lost)``."""
        if not self.remote.held:
            return "finger up"
        c = self.remote.control
        text = (f"held, gas {c.gas_brake:+.2f} steer {c.steering:+.2f} "
                f"{udp.Gear(c.gear).name.lower()}")
        if self._dead is not None:
            text += f", link DOWN ({self._dead.stats.lost} lost)"
        return text

    def close(self) -> None:
        self.remote.close()
