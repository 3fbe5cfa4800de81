"""The demo's screen: events as they happen (kept for the timeline) and a live status line
(the phase, the unit's state with the brake grade, the car's speed and distance, the link),
refreshed in place on a terminal and written once a second otherwise."""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from typing import TextIO

from estop.demo.bus import BusWatch, Change, grade
from estop.demo.car import LiveCar
from estop.protocol import can, tcp

__all__ = ["View", "reply_text"]


def reply_text(reply: tcp.Reply) -> str:
    """``ACK, unit ARMED reason=none`` or ``NAK 4 (not_authenticated), unit STOPPED ...``."""
    what = ("ACK" if reply.ack else
            f"NAK {reply.nak_code} ({tcp.NAK_NAMES.get(tcp.NakCode(reply.nak_code))})")
    return f"{what}, unit {can.state_name(reply.state)} reason={can.reason_name(reply.reason)}"


@dataclass
class View:
    """Writes to ``out``: events (one line each, kept in :attr:`events`) and the status line
    (``live``: refreshed in place; else a plain line a second)."""

    out: TextIO
    live: bool
    t0: float  # realtime of the demo's start: every time shown is from here
    watch: BusWatch
    car: LiveCar
    phase: str = "boot"
    remote: str = "-"
    events: list[tuple[float, str]] = field(default_factory=list)
    _last_draw: float = 0.0
    _last_plain: float = -10.0

    def event(self, t: float, text: str) -> None:
        """Something the demo did or saw at ``t`` (realtime): shown now, kept for the
        timeline."""
        self.events.append((t, text))
        self.show(t, text)

    def show(self, t: float, text: str) -> None:
        """A line shown now but not kept (the timeline has its own account of it)."""
        self._clear()
        self.out.write(f"  {t - self.t0:7.3f}s  {text}\n")
        self.out.flush()
        self._last_draw = 0.0

    def bus(self, who: str, change: Change) -> None:
        self.show(change.t, f"{who}: {change.text()}")

    def line(self) -> str:
        """The live status line, most important fields first (it is cut to the terminal)."""
        now = time.time() - self.t0
        b = self.watch.brake
        if b is None:
            unit = "no brake frame yet"
        else:
            degraded = " (link degraded)" if b.flags & can.FLAG_LINK_DEGRADED else ""
            unit = f"{can.state_name(b.state):7} {grade(b):16}{degraded}"
        age = self.watch.link_age_ms
        link = "-" if age is None else f"{age} ms"
        return (f"[{now:5.2f}s] {self.phase:14} | {unit} | car {self.car.speed * 3.6:4.1f} km/h "
                f"{self.car.position:6.2f} m | link age {link:>7} | auth failures "
                f"{self.watch.auth_failures:3}/100 ms | remote {self.remote}")

    def draw(self) -> None:
        now = time.monotonic()
        if self.live:
            if now - self._last_draw >= 0.05:
                width = shutil.get_terminal_size().columns - 1
                self.out.write("\r\x1b[2K" + self.line()[:width])
                self.out.flush()
                self._last_draw = now
        elif now - self._last_plain >= 1.0:
            self.out.write("  " + self.line() + "\n")
            self.out.flush()
            self._last_plain = now

    def _clear(self) -> None:
        if self.live:
            self.out.write("\r\x1b[2K")

    def finish(self) -> None:
        self._clear()
        self.out.flush()
