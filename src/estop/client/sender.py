"""The tablet as a library: :class:`Remote` sends control packets over UDP while *held* (a
finger on the screen) and talks to the unit's TCP stop channel.

While held the remote sends control packets at a fixed rate (default 50 Hz). When the finger
lifts it sends no more control packets and tells the unit at once: a lift datagram (a stop
request, reason lift) and two repeats 10 ms apart (spec section 8), so the unit stops without
waiting for its timeout; should all three be lost, the timeout still stops it.

The stop button, RELEASE and STATUS go over the TCP stop channel, one connection kept open.
The stop button also sends a stop datagram to the UDP port at once, and keeps trying (a fresh
connection and another datagram each time) until the unit answers or ``stop_deadline``
(default 3 s) passes.

With a key (spec section 5) the packets are the 60-byte authenticated form and the requests
48-byte frames whose replies must verify; the remote learns the unit's session from replies
(``hold`` asks STATUS first when it does not know it yet) and raises one counter with every
message it sends. While a RELEASE is in flight (from taking its counter until its reply, at most
``release_quiet_s``, default 50 ms) no control packet goes out: one with a higher counter, read
by the unit before the RELEASE, would make the RELEASE stale (NAK 4; issue 25, docs/REMOTE.md
section 4); a packet held back goes out as soon as the reply comes. Stop and lift datagrams are
never held back.

An optional :class:`estop.model.wifi.LinkModel` makes the UDP link lossy and slow like Wi-Fi;
its one-way delay (not its loss) is also applied to each TCP request and its reply.

Library use (the demo, benchmarks, HIL harness)::

    with Remote("127.0.0.1", link=WIFI, seed=1) as r:
        r.hold(); time.sleep(0.5)
        print(r.release())              # tcp.Reply
        r.set_control(gas_brake=0.3, gear=Gear.DRIVE)
        ...
        r.lift()
"""

from __future__ import annotations

import heapq
import math
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from estop.client.button import (
    DEFAULT_STOP_DEADLINE,
    LIFT_GAP,
    LIFT_SENDS,
    LiftDatagram,
    StopDatagram,
    StopOutcome,
    press_stop,
)
from estop.client.channel import StopChannel, StopChannelError
from estop.client.identity import DEFAULT_REMOTE_ID, RELEASE_QUIET_S, Identity
from estop.model.wifi import IDEAL, LinkConfig, LinkModel
from estop.protocol import tcp, udp
from estop.protocol.tcp import Reply
from estop.protocol.udp import ControlPacket

__all__ = [
    "MAX_RATE_HZ",
    "MIN_RATE_HZ",
    "PacketHook",
    "Remote",
    "RemoteStats",
    "check_rate",
    "lift_line",
]

PacketHook = Callable[[float, bytes, float | None], None]

MIN_RATE_HZ = 0.1
MAX_RATE_HZ = 1000.0
# The sender thread always waits at least this long between two turns, even when it is behind
# its schedule, so hold()/lift()/close() get its lock at once at any rate.
_MIN_WAIT = 0.0002


def check_rate(rate_hz: float) -> float:
    """Return ``rate_hz`` if it is a send rate the remote supports (0.1..1000 Hz), else raise
    ValueError with a one-line message."""
    if not isinstance(rate_hz, int | float) or not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise ValueError(f"rate must be {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz, got {rate_hz!r}")
    return float(rate_hz)



@dataclass(slots=True)
class RemoteStats:
    sent: int = 0  # packets handed to the link (lost ones included)
    lost: int = 0  # dropped by the link model
    delivered: int = 0  # written to the UDP socket
    send_errors: int = 0  # sendto() failed
    requests: int = 0  # TCP requests answered
    stop_datagrams: int = 0  # stop datagrams handed to the link (lost ones included)
    lift_datagrams: int = 0  # lift datagrams handed to the link (lost ones included)

    @property
    def loss_fraction(self) -> float:
        return self.lost / self.sent if self.sent else 0.0


class Remote:
    """The tablet: a sender thread for UDP control packets plus a TCP stop channel.

    ``hold()``/``lift()`` start and stop sending, and the end of a hold is reported with lift
    datagrams (:meth:`lift`); ``set_control()`` changes what is sent from the next packet on;
    ``stop()``/``release()``/``status()`` return the unit's :class:`~estop.protocol.tcp.Reply`
    (or raise :class:`~estop.client.channel.StopChannelError`).
    The sender thread starts with ``start()`` or the ``with`` block and ends with ``close()``.
    ``on_packet(t_send, data, t_deliver_or_None)`` is called from the sender thread for every
    packet (times on ``time.monotonic()``).
    """

    def __init__(self, host: str, udp_port: int = udp.DEFAULT_PORT,
                 tcp_port: int = tcp.DEFAULT_PORT, *, rate_hz: float = 50.0,
                 link: LinkConfig = IDEAL, seed: int | None = None,
                 stop_id: int = tcp.DEFAULT_STOP_ID, tcp_timeout: float = 2.0,
                 stop_deadline: float = DEFAULT_STOP_DEADLINE, legacy: bool = False,
                 on_packet: PacketHook | None = None, key: bytes | None = None,
                 remote_id: int = DEFAULT_REMOTE_ID, paced: bool = True,
                 release_quiet_s: float = RELEASE_QUIET_S) -> None:
        self._period = 1.0 / check_rate(rate_hz)
        # paced: the sender thread sends one packet each period while held; not paced: the
        # caller's own clock does, one packet per pulse() (the touch page's fresh frames)
        self.paced = paced
        if not stop_deadline > 0 or not math.isfinite(stop_deadline):
            raise ValueError(f"stop deadline must be > 0 s, got {stop_deadline!r}")
        self.stop_deadline = stop_deadline
        if key is not None and legacy:
            raise ValueError("with a key the remote sends 60-byte packets, not the 16-byte form")
        # one identity for all its messages: one key, remote id and session, one counter
        self.identity = Identity(key, remote_id, release_quiet_s=release_quiet_s)
        self.identity.on_quiet_end = self._quiet_ended
        self.addr = (host, udp_port)
        self.legacy = legacy
        self.on_packet = on_packet
        self.link = LinkModel(link, seed)
        self.channel = StopChannel(host, tcp_port, timeout=tcp_timeout, stop_id=stop_id,
                                   identity=self.identity)
        self.datagram = StopDatagram(host, udp_port, stop_id=stop_id, identity=self.identity,
                                     transmit=self._send_datagram)
        self.lift_datagram = LiftDatagram(host, udp_port, identity=self.identity,
                                          transmit=self._send_lift_datagram)
        self.stats = RemoteStats()
        self._control = ControlPacket()
        self._held = False
        self._next_send = 0.0
        self._inflight: list[tuple[float, int, bytes, bool]] = []  # (due, n, data, control)
        self._n = 0
        self._lifts = 0  # holds ended so far: the seq of their lift datagrams
        self._lift_left = 0  # lift datagrams of the latest lift still to send
        self._lift_due = 0.0  # when the next of them goes out
        self._lift_sent = 0  # lift datagrams of the latest lift handed to the link
        self._owed = False  # a control packet held back while a RELEASE was in flight
        self._closing = False
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._udp = socket.socket(family, socket.SOCK_DGRAM)

    # --------------------------------------------------------------------- life cycle

    def start(self) -> Remote:
        with self._cond:
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="estop-remote-udp",
                                                daemon=True)
                self._thread.start()
        return self

    def close(self, *, flush: bool = True) -> None:
        """Stop sending: a hold still on ends here, with its lift datagrams (:meth:`lift`),
        which go out in any case; with ``flush`` wait for packets still in flight (link
        delay) too."""
        self.lift()
        self.wait_lift_sent()
        with self._cond:
            if flush and self._thread is not None:
                self._cond.wait_for(lambda: not self._inflight, timeout=5.0)
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._udp.close()
        self.channel.close()

    def __enter__(self) -> Remote:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the dead man

    @property
    def held(self) -> bool:
        return self._held

    @property
    def rate_hz(self) -> float:
        return 1.0 / self._period

    @rate_hz.setter
    def rate_hz(self, value: float) -> None:
        period = 1.0 / check_rate(value)
        with self._cond:
            self._period = period
            self._cond.notify_all()

    def hold(self) -> None:
        """Finger down: send a packet now and then one every period. With a key and the
        unit's session not known yet, ask STATUS first to learn it (a packet with another
        session keeps nothing alive); that may raise
        :class:`~estop.client.channel.StopChannelError`."""
        if self.identity.keyed and not self.identity.session and not self._held:
            self.status()
        with self._cond:
            if not self._held:
                self._held = True
                self._next_send = time.monotonic()
                self._cond.notify_all()

    def lift(self) -> int:
        """Finger up: once this returns, no further control packet is sent (those already in
        flight in the link model still arrive, as on a real network) until the next
        :meth:`hold`.

        When this ends a hold, the unit is told at once (spec section 8): a lift datagram goes
        out before this returns, and :data:`~estop.client.button.LIFT_SENDS` - 1 more follow
        from the sender thread, each :data:`~estop.client.button.LIFT_GAP` after the previous
        (:meth:`wait_lift_sent` waits for them, :meth:`close` always does). With a key they
        carry the tag, the known session and the remote's counter, like its other requests.
        Returns the number of lift datagrams this lift sends: LIFT_SENDS, or 0 when the remote
        was not held."""
        with self._cond:
            if not self._held:
                return 0
            self._held = False
            self._owed = False
            self._lifts += 1
            self._lift_left = LIFT_SENDS
            self._lift_sent = 0
            self._send_lift()
            self._cond.notify_all()
            return LIFT_SENDS

    def pulse(self) -> bool:
        """One control packet now, while held (for ``paced=False``: the caller's clock sets
        the rate); False when not held, and nothing is sent. While a RELEASE is in flight the
        packet is held back and goes out when its reply comes."""
        with self._cond:
            if not self._held:
                return False
            self._send_one(time.monotonic())
            return True

    @property
    def lift_sent(self) -> int:
        """Lift datagrams of the latest lift handed to the link so far (0..LIFT_SENDS)."""
        return self._lift_sent

    def wait_lift_sent(self, timeout: float = 1.0) -> bool:
        """Wait (at most ``timeout`` s) until every lift datagram of the latest lift has been
        handed to the link; True if none is left to send. Without the sender thread (never
        started, or closed) the repeats are sent from here."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._lift_left:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                if self._thread is None:
                    if self._lift_due <= time.monotonic():
                        self._send_lift()
                        continue
                    left = min(left, self._lift_due - time.monotonic())
                self._cond.wait(max(_MIN_WAIT, left))
            return True

    @property
    def control(self) -> ControlPacket:
        return self._control

    def set_control(self, packet: ControlPacket | None = None, **fields: Any) -> ControlPacket:
        """Replace the packet sent from now on, or change some of its fields
        (``gas_brake``, ``steering``, ``gear``, ``turn_signal``, ``horn``). Raises
        :class:`~estop.protocol.udp.InvalidPacket` for values the unit would reject."""
        with self._cond:
            new = replace(packet or self._control, **fields)
            new.validate()
            self._control = new
            return new

    # -------------------------------------------------------------------- stop channel

    def _tcp_delay(self) -> None:
        if self.link.config.delay > 0 or self.link.config.jitter > 0:
            with self._cond:
                d = self.link.sample_delay()
            time.sleep(d)

    def request(self, msg_id: int) -> Reply:
        self._tcp_delay()
        reply = self.channel.request(msg_id)
        self._tcp_delay()
        self.stats.requests += 1
        return reply

    def press_stop(self) -> StopOutcome:
        """The stop button: STOP with the vehicle's stop ID, tried again on a fresh connection
        until the unit answers or ``stop_deadline`` passes, with a stop datagram on the UDP
        port at the first try and each retry (see :func:`estop.client.button.press_stop`)."""
        linked = self.link.config.delay > 0 or self.link.config.jitter > 0
        outcome = press_stop(self.channel, deadline=self.stop_deadline,
                             datagram=self.datagram, delay=self._tcp_delay if linked else None)
        if outcome.reply is not None:
            self.stats.requests += 1
        return outcome

    def stop(self) -> Reply:
        """The stop button (:meth:`press_stop`); the unit's reply, or
        :class:`~estop.client.channel.StopChannelError` saying how many tries failed by the
        deadline."""
        outcome = self.press_stop()
        if outcome.reply is None:
            raise StopChannelError(outcome.summary())
        return outcome.reply

    def release(self) -> Reply:
        return self.request(tcp.RELEASE)

    def status(self) -> Reply:
        return self.request(tcp.STATUS)

    # ------------------------------------------------------------------- sender thread

    def _loop(self) -> None:
        # Everything is decided and sent under the lock, so once lift() has held it no packet
        # goes out; and every turn ends in a wait of at least _MIN_WAIT, which lets go of the
        # lock even when the sender is behind its schedule (a slow machine, a slow hook).
        with self._cond:
            while not self._closing:
                now = time.monotonic()
                while self._inflight and self._inflight[0][0] <= now:
                    _, _, data, control = heapq.heappop(self._inflight)
                    self._write(data, control)
                if not self._inflight:
                    self._cond.notify_all()  # close(flush=True) may be waiting
                if self._lift_left and self._lift_due <= now:
                    self._send_lift()
                    self._cond.notify_all()  # wait_lift_sent() may be waiting
                if self._held and self.paced and self._next_send <= now and \
                        self._send_one(now):
                    self._next_send += self._period
                    if self._next_send < now:  # fell behind (paused): no burst, restart
                        self._next_send = now + self._period
                wake = math.inf
                if self._held and self.paced:
                    wake = self._next_send
                    if self._owed:  # held back: until the reply (notified) or the bound
                        wake = max(wake, self.identity.quiet_until())
                if self._lift_left:
                    wake = min(wake, self._lift_due)
                if self._inflight:
                    wake = min(wake, self._inflight[0][0])
                timeout = 0.5 if wake == math.inf else wake - time.monotonic()
                self._cond.wait(min(0.5, max(_MIN_WAIT, timeout)))

    def _send_one(self, now: float) -> bool:
        """One control packet now (the lock is held); False when it is held back because a
        RELEASE is in flight."""
        if self.identity.keyed:
            made = self.identity.control_packet(self._control)
            if made is None:
                self._owed = True
                return False
            data = made
        else:
            data = self._control.encode(legacy=self.legacy)
        self._owed = False
        self.stats.sent += 1
        t_deliver = self._transmit(now, data, True)
        if t_deliver is None:
            self.stats.lost += 1
        if self.on_packet is not None:
            self.on_packet(now, data, t_deliver)
        return True

    def _quiet_ended(self) -> None:
        """The RELEASE's reply came: the packet held back goes out now (the sender thread's,
        woken here; the caller's clock's, sent from here)."""
        with self._cond:
            if self._owed and self._held and not self.paced:
                self._send_one(time.monotonic())
            self._cond.notify_all()

    def _send_lift(self) -> None:
        """One lift datagram of the latest lift, now (the lock is held). The next is due
        LIFT_GAP after this one went out, not after it was planned, so two are never closer
        than LIFT_GAP even when this one was late."""
        try:
            self.lift_datagram.send(self._lifts)
        except OSError:
            self.stats.send_errors += 1
        self._lift_left -= 1
        self._lift_due = time.monotonic() + LIFT_GAP

    def _send_lift_datagram(self, data: bytes) -> None:
        """A lift datagram, through the same link as the control packets."""
        with self._cond:
            self.stats.lift_datagrams += 1
            self._lift_sent += 1
            self._transmit(time.monotonic(), data, False)

    def _send_datagram(self, data: bytes) -> None:
        """A stop datagram, through the same link as the control packets."""
        with self._cond:
            self.stats.stop_datagrams += 1
            self._transmit(time.monotonic(), data, False)
            self._cond.notify_all()

    def _transmit(self, now: float, data: bytes, control: bool) -> float | None:
        t_deliver = self.link.transmit(now)
        if t_deliver is not None and t_deliver <= now:
            self._write(data, control)
        elif t_deliver is not None:
            self._n += 1
            heapq.heappush(self._inflight, (t_deliver, self._n, data, control))
        return t_deliver

    def _write(self, data: bytes, control: bool) -> None:
        try:
            self._udp.sendto(data, self.addr)
            if control:
                self.stats.delivered += 1
        except OSError:
            self.stats.send_errors += 1


def lift_line(remote: Remote) -> str:
    """Lift ``remote``, wait (bounded) for its lift datagrams and say what went out, for the
    tools' output: ``lift sent x3``, or ``not held: nothing to send``."""
    if not remote.lift():
        return "not held: nothing to send"
    remote.wait_lift_sent()
    return f"lift sent x{remote.lift_sent}"
