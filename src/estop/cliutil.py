"""Small helpers shared by the ``estop`` sub-commands: errors with exit codes, output, parsing."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import NoReturn

from estop.protocol import tcp, udp
from estop.settings import (
    ConfigFile,
    Setting,
    SettingError,
    config_path,
    installation_remote_id,
    parse_from,
)

__all__ = [
    "COMMON_SETTINGS",
    "EXIT_ACK",
    "EXIT_CODES",
    "EXIT_CONNECTION",
    "EXIT_FILE",
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_NAK",
    "EXIT_NOT_INSTALLED",
    "EXIT_OK",
    "EXIT_PROBLEM",
    "EXIT_REFUSED",
    "EXIT_UNREACHABLE",
    "EXIT_USAGE",
    "CliError",
    "ConnectionFailure",
    "ErrorOnlyParser",
    "FileFailure",
    "NotInstalled",
    "UsageError",
    "add_can_options",
    "add_key_arguments",
    "add_settings",
    "add_time_option",
    "can_bus_config",
    "err",
    "exit_code_table",
    "non_negative_float",
    "out",
    "parse_u32",
    "port",
    "positive_float",
    "require_extra",
    "resolve_settings",
    "source_of",
]

# One table for every command (``estop --help``, README "Exit codes"; tests/test_cli_exit.py).
EXIT_OK = 0  # done: ACK, report written, no problem found
EXIT_REFUSED = 1  # the answer is no: a NAK, a problem flagged, a script's `expect` failed
EXIT_USAGE = 2  # bad options, or a bad value from the environment or the configuration file
EXIT_UNREACHABLE = 3  # no (valid) answer: refused/closed connection, timeout, bad reply, no bus
EXIT_FILE = 4  # a file cannot be read, written or understood (key file, log, script, plot)
EXIT_NOT_INSTALLED = 5  # a part is not installed: an extra (pip install 'estop[...]'), estopd
EXIT_INTERNAL = 6  # a bug in estop: please report it with the command line
EXIT_INTERRUPTED = 130  # Ctrl-C

EXIT_CODES: tuple[tuple[int, str], ...] = (
    (EXIT_OK, "ok: ACK, report written, no problem found"),
    (EXIT_REFUSED, "refused: NAK, problems flagged, a script's expect failed"),
    (EXIT_USAGE, "usage: bad option, or bad value in the environment or config file"),
    (EXIT_UNREACHABLE, "unreachable: no valid answer (connection refused or closed, timeout, "
                       "malformed or unverified reply; stop: no answer by the deadline; "
                       "CAN bus cannot be opened)"),
    (EXIT_FILE, "file: a file cannot be read, written or understood (key file, log, "
                "script, pcap, plot)"),
    (EXIT_NOT_INSTALLED, "not installed: the command needs an extra (pip install "
                         "'estop[link]', 'estop[bus]') or estopd"),
    (EXIT_INTERNAL, "internal error: a bug in estop, please report it"),
    (EXIT_INTERRUPTED, "interrupted (Ctrl-C)"),
)

# older names of the same codes
EXIT_ACK = EXIT_OK
EXIT_NAK = EXIT_REFUSED
EXIT_PROBLEM = EXIT_REFUSED
EXIT_CONNECTION = EXIT_UNREACHABLE


def exit_code_table() -> str:
    """The exit codes, one per entry, wrapped to 88 columns (``estop --help``)."""
    import textwrap

    return "\n".join(textwrap.fill(text, 88, initial_indent=f"  {code:>3}  ",
                                   subsequent_indent=" " * 7) for code, text in EXIT_CODES)


class CliError(Exception):
    """An error the CLI reports as one line ``estop: error: <message>``."""

    exit_code = EXIT_REFUSED


class UsageError(CliError):
    exit_code = EXIT_USAGE


class ConnectionFailure(CliError):
    exit_code = EXIT_UNREACHABLE


class FileFailure(CliError):
    exit_code = EXIT_FILE


class NotInstalled(CliError):
    exit_code = EXIT_NOT_INSTALLED


def require_extra(extra: str, *modules: str) -> None:
    """Raise :class:`NotInstalled` naming ``estop[extra]`` unless every module imports."""
    import importlib

    missing = []
    for m in modules:
        try:
            importlib.import_module(m)  # the command imports it next anyway
        except ImportError:
            missing.append(_DISTRIBUTIONS.get(m, m))
    if missing:
        raise NotInstalled(f"this needs {', '.join(missing)}: pip install 'estop[{extra}]'")


_DISTRIBUTIONS = {"can": "python-can"}  # import name -> the name pip knows


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


def positive_s(text: str) -> float:
    return positive_float(text)


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


def add_time_option(parser: argparse.ArgumentParser, name: str, dest: str, default_s: float,
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


# ----------------------------------------------------------------- the common settings

COMMON_SETTINGS: dict[str, Setting] = {s.key: s for s in (
    Setting("host", "--host", "ESTOP_HOST", host),
    Setting("udp_port", "--udp-port", "ESTOP_UDP_PORT", port, udp.DEFAULT_PORT),
    Setting("tcp_port", "--tcp-port", "ESTOP_TCP_PORT", port, tcp.DEFAULT_PORT),
    Setting("key_file", "--key-file", "ESTOP_KEY_FILE", key_path),
    Setting("remote_id", "--remote-id", "ESTOP_REMOTE_ID", parse_u32),
    Setting("stop_id", "--stop-id", "ESTOP_STOP_ID", stop_id, tcp.DEFAULT_STOP_ID),
    Setting("rate_hz", "--rate-hz", "ESTOP_RATE_HZ", positive_float, 50.0),
)}

_HELP = {
    "host": "the unit's address",
    "udp_port": "the unit's UDP control port",
    "tcp_port": "the unit's TCP stop port",
    "key_file": "the unit's key (64 hex digits, mode 0600; estop keygen makes one): "
                "authenticated packets and requests, and every reply must verify; none: the "
                "plain forms",
    "remote_id": "this remote's id among those sharing the key (default without a key: 1; "
                 "with a key: this installation's own id, made on first use and kept in the "
                 "config file)",
    "stop_id": "the vehicle's stop ID",
    "rate_hz": "control packets per second",
}
_METAVAR = {"host": "HOST", "udp_port": "PORT", "tcp_port": "PORT", "key_file": "PATH",
            "remote_id": "N", "stop_id": "ID", "rate_hz": "HZ"}
_SETTINGS_ATTR = "_estop_settings"
_SOURCES_ATTR = "_estop_sources"
_HOST_REQUIRED_ATTR = "_estop_host_required"


def add_settings(parser: argparse.ArgumentParser, *keys: str,
                 aliases: Mapping[str, Sequence[str]] | None = None,
                 parse: Mapping[str, Callable[[str], object]] | None = None,
                 help: Mapping[str, str] | None = None,
                 default: Mapping[str, object] | None = None,
                 host_required: bool = True) -> None:
    """Add the common settings ``keys`` (see :data:`COMMON_SETTINGS`) to ``parser``, each with
    its option, environment variable and configuration key; ``aliases`` gives a command's
    older, unlisted option names, ``parse``/``help``/``default`` a command's own reading,
    text or default; ``host_required=False`` for a command that may run without a unit (its
    ``host`` stays None when no source names one). :func:`resolve_settings` fills them in after
    parsing."""
    chosen: dict[str, Setting] = {}
    for key in keys:
        base = COMMON_SETTINGS[key]
        s = Setting(base.key, base.flag, base.env, (parse or {}).get(key, base.parse),
                    (default or {}).get(key, base.default))
        chosen[key] = s
        text = (help or {}).get(key, _HELP[key])
        if s.default is not None:
            shown = f"0x{s.default:08X}" if key == "stop_id" else f"{s.default:g}" \
                if isinstance(s.default, float) else str(s.default)
            text += f"; default {shown}"
        parser.add_argument(s.flag, dest=key, type=s.parse, default=None,
                            metavar=_METAVAR[key], help=f"{text} (${s.env}, config: {key})")
        for flag in (aliases or {}).get(key, ()):
            parser.add_argument(flag, dest=key, type=s.parse, default=argparse.SUPPRESS,
                                help=argparse.SUPPRESS)
    known = dict(parser.get_default(_SETTINGS_ATTR) or {})
    known.update(chosen)
    parser.set_defaults(**{_SETTINGS_ATTR: known})
    if "host" in chosen:
        parser.set_defaults(**{_HOST_REQUIRED_ATTR: host_required})


def add_key_arguments(parser: argparse.ArgumentParser) -> None:
    """``--key-file`` and ``--remote-id`` (spec section 5), for the tools that talk to a unit."""
    add_settings(parser, "key_file", "remote_id")


def source_of(args: argparse.Namespace, key: str) -> str:
    """Where the value of setting ``key`` came from (``--udp-port``, ``ESTOP_UDP_PORT``,
    ``<config>: udp_port``, ``default``), for messages about it."""
    sources: dict[str, str] = getattr(args, _SOURCES_ATTR, {})
    return sources.get(key, key)


def resolve_settings(args: argparse.Namespace, environ: Mapping[str, str] | None = None,
                     config: ConfigFile | None = None) -> None:
    """Fill in each common setting of the parsed command: the command line, else the
    environment, else the configuration file, else the default. A command that uses a key
    without a remote id from any of them gets this installation's id (made and kept on
    first use). Raises :class:`UsageError` (one line naming the source) for a bad value, and
    for a missing ``--host``."""
    settings: dict[str, Setting] = getattr(args, _SETTINGS_ATTR, None) or {}
    if not settings:
        return
    env = os.environ if environ is None else environ
    cfg = config or ConfigFile(config_path(env), COMMON_SETTINGS)
    sources: dict[str, str] = {}
    try:
        for key, s in settings.items():
            if getattr(args, key, None) is not None:
                sources[key] = s.flag
                continue
            value: object = None
            if env.get(s.env):
                value = parse_from(s, env[s.env], f"{s.env}={env[s.env]}")
                sources[key] = s.env
            else:
                found = cfg.lookup(s)
                if found is not None:
                    value, sources[key] = found
                elif s.default is not None:
                    value, sources[key] = s.default, "default"
            setattr(args, key, value)
        if "remote_id" in settings and args.remote_id is None:
            key_file = getattr(args, "key_file", None)
            # only for a key that is there: a command failing on its key file changes nothing
            if key_file is not None and os.path.isfile(key_file):
                args.remote_id = installation_remote_id(cfg)
                sources["remote_id"] = f"{cfg.path}: remote_id"
                err(f"estop: note: this installation's remote id is {args.remote_id}, made "
                    f"now and kept in {cfg.path}")
            else:
                args.remote_id, sources["remote_id"] = 1, "default"
    except SettingError as exc:
        raise UsageError(str(exc)) from None
    if "host" in settings and args.host is None and getattr(args, _HOST_REQUIRED_ATTR, True):
        raise UsageError(f"no unit address: give --host, or set ESTOP_HOST or host in "
                         f"{cfg.path}")
    setattr(args, _SOURCES_ATTR, sources)


# ------------------------------------------------------------------------------- CAN

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


def can_bus_config(args: argparse.Namespace) -> dict[str, object]:
    """The bus to open: the command line over python-can's configuration (its environment
    variables and files, read by can.util.load_config). Raises :class:`UsageError` when no
    interface is named anywhere, :class:`NotInstalled` without python-can."""
    require_extra("bus", "can")
    import can

    given = {k: v for k, v in (("interface", args.interface), ("channel", args.channel),
                               ("bitrate", args.bitrate)) if v is not None}
    nowhere = UsageError("no CAN bus: give --interface (and --channel), or set them in "
                         "python-can's configuration (CAN_INTERFACE, ~/.canrc)")
    try:
        cfg = dict(can.util.load_config(config=given))
    except (can.CanError, ValueError, NotImplementedError) as exc:
        if '"None"' in str(exc):  # python-can's words for no interface named anywhere
            raise nowhere from None
        raise UsageError(f"python-can configuration: {exc}") from None
    if not cfg.get("interface"):
        raise nowhere
    return cfg
