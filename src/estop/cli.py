"""The ``estop`` command line: argparse dispatch to one module per sub-command.

===================================  =======================================================
``estop remote``                     play the tablet: UDP control packets, stop/release keys
                                     or a script (:mod:`estop.remote`)
``estop stop|lift|release|status``   one TCP request (stop and lift: with their datagrams),
                                     print the reply (:mod:`estop.oneshot`)
``estop monitor``                    decode and check ESTOP_BRAKE / ESTOP_STATUS
                                     (:mod:`estop.monitor`)
``estop demo``                       the scripted demo (:mod:`estop.demo`)
``estop keygen PATH``                write a fresh key file, mode 0600 (:mod:`estop.keyfile`)
``estop link``                       false stops per hour per timeout from a recording of the
                                     control link (:mod:`estop.link`)
``estop dashboard``                  the live status page (:mod:`estop.dashboard`)
===================================  =======================================================

Exit codes: 0 success/ACK, 1 NAK or problems found, 2 usage error (one line
``estop: error: ...``), 3 connection, timeout or malformed reply, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from estop import __version__
from estop.cliutil import EXIT_USAGE, CliError, ErrorOnlyParser, err

__all__ = ["build_parser", "main"]

_EPILOG = ("exit codes: 0 success/ACK, 1 NAK or problems found, 2 usage error, "
           "3 connection/timeout/malformed reply")


def build_parser() -> argparse.ArgumentParser:
    from estop import dashboard, keyfile, link, monitor, oneshot, remote

    parser = ErrorOnlyParser(prog="estop", description="Tools for the estop emergency-stop "
                             "unit (wire contract: docs/PROTOCOL.md).", epilog=_EPILOG)
    parser.add_argument("--version", action="version", version=f"estop {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("remote", help="play the tablet (UDP control packets, TCP stop button)",
                       description=remote.DESCRIPTION, epilog=remote.EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    remote.add_arguments(p)
    p.set_defaults(handler=remote.run)

    for name, text in oneshot.COMMANDS.items():
        last = "; for stop: no ACK by the deadline" if name == "stop" else ""
        p = sub.add_parser(name, help=text, description=text, epilog="exit codes: 0 ACK, "
                           f"1 NAK, 2 usage error, 3 connection/timeout/malformed reply{last}")
        oneshot.add_arguments(p, name)
        p.set_defaults(handler=oneshot.run)

    p = sub.add_parser("monitor", help="decode and check ESTOP_BRAKE / ESTOP_STATUS frames",
                       description=monitor.DESCRIPTION,
                       epilog="exit codes: 0 no problem, 1 problems flagged, 2 usage error "
                              "or malformed log line, 3 bus or file cannot be opened")
    monitor.add_arguments(p)
    p.set_defaults(handler=monitor.run)

    p = sub.add_parser("keygen", help="write a fresh random key file (mode 0600)",
                       description=keyfile.DESCRIPTION, epilog=keyfile.EPILOG)
    keyfile.add_arguments(p)
    p.set_defaults(handler=keyfile.run)
    p = sub.add_parser("link", help="false stops per hour per timeout from a recording of "
                       "the control link (estopd log, arrival times or pcap)",
                       description=link.DESCRIPTION, epilog=link.EPILOG)
    link.add_arguments(p)
    p.set_defaults(handler=link.run)

    p = sub.add_parser("dashboard", help="serve the live status page (state, frames, link, "
                       "timeline)", description=dashboard.DESCRIPTION, epilog=dashboard.EPILOG)
    dashboard.add_arguments(p)
    p.set_defaults(handler=dashboard.run)

    # `estop demo ...` is dispatched before parsing (see main); listed here for --help
    sub.add_parser("demo", help="run estopd on loopback and play a scripted drive "
                   "(estop demo --help)")
    return parser


def _demo(args: argparse.Namespace) -> int:
    try:
        demo = importlib.import_module("estop.demo")
    except ModuleNotFoundError as exc:
        if exc.name != "estop.demo":
            raise
        raise CliError("the demo is not installed (estop.demo is missing)") from None
    code = demo.main(list(args.rest))
    return int(code or 0)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``estop`` command line and return its exit code (--help and --version
    included); errors are one line on stderr, never a traceback."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    try:
        if args_list[:1] == ["demo"]:
            # everything after `demo` belongs to the demo's own parser (argparse.REMAINDER
            # would not pass options such as --help through a sub-parser)
            return _demo(argparse.Namespace(rest=args_list[1:]))
        args = build_parser().parse_args(args_list)
        return int(args.handler(args))
    except CliError as exc:
        err(f"estop: error: {exc}")
        return exc.exit_code
    except KeyboardInterrupt:
        err("estop: interrupted")
        return 130
    except BrokenPipeError:
        return 1
    except SystemExit as exc:
        if isinstance(exc.code, int):
            return exc.code
        return EXIT_USAGE if exc.code else 0
    except Exception as exc:  # never a traceback for the user; say what failed in one line
        err(f"estop: error: internal error: {type(exc).__name__}: {exc}")
        return 4
