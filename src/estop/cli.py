"""The ``estop`` command line: the parser built from a table of command modules
(:mod:`estop.commands`, one module per sub-command, each with ``add_parser`` and ``run``).

===================================  =======================================================
``estop remote``                     play the tablet: UDP control packets, stop/release keys
                                     or a script (:mod:`estop.commands.remote`)
``estop stop|lift|release|status``   one TCP request (stop and lift: with their datagrams),
                                     print the reply (:mod:`estop.commands.stop` ...)
``estop monitor``                    decode and check ESTOP_BRAKE / ESTOP_STATUS
                                     (:mod:`estop.commands.monitor`)
``estop demo``                       the scripted demo (:mod:`estop.commands.demo`)
``estop keygen PATH``                write a fresh key file, mode 0600
                                     (:mod:`estop.commands.keygen`)
``estop link``                       false stops per hour per timeout from a recording of the
                                     control link (:mod:`estop.commands.link`)
``estop dashboard``                  the live status page (:mod:`estop.commands.dashboard`)
===================================  =======================================================

Every command takes the common settings (``--host``, ``--udp-port``, ``--tcp-port``,
``--key-file``, ``--remote-id``, ``--stop-id``, ``--rate-hz``) from the command line, the
environment (``ESTOP_HOST`` ...) or the configuration file (:mod:`estop.commands.settings`),
and exits with the codes of :data:`estop.errors.EXIT_CODES`, the same for every command;
errors are one line ``estop: error: ...``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from estop import __version__
from estop.commands.configfile import CONFIG_ENV
from estop.commands.options import ErrorOnlyParser
from estop.commands.output import err, exit_code_table
from estop.commands.settings import resolve_settings
from estop.errors import EXIT_FILE, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_USAGE, CliError

__all__ = ["COMMANDS", "build_parser", "command_module", "main"]

# The sub-commands in the order of ``estop --help``, each the module of estop.commands of its
# name, which adds its parser, whose ``handler`` runs the command. ``estop demo`` parses its
# own options (see main). A command imports its own module only: ``estop stop`` loaded the
# dashboard's asyncio server and the demo as well, 120 of its 155 ms of imports (seconds in a
# VM under TCG, where the systemd and gamepad checks run the command line).
COMMANDS = ("remote", "stop", "lift", "release", "status", "monitor", "keygen", "link",
            "dashboard", "demo")


def command_module(name: str) -> ModuleType:
    """The module of the sub-command ``name`` (one of COMMANDS)."""
    return importlib.import_module(f"estop.commands.{name}")

_EPILOG = f"""\
settings: command line > environment (ESTOP_HOST, ESTOP_UDP_PORT, ESTOP_TCP_PORT,
ESTOP_KEY_FILE, ESTOP_REMOTE_ID, ESTOP_STOP_ID, ESTOP_RATE_HZ) > config file
(${CONFIG_ENV}, else $XDG_CONFIG_HOME/estop/config.toml, else ~/.config/estop/config.toml;
TOML keys host, udp_port, tcp_port, key_file, remote_id, stop_id, rate_hz) > default.
CAN: --interface/--channel/--bitrate over python-can's own configuration.

exit codes (every command):
{exit_code_table()}"""


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``estop`` parser with every sub-command, or with the one named ``only``."""
    parser = ErrorOnlyParser(prog="estop", description="Tools for the estop emergency-stop "
                             "unit (wire contract: docs/PROTOCOL.md).", epilog=_EPILOG,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"estop {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS if only is None else (only,):
        command_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``estop`` command line and return its exit code (--help and --version
    included); errors are one line on stderr, never a traceback."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    try:
        if args_list[:1] == ["demo"]:
            # everything after `demo` belongs to the demo's own parser (argparse.REMAINDER
            # would not pass options such as --help through a sub-parser)
            return int(command_module("demo").main(args_list[1:]) or 0)
        # the named command's parser alone; --help, --version or a wrong name: all of them
        named = args_list[0] if args_list and args_list[0] in COMMANDS else None
        args = build_parser(named).parse_args(args_list)
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
