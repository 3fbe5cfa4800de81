"""How far the car rolls, for the test protocol: the bus record through the vehicle model
(docs/VEHICLE.md) from the moment that mattered (the finger lift, the last control packet) to
standstill. Pure (no sockets, no threads).

Two ways to the same figure, so that each checks the other:

- :func:`bus_roll_out`: ``estop.model.rollout.roll_out`` on the frames on the bus (the project's
  brake controller emulation, ``estop.model.brakecheck``, into ``estop.model.vehicle``);
- :func:`emulator_roll_out`: the harness's own emulator (:class:`hilemu.BrakeController`,
  replayed on the same frames) commanding ``estop.model.vehicle.Vehicle``.

The car: 15 km/h at the moment, emergency deceleration 8 m/s^2, no actuator delay (the
model's defaults, :data:`PARAMS`); :func:`single_stage_distance` and
:func:`two_stage_distance` are the model's figures for an ideal unit with given times.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from estop.model.rollout import RollOut, roll_out
from estop.model.vehicle import Vehicle, VehicleParams, kmh, stopping_distance
from hilemu import BrakeChange, Frame, replay, share_at

SPEED_KMH = 15.0  # a typical research-car speed (docs/VEHICLE.md)
PARAMS = VehicleParams(emergency_decel=8.0, actuator_delay=0.0)  # the model's defaults
AGREE_M = 0.001  # the two ways to the distance must agree to a millimetre
MODEL_TEXT = (f"{SPEED_KMH:g} km/h, emergency deceleration {PARAMS.emergency_decel:g} m/s^2, "
              f"actuator delay {PARAMS.actuator_delay * 1000:g} ms")


def speed() -> float:
    """The car's speed at the moment, m/s."""
    return kmh(SPEED_KMH)


def bus_roll_out(frames: Sequence[Frame], moment: float) -> RollOut:
    """``estop.model.rollout.roll_out`` on the bus record ``frames`` (from well before ``moment``:
    the controller's state at the moment comes from the frames before it)."""
    return roll_out(((f.ts, f.can_id, f.data) for f in frames), moment, speed(),
                    params=PARAMS)


@dataclass(frozen=True, slots=True)
class EmulatorRoll:
    """The car's stop as the harness's emulator commands it."""

    distance: float  # metres from the moment to standstill
    braking_began: float | None  # when the brake first acted on the moving car
    standstill: float | None  # None: released at the end of the record, still rolling


def emulator_roll_out(changes: Sequence[BrakeChange], moment: float) -> EmulatorRoll:
    """The emulator's graded commands (a replay's :attr:`BrakeController.changes`) from
    ``moment`` on, on a car at :func:`speed` then."""
    car = Vehicle(speed(), moment, share=share_at(changes, moment), params=PARAMS)
    for c in changes:
        if c.ts > moment:
            car.command(c.ts, c.share)
    standstill = car.run_to_standstill()
    return EmulatorRoll(car.position, car.braking_began, standstill)


@dataclass(frozen=True, slots=True)
class Roll:
    """Both ways to the car's stop from one moment, and whether they agree."""

    moment: float
    bus: RollOut
    emulator: EmulatorRoll

    @property
    def agree(self) -> bool:
        return (self.emulator.standstill is not None
                and abs(self.bus.distance - self.emulator.distance) <= AGREE_M)

    def figures(self) -> dict[str, float | None]:
        """For the protocol: metres and ms from the moment."""
        b = self.bus
        return {"distance_m": round(b.distance, 3),
                "braking_after_ms": None if b.reaction_time is None
                else round(b.reaction_time * 1000, 3),
                "rolled_before_braking_m": round(b.distance_before_braking, 3),
                "standstill_after_ms": round(b.time_to_standstill * 1000, 1)}

    def disagreement(self) -> str:
        e = self.emulator
        return (f"estop.model.rollout {self.bus.distance:.4f} m, the harness's emulator "
                f"{e.distance:.4f} m" + ("" if e.standstill is not None
                                         else " (released at the end: never stops)"))


def roll(frames: Sequence[Frame], moment: float) -> Roll:
    """The car's stop from ``moment``, both ways, on the bus record ``frames``."""
    return Roll(moment, bus_roll_out(frames, moment),
                emulator_roll_out(replay(frames).changes, moment))


def single_stage_distance(timeout_s: float) -> float:
    """The model's figure for a unit that brakes fully ``timeout_s`` after the moment."""
    return stopping_distance(speed(), delay=timeout_s, params=PARAMS)


def two_stage_distance(slow_s: float, timeout_s: float, level: int) -> float:
    """The model's figure for a two-stage unit: ``level`` % from ``slow_s``, fully from
    ``timeout_s`` after the moment."""
    car = Vehicle(speed(), 0.0, params=PARAMS)
    car.command(slow_s, level / 100.0)
    car.command(timeout_s, 1.0)
    car.run_to_standstill()
    return car.position


def speed_after(changes: Sequence[BrakeChange], t0: float, t1: float) -> float:
    """The car's speed (m/s) at ``t1`` when it was at :func:`speed` at ``t0`` and braked as
    ``changes`` command in between (what a burst of silence costs)."""
    car = Vehicle(speed(), t0, share=share_at(changes, t0), params=PARAMS)
    for c in changes:
        if t0 < c.ts <= t1:
            car.command(c.ts, c.share)
    car.advance(t1)
    return car.speed
