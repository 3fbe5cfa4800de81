"""A longitudinal model of the car: how far it rolls while the brake controller does what the
ESTOP_BRAKE frames ask (docs/VEHICLE.md).

The car moves in a straight line: speed ``v >= 0`` (m/s), position ``x`` (m). Between two brake
commands the deceleration is constant: ``a = share * a_e``, where ``share`` is what the brake
controller commands (spec section 7: 0 release, brake_level/100 for a controlled stop, 1 for an
emergency brake) and ``a_e`` the car's emergency deceleration (default 8 m/s^2, about 0.8 g:
a car's full braking on dry asphalt; set it for the car at hand). So, over a phase of ``dt``
seconds at deceleration ``a`` from speed ``v``::

    v >  a dt:   v' = v - a dt,   x' = x + v dt - a dt^2 / 2
    v <= a dt:   the car stops after v / a seconds, having rolled v^2 / (2 a); it stays there

and from a constant speed with a constant share after a delay ``d``, the stopping distance is
``v d + v^2 / (2 share a_e)``: at 15 km/h (4.17 m/s, a typical research car) and 8 m/s^2 the
car stops in 1.085 m of braking, and every 200 ms before braking adds 0.83 m.

What the model leaves out, and why that is the cautious side: no drive force (released, the car
keeps its speed; gas would only lengthen a stop the unit has not commanded yet) and no drag or
rolling resistance (they would shorten every stop). At standstill the car stays at rest:
braking holds it (spec section 7), and released it has nothing to move it.

The brake actuator may lag the controller by a fixed ``actuator_delay`` (default 0): the
deceleration at ``t`` is what the controller commanded at ``t - actuator_delay``.

:class:`Vehicle` is the model, stepped by brake commands; :func:`stopping_distance` the closed
form for one constant share. :mod:`estop.model.rollout` drives the model from recorded CAN frames.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = [
    "DEFAULT_EMERGENCY_DECEL",
    "DEFAULT_PARAMS",
    "Vehicle",
    "VehicleParams",
    "kmh",
    "stopping_distance",
]

DEFAULT_EMERGENCY_DECEL = 8.0  # m/s^2, a_e: full braking on dry asphalt, about 0.8 g


def kmh(speed_kmh: float) -> float:
    """A speed in km/h as m/s."""
    return speed_kmh / 3.6


def _check_share(share: float) -> float:
    if not 0.0 <= share <= 1.0:  # also refuses NaN
        raise ValueError(f"a deceleration share is 0..1, got {share!r}")
    return float(share)


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """The car: its emergency deceleration (m/s^2, > 0) and the brake actuator's delay behind
    the controller (s, >= 0)."""

    emergency_decel: float = DEFAULT_EMERGENCY_DECEL
    actuator_delay: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.emergency_decel) and self.emergency_decel > 0):
            raise ValueError(f"emergency deceleration must be > 0 m/s^2, got "
                             f"{self.emergency_decel!r}")
        if not (math.isfinite(self.actuator_delay) and self.actuator_delay >= 0):
            raise ValueError(f"actuator delay must be >= 0 s, got {self.actuator_delay!r}")


DEFAULT_PARAMS = VehicleParams()  # 8 m/s^2, no actuator delay


def stopping_distance(speed: float, *, share: float = 1.0, delay: float = 0.0,
                      params: VehicleParams = DEFAULT_PARAMS) -> float:
    """Metres a car at ``speed`` (m/s) rolls when the brake acts with ``share`` after
    ``delay`` seconds (plus the actuator's delay): ``v (delay + actuator_delay) +
    v^2 / (2 share a_e)``; ``inf`` when it never brakes (share 0 and moving)."""
    if not (math.isfinite(speed) and speed >= 0):
        raise ValueError(f"speed must be >= 0 m/s, got {speed!r}")
    if not (math.isfinite(delay) and delay >= 0):
        raise ValueError(f"delay must be >= 0 s, got {delay!r}")
    if speed == 0:
        return 0.0
    if _check_share(share) == 0:
        return math.inf
    return (speed * (delay + params.actuator_delay)
            + speed * speed / (2 * share * params.emergency_decel))


class Vehicle:
    """The car from time ``t`` on, at ``speed`` (m/s) and ``position`` (m), with the brake
    acting at ``share`` (the controller's command from before ``t``; with an actuator delay,
    commands given before ``t`` still due are passed to :meth:`command` as well).

    :meth:`command` tells it what the controller asks from a time on (in time order);
    :meth:`advance` moves it on to a time; :meth:`run_to_standstill` to rest. It remembers
    when the brake first acted on the moving car (:attr:`braking_began`), when at full force
    (:attr:`full_braking_began`) and when it came to rest (:attr:`standstill`).
    """

    def __init__(self, speed: float, t: float = 0.0, *, share: float = 0.0,
                 position: float = 0.0, params: VehicleParams = DEFAULT_PARAMS) -> None:
        if not (math.isfinite(speed) and speed >= 0):
            raise ValueError(f"speed must be >= 0 m/s, got {speed!r}")
        if not (math.isfinite(t) and math.isfinite(position)):
            raise ValueError("time and position must be finite")
        self.params = params
        self.t = float(t)
        self.speed = float(speed)
        self.position = float(position)
        self.share = 0.0
        self.braking_began: float | None = None
        self.full_braking_began: float | None = None
        self.standstill: float | None = self.t if self.speed == 0 else None
        self._pending: deque[tuple[float, float]] = deque()  # (when it acts, share)
        self._act(_check_share(share))

    def command(self, t: float, share: float) -> None:
        """From ``t`` on the controller asks for ``share``; the brake acts on it from
        ``t + actuator_delay``. Commands come in time order, and not for the past."""
        due = t + self.params.actuator_delay
        last = self._pending[-1][0] if self._pending else self.t
        if not due >= last:  # also refuses NaN
            raise ValueError(f"brake command for {t!r} is out of order (the model is at "
                             f"{self.t!r})")
        self._pending.append((due, _check_share(share)))

    def advance(self, t: float) -> None:
        """Move on to ``t`` (not before :attr:`t`), acting on the commands due by then."""
        if not t >= self.t:
            raise ValueError(f"cannot go back from {self.t!r} to {t!r}")
        while self._pending and self._pending[0][0] <= t:
            due, share = self._pending.popleft()
            self._roll(due)
            self._act(share)
        self._roll(t)

    def run_to_standstill(self) -> float | None:
        """Act on every command given, then go on until the car is at rest; return that
        time, or None if it never comes (released and moving when the commands end)."""
        while self._pending:
            self.advance(self._pending[0][0])
        if self.speed > 0 and self.share > 0:
            self._roll(self.t + self.speed / (self.share * self.params.emergency_decel))
        return self.standstill

    def _act(self, share: float) -> None:
        self.share = share
        if self.speed > 0 and share > 0 and self.braking_began is None:
            self.braking_began = self.t
        if self.speed > 0 and share >= 1.0 and self.full_braking_began is None:
            self.full_braking_began = self.t

    def _roll(self, t: float) -> None:
        """From :attr:`t` to ``t`` at the present deceleration (closed form)."""
        dt = t - self.t
        if self.speed > 0:
            decel = self.share * self.params.emergency_decel
            # compare times, not speeds: a stop planned for exactly t happens at t
            stops_at = self.t + self.speed / decel if decel > 0 else math.inf
            if stops_at <= t:
                self.position += self.speed * self.speed / (2 * decel)
                self.speed = 0.0
                self.standstill = stops_at
            else:
                self.position += self.speed * dt - decel * dt * dt / 2
                self.speed = max(0.0, self.speed - decel * dt)  # >= 0 despite rounding
                if self.speed == 0:
                    self.standstill = t
        self.t = t
