"""State changes on the bus and in the daemon's log, and what a row expects of them. Pure (no
sockets, no threads): the version 3 rows and the whole-run log check judge with these.

On the bus a change is a good ESTOP_BRAKE frame whose (state, reason) differs from the good
frame before it; in the log it is a ``state`` line (``from``, ``to``, ``reason``, ``src``,
``cause``; firmware/estopd/README.md lists the causes).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from estop.protocol.can import BRAKE_ID, BrakeFrame, reason_name, state_name
from estop.unit import events
from hilemu import Frame

# The cause each kind of change may carry (firmware/estopd/README.md, "Events"): into STOPPED
# by its reason, the others by where they lead from and to.
STOP_CAUSES: dict[str, frozenset[str]] = {
    "tcp_stop": frozenset({"tcp_stop", "stop_datagram"}),
    "lift": frozenset({"lift", "lift_datagram"}),
    "udp_timeout": frozenset({"udp_timeout"}),
    "fault": frozenset({"fault", "clock_backwards"}),
}
MOVE_CAUSES: dict[tuple[str, str], str] = {
    ("ARMED", "SLOWING"): "udp_silence",
    ("SLOWING", "ARMED"): "link_back",
    ("STOPPED", "ARMED"): "release",
    ("STOPPED", "SLOWING"): "release",  # a link silent for S, not T, when released
}


@dataclass(frozen=True, slots=True)
class StateChange:
    """A change of (state, reason) on the bus, at the frame that showed it first."""

    ts: float
    state: int
    reason: int
    data: bytes

    def text(self) -> str:
        return f"{state_name(self.state)}/{reason_name(self.reason)}"


def state_changes(frames: Iterable[Frame], t0: float,
                  t1: float = math.inf) -> list[StateChange]:
    """The changes among the good ESTOP_BRAKE frames stamped in ``(t0, t1]`` (``frames`` in
    time order), each against the good frame before it, which may be at or before ``t0``
    (with none before, the first one in the window is a change)."""
    out: list[StateChange] = []
    prev: tuple[int, int] | None = None
    for f in frames:
        if f.ts > t1:
            break
        if f.can_id != BRAKE_ID or BrakeFrame.check(f.data):
            continue
        b = BrakeFrame.parse(f.data)
        now = (b.state, b.reason)
        if f.ts > t0 and now != prev:
            out.append(StateChange(f.ts, b.state, b.reason, f.data))
        prev = now
    return out


def _names(pairs: Iterable[tuple[int, int]]) -> str:
    return " -> ".join(f"{state_name(s)}/{reason_name(r)}" for s, r in pairs) or "none"


def sequence_problem(changes: Sequence[StateChange], want: Sequence[tuple[int, int]],
                     what: str) -> str | None:
    """None when the changes are exactly ``want`` ((state, reason) each), in order."""
    got = [(c.state, c.reason) for c in changes]
    if got == list(want):
        return None
    return f"{what}: the bus showed {_names(got)}, want {_names(want)}"


def frame_problem(data: bytes, prefix: bytes, what: str) -> str | None:
    """None when ``data`` is a good ESTOP_BRAKE frame that starts with ``prefix`` (bytes
    0..3: brake_request, brake_level, state, reason)."""
    bad = BrakeFrame.check(data)
    if bad:
        return f"{what}: {data.hex(' ')} fails the frame checks ({bad[0]})"
    if not data.startswith(prefix):
        return f"{what}: {data.hex(' ')}, want {prefix.hex(' ')} ..."
    return None


# --------------------------------------------------------------------------- log lines

@dataclass(frozen=True, slots=True)
class LogChange:
    """One ``state`` line of the daemon's log."""

    frm: str
    to: str
    reason: str
    cause: str | None
    src: str | None

    def text(self) -> str:
        return f"{self.frm}->{self.to} {self.reason} cause={self.cause}"


def log_changes(records: Iterable[dict]) -> list[LogChange]:
    """The ``state`` lines among the log records, in order (read by estop.unit.events, as
    every reader of estopd's log reads them)."""
    changes = (events.state_change(events.Event.of(r)) for r in records)
    return [LogChange(c.frm, c.to, c.reason, c.cause, c.src) for c in changes if c is not None]


def log_problem(changes: Sequence[LogChange], want: Sequence[tuple[str, str, str, str]],
                what: str) -> str | None:
    """None when the state lines are exactly ``want`` ((from, to, reason, cause) each)."""
    got = [(c.frm, c.to, c.reason, c.cause) for c in changes]
    if got == list(want):
        return None
    show = "; ".join(c.text() for c in changes) or "none"
    return (f"{what}: log {show}, want "
            + "; ".join(f"{f}->{t} {r} cause={c}" for f, t, r, c in want))


def cause_problem(change: LogChange) -> str | None:
    """None when the line's cause is one the README allows for its kind of change."""
    if change.cause is None:
        return f"{change.frm}->{change.to}: no cause"
    if change.to == "STOPPED":
        allowed = STOP_CAUSES.get(change.reason, frozenset({change.reason}))
    else:
        want = MOVE_CAUSES.get((change.frm, change.to))
        allowed = frozenset() if want is None else frozenset({want})
    if change.cause in allowed:
        return None
    return f"{change.text()}: cause not one of {sorted(allowed) or 'none (no such change)'}"


def bus_transitions(frames: Iterable[Frame]) -> Counter[str]:
    """``FROM->TO`` state changes among the good ESTOP_BRAKE frames (one daemon's), counted."""
    out: Counter[str] = Counter()
    prev: int | None = None
    for f in frames:
        if f.can_id != BRAKE_ID or BrakeFrame.check(f.data):
            continue
        st = f.data[2]
        if prev is not None and st != prev:
            out[f"{state_name(prev)}->{state_name(st)}"] += 1
        prev = st
    return out
