"""The ``estop`` commands' option vocabulary: the parser whose usage error is one line, the
argparse types (u32, port, finite numbers, times with their unit in the name, host, stop ID,
key path, listen address) and the option groups every command spells alike (``--NAME-ms``,
python-can's ``--interface``/``--channel``/``--bitrate``)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from typing import NoReturn

from estop.commands.output import err
from estop.errors import EXIT_USAGE, UsageError
from estop.protocol import tcp
from estop.protocol.can import BRAKE_ID, STATUS_ID

__all__ = [
    "ErrorOnlyParser",
    "add_can_options",
    "add_frame_id_options",
    "can_id",
    "add_time_option",
    "host",
    "key_path",
    "non_negative_float",
    "parse_listen",
    "parse_u32",
    "port",
    "positive_float",
    "positive_ms_as_seconds",
    "stop_id",
]


class ErrorOnlyParser(argparse.ArgumentParser):
    """argparse, but a usage error is the single line ``estop: error: ...`` (exit 2)."""

    def error(self, message: str) -> NoReturn:
        prog = self.prog.split()[0] if self.prog else "estop"
        err(f"{prog}: error: {message}")
        raise SystemExit(EXIT_USAGE)


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


def non_negative_float(text: str) -> float:
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text}")
    return value


def positive_ms_as_seconds(text: str) -> float:
    """A time in milliseconds (> 0), kept in seconds."""
    return positive_float(text) / 1000.0


def host(text: str) -> str:
    if not text or text != text.strip():
        raise argparse.ArgumentTypeError(f"not a host name or address: {text!r}")
    return text


def stop_id(text: str) -> int:
    """argparse type: the vehicle's stop ID (a u32 the protocol does not reserve)."""
    value = parse_u32(text)
    try:
        return tcp.check_stop_id(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def key_path(text: str) -> str:
    if not text:
        raise argparse.ArgumentTypeError("empty path")
    return os.path.expanduser(text)


def add_time_option(parser: argparse._ActionsContainer, name: str, dest: str, default_s: float,
                    help_text: str, *, ms_aliases: Sequence[str] = (),
                    s_aliases: Sequence[str] | None = None) -> None:
    """``--NAME-ms MS``, the project's vocabulary (the unit in the name), stored in seconds in
    ``dest``. Older spellings stay as unlisted names of the same option: ``ms_aliases`` in ms,
    ``s_aliases`` in seconds (default ``--NAME``)."""
    parser.add_argument(f"--{name}-ms", dest=dest, type=positive_ms_as_seconds,
                        default=default_s, metavar="MS",
                        help=f"{help_text} (default {default_s * 1000:g})")
    for flag in ms_aliases:
        parser.add_argument(flag, dest=dest, type=positive_ms_as_seconds,
                            default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    for flag in (f"--{name}",) if s_aliases is None else s_aliases:
        parser.add_argument(flag, dest=dest, type=positive_float,
                            default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8080`` for IPv6) -> (host, port); port 0: any free one."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not host:
        raise UsageError(f"--listen must be ADDR:PORT, got {text!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        number = int(port_text, 10)
    except ValueError:
        raise UsageError(f"--listen: not a port number: {port_text!r}") from None
    if not 0 <= number <= 65535:
        raise UsageError(f"--listen: port {number} out of range 0..65535")
    return host, number


def can_id(text: str) -> int:
    """argparse type: an 11-bit CAN ID, decimal or 0x-hex."""
    value = parse_u32(text)
    if value > 0x7FF:
        raise argparse.ArgumentTypeError(f"{text} is not an 11-bit CAN ID (0..0x7FF)")
    return value


def add_frame_id_options(parser: argparse.ArgumentParser) -> None:
    """``--brake-id`` and ``--status-id``: the CAN IDs the unit's frames are read at."""
    parser.add_argument("--brake-id", type=can_id, default=BRAKE_ID, metavar="ID",
                        help=f"ESTOP_BRAKE CAN ID (default {BRAKE_ID:#05x})")
    parser.add_argument("--status-id", type=can_id, default=STATUS_ID, metavar="ID",
                        help=f"ESTOP_STATUS CAN ID (default {STATUS_ID:#05x})")


def add_can_options(parser: argparse.ArgumentParser) -> None:
    """python-can's own vocabulary for a bus: ``--interface``, ``--channel``, ``--bitrate``;
    what is not given comes from python-can's configuration (``CAN_INTERFACE``,
    ``CAN_CHANNEL``, ``CAN_BITRATE``, ``~/.canrc``, ``can.ini``: can.util.load_config)."""
    parser.add_argument("-i", "--interface", metavar="IF",
                        help="python-can interface (socketcan, virtual, ...; default: "
                             "python-can's configuration, $CAN_INTERFACE or ~/.canrc)")
    parser.add_argument("-c", "--channel", metavar="CH",
                        help="python-can channel (can0, vcan0, ...; default: python-can's "
                             "configuration)")
    parser.add_argument("--bitrate", type=int, metavar="BPS",
                        help="bus bitrate, for interfaces that set it (default: python-can's "
                             "configuration)")
