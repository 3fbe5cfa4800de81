"""The dead-man across the page's hop: which held frames make a control packet. Pure logic,
times passed in (seconds, ``time.monotonic()``), so it is tested without a browser.

The page sends a held frame every control period while a finger is on its drive area; the
remote sends one control packet for each *fresh* frame and none otherwise, so the packets stop
when the frames stop (a frozen page, a dead tab, a cut network) and the unit slows at S and
stops at T. A frame is fresh when:

- it comes from the page that holds (one page drives at a time: the first to put a finger
  down, until its hold ends);
- it was not held up on its way: its age, estimated from the page's own clock as the delay
  above the smallest delay seen (which may rise by :data:`DRIFT` per second, so that a lasting
  change of route re-baselines within seconds), is at most two periods. Frames that waited in
  a buffer (a Wi-Fi stall, a paused page whose socket delivers late) are dropped instead of
  being replayed as if the finger were still there now;
- it was sent at least half a period after the frame of the previous packet (by the page's
  clock, so that the network's jitter costs no packet), and arrives at least a quarter period
  after that packet: a backlog delivered at once is not a burst of packets, and a page that
  sends too fast does not raise the rate (docs/REMOTE.md: no bursts to catch up).

A constant delay cannot be told from none without synchronised clocks; the page shows the
round trip so the driver sees it.

Once no fresh frame came for two periods the hold is *stalled* (reported once per stall);
nothing is sent until fresh frames come again. Only the end of the hold (the page's lift, its
socket closing) makes the lift datagrams.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["DRIFT", "STALE_PERIODS", "DeadMan", "HoldStats", "Verdict"]

STALE_PERIODS = 2.0  # a frame older than this many periods is not fresh; no fresh one for
#                      this long: the hold is stalled
DRIFT = 0.010  # s per s: how fast the smallest delay seen may rise (clock drift, a new route)


class Verdict(enum.Enum):
    SEND = "send"  # fresh: one control packet now
    STALE = "stale"  # held up on its way: nothing
    EARLY = "early"  # too soon after the previous packet's frame: nothing
    OTHER = "other"  # another page holds: nothing


@dataclass
class HoldStats:
    frames: int = 0  # held frames judged
    fresh: int = 0  # ... that made a packet
    stale: int = 0
    early: int = 0
    other: int = 0
    missed: int = 0  # control periods of a hold without a fresh frame (by the page's clock)
    holds: int = 0
    stalls: int = 0

    @property
    def late(self) -> int:
        """Frames that did not come in time: dropped as stale or early, or never came."""
        return self.stale + self.early + self.missed


class _PageClock:
    """The page's clock against ours: the smallest (arrival - page time) seen, rising slowly."""

    def __init__(self) -> None:
        self.base: float | None = None
        self.base_at = 0.0

    def age(self, page_s: float, now: float) -> float:
        offset = now - page_s
        if self.base is None:
            self.base, self.base_at = offset, now
        else:
            risen = self.base + DRIFT * max(0.0, now - self.base_at)
            if offset <= risen:
                self.base, self.base_at = offset, now
            else:
                self.base, self.base_at = risen, now
        return offset - self.base


class DeadMan:
    """Judges the held frames of every connected page (by connection id) at ``period``."""

    def __init__(self, period: float) -> None:
        if not period > 0:
            raise ValueError(f"period must be > 0 s, got {period!r}")
        self.period = period
        self.holder: int | None = None
        self.stats = HoldStats()
        self.last_fresh = 0.0
        self._last_sent = -1e9
        self._last_sent_page_s = -1e9  # the page time of the latest packet's frame
        self._stalled = False
        self._clocks: dict[int, _PageClock] = {}

    @property
    def holding(self) -> bool:
        return self.holder is not None

    def frame(self, conn: int, at_ms: float, now: float) -> Verdict:
        """A held frame from page ``conn`` sent at its clock's ``at_ms``, arriving ``now``.
        SEND starts a hold when none is on (the caller then holds the remote)."""
        self.stats.frames += 1
        clock = self._clocks.setdefault(conn, _PageClock())
        age = clock.age(at_ms / 1000.0, now)
        if self.holder is not None and self.holder != conn:
            self.stats.other += 1
            return Verdict.OTHER
        if age > STALE_PERIODS * self.period:
            self.stats.stale += 1
            return Verdict.STALE
        page_s = at_ms / 1000.0
        if self.holder is None:
            self._last_sent_page_s = -1e9  # a new hold: the page's clock may be another's
        if (page_s - self._last_sent_page_s < self.period / 2
                or now - self._last_sent < self.period / 4):
            self.stats.early += 1
            return Verdict.EARLY
        if self.holder is None:
            self.holder = conn
            self.stats.holds += 1
        else:  # periods the page sent nothing for, or whose frames were dropped
            gap = page_s - self._last_sent_page_s
            self.stats.missed += max(0, round(gap / self.period) - 1)
        self.stats.fresh += 1
        self.last_fresh = self._last_sent = now
        self._last_sent_page_s = page_s
        self._stalled = False
        return Verdict.SEND

    def end(self, conn: int) -> bool:
        """Page ``conn``'s hold ends (its lift, its socket closed). True when it held: the
        caller lifts. The end of another page's finger changes nothing."""
        if self.holder is None or self.holder != conn:
            return False
        self.holder = None
        self._stalled = False
        return True

    def forget(self, conn: int) -> None:
        """Page ``conn`` has gone: its clock too (the caller ends its hold first)."""
        self._clocks.pop(conn, None)

    def stalled(self, now: float) -> bool:
        """True once per stall: holding, and no fresh frame for two periods."""
        if self.holder is None or self._stalled:
            return False
        if now - self.last_fresh > STALE_PERIODS * self.period:
            self._stalled = True
            self.stats.stalls += 1
            return True
        return False

    @property
    def is_stalled(self) -> bool:
        return self._stalled
