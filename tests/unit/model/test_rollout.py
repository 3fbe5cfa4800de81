"""Roll-out from CAN frames (estop.model.rollout): ESTOP_BRAKE frames through the brake controller
emulation into the vehicle model, checked against the closed forms of docs/VEHICLE.md."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from estop.model.rollout import RollOutReplay, TimedFrame, roll_out, timed_frames
from estop.model.vehicle import VehicleParams, kmh
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.canlog import CanLogRecord
from estop.protocol.crc import e2e_crc8

V = kmh(15)
A = 8.0


class Bus:
    """ESTOP_BRAKE frames every 10 ms, with the alive counter in order."""

    def __init__(self) -> None:
        self.frames: list[TimedFrame] = []
        self.t = 0.0
        self.counter = 0

    def send(self, data: bytes) -> None:
        self.frames.append((round(self.t, 6), 0x050, data))
        self.t += 0.010
        self.counter = (self.counter + 1) % 15

    def state(self, n: int, state: int, reason: int = 0, level: int = 30) -> Bus:
        for _ in range(n):
            self.send(BrakeFrame.for_state(state, reason, 0, self.counter,
                                           slow_level=level).encode())
        return self

    def raw(self, n: int, brake_request: int) -> Bus:
        """Frames from the unit (right CRC, counter in order) with any brake_request."""
        for _ in range(n):
            payload = bytes((brake_request, 0, 1, 0, 0, 0, self.counter))
            self.send(payload + bytes((e2e_crc8(0x0E57, payload),)))
        return self


ARMED, STOPPED, SLOWING = 1, 0, 2


def test_constant_speed_then_a_full_brake() -> None:
    # the finger lifts at 0.200; the unit's STOPPED (reason lift) frame comes at 0.500
    bus = Bus().state(50, ARMED).state(100, STOPPED, reason=5)
    out = roll_out(bus.frames, 0.200, V)
    assert out.braking_began == out.full_braking_began == pytest.approx(0.500)
    assert out.reaction_time == pytest.approx(0.300)
    assert out.distance_before_braking == pytest.approx(V * 0.3)
    assert out.distance == pytest.approx(V * 0.3 + V * V / (2 * A))
    assert out.standstill == pytest.approx(0.5 + V / A)
    assert out.time_to_standstill == pytest.approx(0.3 + V / A)
    assert not out.beyond_record
    assert out.summary() == ("at 15.0 km/h: braking began +300.0 ms, standstill +820.8 ms, "
                             "rolled 2.335 m")
    # 200 ms of actuator delay: 0.83 m more
    late = roll_out(bus.frames, 0.200, V, params=VehicleParams(actuator_delay=0.2))
    assert late.braking_began == pytest.approx(0.700)
    assert late.distance - out.distance == pytest.approx(0.2 * V)


def test_a_slowing_phase_at_30_percent_then_stopped() -> None:
    # last packet at 0.0; SLOWING (level 30) from 0.2, STOPPED (udp timeout) from 0.4
    bus = Bus().state(20, ARMED).state(20, SLOWING, level=30).state(100, STOPPED, reason=3)
    out = roll_out(bus.frames, 0.0, V)
    a_slow = 0.3 * A
    v1 = V - a_slow * 0.2
    x1 = V * 0.2 + V * 0.2 - a_slow * 0.2 ** 2 / 2  # 0.2 s released, 0.2 s at 30 %
    assert out.braking_began == pytest.approx(0.2)
    assert out.full_braking_began == pytest.approx(0.4)
    assert out.distance == pytest.approx(x1 + v1 * v1 / (2 * A))
    assert out.standstill == pytest.approx(0.4 + v1 / A)


def test_the_50_ms_silence_rule_brakes() -> None:
    bus = Bus().state(31, ARMED)  # the last ESTOP_BRAKE at 0.300, then the unit is silent
    bus.frames.append((0.320, 0x051, StatusFrame(1, 0, 0, 0, 5, 0).encode()))  # other frames
    out = roll_out(bus.frames, 0.100, V)
    assert out.braking_began == pytest.approx(0.350)  # 50 ms after the last good one
    assert out.distance == pytest.approx(V * 0.25 + V * V / (2 * A))
    assert out.record_end == pytest.approx(0.320) and out.beyond_record
    assert "(after the end of the record: silence)" in out.summary()
    # a gap inside the record: braking from 50 ms into it (the unit's later frames are
    # accepted again, but the car is at rest by then)
    gap = Bus().state(11, ARMED)
    gap.t += 2.0
    gap.state(5, ARMED)
    inside = roll_out(gap.frames, 0.0, V)
    assert inside.braking_began == pytest.approx(0.150) and not inside.beyond_record
    assert inside.distance == pytest.approx(V * 0.15 + V * V / (2 * A))


@pytest.mark.parametrize("unknown", [3, 255])
def test_an_unknown_brake_request_is_an_emergency_brake_at_once(unknown: int) -> None:
    # ARMED, then the unit sends brake_request 3 (or 255) from 0.300 on: the car brakes fully
    # at 0.300, neither 50 ms later (a rejected frame taken as silence) nor never (a release)
    bus = Bus().state(30, ARMED).raw(100, unknown)
    out = roll_out(bus.frames, 0.0, V)
    assert out.braking_began == out.full_braking_began == pytest.approx(0.300)
    assert out.distance == pytest.approx(V * 0.3 + V * V / (2 * A))


def test_what_the_record_does_not_show_is_taken_as_released() -> None:
    # the record starts at 1.0, after the moment: released until then (the cautious side of
    # a distance), then ARMED, then braking 50 ms after the last frame (1.49)
    bus = Bus()
    bus.t = 1.0
    bus.state(50, ARMED)
    early = roll_out(bus.frames, 0.5, V)
    assert early.braking_began == pytest.approx(1.54)
    assert early.distance == pytest.approx(V * 1.04 + V * V / (2 * A))
    # a record whose ESTOP_BRAKE frames start late: silence from the record's start brakes
    late = [(0.0, 0x051, StatusFrame(1, 0, 0, 0, 5, 0).encode()), *Bus().state(1, ARMED).frames]
    late[1] = (0.2, *late[1][1:])
    out = roll_out(late, 0.0, V)
    assert out.braking_began == pytest.approx(0.050)
    # no frame at all: silence is a failure, counted from the moment
    nothing = roll_out([], 3.0, V)
    assert nothing.braking_began == pytest.approx(3.05) and nothing.record_end is None
    assert nothing.beyond_record
    # with an actuator delay the commands before the record are not seen either: released
    delayed = roll_out(Bus().state(30, STOPPED, reason=5).frames, 0.0, V,
                       params=VehicleParams(actuator_delay=0.2))
    assert delayed.braking_began == pytest.approx(0.2)
    rest = roll_out(bus.frames, 1.2, 0.0)
    assert (rest.distance, rest.braking_began, rest.standstill) == (0.0, None, 1.2)
    assert rest.summary().startswith("at 0.0 km/h: at rest, standstill +0.0 ms")


@pytest.mark.parametrize("unknown", [3, 255])
def test_a_record_that_begins_with_an_unknown_brake_request_brakes_at_once(
        unknown: int) -> None:
    out = roll_out(Bus().raw(20, unknown).frames, 0.0, V)
    assert out.braking_began == 0.0 and out.distance == pytest.approx(V * V / (2 * A))


def test_the_replay_is_the_same_one_frame_at_a_time_and_reads_can_logs() -> None:
    bus = Bus().state(30, ARMED).state(10, SLOWING, level=50).state(30, STOPPED, reason=5)
    records = [CanLogRecord.at(t, "vcan0", can_id, data) for t, can_id, data in bus.frames]
    records.append(CanLogRecord.at(0.05, "vcan0", 0x1ABCDEF, b"", extended=True))
    replay = RollOutReplay(0.1, V)
    for t, can_id, data in bus.frames:
        replay.feed(t, can_id, data)
    assert replay.result() == roll_out(bus.frames, 0.1, V)
    from_log = roll_out(timed_frames(records[:-1]), 0.1, V)
    assert from_log.distance == pytest.approx(roll_out(bus.frames, 0.1, V).distance)
    assert len(list(timed_frames(records))) == len(bus.frames)  # extended IDs left out


# ------------------------------------------------------------------------------ properties

def frame_stream(kinds: list[tuple[int, int]]) -> list[TimedFrame]:
    """A stream of ARMED / SLOWING / STOPPED / unknown-request / corrupt frames."""
    bus = Bus()
    for kind, gap_ms in kinds:
        bus.t += gap_ms / 1000
        if kind == 0:
            bus.state(1, ARMED)
        elif kind == 1:
            bus.state(1, SLOWING, level=30)
        elif kind == 2:
            bus.state(1, STOPPED, reason=2)
        elif kind == 3:
            bus.raw(1, 3)
        else:
            bus.state(1, ARMED)
            t, can_id, data = bus.frames[-1]
            bus.frames[-1] = (t, can_id, data[:7] + bytes((data[7] ^ 0xFF,)))
    return bus.frames


streams = st.lists(st.tuples(st.integers(0, 4), st.integers(0, 80)), max_size=40)


@given(streams, st.floats(0.0, 0.5), st.floats(0.0, 30.0), st.floats(0.0, 0.3))
def test_every_replay_ends_at_rest_with_a_distance_that_is_never_negative(
        kinds: list[tuple[int, int]], moment: float, speed: float, delay: float) -> None:
    out = roll_out(frame_stream(kinds), moment, speed,
                   params=VehicleParams(actuator_delay=delay))
    assert math.isfinite(out.distance) and out.distance >= 0.0
    assert out.standstill >= moment
    if speed > 0:
        assert out.braking_began is not None and moment <= out.braking_began <= out.standstill
    # never more than rolling at full speed until the record's silence rule, then braking
    end = max([moment, *(t for t, _, _ in frame_stream(kinds))]) + 0.05 + delay
    assert out.distance <= speed * (end - moment) + speed * speed / (2 * A) + 1e-9


@given(st.lists(st.integers(0, 2), max_size=40).map(sorted), st.floats(0.0, 0.5),
       st.floats(0.1, 30.0), st.floats(0.0, 0.3), st.floats(0.0, 0.3))
def test_more_actuator_delay_never_less_distance(kinds: list[int], moment: float,
                                                 speed: float, d1: float, d2: float) -> None:
    # frames 10 ms apart whose command only grows (ARMED, SLOWING, STOPPED), as in a stop
    frames = frame_stream([(k, 0) for k in kinds])
    short, long = sorted((d1, d2))
    near = roll_out(frames, moment, speed, params=VehicleParams(actuator_delay=short))
    far = roll_out(frames, moment, speed, params=VehicleParams(actuator_delay=long))
    assert far.distance >= near.distance - 1e-9
