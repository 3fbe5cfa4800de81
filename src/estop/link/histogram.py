"""estopd's ``--log-json`` log as ``estop link`` reads it: the ``link_histogram`` events (the
gaps between valid control packets, binned), summed over the daemon's runs, and, from a
version 3 daemon, its own count of slow-downs and timeouts with the time it spent moving.

The log may come as estopd wrote it (or ``journalctl -u estopd -o cat``), as plain
``journalctl`` lines (``Nov 25 10:00:00 car estopd[812]: {...}``, any prefix ending in
``name[pid]: ``), or as ``journalctl -o json`` (the line is the entry's MESSAGE). Lines that
hold no estopd event are counted, and the report says how many and shows the first; only
journalctl's own ``-- ...`` marker lines and blank lines pass unremarked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from estop.link.gaps import U32_MAX, Histogram, LinkInputError, UnitRecord
from estop.unit import events

__all__ = ["UNIT_KEYS", "HistogramReader", "open_text", "read_histogram_log"]

def _event(line: str) -> dict[str, Any] | None:
    """The estopd event on one line of the log in its JSON form (:mod:`estop.unit.events`
    reads either form and unwraps the journal's), or None."""
    ev = events.parse(line)
    return dict(ev.fields) if ev is not None and ev.json else None


class _Skipped:
    """Lines that held no estopd event: how many, and the first."""

    def __init__(self) -> None:
        self.count = 0
        self.first = ""

    def add(self, no: int, line: str) -> None:
        if not line or line.startswith("-- "):  # journalctl's `-- Boot ... --` markers
            return
        self.count += 1
        if self.count == 1:
            self.first = f"line {no}: {line[:60]!r}"

    def note(self) -> str:
        if not self.count:
            return ""
        return (f"skipped {self.count} line(s) that hold no estopd --log-json event (first, "
                f"{self.first})")


# the keys a version 3 daemon adds to link_histogram (PROTOCOL.md 3): counted since its start
UNIT_KEYS = ("slowdowns", "timeouts", "slow_us", "timeout_us")


def open_text(path: str) -> Any:
    try:
        return open(path, encoding="utf-8", errors="strict")
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None


def _int_field(ev: dict[str, Any], key: str, where: str) -> int:
    v = ev.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise LinkInputError(f"{where}: link_histogram field {key!r} is not a count: {v!r}")
    return v


def _check_histogram(ev: dict[str, Any], where: str) -> None:
    e = ev.get("edges_us")
    c = ev.get("counts")
    if not (isinstance(e, list) and isinstance(c, list) and len(e) >= 2
            and len(c) == len(e)
            and all(isinstance(x, int) and not isinstance(x, bool) for x in e + c)
            and e[0] == 0 and all(b > a for a, b in zip(e, e[1:], strict=False))
            and all(x >= 0 for x in c)):
        raise LinkInputError(f"{where}: malformed link_histogram event (edges_us "
                             "and counts must be equal-length integer lists, "
                             "edges rising from 0)")
    for key in ("valid", "invalid", "silences", "warn_us"):
        _int_field(ev, key, where)
    for key in UNIT_KEYS:
        if key in ev:
            _int_field(ev, key, where)
    if "slow_us" in ev and "timeout_us" in ev \
            and not 0 < ev["slow_us"] <= ev["timeout_us"]:
        raise LinkInputError(f"{where}: link_histogram slow_us {ev['slow_us']} and timeout_us "
                             f"{ev['timeout_us']} break 0 < S <= T")


def _t_mono(ev: dict[str, Any]) -> float | None:
    t = ev.get("t_mono")
    if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t):
        return float(t)
    return None


@dataclass
class _Run:
    """One run of the daemon: its latest link_histogram event and the time it spent moving
    (ARMED or SLOWING; it boots STOPPED), from its ``state`` events. Only a run seen from its
    ``start`` event has all of them: without it, the time moving is unknown."""

    started: bool = False
    last: dict[str, Any] | None = None
    moving_s: float = 0.0
    moving_since: float | None = None  # t_mono of the change into a moving state
    last_t: float | None = None
    states: int = 0
    notes: list[str] = field(default_factory=list)

    def saw(self, t: float | None) -> None:
        if t is not None:
            self.last_t = t if self.last_t is None else max(self.last_t, t)

    def state(self, to: Any, t: float | None) -> None:
        self.states += 1
        self.stop_clock(t)
        # every state but STOPPED lets the car move (a name this reader does not know too)
        if to != "STOPPED" and t is not None:
            self.moving_since = t

    def stop_clock(self, t: float | None) -> None:
        if self.moving_since is not None and t is not None and t >= self.moving_since:
            self.moving_s += t - self.moving_since
        self.moving_since = None

    def close(self) -> None:
        self.stop_clock(self.last_t)


class HistogramReader:
    """estopd's --log-json events, one at a time (a file, or a log being followed): sums the
    last ``link_histogram`` event of every run. A run starts at a ``start`` event (or where
    the counts go down); events other than ``link_histogram``, ``state``, ``exit`` and
    ``output_dropped`` are ignored. ``estop link`` reads a file with it
    (:func:`read_histogram_log`), ``estop dashboard`` a log as it is written."""

    def __init__(self) -> None:
        self._runs: list[tuple[_Run, dict[str, Any]]] = []
        self._run = _Run()
        self._edges: list[int] | None = None
        self._dropped = False
        self.histograms = 0  # link_histogram events taken

    def _finish(self) -> None:
        self._run.close()
        if self._run.last is not None:
            self._runs.append((self._run, self._run.last))

    def feed_line(self, line: str, where: str) -> bool:
        """One log line, as written or as journalctl prints it (lines without an event are
        skipped); True if it was a ``link_histogram``. Raises :class:`LinkInputError` for a
        malformed one."""
        ev = _event(line.strip())
        return ev is not None and self.feed(ev, where)

    def feed(self, ev: dict[str, Any], where: str) -> bool:
        """One decoded event; True if it was a ``link_histogram``."""
        kind = ev.get("event")
        t = _t_mono(ev)
        run = self._run
        if kind == "start":
            self._finish()
            self._run = _Run(started=True)
            self._run.saw(t)
            return False
        if kind == "output_dropped" and ev.get("stream", "log") == "log":
            self._dropped = True
        if kind == "state":
            run.state(ev.get("to"), t)
        elif kind == "exit":
            run.stop_clock(t)  # the daemon brakes as it ends
        if kind != "link_histogram":
            run.saw(t)
            return False
        _check_histogram(ev, where)
        if self._edges is None:
            self._edges = ev["edges_us"]
        elif ev["edges_us"] != self._edges:
            raise LinkInputError(f"{where}: link_histogram bins differ from earlier "
                                 "events (logs of different daemons mixed?)")
        if run.last is not None and any(
                b < a for a, b in zip(run.last["counts"], ev["counts"], strict=True)):
            self._finish()  # counts went down: a restart without `start`
            self._run = run = _Run()
        run.last = ev
        run.saw(t)
        self.histograms += 1
        return True

    def histogram(self, path: str, skipped_note: str = "") -> Histogram:
        """The sum so far (the current run up to its latest event); ``path`` names the log in
        the error raised when there is no ``link_histogram`` yet, ``skipped_note`` says which
        lines held no event."""
        current = self._run
        runs = list(self._runs)
        if current.last is not None:
            # a copy, so that the run goes on counting its time moving as events come
            snap = _Run(current.started, current.last, current.moving_s, current.moving_since,
                        current.last_t, current.states)
            snap.close()
            runs.append((snap, current.last))
        edges = self._edges
        if not runs or edges is None:
            why = f"; {skipped_note}" if skipped_note else ""
            raise LinkInputError(f"{path}: no link_histogram event (is it estopd's --log-json "
                                 f"log?){why}")
        total = [0] * len(edges)
        valid = invalid = silences = 0
        saturated = False
        for _, ev in runs:
            for i, x in enumerate(ev["counts"]):
                total[i] += x
                saturated |= x >= U32_MAX
            valid += ev["valid"]
            invalid += ev["invalid"]
            silences += ev["silences"]
        unit, note = _unit_record(runs, self._dropped)
        return Histogram(tuple(edges), tuple(total), valid, invalid, silences,
                         runs[-1][1]["warn_us"], len(runs), saturated, unit, note, skipped_note)


def read_histogram_log(path: str) -> Histogram:
    """Sum the last ``link_histogram`` event of every run in estopd's --log-json log, as
    written or as journalctl prints it (see :class:`HistogramReader`); lines that hold no
    event are counted and the first is named."""
    reader = HistogramReader()
    skipped = _Skipped()
    try:
        with open_text(path) as f:
            for no, raw in enumerate(f, 1):
                line = raw.strip()
                ev = _event(line)
                if ev is None:
                    skipped.add(no, line)
                    continue
                reader.feed(ev, f"{path}:{no}")
    except UnicodeDecodeError:
        raise LinkInputError(f"{path}: not a text file (use --format pcap for captures)") \
            from None
    return reader.histogram(path, skipped.note())


def _unit_record(runs: list[tuple[_Run, dict[str, Any]]],
                 dropped: bool) -> tuple[UnitRecord | None, str]:
    """The runs' own counts, when every run has them and all ran with the same S and T;
    otherwise None and why (empty for a log of older daemons, which have none of the keys)."""
    events = [ev for _, ev in runs]
    having = [ev for ev in events if all(k in ev for k in UNIT_KEYS)]
    if not any(k in ev for ev in events for k in UNIT_KEYS):
        return None, ""
    if len(having) < len(events):
        return None, (f"{len(events) - len(having)} of {len(events)} run(s) lack the unit's "
                      "own counts (" + ", ".join(UNIT_KEYS) + "): no check against them")
    settings = sorted({(ev["slow_us"], ev["timeout_us"]) for ev in having})
    if len(settings) > 1:
        both = ", ".join(f"S {s / 1000:g} ms T {t / 1000:g} ms" for s, t in settings)
        return None, (f"the runs used different slow times or timeouts ({both}): no check "
                      "against the unit's own counts")
    slow_us, timeout_us = settings[0]
    notes: list[str] = []
    moving: float | None = sum(r.moving_s for r, _ in runs)
    if not all(r.started for r, _ in runs):
        moving = None  # a log cut or filtered: the unit may have moved before its first line
    elif any(r.states == 0 and ev["slowdowns"] + ev["timeouts"] > 0 for r, ev in runs):
        moving = None
        notes.append("a run counted slow-downs or timeouts but logged no state change: the "
                     "time the unit moved is unknown")
    if dropped and moving is not None:
        notes.append("the daemon dropped log lines (output_dropped): the time it moved, taken "
                     "from its state events, may be off")
    return UnitRecord(sum(ev["slowdowns"] for ev in having),
                      sum(ev["timeouts"] for ev in having), slow_us, timeout_us, moving,
                      tuple(notes)), ""
