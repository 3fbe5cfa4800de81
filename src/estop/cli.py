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

Every command takes the common settings (``--host``, ``--udp-port``, ``--tcp-port``,
``--key-file``, ``--remote-id``, ``--stop-id``, ``--rate-hz``) from the command line, the
environment (``ESTOP_HOST`` ...) or the configuration file (:mod:`estop.settings`), and exits
with the codes of :data:`estop.cliutil.EXIT_CODES`, the same for every command; errors are one
line ``estop: error: ...``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from estop import __version__
from estop.cliutil import (
    EXIT_FILE,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    CliError,
    ErrorOnlyParser,
    NotInstalled,
    err,
    exit_code_table,
    resolve_settings,
)
from estop.settings import CONFIG_ENV

__all__ = ["build_parser", "main"]

_EPILOG = f"""\
settings: command line > environment (ESTOP_HOST, ESTOP_UDP_PORT, ESTOP_TCP_PORT,
ESTOP_KEY_FILE, ESTOP_REMOTE_ID, ESTOP_STOP_ID, ESTOP_RATE_HZ) > config file
(${CONFIG_ENV}, else $XDG_CONFIG_HOME/estop/config.toml, else ~/.config/estop/config.toml;
TOML keys host, udp_port, tcp_port, key_file, remote_id, stop_id, rate_hz) > default.
CAN: --interface/--channel/--bitrate over python-can's own configuration.

exit codes (every command):
{exit_code_table()}"""
_SUB_EPILOG = "exit codes: as for every estop command (estop --help)"


def build_parser() -> argparse.ArgumentParser:
    from estop import dashboard, keyfile, link, monitor, oneshot, remote

    parser = ErrorOnlyParser(prog="estop", description="Tools for the estop emergency-stop "
                             "unit (wire contract: docs/PROTOCOL.md).", epilog=_EPILOG,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"estop {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("remote", help="play the tablet (UDP control packets, TCP stop button)",
                       description=remote.DESCRIPTION, epilog=remote.EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    remote.add_arguments(p)
    p.set_defaults(handler=remote.run)

    for name, text in oneshot.COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text, epilog=_SUB_EPILOG)
        oneshot.add_arguments(p, name)
        p.set_defaults(handler=oneshot.run)

    p = sub.add_parser("monitor", help="decode and check ESTOP_BRAKE / ESTOP_STATUS frames",
                       description=monitor.DESCRIPTION, epilog=_SUB_EPILOG)
    monitor.add_arguments(p)
    p.set_defaults(handler=monitor.run)

    p = sub.add_parser("keygen", help="write a fresh random key file (mode 0600)",
                       description=keyfile.DESCRIPTION, epilog=_SUB_EPILOG)
    keyfile.add_arguments(p)
    p.set_defaults(handler=keyfile.run)
    p = sub.add_parser("link", help="false stops per hour per timeout from a recording of "
                       "the control link (estopd log, arrival times or pcap)",
                       description=link.DESCRIPTION, epilog=f"{link.EPILOG} {_SUB_EPILOG}")
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
        raise NotInstalled("the demo is not installed (estop.demo is missing)") from None
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
        resolve_settings(args)
        return int(args.handler(args))
    except CliError as exc:
        err(f"estop: error: {exc}")
        return exc.exit_code
    except KeyboardInterrupt:
        err("estop: interrupted")
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader of our output went away
        return EXIT_FILE
    except SystemExit as exc:
        if isinstance(exc.code, int):
            return exc.code
        return EXIT_USAGE if exc.code else 0
    except Exception as exc:  # never a traceback for the user; say what failed in one line
        err(f"estop: error: internal error (a bug, please report it): "
            f"{type(exc).__name__}: {exc}")
        return EXIT_INTERNAL
