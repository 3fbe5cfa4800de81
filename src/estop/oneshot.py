"""``estop stop | lift | release | status``: one request over the TCP stop channel.

Opens a connection, sends one frame, prints the decoded reply and exits with:

- 0: ACK
- 1: NAK (the reply line says why, e.g. ``nak=no_live_link``; a ``not_authenticated`` gets a
  second line on stderr saying what the client can tell: no key given, or the unit refused
  this remote id's counter as a replay)
- 2: usage error (bad options or settings)
- 3: connection refused or closed, timeout, or a malformed reply (bad CRC, wrong seq); for
  ``stop``: no ACK by the deadline
- 4: the key file cannot be used

(the table of every command: :data:`estop.cliutil.EXIT_CODES`)

``stop`` is the stop button: it sends a stop datagram to the UDP control port at once (spec
section 1; it needs no handshake), then STOP over TCP, and tries both again, each time on a
fresh connection, until the unit answers or ``--stop-deadline-ms`` (default 3000) passes. The
reply line says how many tries it took (``... (after 2 attempts)``).

``lift`` does what a remote does when the last finger leaves the screen (spec section 8): three
lift datagrams to the UDP control port, 10 ms apart, then LIFT over TCP, whose reply it prints
(``... (lift sent x3)``). The unit stops with reason lift (a LIFT is a stop request: anyone
may send it).

With ``--key-file`` (spec section 5) requests are 48-byte frames and every reply must verify
under the key, else exit 3 (``does NOT verify``); ``release`` first asks STATUS on the same
connection to learn the unit's session.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from dataclasses import dataclass

from estop.cliutil import (
    EXIT_ACK,
    EXIT_NAK,
    ConnectionFailure,
    UsageError,
    add_settings,
    add_time_option,
    err,
    out,
    parse_u32,
)
from estop.keyfile import key_from_args
from estop.protocol import tcp, udp
from estop.stopbutton import (
    DEFAULT_STOP_DEADLINE,
    LiftDatagram,
    StopDatagram,
    StopOutcome,
    press_stop,
    send_lift,
)
from estop.stopchannel import (
    DEFAULT_REMOTE_ID,
    MessageCounter,
    StopChannel,
    StopChannelError,
    format_reply,
    reply_dict,
)

__all__ = ["COMMANDS", "LiftOutcome", "add_arguments", "lift_once", "run", "send_once",
           "stop_once"]

COMMANDS = {
    "stop": "press the stop button: a stop datagram (UDP) and STOP (TCP), tried again until "
            "the unit answers or the deadline passes; print the reply",
    "lift": "end a dead-man hold as a remote does: three lift datagrams (UDP, 10 ms apart) "
            "and LIFT (TCP); the unit stops with reason lift; print the reply",
    "release": "ask the unit to leave the stopped state (RELEASE) and print the reply",
    "status": "ask for the unit's state (STATUS, changes nothing) and print the reply",
}


def add_arguments(parser: argparse.ArgumentParser, kind: str = "") -> None:
    """Options of ``estop KIND`` (``stop`` and ``lift`` also get ``--udp-port``, ``stop``
    ``--stop-deadline-ms``). The older names still work, unlisted: ``--port`` for
    ``--tcp-port``; ``--timeout-ms`` (ms) and ``--timeout`` (s) for ``--reply-timeout-ms``;
    ``--stop-deadline`` (s) for ``--stop-deadline-ms``."""
    keys = ["host", "tcp_port"]
    if kind in ("stop", "lift"):
        keys.append("udp_port")
    if kind != "lift":
        keys.append("stop_id")
    else:
        parser.set_defaults(stop_id=tcp.DEFAULT_STOP_ID)  # a LIFT does not name the vehicle
    add_settings(parser, *keys, "key_file", "remote_id", aliases={"tcp_port": ["--port"]})
    parser.add_argument("--seq", type=parse_u32, default=1,
                        help="sequence number echoed in the reply (default 1)")
    add_time_option(parser, "reply-timeout", "timeout", 2.0,
                    "wait this long for connect and reply", ms_aliases=["--timeout-ms"],
                    s_aliases=["--timeout"])
    if kind == "stop":
        add_time_option(parser, "stop-deadline", "stop_deadline", DEFAULT_STOP_DEADLINE,
                        "try again (fresh connection, another stop datagram) until the unit "
                        "answers or this time passes")
    parser.add_argument("--json", action="store_true", help="print the reply as one JSON line")


def send_once(kind: str, host: str, port: int = tcp.DEFAULT_PORT, *, seq: int = 1,
              stop_id: int = tcp.DEFAULT_STOP_ID, timeout: float = 2.0,
              key: bytes | None = None, remote_id: int = DEFAULT_REMOTE_ID) -> tcp.Reply:
    """Send one ``stop``/``lift``/``release``/``status`` request on a fresh connection; return
    the reply.

    With ``key`` the request is a 48-byte frame and the reply must verify; a RELEASE is then
    preceded by a STATUS on the same connection, to learn the unit's session (a RELEASE with
    another session is not authenticated). Raises
    :class:`estop.stopchannel.StopChannelError` on connection/timeout/reply errors.
    """
    return _exchange(kind, host, port, seq=seq, stop_id=stop_id, timeout=timeout, key=key,
                     remote_id=remote_id)[0]


def _exchange(kind: str, host: str, port: int, *, seq: int, stop_id: int, timeout: float,
              key: bytes | None, remote_id: int) -> tuple[tcp.Reply, str | None]:
    """:func:`send_once`, and why a NAK not_authenticated came where the client can tell."""
    msg_id = {"stop": stop_id, "lift": tcp.LIFT, "release": tcp.RELEASE,
              "status": tcp.STATUS}[kind]
    with StopChannel(host, port, timeout=timeout, stop_id=stop_id, key=key,
                     remote_id=remote_id) as channel:
        if key is not None and kind == "release":
            channel.request(tcp.STATUS, seq)
        reply = channel.request(msg_id, seq)
        return reply, channel.nak_hint(reply)


def stop_once(host: str, port: int = tcp.DEFAULT_PORT, udp_port: int = udp.DEFAULT_PORT, *,
              seq: int = 1, stop_id: int = tcp.DEFAULT_STOP_ID, timeout: float = 2.0,
              deadline: float = DEFAULT_STOP_DEADLINE, key: bytes | None = None,
              remote_id: int = DEFAULT_REMOTE_ID) -> StopOutcome:
    """Press the stop button once (see :func:`estop.stopbutton.press_stop`): stop datagrams
    to ``udp_port`` and STOP with ``seq`` on fresh connections until an answer or
    ``deadline`` (with ``key``: 48-byte frames, replies that must verify)."""
    counter = MessageCounter()
    channel = StopChannel(host, port, timeout=timeout, stop_id=stop_id, key=key,
                          remote_id=remote_id, counter=counter)
    datagram = StopDatagram(host, udp_port, stop_id=stop_id, key=key, remote_id=remote_id,
                            counter=counter, session=lambda: channel.session)
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
    Never raises :class:`estop.stopchannel.StopChannelError`: failures are in the outcome."""
    counter = MessageCounter()
    datagram = LiftDatagram(host, udp_port, key=key, remote_id=remote_id, counter=counter)
    with contextlib.closing(datagram):
        sent, errors = send_lift(datagram, seq)
    try:
        with StopChannel(host, port, timeout=timeout, key=key, remote_id=remote_id,
                         counter=counter) as channel:
            reply: tcp.Reply | None = channel.request(tcp.LIFT, seq)
    except StopChannelError as exc:
        reply = None
        errors.append(str(exc))
    return LiftOutcome(reply, sent, tuple(errors))


def run(args: argparse.Namespace) -> int:
    kind: str = args.command
    try:
        tcp.check_stop_id(args.stop_id)
    except ValueError as exc:
        raise UsageError(f"--stop-id: {exc}") from None
    key = key_from_args(args)
    if kind == "stop":
        return _run_stop(args, key)
    if kind == "lift":
        return _run_lift(args, key)
    try:
        reply, hint = _exchange(kind, args.host, args.tcp_port, seq=args.seq,
                                stop_id=args.stop_id, timeout=args.timeout, key=key,
                                remote_id=args.remote_id)
    except StopChannelError as exc:
        raise ConnectionFailure(str(exc)) from None
    if args.json:
        out(json.dumps({"request": kind, **reply_dict(reply)}, sort_keys=True))
    else:
        out(format_reply(reply))
    if hint is not None:
        err(f"estop: {kind} refused: {hint}")
    return EXIT_ACK if reply.ack else EXIT_NAK


def _run_stop(args: argparse.Namespace, key: bytes | None) -> int:
    outcome = stop_once(args.host, args.tcp_port, args.udp_port, seq=args.seq,
                        stop_id=args.stop_id, timeout=args.timeout,
                        deadline=args.stop_deadline, key=key, remote_id=args.remote_id)
    reply = outcome.reply
    if reply is None:
        raise ConnectionFailure(outcome.summary())
    if args.json:
        out(json.dumps({"request": "stop", **reply_dict(reply), "attempts": outcome.attempts,
                        "stop_datagrams": outcome.datagrams}, sort_keys=True))
    else:
        out(outcome.line())
    return EXIT_ACK if reply.ack else EXIT_NAK


def _run_lift(args: argparse.Namespace, key: bytes | None) -> int:
    outcome = lift_once(args.host, args.tcp_port, args.udp_port, seq=args.seq,
                        timeout=args.timeout, key=key, remote_id=args.remote_id)
    reply = outcome.reply
    if reply is None:
        raise ConnectionFailure(outcome.line())
    if args.json:
        out(json.dumps({"request": "lift", **reply_dict(reply),
                        "lift_datagrams": outcome.datagrams}, sort_keys=True))
    else:
        out(outcome.line())
    return EXIT_ACK if reply.ack else EXIT_NAK
