"""can-utils log lines (``candump -L`` / ``canplayer`` format), classic CAN data frames.

``(1700000000.123456) estop 050#016400010000009C``: timestamp in seconds with microseconds,
interface name, then ``ID#DATA`` with a 3-digit (11-bit) or 8-digit (29-bit) hex ID and
0..8 data bytes in hex. Timestamps are kept as integer microseconds so lines round-trip exactly.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TextIO

__all__ = ["CanLogError", "CanLogRecord", "format_line", "parse_line", "read_log", "write_record"]

_LINE = re.compile(
    r"^\((?P<sec>\d+)(?:\.(?P<frac>\d{1,9}))?\)\s+(?P<iface>\S+)\s+"
    r"(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#(?P<data>(?:[0-9A-Fa-f]{2})*)$"
)
_SFF_MAX = 0x7FF
_EFF_MAX = 0x1FFFFFFF


class CanLogError(ValueError):
    """A line that is not a classic CAN data frame in can-utils log format."""


@dataclass(frozen=True, slots=True)
class CanLogRecord:
    timestamp_us: int
    interface: str
    can_id: int
    data: bytes
    extended: bool = False

    @property
    def timestamp(self) -> float:
        """Seconds as a float (use ``timestamp_us`` for exact arithmetic)."""
        return self.timestamp_us / 1_000_000

    @classmethod
    def at(cls, timestamp: float, interface: str, can_id: int, data: bytes,
           extended: bool = False) -> CanLogRecord:
        """Build a record from a float timestamp in seconds (rounded to the microsecond)."""
        return cls(round(timestamp * 1_000_000), interface, can_id, bytes(data), extended)


def parse_line(line: str) -> CanLogRecord:
    """Parse one log line; raise :class:`CanLogError` with a one-line reason."""
    text = line.strip()
    m = _LINE.match(text)
    if m is None:
        if "##" in text:
            raise CanLogError(f"CAN FD frames are not supported: {text!r}")
        if re.search(r"#R", text):
            raise CanLogError(f"remote frames are not supported: {text!r}")
        raise CanLogError(f"not a can-utils log line: {text!r}")
    frac = (m["frac"] or "").ljust(6, "0")
    if len(frac) > 6:
        frac = frac[:6]  # sub-microsecond digits are dropped
    timestamp_us = int(m["sec"]) * 1_000_000 + int(frac)
    ident = m["id"]
    can_id = int(ident, 16)
    extended = len(ident) == 8
    if extended and can_id > _EFF_MAX:
        raise CanLogError(f"29-bit ID {ident} out of range")
    if not extended and can_id > _SFF_MAX:
        raise CanLogError(f"11-bit ID {ident} out of range")
    data = bytes.fromhex(m["data"])
    if len(data) > 8:
        raise CanLogError(f"{len(data)} data bytes, classic CAN carries at most 8")
    return CanLogRecord(timestamp_us, m["iface"], can_id, data, extended)


def format_line(record: CanLogRecord) -> str:
    """One log line, without the newline."""
    sec, usec = divmod(record.timestamp_us, 1_000_000)
    if record.timestamp_us < 0:
        raise ValueError("negative timestamp")
    if not record.interface or any(c.isspace() for c in record.interface):
        raise ValueError(f"interface name {record.interface!r} must be non-empty, no spaces")
    if len(record.data) > 8:
        raise ValueError(f"{len(record.data)} data bytes, classic CAN carries at most 8")
    if record.extended:
        if not 0 <= record.can_id <= _EFF_MAX:
            raise ValueError(f"29-bit ID {record.can_id:#x} out of range")
        ident = f"{record.can_id:08X}"
    else:
        if not 0 <= record.can_id <= _SFF_MAX:
            raise ValueError(f"11-bit ID {record.can_id:#x} out of range")
        ident = f"{record.can_id:03X}"
    return f"({sec}.{usec:06d}) {record.interface} {ident}#{record.data.hex().upper()}"


def read_log(lines: Iterable[str], *, skip_bad: bool = False) -> Iterator[CanLogRecord]:
    """Records from an iterable of lines (a file, ``sys.stdin``). Blank lines are skipped;
    a bad line raises :class:`CanLogError` (with its line number) unless ``skip_bad``."""
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            yield parse_line(line)
        except CanLogError as exc:
            if not skip_bad:
                raise CanLogError(f"line {number}: {exc}") from None


def write_record(stream: TextIO, record: CanLogRecord, *, flush: bool = True) -> None:
    """Write one line (and flush by default, as estopd does)."""
    stream.write(format_line(record) + "\n")
    if flush:
        stream.flush()
