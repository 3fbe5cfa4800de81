"""How far the car rolls: recorded ESTOP_BRAKE frames, replayed through the brake controller
emulation (:class:`estop.model.brakecheck.BrakeFrameChecker`, spec section 7) into the vehicle model
(:mod:`estop.model.vehicle`), from a moment that mattered (the finger lift, the last control packet,
the start of a watch) at a given speed (docs/VEHICLE.md).

The car is at ``speed`` at ``moment``, whatever came before; from then on it brakes with the
share the controller commands, each change on the frame that caused it, or where the 50 ms
silence rule starts braking. The controller's state at ``moment`` comes from the frames before
it, so feed the record from its start.

What the record does not show is taken as released, as a distance estimate must not count on
braking it cannot see: before the record's first frame (of any ID), and in its first 50 ms
until an ESTOP_BRAKE commands. From there on silence is a failure, as for the controller: no
accepted ESTOP_BRAKE in the record's first 50 ms, or none for 50 ms later, brakes fully. After
the last frame the record is silent, so a replay always ends at standstill;
:attr:`RollOut.beyond_record` tells when the braking began only after the record ended. (A
record without any frame starts at ``moment``.)

Use, e.g. in the demo or the HIL harness, with frames on one clock (here a can-log)::

    from estop.model.rollout import roll_out, timed_frames
    from estop.model.vehicle import VehicleParams, kmh

    out = roll_out(timed_frames(records), moment=t_lift, speed=kmh(15))
    out.distance, out.time_to_standstill, out.braking_began, out.summary()

:class:`RollOutReplay` does the same one frame at a time, in constant memory (``estop
monitor --speed-kmh``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from estop.model.brakecheck import BRAKE_TIMEOUT, EMERGENCY, BrakeFrameChecker
from estop.model.vehicle import DEFAULT_PARAMS, Vehicle, VehicleParams
from estop.protocol.can import BRAKE_ID
from estop.protocol.canlog import CanLogRecord

__all__ = ["RollOut", "RollOutReplay", "TimedFrame", "roll_out", "timed_frames"]

TimedFrame = tuple[float, int, bytes]  # (seconds on the record's clock, CAN ID, data)


def timed_frames(records: Iterable[CanLogRecord]) -> Iterator[TimedFrame]:
    """The standard-ID frames of can-log records as (seconds, CAN ID, data)."""
    for rec in records:
        if not rec.extended:
            yield rec.timestamp, rec.can_id, rec.data


@dataclass(frozen=True, slots=True)
class RollOut:
    """The car's stop, from ``moment`` at ``speed`` (times on the frames' clock, seconds)."""

    moment: float
    speed: float  # m/s at the moment
    braking_began: float | None  # the brake first acted on the moving car (None: at rest)
    full_braking_began: float | None  # ... at full force (None: never, or at rest)
    standstill: float  # the car came to rest
    distance: float  # metres rolled from the moment to rest
    record_end: float | None  # the last frame fed (any ID); None: none

    @property
    def time_to_standstill(self) -> float:
        return self.standstill - self.moment

    @property
    def reaction_time(self) -> float | None:
        """Seconds from the moment until the brake acted (at any share)."""
        return None if self.braking_began is None else self.braking_began - self.moment

    @property
    def distance_before_braking(self) -> float:
        """Metres rolled at full speed before the brake acted."""
        reaction = self.reaction_time
        return 0.0 if reaction is None else self.speed * max(0.0, reaction)

    @property
    def beyond_record(self) -> bool:
        """The braking began only after the record ended (by the silence rule): the record
        does not show what the unit commanded then."""
        return self.braking_began is not None and (self.record_end is None
                                                   or self.braking_began > self.record_end)

    def summary(self) -> str:
        """One line, e.g. ``at 15.0 km/h: braking began +12.0 ms, standstill +532.8 ms,
        rolled 1.135 m``."""
        began = ("at rest" if self.reaction_time is None
                 else f"braking began {self.reaction_time * 1000:+.1f} ms")
        if self.beyond_record:
            began += " (after the end of the record: silence)"
        return (f"at {self.speed * 3.6:.1f} km/h: {began}, standstill "
                f"{self.time_to_standstill * 1000:+.1f} ms, rolled {self.distance:.3f} m")


class RollOutReplay:
    """Feed frames (in the order received) with :meth:`feed`; :meth:`result` gives the
    :class:`RollOut`. ``brake_id`` and ``timeout`` as for the brake controller
    (:class:`~estop.model.brakecheck.BrakeFrameChecker`)."""

    def __init__(self, moment: float, speed: float, *, params: VehicleParams = DEFAULT_PARAMS,
                 brake_id: int = BRAKE_ID, timeout: float = BRAKE_TIMEOUT) -> None:
        self.moment = moment
        self.speed = speed
        self.params = params
        self.checker = BrakeFrameChecker(brake_id=brake_id, status_id=None, timeout=timeout)
        self._share = 0.0  # the command so far: before the record, taken as released
        self._vehicle: Vehicle | None = None  # starts with the first command it must act on
        self._began: float | None = None  # the record's first frame
        self._last_t: float | None = None
        Vehicle(speed, moment, params=params)  # refuse a bad speed or moment now

    def feed(self, t: float, can_id: int, data: bytes | bytearray | memoryview) -> None:
        if self._began is None:
            self._began = t
        self._last_t = t if self._last_t is None else max(self._last_t, t)
        deadline = self._silence_deadline()
        if deadline is not None and deadline <= t:
            self._command(deadline, EMERGENCY)  # 50 ms without an accepted frame
        if self.checker.feed(t, can_id, data) is not None:
            self._command(t, self._controller_share(t))

    def result(self) -> RollOut:
        """The car's stop: the frames fed, then the silence after them."""
        if self._began is None:
            self._began = self.moment  # no frame at all: the record starts at the moment
        deadline = self._silence_deadline()
        if deadline is not None:
            self._command(deadline, EMERGENCY)
        vehicle = self._vehicle or Vehicle(self.speed, self.moment, share=self._share,
                                           params=self.params)
        self._vehicle = vehicle
        standstill = vehicle.run_to_standstill()
        assert standstill is not None  # the silence rule always ends in an emergency brake
        return RollOut(self.moment, self.speed, vehicle.braking_began,
                       vehicle.full_braking_began, standstill, vehicle.position, self._last_t)

    def _silence_deadline(self) -> float | None:
        """When silence brakes: 50 ms after the last accepted ESTOP_BRAKE, or after the
        record's start before the first."""
        deadline = self.checker.silence_deadline
        if deadline is None and self._began is not None:
            deadline = self._began + self.checker.timeout
        return deadline

    def _controller_share(self, t: float) -> float:
        if self.checker.silence_deadline is not None:
            return self.checker.deceleration_share(t)
        # no ESTOP_BRAKE accepted in the record yet: a frame from the unit that failed the
        # content check brakes; else released (not seen) for the record's first 50 ms
        assert self._began is not None
        if self.checker.commanded_share is None and t < self._began + self.checker.timeout:
            return 0.0
        return EMERGENCY

    def _command(self, t: float, share: float) -> None:
        if share == self._share:
            return
        if self._vehicle is None:
            if t + self.params.actuator_delay <= self.moment:
                self._share = share  # acts on the car by the moment: where it starts
                return
            self._vehicle = Vehicle(self.speed, self.moment, share=self._share,
                                    params=self.params)
        self._vehicle.command(t, share)
        self._share = share


def roll_out(frames: Iterable[TimedFrame], moment: float, speed: float, *,
             params: VehicleParams = DEFAULT_PARAMS, brake_id: int = BRAKE_ID,
             timeout: float = BRAKE_TIMEOUT) -> RollOut:
    """The car's stop from ``moment`` at ``speed`` (m/s), given the frames on the bus
    ((seconds, CAN ID, data), in the order received, from the record's start)."""
    replay = RollOutReplay(moment, speed, params=params, brake_id=brake_id, timeout=timeout)
    for t, can_id, data in frames:
        replay.feed(t, can_id, data)
    return replay.result()
