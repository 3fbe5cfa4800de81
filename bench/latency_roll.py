"""How far the car rolled in a stop-latency trial: the trial's can-log frames replayed through
the brake controller and the vehicle model (:mod:`estop.model.rollout`, docs/VEHICLE.md), from the
moment that mattered (the last valid packet of a silence trial, the first lift datagram of a
lift trial) to standstill. Pure: tests/harness/test_bench_smoke.py feeds it synthetic frames.

A trial's record is every frame the bench read from the can-log since the previous trial's
stop frame, up to and including this trial's first emergency stop frame (brake_request 1):
the controller's state at the moment comes from the frames before it, and a SLOWING phase
(brake_request 2) between the moment and the stop brakes at its level. After the stop frame
the controller brakes fully, so the record may end there.
"""

from __future__ import annotations

from collections.abc import Iterable

from estop.model.rollout import RollOut, roll_out, timed_frames
from estop.model.vehicle import DEFAULT_PARAMS, VehicleParams, kmh, stopping_distance
from estop.protocol.canlog import CanLogRecord

DEFAULT_SPEED_KMH = 15.0  # a research car driven remotely on a test ground


def roll_from_record(record: Iterable[CanLogRecord], moment: float, speed_kmh: float, *,
                     params: VehicleParams = DEFAULT_PARAMS) -> RollOut:
    """The car's stop from ``moment`` (time.time() seconds, the can-log's clock) at
    ``speed_kmh``, given the trial's can-log records in the order read."""
    return roll_out(timed_frames(record), moment, kmh(speed_kmh), params=params)


def braking_distance(speed_kmh: float, params: VehicleParams = DEFAULT_PARAMS) -> float:
    """Metres of full braking alone from ``speed_kmh`` (no reaction time): the floor of every
    distance in the report."""
    return stopping_distance(kmh(speed_kmh), params=params)


def fmt_m(v: float) -> str:
    """Metres with millimetres: a reaction time of 1 ms at 15 km/h is 4 mm."""
    return "-" if v != v else f"{v:.3f}"  # NaN: no value
