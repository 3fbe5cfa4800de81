"""estopd's event log read into typed events, in one place for every reader (the demo, the
dashboard, ``estop link``, the loopback runner of the demo and the benchmarks, the HIL
harness).

A line comes as estopd writes it, in either form of its README (firmware/estopd/README.md):
text, ``estopd <t_mono> <event> key=value ...`` (a ``state`` event's first word is
``FROM->TO``), or ``--log-json``, one JSON object with ``t_mono`` and ``event``; and as the
journal gives it: after a syslog-style ``name[pid]: `` prefix (plain ``journalctl``), or as the
``MESSAGE`` of ``journalctl -o json``. :func:`parse` reads one line into an :class:`Event`;
the typed views (:class:`StateChange`, :class:`Start`, :class:`OutputDropped`) are read from
events of their kind.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Event",
    "OutputDropped",
    "Start",
    "StateChange",
    "output_dropped",
    "parse",
    "start",
    "state_change",
    "state_changes",
]

# syslog-style prefix of plain journalctl output (short, short-iso, short-precise,
# short-monotonic ...): anything, then `identifier[pid]: ` right before the message
_PREFIX = re.compile(r"^.*?\S\[\d+\]: (?=[{\w])")
_TEXT = re.compile(r"^(?P<name>\S+)\s+(?P<t>\d+(?:\.\d+)?)\s+(?P<kind>[a-z_]+)\b(?P<rest>.*)$")
# a stand-in's line without the name and time (``start udp=... tcp=...``): fields required
_BARE = re.compile(r"^(?P<kind>[a-z_]+)(?P<rest>(?:\s+\S+=\S*)+)\s*$")


@dataclass(frozen=True, slots=True)
class Event:
    """One event of estopd's log: its kind (``state``, ``start``, ``link_histogram`` ...), the
    unit's clock when it was written (``t_mono``, seconds; None where the line has none) and
    its fields: every key of the JSON object (``event`` and ``t_mono`` included), or of the
    text line (``event``, ``t_mono`` and each ``key=value`` as text; the words without ``=``
    in ``args``). ``json`` says which form it came in."""

    kind: str
    t_mono: float | None
    fields: Mapping[str, Any]
    json: bool

    def get(self, key: str, default: Any = None) -> Any:
        return self.fields.get(key, default)

    def integer(self, key: str) -> int | None:
        """Field ``key`` as an integer (decimal or 0x-hex text, or a JSON integer); None when
        it is missing or not one."""
        v = self.fields.get(key)
        if isinstance(v, bool):
            return None
        if isinstance(v, int):
            return v
        if isinstance(v, str):
            try:
                return int(v, 0)
            except ValueError:
                return None
        return None

    @classmethod
    def of(cls, record: Mapping[str, Any]) -> Event | None:
        """The event of a JSON object already decoded (None: no ``event`` in it)."""
        kind = record.get("event")
        if not isinstance(kind, str):
            return None
        return cls(kind, _number(record.get("t_mono")), record, True)


def _number(v: object) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float | str):
        return None
    try:
        f = float(v)
    except ValueError:
        return None
    return f if math.isfinite(f) else None


def parse(line: str) -> Event | None:
    """The event on one line of estopd's log (either form, journal prefixes and journalctl's
    JSON entries unwrapped); None for a line that holds none."""
    text = line.strip()
    if not text:
        return None
    if not text.startswith("{"):
        ev = _parse_text(text)
        if ev is not None:
            return ev
        m = _PREFIX.match(text)
        if m is None:
            return None
        text = text[m.end():]
        if not text.startswith("{"):
            return _parse_text(text)
    try:
        record = json.loads(text)
    except ValueError:
        return None
    if not isinstance(record, dict):
        return None
    if "event" not in record and "MESSAGE" in record:  # journalctl -o json: the entry around it
        msg = record["MESSAGE"]
        if isinstance(msg, list) and all(isinstance(b, int) for b in msg):
            msg = bytes(b & 0xFF for b in msg).decode("utf-8", "replace")
        return parse(msg) if isinstance(msg, str) else None
    return Event.of(record)


def _parse_text(text: str) -> Event | None:
    m = _TEXT.match(text) or _BARE.match(text)
    if m is None:
        return None
    t_mono = m["t"] if "t" in m.groupdict() else None
    fields: dict[str, Any] = {"event": m["kind"], "t_mono": t_mono}
    args: list[str] = []
    for word in m["rest"].split():
        key, eq, value = word.partition("=")
        if eq:
            fields[key] = value
        else:
            args.append(word)
    fields["args"] = args
    return Event(m["kind"], None if t_mono is None else float(t_mono), fields, False)


# ------------------------------------------------------------------------------- state

@dataclass(frozen=True, slots=True)
class StateChange:
    """A ``state`` event: the time the core was given for the change (the unit's clock,
    seconds), the states, the reason's name, the peer (``-``: the clock or the host) and the
    cause (None where the log names none)."""

    t_mono: float
    frm: str
    to: str
    reason: str
    src: str
    cause: str | None

    def text(self) -> str:
        return f"{self.frm}->{self.to} reason={self.reason} cause={self.cause}"


def state_change(ev: Event | None) -> StateChange | None:
    """The state change an event tells (None for an event of another kind)."""
    if ev is None or ev.kind != "state":
        return None
    frm, to = ev.get("from"), ev.get("to")
    if frm is None or to is None:  # the text form: FROM->TO is the first word
        pair = next((a for a in ev.get("args", ()) if "->" in a), "")
        frm, _, to = pair.partition("->")
    cause = ev.get("cause")
    return StateChange(ev.t_mono if ev.t_mono is not None else math.nan, str(frm), str(to),
                       str(ev.get("reason", "none")), str(ev.get("src", "-")),
                       None if cause is None else str(cause))


def state_changes(lines: Iterable[str]) -> list[StateChange]:
    """Every state change on the log lines ``lines``, in order."""
    return [c for c in map(state_change, map(parse, lines)) if c is not None]


# ------------------------------------------------------------------------------- start

@dataclass(frozen=True, slots=True)
class Start:
    """A ``start`` event: the ports the daemon bound (the real ones where 0 asked for free
    ones), its session (0 where the line has none) and every field as written."""

    udp_port: int
    tcp_port: int
    session: int
    fields: Mapping[str, Any]


def _port(ev: Event, kind: str) -> int | None:
    for key in (kind, f"{kind}_port"):  # udp=127.0.0.1:5700, udp_port=5700 (a peer's)
        v = ev.get(key)
        if isinstance(v, int) and not isinstance(v, bool):
            return v
        if isinstance(v, str):
            tail = v.rpartition(":")[2]
            if tail.isdigit():
                return int(tail)
    return None


def start(ev: Event | None) -> Start | None:
    """The start event an event is (None for another kind, or one without both ports)."""
    if ev is None or ev.kind != "start":
        return None
    udp, tcp = _port(ev, "udp"), _port(ev, "tcp")
    if udp is None or tcp is None:
        return None
    session = ev.get("session")
    try:
        sid = int(session, 16) if isinstance(session, str) else 0
    except ValueError:
        sid = 0
    return Start(udp, tcp, sid, ev.fields)


# ----------------------------------------------------------------------- output dropped

@dataclass(frozen=True, slots=True)
class OutputDropped:
    """An ``output_dropped`` event: ``dropped`` lines of ``stream`` lost since the previous
    report, ``total`` since start; ``t_mono`` is the daemon's clock in seconds."""

    t_mono: float
    stream: str
    dropped: int
    total: int
    err: str


def output_dropped(ev: Event | None) -> OutputDropped | None:
    """The output_dropped report an event is (None for another kind, or a malformed one)."""
    if ev is None or ev.kind != "output_dropped" or ev.t_mono is None:
        return None
    dropped, total = ev.integer("dropped"), ev.integer("total")
    stream = ev.get("stream")
    if dropped is None or total is None or stream is None:
        return None
    return OutputDropped(ev.t_mono, str(stream), dropped, total, str(ev.get("err", "")))
