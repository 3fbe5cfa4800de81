"""The longitudinal vehicle model (estop.model.vehicle, docs/VEHICLE.md): closed forms, and the
properties a stopping distance must have whatever the brake commands."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from estop.model.vehicle import (
    DEFAULT_EMERGENCY_DECEL,
    Vehicle,
    VehicleParams,
    kmh,
    stopping_distance,
)
from repo import ROOT

V15 = 15 / 3.6  # m/s
DOC = ROOT / "docs" / "VEHICLE.md"


def test_the_documented_figures() -> None:
    assert DEFAULT_EMERGENCY_DECEL == 8.0
    assert kmh(15) == pytest.approx(V15)
    assert stopping_distance(V15) == pytest.approx(1.085, abs=0.0005)  # v^2 / (2 a)
    assert stopping_distance(V15, delay=0.2) - stopping_distance(V15) == pytest.approx(
        0.833, abs=0.0005)
    assert stopping_distance(V15, params=VehicleParams(actuator_delay=0.2)) == pytest.approx(
        stopping_distance(V15, delay=0.2))
    assert stopping_distance(V15, share=0.3) == pytest.approx(V15 ** 2 / (2 * 0.3 * 8))
    assert stopping_distance(0.0, share=0.0) == 0.0
    assert stopping_distance(V15, share=0.0) == math.inf


def test_docs_vehicle_states_the_models_figures() -> None:
    text = DOC.read_text()
    assert f"**{stopping_distance(V15):.3f} m**" in text  # 1.085 m
    assert f"adds **{0.2 * V15:.2f} m**" in text  # 0.83 m per 200 ms
    assert f"30 % needs {stopping_distance(V15, share=0.3):.1f} m" in text
    assert f"{stopping_distance(V15, delay=0.2):.3f} m" in text
    assert f"`a_e`           | {DEFAULT_EMERGENCY_DECEL:g} m/s^2" in text


def test_constant_speed_then_full_brake() -> None:
    car = Vehicle(V15, 10.0)
    car.command(10.3, 1.0)
    assert car.run_to_standstill() == pytest.approx(10.3 + V15 / 8)
    assert car.position == pytest.approx(V15 * 0.3 + V15 ** 2 / 16)
    assert (car.braking_began, car.full_braking_began) == (10.3, 10.3)
    assert car.speed == 0.0
    car.advance(20.0)  # at rest it stays there
    assert car.position == pytest.approx(V15 * 0.3 + V15 ** 2 / 16) and car.speed == 0.0


def test_a_controlled_phase_then_full_brake_piecewise() -> None:
    car = Vehicle(V15)
    car.command(0.0, 0.3)
    car.command(0.2, 1.0)
    car.advance(0.2)
    assert car.speed == pytest.approx(V15 - 2.4 * 0.2)
    assert car.position == pytest.approx(V15 * 0.2 - 2.4 * 0.04 / 2)
    v1, x1 = car.speed, car.position
    assert car.run_to_standstill() == pytest.approx(0.2 + v1 / 8)
    assert car.position == pytest.approx(x1 + v1 ** 2 / 16)
    assert (car.braking_began, car.full_braking_began) == (0.0, 0.2)


def test_the_actuator_delay_shifts_every_command() -> None:
    car = Vehicle(V15, params=VehicleParams(actuator_delay=0.2))
    car.command(0.0, 1.0)
    car.advance(0.1)
    assert car.speed == V15 and car.share == 0.0  # the brake has not acted yet
    assert car.run_to_standstill() == pytest.approx(0.2 + V15 / 8)
    assert car.position == pytest.approx(stopping_distance(V15, delay=0.2))


def test_released_it_keeps_rolling_and_at_rest_it_stays() -> None:
    car = Vehicle(V15, share=0.0)
    car.advance(2.0)
    assert car.position == pytest.approx(2 * V15) and car.run_to_standstill() is None
    rest = Vehicle(0.0, share=0.0)
    rest.command(1.0, 0.0)
    assert rest.run_to_standstill() == 0.0 and rest.position == 0.0
    assert rest.braking_began is None


def test_bad_inputs_are_refused() -> None:
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            Vehicle(bad)
    with pytest.raises(ValueError):
        VehicleParams(emergency_decel=0.0)
    with pytest.raises(ValueError):
        VehicleParams(actuator_delay=-0.1)
    car = Vehicle(1.0, 5.0)
    for share in (-0.1, 1.1, math.nan):
        with pytest.raises(ValueError):
            car.command(6.0, share)
    with pytest.raises(ValueError):
        car.command(4.0, 1.0)  # the past
    car.command(6.0, 0.5)
    with pytest.raises(ValueError):
        car.command(5.5, 1.0)  # out of order
    with pytest.raises(ValueError):
        car.advance(4.0)


# ------------------------------------------------------------------------------ properties

# a brake schedule: (seconds after the previous command, share), the last one braking
shares = st.floats(0.0, 1.0)
schedules = st.lists(st.tuples(st.floats(0.0, 0.5), shares), max_size=12).flatmap(
    lambda head: st.tuples(st.just(head), st.tuples(st.floats(0.0, 0.5), st.floats(0.01, 1.0))))
speeds = st.floats(0.0, 40.0)
delays = st.floats(0.0, 0.5)


def distance(speed: float, schedule: list[tuple[float, float]], delay: float = 0.0,
             initial: float = 0.0) -> float:
    car = Vehicle(speed, share=initial, params=VehicleParams(actuator_delay=delay))
    t = 0.0
    for gap, share in schedule:
        t += gap
        car.command(t, share)
    assert car.run_to_standstill() is not None
    return car.position


def flatten(sched: tuple[list[tuple[float, float]], tuple[float, float]]
            ) -> list[tuple[float, float]]:
    head, last = sched
    return [*head, last]


@given(speeds, schedules, delays)
def test_distance_is_never_negative_and_speed_never_below_zero(
        speed: float, sched: tuple[list[tuple[float, float]], tuple[float, float]],
        delay: float) -> None:
    car = Vehicle(speed, params=VehicleParams(actuator_delay=delay))
    t, x = 0.0, 0.0
    for gap, share in flatten(sched):
        t += gap
        car.command(t, share)
        car.advance(t)
        assert car.speed >= 0.0 and car.position >= x  # it never rolls back
        x = car.position
    assert car.run_to_standstill() is not None
    assert car.position >= 0.0 and math.isfinite(car.position)
    # at most full speed until the last command acts, then at least its share
    bound = speed * (t + delay) + stopping_distance(speed, share=flatten(sched)[-1][1])
    assert car.position <= bound + 1e-9


@given(speeds, st.lists(st.tuples(st.floats(0.0, 0.5), shares), max_size=12),
       st.floats(0.01, 1.0), delays, delays)
def test_more_delay_never_less_distance(speed: float, head: list[tuple[float, float]],
                                        last: float, d1: float, d2: float) -> None:
    # the commands of a stop only grow stronger (release, controlled, emergency): a later
    # brake can only brake less at every moment
    raw = [*head, (0.0, last)]
    ordered = sorted(s for _, s in raw)
    schedule = [(gap, s) for (gap, _), s in zip(raw, ordered, strict=True)]
    short, long = sorted((d1, d2))
    assert distance(speed, schedule, long) >= distance(speed, schedule, short) - 1e-9


@given(speeds, schedules, st.lists(st.floats(0.0, 1.0), min_size=13, max_size=13), delays)
def test_a_higher_share_never_more_distance(
        speed: float, sched: tuple[list[tuple[float, float]], tuple[float, float]],
        boosts: list[float], delay: float) -> None:
    schedule = flatten(sched)
    stronger = [(gap, min(1.0, s + b)) for (gap, s), b in zip(schedule, boosts, strict=False)]
    assert distance(speed, stronger, delay) <= distance(speed, schedule, delay) + 1e-9
