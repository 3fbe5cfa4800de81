"""The CAN bus a command opens: the command line over python-can's own configuration."""

from __future__ import annotations

import argparse

from estop.errors import UsageError
from estop.extras import require_extra

__all__ = ["can_bus_config"]


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
