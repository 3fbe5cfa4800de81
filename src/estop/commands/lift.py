"""``estop lift``: what a remote does when the last finger leaves the screen (spec section 8):
three lift datagrams to the UDP control port, 10 ms apart, then LIFT over TCP, whose reply it
prints (``... (lift sent x3)``). The unit stops with reason lift (a LIFT is a stop request:
anyone may send it)."""

from __future__ import annotations

import argparse

from estop.client.oneshot import lift_once
from estop.commands.request import add_request_parser, checked_key, print_reply
from estop.errors import ConnectionFailure

__all__ = ["add_parser", "run"]

HELP = ("end a dead-man hold as a remote does: three lift datagrams (UDP, 10 ms apart) and "
        "LIFT (TCP); the unit stops with reason lift; print the reply")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    add_request_parser(sub, "lift", HELP).set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    key = checked_key(args)
    outcome = lift_once(args.host, args.tcp_port, args.udp_port, seq=args.seq,
                        timeout=args.timeout, key=key, remote_id=args.remote_id)
    if outcome.reply is None:
        raise ConnectionFailure(outcome.line())
    return print_reply(args, outcome.reply, outcome.line(),
                       lift_datagrams=outcome.datagrams)
