"""The CAN bus the unit's frames are read from: python-can's bus opened from a configuration
(:func:`estop.commands.canbus.can_bus_config`: the command line over python-can's own), its
failure one line."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from estop.errors import ConnectionFailure

__all__ = ["open_bus"]


def open_bus(config: Mapping[str, Any]) -> Any:
    """``can.Bus(**config)``; a bus that cannot be opened is a :class:`ConnectionFailure`
    (exit 3) naming the interface and channel."""
    import can  # python-can, imported only when a bus is used

    try:
        return can.Bus(**config)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConnectionFailure(f"cannot open {config.get('interface')} bus "
                                f"{config.get('channel') or ''}: {why}") from None
