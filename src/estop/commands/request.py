"""What ``estop stop | lift | release | status`` share: their options and how a reply is
printed. Each opens a connection, sends one request, prints the decoded reply and exits with
0 for an ACK, 1 for a NAK (the reply line says why, e.g. ``nak=no_live_link``; a
``not_authenticated`` gets a second line on stderr saying what the client can tell: no key
given, or the unit refused this remote id's counter as a replay), 2 for a usage error, 3 when
the connection was refused or closed, timed out or the reply was malformed (bad CRC, wrong seq;
for ``stop``: no ACK by the deadline), 4 when the key file cannot be used (the table of every
command: :data:`estop.errors.EXIT_CODES`).

With ``--key-file`` (spec section 5) requests are 48-byte frames and every reply must verify
under the key, else exit 3 (``does NOT verify``).
"""

from __future__ import annotations

import argparse
import json

from estop.client.button import DEFAULT_STOP_DEADLINE
from estop.client.channel import StopChannelError, format_reply, reply_dict
from estop.client.oneshot import exchange
from estop.commands.options import add_time_option, parse_u32
from estop.commands.output import SUB_EPILOG, err, out
from estop.commands.settings import add_settings, key_from_args
from estop.errors import EXIT_OK, EXIT_REFUSED, ConnectionFailure, UsageError
from estop.protocol import tcp

__all__ = ["add_request_parser", "checked_key", "print_reply", "run_request"]


def add_request_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], kind: str,
                       text: str) -> argparse.ArgumentParser:
    """The parser of ``estop KIND`` (``stop`` and ``lift`` also get ``--udp-port``, ``stop``
    ``--stop-deadline-ms``). The older names still work, unlisted: ``--port`` for
    ``--tcp-port``; ``--timeout-ms`` (ms) and ``--timeout`` (s) for ``--reply-timeout-ms``;
    ``--stop-deadline`` (s) for ``--stop-deadline-ms``."""
    parser = sub.add_parser(kind, help=text, description=text, epilog=SUB_EPILOG)
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
    return parser


def checked_key(args: argparse.Namespace) -> bytes | None:
    """The key of the settings, after checking the stop ID (a usage error, exit 2)."""
    try:
        tcp.check_stop_id(args.stop_id)
    except ValueError as exc:
        raise UsageError(f"--stop-id: {exc}") from None
    return key_from_args(args)


def print_reply(args: argparse.Namespace, reply: tcp.Reply, line: str,
                **extra: object) -> int:
    """The reply as ``line`` or, with ``--json``, one JSON line with ``extra``; the exit code."""
    if args.json:
        out(json.dumps({"request": args.command, **reply_dict(reply), **extra},
                       sort_keys=True))
    else:
        out(line)
    return EXIT_OK if reply.ack else EXIT_REFUSED


def run_request(args: argparse.Namespace) -> int:
    """``estop release`` and ``estop status``: one request, its reply."""
    kind: str = args.command
    key = checked_key(args)
    try:
        reply, hint = exchange(kind, args.host, args.tcp_port, seq=args.seq,
                               stop_id=args.stop_id, timeout=args.timeout, key=key,
                               remote_id=args.remote_id)
    except StopChannelError as exc:
        raise ConnectionFailure(str(exc)) from None
    code = print_reply(args, reply, format_reply(reply))
    if hint is not None:
        err(f"estop: {kind} refused: {hint}")
    return code
