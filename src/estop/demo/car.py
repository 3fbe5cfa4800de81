"""The car behind the demo's bus, live: the brake controller emulation
(:class:`estop.model.brakecheck.BrakeFrameChecker`, spec section 7) fed the unit's logged frames as
they come, and the vehicle model (:mod:`estop.model.vehicle`) braking with the share it commands.

The model has no drive force (docs/VEHICLE.md), so the demo adds the operator's part: while
:attr:`LiveCar.driving` (the operator gives gas and the packets reach the car) and the brake
is released, the car speeds up to the demo's speed within :data:`DRIVE_RAMP_S`, then holds it.
Braking is the model's alone. Times are the frames' can-log stamps (seconds, CLOCK_REALTIME).

This is what the live view shows; the stop table's figures come from
:func:`estop.model.rollout.roll_out` over the whole record after the run.
"""

from __future__ import annotations

import math

from estop.model.brakecheck import EMERGENCY, BrakeFrameChecker
from estop.model.vehicle import Vehicle

__all__ = ["DRIVE_RAMP_S", "LiveCar"]

DRIVE_RAMP_S = 1.0  # seconds from rest to the demo's speed while driving


class LiveCar:
    """The car at ``cruise`` m/s when driven, braked by what the bus says."""

    def __init__(self, cruise: float) -> None:
        if not (math.isfinite(cruise) and cruise > 0):
            raise ValueError(f"the demo's speed must be > 0 m/s, got {cruise!r}")
        self.cruise = cruise
        self.accel = cruise / DRIVE_RAMP_S
        self.checker = BrakeFrameChecker(status_id=None)
        self.driving = False
        self.low = math.inf  # the lowest speed since :meth:`watch_low`
        self._vehicle: Vehicle | None = None  # from the first frame on

    @property
    def speed(self) -> float:
        """m/s, at the latest frame."""
        return 0.0 if self._vehicle is None else self._vehicle.speed

    @property
    def position(self) -> float:
        """Metres driven since the start (the odometer)."""
        return 0.0 if self._vehicle is None else self._vehicle.position

    @property
    def at_rest(self) -> bool:
        return self.speed == 0.0

    @property
    def share(self) -> float:
        """The share of the emergency deceleration the brake acts with now."""
        return EMERGENCY if self._vehicle is None else self._vehicle.share

    def watch_low(self) -> None:
        """Start following the lowest speed (:attr:`low`) from now."""
        self.low = self.speed

    def feed(self, t: float, can_id: int, data: bytes) -> None:
        """One logged frame at ``t`` (in order)."""
        if self._vehicle is None:
            # before the first accepted frame the controller brakes (spec section 7)
            self._vehicle = Vehicle(0.0, t, share=EMERGENCY)
        deadline = self.checker.silence_deadline
        if deadline is not None and deadline <= t and self.share < EMERGENCY:
            self._step(max(deadline, self._vehicle.t))
            self._command(EMERGENCY)  # no accepted ESTOP_BRAKE for 50 ms
        self._step(t)
        verdict = self.checker.feed(t, can_id, data)
        if verdict is not None and verdict.share is not None:
            self._command(verdict.share)
        self.low = min(self.low, self.speed)

    def _command(self, share: float) -> None:
        v = self._vehicle
        assert v is not None
        v.command(v.t, share)
        v.advance(v.t)

    def _step(self, t: float) -> None:
        """On to ``t``: the model's braking, or the operator's drive while released."""
        v = self._vehicle
        assert v is not None
        if t <= v.t:
            return
        if not (self.driving and v.share == 0.0 and v.speed < self.cruise):
            v.advance(t)
            return
        dt = t - v.t
        ramp = (self.cruise - v.speed) / self.accel  # seconds until the demo's speed
        if dt >= ramp:
            x = v.position + v.speed * ramp + self.accel * ramp * ramp / 2
            x += self.cruise * (dt - ramp)
            speed = self.cruise
        else:
            x = v.position + v.speed * dt + self.accel * dt * dt / 2
            speed = v.speed + self.accel * dt
        self._vehicle = Vehicle(speed, t, share=0.0, position=x)
