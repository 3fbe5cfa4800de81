"""One request to a unit on a fresh connection, as ``estop stop | lift | release | status``
and the dashboard's stop button send it.

- :func:`send_once`: one ``stop``/``lift``/``release``/``status`` request, its reply (with a
  key, ``release`` first asks STATUS on the same connection to learn the unit's session);
- :func:`stop_once`: the stop button (:func:`estop.client.button.press_stop`): a stop
  datagram to the UDP control port at once (spec section 1; it needs no handshake), then STOP
  over TCP, both tried again on fresh connections until the unit answers or the deadline;
- :func:`lift_once`: what a remote does when the last finger leaves the screen (spec section
  8): three lift datagrams 10 ms apart, then LIFT over TCP.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

from estop.client.button import (
    DEFAULT_STOP_DEADLINE,
    LiftDatagram,
    StopDatagram,
    StopOutcome,
    press_stop,
    send_lift,
)
from estop.client.channel import StopChannel, StopChannelError, format_reply
from estop.client.identity import DEFAULT_REMOTE_ID, Identity
from estop.protocol import tcp, udp

__all__ = ["LiftOutcome", "exchange", "lift_once", "send_once", "stop_once"]


def send_once(kind: str, host: str, port: int = tcp.DEFAULT_PORT, *, seq: int = 1,
              stop_id: int = tcp.DEFAULT_STOP_ID, timeout: float = 2.0,
              key: bytes | None = None, remote_id: int = DEFAULT_REMOTE_ID) -> tcp.Reply:
    """Send one ``stop``/``lift``/``release``/``status`` request on a fresh connection; return
    the reply.

    With ``key`` the request is a 48-byte frame and the reply must verify; a RELEASE is then
    preceded by a STATUS on the same connection, to learn the unit's session (a RELEASE with
    another session is not authenticated). Raises
    :class:`estop.client.channel.StopChannelError` on connection/timeout/reply errors.
    """
    return exchange(kind, host, port, seq=seq, stop_id=stop_id, timeout=timeout, key=key,
                     remote_id=remote_id)[0]


def exchange(kind: str, host: str, port: int, *, seq: int, stop_id: int, timeout: float,
              key: bytes | None, remote_id: int) -> tuple[tcp.Reply, str | None]:
    """:func:`send_once`, and why a NAK not_authenticated came where the client can tell."""
    msg_id = {"stop": stop_id, "lift": tcp.LIFT, "release": tcp.RELEASE,
              "status": tcp.STATUS}[kind]
    with StopChannel(host, port, timeout=timeout, stop_id=stop_id,
                     identity=Identity(key, remote_id)) as channel:
        if key is not None and kind == "release":
            channel.request(tcp.STATUS, seq)
        reply = channel.request(msg_id, seq)
        return reply, channel.nak_hint(reply)


def stop_once(host: str, port: int = tcp.DEFAULT_PORT, udp_port: int = udp.DEFAULT_PORT, *,
              seq: int = 1, stop_id: int = tcp.DEFAULT_STOP_ID, timeout: float = 2.0,
              deadline: float = DEFAULT_STOP_DEADLINE, key: bytes | None = None,
              remote_id: int = DEFAULT_REMOTE_ID) -> StopOutcome:
    """Press the stop button once (see :func:`estop.client.button.press_stop`): stop datagrams
    to ``udp_port`` and STOP with ``seq`` on fresh connections until an answer or
    ``deadline`` (with ``key``: 48-byte frames, replies that must verify)."""
    identity = Identity(key, remote_id)
    channel = StopChannel(host, port, timeout=timeout, stop_id=stop_id, identity=identity)
    datagram = StopDatagram(host, udp_port, stop_id=stop_id, identity=identity)
    with contextlib.closing(datagram), channel:
        return press_stop(channel, deadline=deadline, seq=seq, datagram=datagram)


@dataclass(frozen=True, slots=True)
class LiftOutcome:
    """What :func:`lift_once` achieved."""

    reply: tcp.Reply | None  # the unit's answer to the TCP LIFT, None when it failed
    datagrams: int  # lift datagrams sent
    errors: tuple[str, ...] = ()  # one line per failure (datagram or TCP)

    def line(self) -> str:
        """``ACK seq=1 state=STOPPED reason=lift flags=0x00 (lift sent x3)``, or the failure."""
        sent = f"lift sent x{self.datagrams}"
        if self.reply is None:
            return f"{sent}, but no reply: {'; '.join(self.errors)}"
        return f"{format_reply(self.reply)} ({sent})"


def lift_once(host: str, port: int = tcp.DEFAULT_PORT, udp_port: int = udp.DEFAULT_PORT, *,
              seq: int = 1, timeout: float = 2.0, key: bytes | None = None,
              remote_id: int = DEFAULT_REMOTE_ID) -> LiftOutcome:
    """End a dead-man hold as a remote does (spec section 8): three lift datagrams with
    ``seq`` to ``udp_port``, 10 ms apart, then LIFT with ``seq`` over TCP on a fresh
    connection (with ``key``: 48-byte frames under the key, a reply that must verify).
    Never raises :class:`estop.client.channel.StopChannelError`: failures are in the outcome."""
    identity = Identity(key, remote_id)
    datagram = LiftDatagram(host, udp_port, identity=identity)
    with contextlib.closing(datagram):
        sent, errors = send_lift(datagram, seq)
    try:
        with StopChannel(host, port, timeout=timeout, identity=identity) as channel:
            reply: tcp.Reply | None = channel.request(tcp.LIFT, seq)
    except StopChannelError as exc:
        reply = None
        errors.append(str(exc))
    return LiftOutcome(reply, sent, tuple(errors))
