"""What ``estop dashboard`` shows, kept up to date from its inputs (no I/O here): the unit's
state from its ESTOP_BRAKE frames, the frames' health, the ESTOP_STATUS fields as the DBC
names them, the link from estopd's ``link_histogram`` events, a timeline of state changes and
the stops by reason.

The frames go through the same checks a brake controller makes (:mod:`estop.model.brakecheck`):
only a good ESTOP_BRAKE frame (right length, CRC, new alive counter, consistent fields)
counts. Silence is a failure (PROTOCOL.md 7): no good ESTOP_BRAKE frame for 50 ms, or none
at all yet, is ``NO SIGNAL``, whatever the last frame said. Frame times are the frames' own
stamps (the can-log's, python-can's); the silence is measured on the wall clock
(``time.time()``) from the last good frame's stamp carried over by the smallest delay (arrival
minus stamp) of the last 100 good frames. So a log read from its start does not look silent
while it is caught up, a pipe from another machine whose clock is off is judged by its own
period, and a frame that came late (a slow reader) counts as late.

The link figures come from the same code as ``estop link`` (:mod:`estop.dashboard.linkbox`).

Bad input is counted, never fatal: a can-log line that does not parse, a log line that is not
JSON, a frame that fails a check (by kind), a malformed ``link_histogram``.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from estop.dashboard.linkbox import LinkBox
from estop.link.gaps import LinkInputError
from estop.model.brakecheck import EVENT_KINDS, BrakeFrameChecker, CheckEvent, grade_text
from estop.protocol.can import (
    BRAKE_ID,
    STATUS_ID,
    BrakeFrame,
    State,
    StatusFrame,
    dbc_text,
    flag_names,
    reason_name,
    state_name,
)
from estop.unit import events

__all__ = ["NO_SIGNAL", "SIGNAL_TIMEOUT", "DashboardModel", "StatusFields", "reason_words"]

SIGNAL_TIMEOUT = 0.050  # s without a good ESTOP_BRAKE: a brake controller brakes (section 7)
NO_SIGNAL = "NO SIGNAL"
TIMELINE_LEN = 12  # state changes kept for the page
PERIOD_WINDOW = 100  # good ESTOP_BRAKE frames the period is measured over
CAUSE_MATCH_S = 2.0  # a log `state` event explains a frame change at most this far apart
_STOPPED = state_name(State.STOPPED)
_MOVING = {state_name(State.ARMED), state_name(State.SLOWING)}


def reason_words(reason: int | str) -> str:
    """``udp_timeout`` -> ``udp timeout`` (the page shows words)."""
    name = reason_name(reason) if isinstance(reason, int) else reason
    return "" if name == "none" else name.replace("_", " ")


class StatusFields:
    """ESTOP_STATUS decoded by the DBC (cantools): every signal but the E2E ones (alive
    counter, CRC, reserved bits), with its unit and comment. A count per window (no unit)
    is also summed since the page started; a value with a unit (link_age) is shown as is."""

    _HIDDEN = {"alive_counter", "counter_reserved", "crc"}

    def __init__(self) -> None:
        import cantools  # the DBC read by cantools, as any CAN tool reads it

        db = cantools.database.load_string(dbc_text(), database_format="dbc")
        assert isinstance(db, cantools.database.can.Database)
        self._message = db.get_message_by_frame_id(STATUS_ID)  # its layout, whatever the ID
        self.signals = [s for s in self._message.signals if s.name not in self._HIDDEN]
        self.last: dict[str, Any] = {}
        self.totals: Counter[str] = Counter()

    def take(self, data: bytes) -> None:
        values = self._message.decode(data, decode_choices=True, scaling=True)
        if not isinstance(values, Mapping):  # a multiplexed message would be; this is not
            return
        self.last = {s.name: values[s.name] for s in self.signals}
        for s in self.signals:
            v = values[s.name]
            if not s.unit and isinstance(v, (int, float)):
                self.totals[s.name] += int(v)

    def rows(self) -> list[dict[str, Any]]:
        rows = []
        for s in self.signals:
            v = self.last.get(s.name)
            rows.append({"name": s.name, "value": None if v is None else str(v),
                         "unit": s.unit or "",
                         "total": None if s.unit else self.totals[s.name],
                         "comment": s.comment or ""})
        return rows


@dataclass
class Change:
    """One entry of the timeline: the state shown from ``t`` on, and why."""

    t: float  # the frame's time (or when the silence began, or the log line arrived)
    state: str
    reason: str  # words, empty unless STOPPED
    source: str  # "frames", "silence" or "log"
    cause: str = ""  # estopd's cause (log `state` event), e.g. udp_silence, lift, release
    src: str = ""  # whose input (an address, or "-" for the clock)

    def as_dict(self) -> dict[str, Any]:
        return {"t": self.t, "state": self.state, "reason": self.reason, "source": self.source,
                "cause": self.cause, "src": self.src}


@dataclass
class _LogState:
    """A `state` event of estopd's log not yet matched to a frame change."""

    to: str
    reason: str
    cause: str
    src: str
    arrived: float


@dataclass
class Inputs:
    """Lines and frames taken from each input, and the bad ones (with the latest reason)."""

    can_lines: int = 0
    can_bad: int = 0
    log_lines: int = 0
    log_bad: int = 0
    link_bad: int = 0
    last_bad: str = ""
    notes: list[str] = field(default_factory=list)  # one-line input problems (bus errors...)


class DashboardModel:
    """Feed it frames (:meth:`frame`), can-log and log lines (:meth:`can_line`,
    :meth:`log_line`); read :meth:`snapshot` for the page. :attr:`version` grows with every
    change, so a server sends only what is new. ``rate_hz`` is the remote's send rate, for
    the link fit (as ``estop link --rate-hz``)."""

    def __init__(self, *, brake_id: int = BRAKE_ID, status_id: int = STATUS_ID,
                 rate_hz: float = 50.0, signal_timeout: float = SIGNAL_TIMEOUT) -> None:
        self.checker = BrakeFrameChecker(brake_id=brake_id, status_id=status_id,
                                         timeout=signal_timeout)
        self.signal_timeout = signal_timeout
        self.rate_hz = rate_hz
        self.status = StatusFields()
        self.inputs = Inputs()
        self.version = 0
        self.changes = 0  # timeline entries added: a change the page shows at once
        self.timeline: deque[Change] = deque(maxlen=TIMELINE_LEN)
        self.stops: Counter[str] = Counter()
        self.unit: dict[str, Any] = {}  # S, T, slow level... from the daemon's `start` event
        self.log_events: Counter[str] = Counter()
        self.link = LinkBox(rate_hz)
        self._times: deque[float] = deque(maxlen=PERIOD_WINDOW)
        self._delays: deque[float] = deque(maxlen=PERIOD_WINDOW)  # arrival - stamp
        self._shown: tuple[str, str] | None = None  # (state, reason) of the last timeline entry
        self._moving_state: str | None = None  # the last state the frames said, for stops
        self._pending: deque[_LogState] = deque(maxlen=8)
        self._last_event: CheckEvent | None = None

    # ------------------------------------------------------------------------- inputs

    def _changed(self) -> None:
        self.version += 1

    def note(self, text: str) -> None:
        """An input problem in one line (a bus that fails, a file that cannot be read)."""
        self.inputs.notes = [*self.inputs.notes[-4:], text]
        self._changed()

    def can_line(self, line: str, arrived: float) -> None:
        """One can-utils log line; a bad one is counted."""
        from estop.protocol.canlog import CanLogError, parse_line

        if not line.strip():
            return
        self.inputs.can_lines += 1
        try:
            rec = parse_line(line)
        except CanLogError as exc:
            self.inputs.can_bad += 1
            self.inputs.last_bad = f"can-log: {exc}"[:200]
            self._changed()
            return
        if not rec.extended:
            self.frame(rec.timestamp, rec.can_id, rec.data, arrived)

    def frame(self, t: float, can_id: int, data: bytes, arrived: float) -> None:
        """One classic CAN frame stamped ``t``, here at ``arrived`` (wall-clock seconds)."""
        verdict = self.checker.feed(t, can_id, data)
        if verdict is None:
            return
        self._changed()
        if verdict.events:
            self._last_event = verdict.events[-1]
        if not verdict.accepted:
            return
        frame = verdict.frame
        if isinstance(frame, StatusFrame):
            self.status.take(data)
            return
        assert isinstance(frame, BrakeFrame)
        if self._times and any(ev.kind == "gap" for ev in verdict.events) \
                and (self._shown is None or self._shown[0] != NO_SIGNAL):
            # a silence nobody saw live (a log read from its start, a stalled reader): the
            # timeline still shows it, dated when it began
            prev = self._times[-1]
            self._add(Change(prev + self.signal_timeout, NO_SIGNAL, "", "silence",
                             f"gap of {(t - prev) * 1000:.0f} ms between good ESTOP_BRAKE "
                             "frames"))
        elif self._times and self._shown is not None and self._shown[0] == NO_SIGNAL \
                and self.timeline and self.timeline[-1].source == "silence":
            # the frames show no gap: what was silent was the way to this page
            self.timeline[-1].cause = (f"no good ESTOP_BRAKE here for "
                                       f"{self.signal_timeout * 1000:g} ms; the frames show "
                                       f"no gap (the feed was late)")
        self._times.append(t)
        self._delays.append(arrived - t)
        state = state_name(frame.state)
        reason = reason_words(frame.reason) if state == _STOPPED else ""
        if self._shown != (state, reason):
            self._add(Change(t, state, reason, "frames"))
        if state == _STOPPED and self._moving_state in _MOVING:
            self.stops[reason or "unknown"] += 1
        self._moving_state = state

    def _add(self, change: Change) -> None:
        for i, pending in enumerate(self._pending):
            if pending.to == change.state and pending.reason == change.reason:
                change.cause, change.src = pending.cause, pending.src
                del self._pending[i]
                break
        self.timeline.append(change)
        self._shown = (change.state, change.reason)
        self.changes += 1

    def tick(self, now: float) -> None:
        """The clock moves on: a silence of 50 ms becomes a NO SIGNAL entry (at the moment
        it began)."""
        if self._shown is not None and self._shown[0] == NO_SIGNAL:
            return
        since = self.checker.last_brake_time
        if since is None or self.signal(now):
            return
        self._add(Change(since + self.signal_timeout, NO_SIGNAL, "", "silence",
                         f"no good ESTOP_BRAKE for {self.signal_timeout * 1000:g} ms"))
        self._changed()

    def log_line(self, line: str, arrived: float) -> None:
        """One line of estopd's log (either form, a journal line too; :mod:`estop.unit.events`);
        a line that holds no event is counted."""
        text = line.strip()
        if not text:
            return
        self.inputs.log_lines += 1
        ev = events.parse(text)
        if ev is None:
            self.inputs.log_bad += 1
            self.inputs.last_bad = f"log: not an estopd event: {text[:120]!r}"
            self._changed()
            return
        self._changed()
        self.log_events[ev.kind] += 1
        if ev.kind == "start":
            self.unit = {k: ev.get(k) for k in ("slow_ms", "timeout_ms", "slow_level",
                                                "warn_ms", "auth", "udp", "tcp", "pid")}
        change = events.state_change(ev)
        if change is not None:
            self._log_state(change, arrived)
        if not ev.json:
            return  # the link box reads the JSON form's link_histogram events
        try:
            self.link.feed(dict(ev.fields), self.unit)
        except LinkInputError as exc:
            self.inputs.link_bad += 1
            self.inputs.last_bad = f"log: {exc}"[:200]

    def _log_state(self, change: events.StateChange, arrived: float) -> None:
        to = change.to
        reason = reason_words(change.reason) if to == _STOPPED else ""
        cause, src = change.cause or "", change.src
        # the frame change usually came first: explain the latest unexplained one
        for c in reversed(self.timeline):
            if c.source == "frames" and not c.cause \
                    and (c.state, c.reason) == (to, reason) \
                    and abs(arrived - c.t) <= CAUSE_MATCH_S:
                c.cause, c.src = cause, src
                return
        if self.checker.last_brake_time is None:
            # no frames at all (a log alone): the log is the timeline
            self._add(Change(arrived, to, reason, "log", cause, src))
            return
        self._pending.append(_LogState(to, reason, cause, src, arrived))

    # ------------------------------------------------------------------------- reading

    def _last_good(self) -> float | None:
        """The last good ESTOP_BRAKE's stamp on the wall clock (see the module's docstring)."""
        last = self.checker.last_brake_time
        return None if last is None or not self._delays else last + min(self._delays)

    def signal(self, now: float) -> bool:
        """A good ESTOP_BRAKE frame came within the last 50 ms."""
        last = self._last_good()
        return last is not None and now - last < self.signal_timeout

    def deadline(self, now: float) -> float | None:
        """When the state turns NO SIGNAL unless a good frame comes first (None: already)."""
        last = self._last_good()
        if last is None or now - last >= self.signal_timeout:
            return None
        return last + self.signal_timeout

    def snapshot(self, now: float) -> dict[str, Any]:
        """Everything the page shows, as JSON-able values."""
        self.tick(now)
        c = self.checker
        frame = c.last_brake
        last_t = c.last_brake_time
        head: dict[str, Any]
        if frame is None or not self.signal(now):
            head = {"state": NO_SIGNAL, "reason": "", "brake": "EMERGENCY (controller's own)",
                    "degraded": False,
                    "t": None if last_t is None else last_t + self.signal_timeout,
                    "why": ("no good ESTOP_BRAKE frame yet" if last_t is None else
                            f"no good ESTOP_BRAKE for "
                            f"{(now - (self._last_good() or now)) * 1000:.0f} ms")}
        else:
            state = state_name(frame.state)
            since = self.timeline[-1].t if self.timeline else last_t
            head = {"state": state,
                    "reason": reason_words(frame.reason) if state == _STOPPED else "",
                    "brake": grade_text(frame.deceleration_share),
                    "degraded": "link_degraded" in flag_names(frame.flags),
                    "t": since, "why": ""}
        times = self._times
        period = ((times[-1] - times[0]) / (len(times) - 1) * 1000 if len(times) > 1
                  else None)
        worst = (max(b - a for a, b in zip(times, list(times)[1:], strict=False)) * 1000
                 if len(times) > 1 else None)
        ev = self._last_event
        return {
            "now": now,
            **head,
            "frame_t": last_t,
            "health": {"frames": c.frames, "accepted": c.accepted,
                       "period_ms": _round(period), "worst_gap_ms": _round(worst),
                       "errors": {k: c.counts[k] for k in EVENT_KINDS
                                  if k not in ("timeout", "no_brake_frame")},
                       "last_error": "" if ev is None else f"{ev.kind}: {ev.message}"},
            "status": self.status.rows(),
            "link": self.link.view,
            "unit": self.unit,
            "timeline": [ch.as_dict() for ch in reversed(self.timeline)],
            "stops": dict(self.stops),
            "inputs": {"can_lines": self.inputs.can_lines, "can_bad": self.inputs.can_bad,
                       "log_lines": self.inputs.log_lines, "log_bad": self.inputs.log_bad,
                       "link_bad": self.inputs.link_bad, "last_bad": self.inputs.last_bad,
                       "notes": list(self.inputs.notes),
                       "log_events": dict(self.log_events)},
        }


def _round(x: float | None, digits: int = 1) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, digits)
