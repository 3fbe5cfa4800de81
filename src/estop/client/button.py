"""The stop button and the request frames a remote sends on the UDP control port.

- :func:`press_stop`: STOP over the stop channel, which does not give up after one failed try
  (a fresh connection and another stop datagram each time) until an answer or its deadline;
- :class:`StopDatagram`, :class:`LiftDatagram` (:class:`RequestDatagram`): the stop and lift
  datagrams of spec section 1; :func:`send_lift` the end of a hold (spec section 8).

Built on :class:`estop.client.channel.StopChannel`; used by ``estop stop|lift`` and
:class:`estop.client.sender.Remote`.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from estop.client.channel import StopChannel, StopChannelError, format_reply
from estop.client.identity import Identity
from estop.protocol import tcp
from estop.protocol.tcp import Reply

__all__ = [
    "DEFAULT_STOP_DEADLINE",
    "LIFT_GAP",
    "LIFT_SENDS",
    "LiftDatagram",
    "RequestDatagram",
    "StopDatagram",
    "StopOutcome",
    "press_stop",
    "send_lift",
]

DEFAULT_STOP_DEADLINE = 3.0  # seconds a stop press keeps trying for an ACK
LIFT_SENDS = 3  # lift datagrams at the end of a hold: one at once, two repeats (spec section 8)
LIFT_GAP = 0.010  # seconds between two lift datagrams (spec section 8)
_RETRY_GAPS = (0.05, 0.1, 0.2, 0.25)  # pause after the 1st, 2nd, 3rd, later failed attempts


class RequestDatagram:
    """Sends 48-byte request frames (spec section 5.2) with one msg_id to the unit's UDP control
    port: the stop and lift datagrams of spec section 1, under the remote's
    :class:`~estop.client.identity.Identity` (without a key the tag is 16 zero bytes; the
    session is 0 until the identity learns one; its counter rises with every datagram: the
    unit checks none of them on a stop request, but a remote raises its counter with every
    message). No reply comes over UDP.

    ``send(seq)`` writes one datagram; it raises OSError when the socket refuses.
    ``transmit`` replaces the plain ``sendto`` (the remote passes its link model)."""

    def __init__(self, host: str, port: int, msg_id: int, *, identity: Identity | None = None,
                 transmit: Callable[[bytes], None] | None = None) -> None:
        self.addr = (host, port)
        self.msg_id = msg_id
        self.identity = identity or Identity()
        self._transmit = transmit
        self._sock: socket.socket | None = None
        self.sent = 0

    def encode(self, seq: int) -> bytes:
        return self.identity.request_frame(self.msg_id, seq)

    def send(self, seq: int) -> None:
        data = self.encode(seq)
        if self._transmit is not None:
            self._transmit(data)
        else:
            if self._sock is None:
                family = socket.AF_INET6 if ":" in self.addr[0] else socket.AF_INET
                self._sock = socket.socket(family, socket.SOCK_DGRAM)
            self._sock.sendto(data, self.addr)
        self.sent += 1

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class StopDatagram(RequestDatagram):
    """The stop datagram: a request frame whose msg_id is the vehicle's stop ID. The unit stops
    on it (reason tcp stop) whatever its tag says, without waiting for a TCP handshake;
    ``send(seq)`` takes the seq of the TCP STOP it goes with."""

    def __init__(self, host: str, port: int, *, stop_id: int = tcp.DEFAULT_STOP_ID,
                 identity: Identity | None = None,
                 transmit: Callable[[bytes], None] | None = None) -> None:
        super().__init__(host, port, tcp.check_stop_id(stop_id), identity=identity,
                         transmit=transmit)
        self.stop_id = stop_id


class LiftDatagram(RequestDatagram):
    """The lift datagram: a request frame with msg_id LIFT (3). A remote sends it when the last
    finger leaves the screen, at once and twice more :data:`LIFT_GAP` apart (spec section 8);
    the unit stops on it with reason lift whatever its tag says."""

    def __init__(self, host: str, port: int, *, identity: Identity | None = None,
                 transmit: Callable[[bytes], None] | None = None) -> None:
        super().__init__(host, port, tcp.LIFT, identity=identity, transmit=transmit)


def send_lift(datagram: LiftDatagram, seq: int, *, sends: int = LIFT_SENDS,
              gap: float = LIFT_GAP) -> tuple[int, list[str]]:
    """The end of a hold, blocking: ``sends`` lift datagrams with ``seq``, the first at once,
    each next one ``gap`` seconds after the previous went out (spec section 8). A send the
    socket refuses does not stop the others. Returns (datagrams sent, one line per failure).
    """
    sent = 0
    errors: list[str] = []
    for i in range(sends):
        if i:
            time.sleep(gap)
        try:
            datagram.send(seq)
            sent += 1
        except OSError as exc:
            errors.append(f"lift datagram not sent: {exc.strerror or exc}")
    return sent, errors


@dataclass(frozen=True, slots=True)
class StopOutcome:
    """What one press of the stop button achieved."""

    reply: Reply | None  # the unit's answer, None when none came before the deadline
    attempts: int  # TCP requests tried (each retry on a fresh connection)
    datagrams: int  # stop datagrams sent
    elapsed: float  # seconds from the press to the outcome
    deadline: float  # seconds the press was allowed
    errors: tuple[str, ...] = ()  # why each failed attempt failed (one line each)

    @property
    def acked(self) -> bool:
        return self.reply is not None and self.reply.ack

    @property
    def tries(self) -> str:
        """``1 attempt``, ``2 attempts``, ..."""
        return f"{self.attempts} attempt{'' if self.attempts == 1 else 's'}"

    def summary(self) -> str:
        """``ACK after 2 attempts``, ``NAK after 1 attempt`` or
        ``no ACK within 3 s: 5 attempts failed (last: ...)``."""
        if self.reply is not None:
            return f"{'ACK' if self.reply.ack else 'NAK'} after {self.tries}"
        last = self.errors[-1] if self.errors else "none"
        return f"no ACK within {self.deadline:g} s: {self.tries} failed (last: {last})"

    def line(self) -> str:
        """The reply line with the attempts (``ACK seq=1 ... flags=0x00 (after 2 attempts)``),
        or the failure summary."""
        if self.reply is None:
            return self.summary()
        return f"{format_reply(self.reply)} (after {self.tries})"


def press_stop(channel: StopChannel, *, deadline: float = DEFAULT_STOP_DEADLINE,
               seq: int | None = None, datagram: StopDatagram | None = None,
               delay: Callable[[], None] | None = None) -> StopOutcome:
    """Press the stop button: STOP over TCP until the unit answers or ``deadline`` seconds
    have passed, each retry on a fresh connection (a failed one is closed), and a stop
    datagram (if given) with the first try and again with each retry.

    A NAK ends the press too: the unit answered, and the same request would get the same
    answer. ``seq`` fixes the seq of every try (default: the channel's next for each).
    ``delay`` is called before and after each TCP try (the remote's link delay).
    Never raises :class:`StopChannelError`: failures are in the outcome.
    """
    if not deadline > 0:
        raise ValueError(f"stop deadline must be > 0 s, got {deadline!r}")
    t0 = time.monotonic()
    end = t0 + deadline
    attempts = 0
    errors: list[str] = []
    sent_before = datagram.sent if datagram is not None else 0

    def outcome(reply: Reply | None) -> StopOutcome:
        sent = datagram.sent - sent_before if datagram is not None else 0
        return StopOutcome(reply, attempts, sent, time.monotonic() - t0, deadline,
                           tuple(errors))

    while True:
        this_seq = channel.take_seq() if seq is None else seq
        if datagram is not None:
            try:
                datagram.send(this_seq)
            except OSError as exc:
                errors.append(f"stop datagram not sent: {exc.strerror or exc}")
        attempts += 1
        try:
            if delay is not None:
                delay()
            left = end - time.monotonic()
            reply = channel.request(channel.stop_id, this_seq,
                                    timeout=max(0.01, min(channel.timeout, left)))
            if delay is not None:
                delay()
            return outcome(reply)
        except StopChannelError as exc:
            errors.append(str(exc))
        left = end - time.monotonic()
        if left <= 0:
            return outcome(None)
        time.sleep(min(_RETRY_GAPS[min(attempts, len(_RETRY_GAPS)) - 1], left))
        if time.monotonic() >= end:
            return outcome(None)
