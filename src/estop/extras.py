"""Which optional parts (the extras of pyproject.toml) are installed: a command that needs one
says which, in one line, before it imports it."""

from __future__ import annotations

import importlib

from estop.errors import NotInstalled

__all__ = ["require_extra"]

_DISTRIBUTIONS = {"can": "python-can"}  # import name -> the name pip knows


def require_extra(extra: str, *modules: str) -> None:
    """Raise :class:`NotInstalled` naming ``estop[extra]`` unless every module imports."""
    missing = []
    for m in modules:
        try:
            importlib.import_module(m)  # the command imports it next anyway
        except ImportError:
            missing.append(_DISTRIBUTIONS.get(m, m))
    if missing:
        raise NotInstalled(f"this needs {', '.join(missing)}: pip install 'estop[{extra}]'")
