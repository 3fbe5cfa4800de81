"""The common settings of the ``estop`` commands on a parser: each with its option, its
environment variable and its configuration key (:mod:`estop.commands.configfile`), resolved
after parsing (the command line, else the environment, else the configuration file, else the
default), and the key they name."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Mapping, Sequence

from estop.client.keyfile import KeyFileError, load_key_file
from estop.commands.configfile import (
    ConfigFile,
    Setting,
    SettingError,
    config_path,
    installation_remote_id,
    parse_from,
)
from estop.commands.options import host, key_path, parse_u32, port, positive_float, stop_id
from estop.commands.output import err
from estop.errors import FileFailure, UsageError
from estop.protocol import tcp, udp

__all__ = [
    "COMMON_SETTINGS",
    "add_key_arguments",
    "add_settings",
    "key_from_args",
    "resolve_settings",
    "source_of",
]


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
                 host_required: bool = True,
                 group: argparse._ArgumentGroup | None = None) -> None:
    """Add the common settings ``keys`` (see :data:`COMMON_SETTINGS`) to ``parser``, each with
    its option, environment variable and configuration key; ``aliases`` gives a command's
    older, unlisted option names, ``parse``/``help``/``default`` a command's own reading,
    text or default; ``host_required=False`` for a command that may run without a unit (its
    ``host`` stays None when no source names one); ``group``: the options are listed in that
    group of ``parser``'s help. :func:`resolve_settings` fills them in after parsing."""
    where: argparse._ActionsContainer = parser if group is None else group
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
        where.add_argument(s.flag, dest=key, type=s.parse, default=None,
                           metavar=_METAVAR[key], help=f"{text} (${s.env}, config: {key})")
        for flag in (aliases or {}).get(key, ()):
            where.add_argument(flag, dest=key, type=s.parse, default=argparse.SUPPRESS,
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


def key_from_args(args: argparse.Namespace) -> bytes | None:
    """The key of the ``key_file`` setting (``--key-file``, $ESTOP_KEY_FILE or the
    configuration's ``key_file``; none: no key, the plain forms). A key file that cannot be
    used is a file error (exit 4) naming where its path came from."""
    path: str | None = getattr(args, "key_file", None)
    if path is None:
        return None
    try:
        return load_key_file(path)
    except KeyFileError as exc:
        raise FileFailure(f"{source_of(args, 'key_file')}: {exc}") from None
