"""The parts of ``estop demo`` without a daemon: the live car behind the bus, the unit's state
lines and their match to the frames, the checks that fail the demo when its story did not
happen, and the report's refusal to give a figure when can-log lines were lost. Fast: no
process, no socket, no sleep."""

from __future__ import annotations

import io
import math

import pytest

from estop.demo.bus import BusWatch, Change
from estop.demo.car import DRIVE_RAMP_S, LiveCar
from estop.demo.checks import check
from estop.demo.report import match_causes, write_report
from estop.demo.result import BurstMeasure, Result, Settings, StopMeasure
from estop.demo.view import View
from estop.model.rollout import roll_out, timed_frames
from estop.model.vehicle import kmh
from estop.protocol import can, canlog
from estop.protocol.can import Reason, State
from estop.unit.events import state_changes

CRUISE = kmh(15)
A_E = 8.0  # the model's default emergency deceleration
T0 = 1_700_000_000.0


class Bus:
    """ESTOP_BRAKE frames every 10 ms with a proper alive counter, into a car and a watch."""

    def __init__(self, car: LiveCar | None = None) -> None:
        self.watch = BusWatch(car)
        self.t = T0
        self.ctr = 0

    def run(self, seconds: float, state: int, reason: int = 0, *, gap: float = 0.01) -> None:
        for _ in range(round(seconds / gap)):
            self.t += gap
            data = can.BrakeFrame.for_state(state, reason, counter=self.ctr).encode()
            self.ctr = (self.ctr + 1) % can.COUNTER_MODULO
            self.watch.take(canlog.CanLogRecord.at(self.t, "estop", can.BRAKE_ID, data))


# --------------------------------------------------------------------------- the live car

def test_the_car_drives_up_to_the_demo_speed_only_while_driven_and_released() -> None:
    car = LiveCar(CRUISE)
    bus = Bus(car)
    bus.run(0.2, State.STOPPED, Reason.BOOT)
    car.driving = True
    bus.run(0.3, State.STOPPED, Reason.BOOT)
    assert car.at_rest and car.position == 0.0  # braked: gas does nothing
    bus.run(0.5, State.ARMED)
    assert car.speed == pytest.approx(CRUISE * (0.5 - 0.01) / DRIVE_RAMP_S, rel=0.03)
    bus.run(1.0, State.ARMED)
    assert car.speed == pytest.approx(CRUISE)
    x = car.position
    car.driving = False
    bus.run(0.5, State.ARMED)  # released, no gas: the model keeps its speed
    assert car.speed == pytest.approx(CRUISE)
    assert car.position - x == pytest.approx(CRUISE * 0.5, abs=1e-5)


def test_the_car_slows_at_the_level_then_stops_at_full_braking() -> None:
    car = LiveCar(CRUISE)
    bus = Bus(car)
    car.driving = True
    bus.run(1.5, State.ARMED)
    car.watch_low()
    bus.run(0.2, State.SLOWING)
    slowed = CRUISE - 0.3 * A_E * 0.2
    assert car.speed == pytest.approx(slowed, abs=0.3 * A_E * 0.011)
    assert car.share == pytest.approx(0.3)
    bus.run(0.2, State.ARMED)  # link back: driven up again
    assert car.low == pytest.approx(slowed, abs=0.03) and car.speed > car.low
    bus.run(1.0, State.ARMED)
    x = car.position
    bus.run(1.0, State.STOPPED, Reason.LIFT)
    assert car.at_rest
    assert car.position - x == pytest.approx(CRUISE ** 2 / (2 * A_E), abs=CRUISE * 0.011)


def test_the_car_brakes_by_itself_when_the_bus_falls_silent() -> None:
    car = LiveCar(CRUISE)
    bus = Bus(car)
    car.driving = True
    bus.run(1.5, State.ARMED)
    x, t_last = car.position, bus.t
    bus.run(1.0, State.ARMED, gap=1.0)  # the next frame comes a second later
    # full braking from 50 ms after the last frame, then the frame releases a car at rest
    assert car.at_rest
    assert car.position - x == pytest.approx(CRUISE * 0.05 + CRUISE ** 2 / (2 * A_E), abs=1e-5)
    assert bus.t - t_last == pytest.approx(1.0)


def test_the_live_car_and_the_roll_out_agree_on_a_stop() -> None:
    """The live view and the stop table tell the same distance for the same frames."""
    car = LiveCar(CRUISE)
    bus = Bus(car)
    car.driving = True
    bus.run(1.5, State.ARMED)
    moment, x = bus.t, car.position
    bus.run(0.2, State.SLOWING)
    bus.run(1.0, State.STOPPED, Reason.UDP_TIMEOUT)
    out = roll_out(timed_frames(bus.watch.records), moment, CRUISE)
    assert car.position - x == pytest.approx(out.distance, abs=1e-5)  # stamps in whole us


def test_the_car_wants_a_speed() -> None:
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            LiveCar(bad)


# ---------------------------------------------------------------- the unit's account

LOG = """\
estopd 100.000000 start udp=127.0.0.1:1 tcp=127.0.0.1:2 session=0x1
estopd 101.000000 state STOPPED->ARMED reason=none src=127.0.0.1:4 cause=release
estopd 102.000000 state ARMED->SLOWING reason=none src=- cause=udp_silence
estopd 102.260000 state SLOWING->ARMED reason=none src=127.0.0.1:5 cause=link_back
estopd 103.000000 client_open slot=1 src=127.0.0.1:9
estopd 104.000000 state ARMED->STOPPED reason=lift src=127.0.0.1:5 cause=lift_datagram
"""


def test_state_lines_are_read_with_their_cause() -> None:
    lines = state_changes(LOG.splitlines())
    assert [(ln.frm, ln.to, ln.reason, ln.cause) for ln in lines] == [
        ("STOPPED", "ARMED", "none", "release"), ("ARMED", "SLOWING", "none", "udp_silence"),
        ("SLOWING", "ARMED", "none", "link_back"), ("ARMED", "STOPPED", "lift", "lift_datagram")]
    assert lines[1].t_mono == 102.0 and lines[3].src == "127.0.0.1:5"


def _change(t: float, state: int, reason: int = 0, flags_only: bool = False) -> Change:
    return Change(t, can.BrakeFrame.for_state(state, reason), flags_only)


def test_each_change_on_the_bus_gets_the_cause_of_its_own_state_line() -> None:
    clock = T0 - 100.0  # realtime - monotonic
    changes = [_change(T0, State.STOPPED, Reason.BOOT), _change(T0 + 1.0001, State.ARMED),
               _change(T0 + 2.0001, State.SLOWING), _change(T0 + 2.1, State.SLOWING, 0, True),
               _change(T0 + 2.2601, State.ARMED), _change(T0 + 4.0001, State.STOPPED, Reason.LIFT)]
    causes = match_causes(changes, state_changes(LOG.splitlines()), clock)
    assert [causes[id(c)].cause if id(c) in causes else None for c in changes] == [
        None, "release", "udp_silence", None, "link_back", "lift_datagram"]
    # a line too far from its frame (a clock taken wrong) is no match
    assert match_causes(changes, state_changes(LOG.splitlines()), clock + 5.0) == {}


# ----------------------------------------------------------------------------- the checks

def _story() -> Result:
    """A result in which the whole story happened."""
    res = Result(Settings())
    res.boot_release_nak = 2
    res.lift = StopMeasure("the finger lifts", "the lift", T0,
                           stop=_change(T0 + 0.0001, State.STOPPED, Reason.LIFT))
    res.lift_datagrams = 3
    res.v2 = StopMeasure("the same lift, v2 unit", "the lift", T0, unit="v2",
                         stop=_change(T0 + 0.2, State.STOPPED, Reason.UDP_TIMEOUT))
    res.forged_release_nak = 4
    res.burst = BurstMeasure(T0 + 3.0, T0 + 3.4, T0 + 2.999, 20,
                             slowing=_change(T0 + 3.2, State.SLOWING),
                             armed=_change(T0 + 3.46, State.ARMED))
    slowing = _change(T0 + 5.2, State.SLOWING)
    res.loss = StopMeasure("the Wi-Fi dies", "the last packet", T0 + 5.0, slowing=slowing,
                           stop=_change(T0 + 6.0, State.STOPPED, Reason.UDP_TIMEOUT),
                           between=[slowing])
    res.datagram = StopMeasure("the stop datagram", "its sending", T0 + 8.0,
                               stop=_change(T0 + 8.0001, State.STOPPED, Reason.TCP_STOP))
    res.button = StopMeasure("the stop button", "the press", T0 + 10.0,
                             stop=_change(T0 + 10.0001, State.STOPPED, Reason.TCP_STOP))
    res.latched_release_nak = 3
    return res


def _stopped_bus() -> BusWatch:
    bus = Bus()
    bus.run(0.1, State.STOPPED, Reason.TCP_STOP)
    return bus.watch


def test_a_whole_story_has_no_problem() -> None:
    assert check(_story(), _stopped_bus(), 0, -15) == []


def test_a_lift_the_unit_did_not_stop_on_is_named() -> None:
    res = _story()
    assert res.lift is not None
    res.lift.between = [_change(T0 + 0.2, State.SLOWING)]
    res.lift.stop = _change(T0 + 1.0, State.STOPPED, Reason.UDP_TIMEOUT)
    res.lift_datagrams = 1
    assert check(res, _stopped_bus(), 0) == [
        "the finger lift stopped the car with reason udp_timeout, not lift",
        "the remote sent 1 lift datagrams, not 3",
        "the unit slowed before the lift stopped it: it waited for the silence"]
    res.lift.stop = None
    assert check(res, _stopped_bus(), 0)[0] == "no stop after the finger lift"


def test_a_burst_that_latched_a_stop_or_did_not_slow_is_named() -> None:
    res = _story()
    b = res.burst
    assert b is not None
    b.stops = [_change(T0 + 4.0, State.STOPPED, Reason.UDP_TIMEOUT)]
    assert check(res, _stopped_bus(), 0) == [
        "the burst of 400 ms (shorter than the timeout) latched a stop, reason udp_timeout"]
    b.stops, b.armed = [], None
    assert check(res, _stopped_bus(), 0) == [
        "the unit did not come back to ARMED after the burst of 400 ms"]
    b.slowing = None
    assert check(res, _stopped_bus(), 0) == [
        "the burst of 400 ms (longer than the slow time) did not slow the car: no SLOWING"]


def test_a_loss_that_did_not_slow_first_or_was_kept_alive_is_named() -> None:
    res = _story()
    m = res.loss
    assert m is not None
    m.slowing, m.between = None, []
    assert check(res, _stopped_bus(), 0) == [
        "the loss of the link did not slow the car first: no SLOWING before the stop"]
    m.slowing = _change(T0 + 5.2, State.SLOWING)
    m.between = [m.slowing, _change(T0 + 5.3, State.ARMED), _change(T0 + 5.6, State.SLOWING)]
    assert check(res, _stopped_bus(), 0) == [
        "the unit went back to ARMED while the link was down: the attacker's heartbeats "
        "counted"]
    m.stop = _change(T0 + 5.5, State.STOPPED, Reason.TCP_STOP)
    assert check(res, _stopped_bus(), 0)[0] == (
        "the loss of the link stopped the car with reason tcp_stop, not udp_timeout")


def test_refusals_stops_and_the_end_are_checked() -> None:
    res = _story()
    res.boot_release_nak, res.forged_release_nak, res.latched_release_nak = 0, 2, 4
    assert res.v2 is not None and res.datagram is not None
    res.v2.stop = _change(T0 + 0.01, State.STOPPED, Reason.LIFT)
    res.datagram.stop = None
    assert check(res, _stopped_bus(), 1, 2) == [
        "the RELEASE before any packet was not refused with NAK 2 (no_live_link): got an ACK",
        "the lift on the version-2 unit stopped the car with reason lift, not udp_timeout",
        "the attacker's forged RELEASE was not refused with NAK 4 (not_authenticated): got "
        "NAK 2",
        "no stop after the attacker's stop datagram",
        "the RELEASE with the gas pressed was not refused with NAK 3 (not_neutral): got NAK 4",
        "estopd ended abnormally (exit code 1)",
        "the version-2 estopd ended abnormally (exit code 2)"]
    short = Result(Settings())
    armed = Bus()
    armed.run(0.1, State.ARMED)
    assert check(short, armed.watch, 0) == [
        "the story did not reach its end",
        "the unit's last frame did not request the emergency brake"]


# ------------------------------------------------------------------------------ settings

@pytest.mark.parametrize(("slow", "timeout"), [(200, 1000), (1, 201), (100, 300), (500, 5000)])
def test_the_burst_lies_well_between_s_and_t(slow: int, timeout: int) -> None:
    s = Settings(slow, timeout)
    assert s.slow_ms + 100 <= s.burst_ms <= s.timeout_ms - 100
    assert s.unit_args() == ["--slow-ms", str(slow), "--slow-level", "30"]


@pytest.mark.parametrize(("slow", "timeout"), [(0, 1000), (200, 399), (1000, 200), (1, 60001)])
def test_settings_without_room_for_the_story_are_refused(slow: int, timeout: int) -> None:
    with pytest.raises(ValueError):
        Settings(slow, timeout)


# ------------------------------------------------------------------------------ the report

def test_no_figure_for_a_stop_with_lost_lines() -> None:
    res = _story()
    assert res.lift is not None and res.loss is not None
    res.lift.lost = 3
    bus = _stopped_bus()
    view = View(out=io.StringIO(), live=False, t0=T0, watch=bus, car=LiveCar(CRUISE))
    out = io.StringIO()
    write_report(out, view, res, {})
    text = out.getvalue()
    assert "the finger lifts, from the lift" in text
    lift_row = next(ln for ln in text.splitlines() if "the finger lifts, from" in ln)
    assert "not measured: 3 can-log lines lost" in lift_row and " m in " not in lift_row
    assert "a figure is only given when no can-log line was lost" in text
    assert "The lift: the car stood still" not in text  # no comparison from a lost figure
