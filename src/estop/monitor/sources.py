"""What ``estop monitor`` reads besides a live bus, and the DBC decoding of what it reads.

- :func:`read_records`: a recorded log as ``(t, can_id, data, extended)``; the formats
  python-can knows by their suffix (.asc .blf .csv .db .mf4 .trc, also gzipped) are read by
  ``can.LogReader``, everything else as can-utils lines (``candump -L``, estop's own can-log,
  standard input) by :mod:`estop.protocol.canlog`.
- :class:`DbcDecoder`: decodes frames with cantools from a DBC (the unit's own by default,
  estop/dbc/estop.dbc) and says where the DBC and estop's codecs read a frame differently.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from estop.errors import FileFailure
from estop.extras import require_extra
from estop.protocol import can as estop_can
from estop.protocol.canlog import CanLogError, read_log

__all__ = ["PYTHON_CAN_SUFFIXES", "DbcDecoder", "Record", "read_records"]

Record = tuple[float, int, bytes, bool]  # timestamp (s), CAN ID, data, extended ID
# the formats python-can reads and can-utils does not (python-can's .log is can-utils' own)
PYTHON_CAN_SUFFIXES = (".asc", ".blf", ".csv", ".db", ".mf4", ".trc")


def read_records(name: str, lines: Iterable[str] | None = None) -> Iterator[Record]:
    """The frames of the log ``name`` (``lines``: an open text stream of can-utils lines, e.g.
    stdin). Raises :class:`FileFailure` (one line naming the file) when it cannot be read."""
    suffixes = [x.lower() for x in Path(name).suffixes[-2:]]
    if lines is None and any(x in PYTHON_CAN_SUFFIXES for x in suffixes):  # a.asc, a.asc.gz
        yield from _python_can(name)
    else:
        yield from _canutils(name, lines)


def _canutils(name: str, lines: Iterable[str] | None) -> Iterator[Record]:
    try:
        if lines is None:
            with open(name, encoding="utf-8", errors="replace") as stream:
                for rec in read_log(stream):
                    yield rec.timestamp, rec.can_id, rec.data, rec.extended
        else:
            for rec in read_log(lines):
                yield rec.timestamp, rec.can_id, rec.data, rec.extended
    except CanLogError as exc:
        raise FileFailure(f"--log {name}: {exc}") from None
    except OSError as exc:
        raise FileFailure(f"--log {name}: {exc.strerror or exc}") from None


def _python_can(name: str) -> Iterator[Record]:
    require_extra("bus", "can")
    import can

    # python-can's readers raise many kinds of error on a malformed file (BLFParseError,
    # ValueError, struct.error, ...): whatever they raise, the file is what cannot be read
    try:
        reader = can.LogReader(name)
        with reader:
            for msg in reader:
                if msg.is_error_frame or msg.is_remote_frame:
                    continue
                yield float(msg.timestamp), msg.arbitration_id, bytes(msg.data), \
                    bool(msg.is_extended_id)
    except OSError as exc:
        raise FileFailure(f"--log {name}: {exc.strerror or exc}") from None
    except Exception as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise FileFailure(f"--log {name}: not a readable {Path(name).suffix} log: "
                          f"{why}") from None


def _estop_fields(can_id: int, data: bytes) -> dict[str, int] | None:
    """What estop's codecs read, under the DBC's signal names (None: not an estop frame or
    not whole)."""
    if len(data) != estop_can.DLC:
        return None
    try:
        if can_id == estop_can.BRAKE_ID:
            b = estop_can.BrakeFrame.parse(data)
            return {"brake_request": b.brake_request, "brake_level": b.brake_level,
                    "state": b.state, "reason": b.reason, "flags": b.flags,
                    "alive_counter": b.counter}
        if can_id == estop_can.STATUS_ID:
            s = estop_can.StatusFrame.parse(data)
            return {"valid_packets": s.valid_packets, "invalid_packets": s.invalid_packets,
                    "auth_failures": s.auth_failures, "stops": s.stops,
                    "slowdowns": s.slowdowns, "link_age": s.link_age_ms,
                    "alive_counter": s.counter}
    except (ValueError, TypeError):
        return None
    return None


class DbcDecoder:
    """cantools over one DBC: :meth:`line` is `` dbc: NAME sig=value ...`` for a frame the DBC
    knows, with `` MISMATCH(...)`` where estop's codecs read a field otherwise."""

    def __init__(self, path: str | None = None) -> None:
        require_extra("bus", "cantools")
        import cantools

        self.path = path or str(estop_can.dbc_path())
        try:
            self.db: Any = cantools.database.load_file(self.path, strict=True)
        except OSError as exc:
            raise FileFailure(f"--dbc {self.path}: {exc.strerror or exc}") from None
        except Exception as exc:  # cantools raises its own parse errors
            raise FileFailure(f"--dbc {self.path}: {str(exc).splitlines()[0]}") from None
        self.mismatches = 0

    def line(self, can_id: int, data: bytes) -> str | None:
        try:
            msg = self.db.get_message_by_frame_id(can_id)
        except KeyError:
            return None
        try:
            raw = msg.decode(data, decode_choices=False, scaling=False)
            shown = msg.decode(data, decode_choices=True)
        except Exception as exc:  # a frame the DBC cannot read (length, ranges)
            return f"  dbc: {msg.name} cannot decode: {str(exc).splitlines()[0]}"
        text = " ".join(f"{k}={v}" for k, v in shown.items())
        ours = _estop_fields(can_id, data)
        if ours is not None:
            differ = [k for k, v in ours.items() if k in raw and int(raw[k]) != v]
            if differ:
                self.mismatches += 1
                text += f"  MISMATCH({','.join(differ)})"
        return f"  dbc: {msg.name} {text}"
