"""Where the ``estop`` commands take their common settings from, and the per-installation remote
id.

A team sets the unit's address, ports, key file, remote id, stop ID and send rate once: in the
configuration file or in environment variables. For each setting the first source that has it
wins: the command line, then the environment (``ESTOP_HOST`` ...), then the configuration file,
then the built-in default. A bad value is a one-line :class:`SettingError` naming its source.

The configuration file is TOML, ``$ESTOP_CONFIG``, else ``$XDG_CONFIG_HOME/estop/config.toml``,
else ``~/.config/estop/config.toml``; every key is optional, unknown keys are refused::

    host = "192.168.8.20"
    udp_port = 5700
    tcp_port = 5701
    key_file = "~/.config/estop/key"   # relative paths: from this file's directory
    remote_id = 2891327                # estop writes one on first use with a key
    stop_id = 0xE570E570
    rate_hz = 50

CAN settings are python-can's own (its configuration file and ``CAN_INTERFACE`` ...): see
:func:`estop.commands.canbus.can_bus_config`.
"""

from __future__ import annotations

import argparse
import fcntl
import os
import secrets
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "CONFIG_ENV",
    "INSTALLATION_ID_RANGE",
    "ConfigFile",
    "Setting",
    "SettingError",
    "config_path",
    "installation_remote_id",
]

CONFIG_ENV = "ESTOP_CONFIG"
INSTALLATION_ID_RANGE = (0x100, 0xFFFFFFFF)  # made ids stay clear of the small hand-picked ones


class SettingError(ValueError):
    """A setting that cannot be used; ``str()`` is one line naming where the value came from."""


@dataclass(frozen=True, slots=True)
class Setting:
    """One common setting: its configuration key (also the ``argparse`` dest), its option,
    its environment variable, how a text value is read, and its default (None: none)."""

    key: str
    flag: str
    env: str
    parse: Callable[[str], object]
    default: object = None


def config_path(environ: Mapping[str, str] | None = None) -> Path:
    """The configuration file's path (it need not exist)."""
    env = os.environ if environ is None else environ
    given = env.get(CONFIG_ENV)
    if given:
        return Path(given).expanduser()
    base = env.get("XDG_CONFIG_HOME") or ""
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".config"
    return root / "estop" / "config.toml"


class ConfigFile:
    """The configuration file, read once on first use (a missing file is an empty one)."""

    def __init__(self, path: Path, known: Mapping[str, Setting]) -> None:
        self.path = path
        self._known = known
        self._values: dict[str, object] | None = None

    def values(self) -> dict[str, object]:
        if self._values is None:
            self._values = self._load()
        return self._values

    def _load(self) -> dict[str, object]:
        try:
            with open(self.path, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            return {}
        except OSError as exc:
            raise SettingError(f"{self.path}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise SettingError(f"{self.path}: not valid TOML: {exc}") from None
        for name in data:
            if name not in self._known:
                raise SettingError(f"{self.path}: unknown setting {name!r} (known: "
                                   f"{', '.join(sorted(self._known))})")
        return data

    def lookup(self, setting: Setting) -> tuple[object, str] | None:
        """(value, source) of ``setting`` in the file, read by its parser; None when absent."""
        if setting.key not in self.values():
            return None
        raw = self.values()[setting.key]
        source = f"{self.path}: {setting.key}"
        if isinstance(raw, bool) or not isinstance(raw, str | int | float):
            raise SettingError(f"{source}: expected a number or a string, got {raw!r}")
        text = str(raw)
        if setting.key == "key_file":
            text = str(self.path.parent / Path(text).expanduser())
        return parse_from(setting, text, source), source


def parse_from(setting: Setting, text: str, source: str) -> object:
    """``setting.parse(text)``, its error as a :class:`SettingError` naming ``source``."""
    try:
        return setting.parse(text)
    except (argparse.ArgumentTypeError, ValueError) as exc:
        raise SettingError(f"{source}: {exc}") from None


def installation_remote_id(config: ConfigFile) -> int:
    """This installation's remote id: the configuration's ``remote_id``, else a new random one
    written there (the file and its directory made if missing; two first uses at once agree on
    one, under a lock on the directory). Random in 32 bits, two installations that share a key
    practically never pick the same id (spec section 5: the unit keeps one counter per remote
    id, so two remotes with one id refuse each other's counters as replays). Raises
    :class:`SettingError` when the file cannot be written."""
    lo, hi = INSTALLATION_ID_RANGE
    path = config.path
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                old = path.read_text(encoding="utf-8")
            except FileNotFoundError:
                old = ""
            made = _remote_id_in(old)
            if made is not None:  # another first use made it while we waited
                rid = made
            else:
                rid = lo + secrets.randbelow(hi - lo + 1)
                if old and not old.endswith("\n"):
                    old += "\n"
                tmp = path.with_name(path.name + ".tmp")
                tmp.write_text(f"{old}# made by estop on first use with a key: this "
                               f"installation's own id among the remotes sharing the key\n"
                               f"remote_id = {rid}\n", encoding="utf-8")
                os.replace(tmp, path)
        finally:
            os.close(lock)
    except OSError as exc:
        raise SettingError(f"{path}: cannot keep this installation's remote id "
                           f"({exc.strerror or exc}); give --remote-id N or set "
                           f"ESTOP_REMOTE_ID") from None
    config._values = None  # read again, with the new id
    return rid


def _remote_id_in(text: str) -> int | None:
    try:
        value = tomllib.loads(text).get("remote_id")
    except tomllib.TOMLDecodeError:
        return None
    return value if isinstance(value, int) and not isinstance(value, bool) else None
