"""Small helpers shared by the ``estop`` sub-commands: errors with exit codes, output, parsing."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

__all__ = [
    "EXIT_ACK",
    "EXIT_CONNECTION",
    "EXIT_NAK",
    "EXIT_OK",
    "EXIT_PROBLEM",
    "EXIT_USAGE",
    "CliError",
    "ConnectionFailure",
    "ErrorOnlyParser",
    "UsageError",
    "add_key_arguments",
    "add_time_option",
    "err",
    "non_negative_float",
    "out",
    "parse_u32",
    "port",
    "positive_float",
]

EXIT_OK = 0
EXIT_ACK = 0
EXIT_NAK = 1
EXIT_PROBLEM = 1  # monitor flagged a problem, a remote script's `expect` failed
EXIT_USAGE = 2
EXIT_CONNECTION = 3  # connection refused/closed, timeout, malformed reply


class CliError(Exception):
    """An error the CLI reports as one line ``estop: error: <message>``."""

    exit_code = 1


class UsageError(CliError):
    exit_code = EXIT_USAGE


class ConnectionFailure(CliError):
    exit_code = EXIT_CONNECTION


def out(line: str = "") -> None:
    """Write one line to standard output and flush (the CLI's output, not debugging)."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def err(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


class ErrorOnlyParser(argparse.ArgumentParser):
    """argparse, but a usage error is the single line ``estop: error: ...`` (exit 2)."""

    def error(self, message: str) -> NoReturn:
        prog = self.prog.split()[0] if self.prog else "estop"
        err(f"{prog}: error: {message}")
        raise SystemExit(EXIT_USAGE)


def add_key_arguments(parser: argparse.ArgumentParser) -> None:
    """``--key-file`` and ``--remote-id`` (spec section 5), for the tools that talk to a unit."""
    from estop.stopchannel import DEFAULT_REMOTE_ID

    parser.add_argument("--key-file", metavar="PATH",
                        help="the unit's key (64 hex digits, mode 0600; estop keygen makes "
                             "one): authenticated 60-byte packets and 48-byte requests, and "
                             "every reply must verify. Default: $ESTOP_KEY_FILE; neither: "
                             "the plain forms")
    parser.add_argument("--remote-id", type=parse_u32, default=DEFAULT_REMOTE_ID, metavar="N",
                        help=f"this remote's id among those sharing the key "
                             f"(default {DEFAULT_REMOTE_ID})")


def parse_u32(text: str) -> int:
    """argparse type: a u32 in decimal or 0x-hex."""
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value <= 0xFFFFFFFF:
        raise argparse.ArgumentTypeError(f"{text} is not a u32 (0..0xFFFFFFFF)")
    return value


def port(text: str) -> int:
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} out of range 1..65535")
    return value


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return value


def positive_float(text: str) -> float:
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text}")
    return value


def positive_ms_as_seconds(text: str) -> float:
    """A time in milliseconds (> 0), kept in seconds."""
    return positive_float(text) / 1000.0


def add_time_option(parser: argparse.ArgumentParser, name: str, dest: str, default_s: float,
                    help_text: str) -> None:
    """``--NAME-ms MS``, the project's vocabulary (the unit in the name), stored in seconds in
    ``dest``; ``--NAME`` in seconds stays as the older, unlisted spelling of the same option."""
    parser.add_argument(f"--{name}-ms", dest=dest, type=positive_ms_as_seconds,
                        default=default_s, metavar="MS",
                        help=f"{help_text} (default {default_s * 1000:g})")
    parser.add_argument(f"--{name}", dest=dest, type=positive_float,
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def non_negative_float(text: str) -> float:
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text}")
    return value
