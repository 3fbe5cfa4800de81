"""``estop stop``: the stop button. A stop datagram to the UDP control port at once (spec
section 1; it needs no handshake), then STOP over TCP, both tried again, each time on a fresh
connection, until the unit answers or ``--stop-deadline-ms`` (default 3000) passes. The reply
line says how many tries it took (``... (after 2 attempts)``)."""

from __future__ import annotations

import argparse

from estop.client.oneshot import stop_once
from estop.commands.request import add_request_parser, checked_key, print_reply
from estop.errors import ConnectionFailure

__all__ = ["add_parser", "run"]

HELP = ("press the stop button: a stop datagram (UDP) and STOP (TCP), tried again until the "
        "unit answers or the deadline passes; print the reply")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    add_request_parser(sub, "stop", HELP).set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    key = checked_key(args)
    outcome = stop_once(args.host, args.tcp_port, args.udp_port, seq=args.seq,
                        stop_id=args.stop_id, timeout=args.timeout,
                        deadline=args.stop_deadline, key=key, remote_id=args.remote_id)
    if outcome.reply is None:
        raise ConnectionFailure(outcome.summary())
    return print_reply(args, outcome.reply, outcome.line(), attempts=outcome.attempts,
                       stop_datagrams=outcome.datagrams)
