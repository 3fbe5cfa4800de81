"""What the demo measures: its settings, each stop (the moment that mattered, the unit's answer
on the bus, the car's roll-out), the burst, the attacker's tally.

The story fills a :class:`Result` as it goes; :func:`settle` adds what needs the whole record,
once the daemons have exited (every can-log line and drop report is in): the roll-out of each
stop (:func:`estop.model.rollout.roll_out` over the unit's logged frames) and the can-log lines that
may be missing around it. A figure is only given when none is: a lost first stop frame would
make the next one look like a late stop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from estop.demo.bus import BusWatch, Change
from estop.model.rollout import RollOut, roll_out, timed_frames
from estop.protocol import can
from estop.unit.daemon import Daemon

__all__ = ["BurstMeasure", "Result", "Settings", "StopMeasure", "settle"]

TIME_MS_MIN, TIME_MS_MAX = 1, 60000  # estopd's range for its times
BURST_ROOM_MS = 200  # the least T - S: room for a burst longer than S and shorter than T


@dataclass(frozen=True, slots=True)
class Settings:
    """The unit's two stages and the demo's speed."""

    slow_ms: int = 200  # S, the figure
    timeout_ms: int = 1000  # T, the figure
    speed: float = 15 / 3.6  # m/s, the car's speed at every moment that matters
    slow_level: int = can.DEFAULT_SLOW_LEVEL  # L, percent

    def __post_init__(self) -> None:
        for name, value in (("slow time", self.slow_ms), ("timeout", self.timeout_ms)):
            if not TIME_MS_MIN <= value <= TIME_MS_MAX:
                raise ValueError(f"the {name} must be {TIME_MS_MIN}..{TIME_MS_MAX} ms "
                                 f"(estopd's range), got {value}")
        if self.timeout_ms - self.slow_ms < BURST_ROOM_MS:
            raise ValueError(f"the timeout ({self.timeout_ms} ms) must be at least "
                             f"{BURST_ROOM_MS} ms above the slow time ({self.slow_ms} ms): the "
                             f"demo's burst of lost packets must fit between them")
        if not self.speed > 0:
            raise ValueError(f"the speed must be > 0, got {self.speed!r}")

    @property
    def burst_ms(self) -> int:
        """The burst of lost packets: longer than S, well short of T."""
        return self.slow_ms + min(200, (self.timeout_ms - self.slow_ms) // 2)

    def unit_args(self) -> list[str]:
        """estopd's options for the two stages (besides --timeout-ms)."""
        return ["--slow-ms", str(self.slow_ms), "--slow-level", str(self.slow_level)]


@dataclass
class StopMeasure:
    """A stop: what happened at ``moment`` (realtime) and what the unit did about it."""

    what: str  # "the finger lifts"
    moment_name: str  # "the lift"
    moment: float
    unit: str = "unit"  # "unit": the demo's unit; "v2": the version-2 unit beside it
    stop: Change | None = None  # the first STOPPED frame at or after the moment
    slowing: Change | None = None  # the first SLOWING frame after it (silence only)
    between: list[Change] = field(default_factory=list)  # state changes, moment .. stop
    rollout: RollOut | None = None
    lost: int = 0  # can-log lines that may be missing from moment .. standstill

    def latency_ms(self, change: Change | None) -> float | None:
        return None if change is None else (change.t - self.moment) * 1000.0


@dataclass
class BurstMeasure:
    """The burst: the link lost every packet from ``cut`` to ``end`` (realtime)."""

    cut: float
    end: float
    last_packet: float  # the last packet the link delivered before the burst
    packets_lost: int
    first_back: float | None = None  # the first packet delivered after it
    slowing: Change | None = None  # SLOWING after the last packet
    armed: Change | None = None  # ARMED again after that SLOWING
    stops: list[Change] = field(default_factory=list)  # STOPPED during the burst: none, please
    speed_before: float = 0.0  # m/s, the live car
    speed_low: float = 0.0
    lost: int = 0

    @property
    def silence_ms(self) -> float | None:
        """Time without a delivered packet."""
        if self.first_back is None:
            return None
        return (self.first_back - self.last_packet) * 1000.0

    def after_last_ms(self, change: Change | None) -> float | None:
        return None if change is None else (change.t - self.last_packet) * 1000.0


@dataclass
class Result:
    settings: Settings = field(default_factory=Settings)
    boot_release_nak: int | None = None  # RELEASE before any packet: NAK 2
    lift: StopMeasure | None = None
    v2: StopMeasure | None = None
    forged_release_nak: int | None = None  # the attacker's RELEASE: NAK 4
    burst: BurstMeasure | None = None
    loss: StopMeasure | None = None
    attacker_sent: dict[str, int] = field(default_factory=dict)
    datagram: StopMeasure | None = None
    button: StopMeasure | None = None
    latched_release_nak: int | None = None  # RELEASE with gas pressed: NAK 3
    lift_datagrams: int = 0
    problems: list[str] = field(default_factory=list)

    def stops(self) -> list[StopMeasure]:
        """Every stop measured, in the story's order."""
        return [m for m in (self.lift, self.v2, self.loss, self.datagram, self.button)
                if m is not None]


def _mono(real: float) -> float:
    return real - (time.time() - time.monotonic())


def _lost(daemon: Daemon, t_from: float, t_to: float) -> int:
    return daemon.lines_lost((t_from, t_to), (_mono(t_from), _mono(t_to)))


def settle(res: Result, unit: Daemon, watch: BusWatch, v2: Daemon | None = None,
           v2_watch: BusWatch | None = None) -> None:
    """Once the daemons have exited: every stop's roll-out and the lines lost around it."""
    for m in res.stops():
        daemon, w = (v2, v2_watch) if m.unit == "v2" else (unit, watch)
        if daemon is None or w is None:
            continue
        m.rollout = roll_out(timed_frames(w.records), m.moment, res.settings.speed)
        m.lost = _lost(daemon, m.moment, max(m.rollout.standstill,
                                             m.stop.t if m.stop is not None else m.moment))
    b = res.burst
    if b is not None:
        end = b.armed.t if b.armed is not None else b.end
        b.lost = _lost(unit, b.last_packet, max(end, b.end))
