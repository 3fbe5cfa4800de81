"""The gamepad remote's event mapping (estop.remote.gamepadmap), pure logic: no device needed.

The same remote with a real (virtual) device: tests/vm/test_gamepad_uinput.py.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from estop.remote.gamepadmap import (
    ABS_NAMES,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    KEY_NAMES,
    SYN_DROPPED,
    SYN_REPORT,
    Act,
    Action,
    AxisRange,
    PadLayout,
    PadMapper,
    choose_deadman,
    parse_control,
)

X, RY, Z = ABS_NAMES["ABS_X"], ABS_NAMES["ABS_RY"], ABS_NAMES["ABS_Z"]
STICK = AxisRange(-32768, 32767, 128)
TRIGGER = AxisRange(0, 1023)
AXES = {X: STICK, RY: STICK, Z: TRIGGER, ABS_NAMES["ABS_HAT0X"]: AxisRange(-1, 1),
        ABS_NAMES["ABS_HAT0Y"]: AxisRange(-1, 1)}


def mapper(deadman: str = "ABS_Z", start_released: bool = True) -> PadMapper:
    m = PadMapper(PadLayout(deadman=parse_control(deadman), axes=AXES))
    if start_released:
        m.sync(set(), {Z: 0, X: 0, RY: 0})
    return m


def acts(actions: list[Action]) -> list[Act]:
    return [a.act for a in actions]


def test_event_codes_are_the_kernels() -> None:
    ecodes = pytest.importorskip("evdev.ecodes", reason="python-evdev not installed")
    for name, code in {**ABS_NAMES, **KEY_NAMES}.items():
        assert ecodes.ecodes[name] == code, name
    assert (EV_SYN, EV_KEY, EV_ABS) == (ecodes.EV_SYN, ecodes.EV_KEY, ecodes.EV_ABS)
    assert (SYN_REPORT, SYN_DROPPED) == (ecodes.SYN_REPORT, ecodes.SYN_DROPPED)


def test_analog_trigger_holds_from_half_way_and_lifts_below_the_release_level() -> None:
    m = mapper()
    assert m.event(EV_ABS, Z, 400) == []  # 39 %: not yet
    assert acts(m.event(EV_ABS, Z, 600)) == [Act.HOLD]
    assert m.event(EV_ABS, Z, 1023) == []  # still held: no second HOLD
    assert m.event(EV_ABS, Z, 450) == []  # 44 %: within the hysteresis, still held
    assert acts(m.event(EV_ABS, Z, 300)) == [Act.LIFT]
    assert m.event(EV_ABS, Z, 0) == []  # released once: one LIFT


def test_button_deadman_and_autorepeat() -> None:
    m = mapper("BTN_TL")
    tl = KEY_NAMES["BTN_TL"]
    assert acts(m.event(EV_KEY, tl, 1)) == [Act.HOLD]
    assert m.event(EV_KEY, tl, 2) == []  # autorepeat of a held button
    assert acts(m.event(EV_KEY, tl, 0)) == [Act.LIFT]


def test_deadman_held_at_start_must_be_let_go_first() -> None:
    m = mapper(start_released=False)
    assert acts(m.sync(set(), {Z: 1023, X: 0, RY: 0})) == [Act.CONTROL, Act.CONTROL]
    assert not m.armed and not m.held
    assert m.event(EV_ABS, Z, 1000) == []  # still the same press: nothing
    assert m.event(EV_ABS, Z, 0) == []  # let go: now armed, nothing to lift
    assert acts(m.event(EV_ABS, Z, 1023)) == [Act.HOLD]


def test_lost_events_resync_lifts_a_deadman_no_longer_held() -> None:
    m = mapper()
    m.event(EV_ABS, Z, 1023)
    assert acts(m.event(EV_SYN, SYN_DROPPED, 0)) == [Act.RESYNC]
    assert m.event(EV_SYN, SYN_REPORT, 0) == []
    got = m.sync(set(), {Z: 0, X: 0, RY: 0})
    assert acts(got)[-1] is Act.LIFT


def test_sticks_steer_and_give_gas_and_brake_with_a_dead_zone() -> None:
    m = mapper()
    assert m.event(EV_ABS, X, 32767) == [Action(Act.CONTROL, {"steering": 1.0})]
    assert m.event(EV_ABS, X, -32768) == [Action(Act.CONTROL, {"steering": -1.0})]
    assert m.event(EV_ABS, X, 500) == [Action(Act.CONTROL, {"steering": 0.0})]  # dead zone
    assert m.event(EV_ABS, RY, -32768) == [Action(Act.CONTROL, {"gas_brake": 1.0})]  # up: gas
    assert m.event(EV_ABS, RY, 32767) == [Action(Act.CONTROL, {"gas_brake": -1.0})]
    half = m.event(EV_ABS, RY, 16383)[0].fields["gas_brake"]
    assert -0.51 < half < -0.49


def test_axis_range_clamps_and_handles_a_degenerate_axis() -> None:
    assert STICK.stick(40000) == 1.0 and STICK.stick(-40000) == -1.0
    assert AxisRange(5, 5).stick(5) == 0.0 and AxisRange(5, 5).trigger(5) == 0.0
    assert TRIGGER.trigger(2000) == 1.0 and TRIGGER.trigger(-3) == 0.0


def test_buttons_act_on_the_press_only() -> None:
    m = mapper()
    for name, act in (("BTN_EAST", Act.STOP), ("BTN_START", Act.RELEASE),
                      ("BTN_SELECT", Act.STATUS), ("BTN_NORTH", Act.NEXT_GEAR)):
        assert acts(m.event(EV_KEY, KEY_NAMES[name], 1)) == [act]
        assert m.event(EV_KEY, KEY_NAMES[name], 2) == []
        assert m.event(EV_KEY, KEY_NAMES[name], 0) == []
    west = KEY_NAMES["BTN_WEST"]
    assert m.event(EV_KEY, west, 1) == [Action(Act.CONTROL, {"horn": 1})]
    assert m.event(EV_KEY, west, 2) == []
    assert m.event(EV_KEY, west, 0) == [Action(Act.CONTROL, {"horn": 0})]


def test_dpad_sets_the_turn_signal() -> None:
    m = mapper()
    hx, hy = ABS_NAMES["ABS_HAT0X"], ABS_NAMES["ABS_HAT0Y"]
    assert m.event(EV_ABS, hx, -1) == [Action(Act.CONTROL, {"turn_signal": 1})]
    assert m.event(EV_ABS, hx, 0) == []  # back to the centre: the signal stays
    assert m.event(EV_ABS, hx, 1) == [Action(Act.CONTROL, {"turn_signal": 2})]
    assert m.event(EV_ABS, hy, 1) == [Action(Act.CONTROL, {"turn_signal": 0})]


def test_choose_deadman_prefers_the_analog_trigger() -> None:
    keys = {KEY_NAMES["BTN_TL"], KEY_NAMES["BTN_TL2"]}
    assert choose_deadman(keys, AXES).name == "ABS_Z"
    assert choose_deadman(keys, {X: STICK}).name == "BTN_TL2"
    assert choose_deadman({KEY_NAMES["BTN_TL"]}, {X: STICK}).name == "BTN_TL"
    assert choose_deadman(keys, AXES, "btn_tl").name == "BTN_TL"
    with pytest.raises(ValueError, match="no BTN_TR"):
        choose_deadman(keys, AXES, "BTN_TR")
    with pytest.raises(ValueError, match="unknown control 'KEY_A'"):
        parse_control("KEY_A")


def _estop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "estop", *args], capture_output=True,
                          text=True, timeout=30, stdin=subprocess.DEVNULL, check=False)


def test_cli_missing_device_is_one_line_exit_3() -> None:
    pytest.importorskip("evdev", reason="python-evdev not installed")
    r = _estop("remote", "--host", "127.0.0.1", "--gamepad", "/dev/input/event-none")
    assert r.returncode == 3, r
    assert r.stderr.count("\n") == 1 and "cannot open /dev/input/event-none" in r.stderr
    assert "Traceback" not in r.stderr


def test_cli_gamepad_and_script_exclude_each_other() -> None:
    r = _estop("remote", "--host", "127.0.0.1", "--gamepad", "--script", "hold")
    assert r.returncode == 2 and "not allowed with" in r.stderr


def test_cli_no_pad_found_is_one_line_exit_3() -> None:
    pytest.importorskip("evdev", reason="python-evdev not installed")
    if any(Path("/dev/input").glob("event*")):
        pytest.skip("this machine has input devices; the VM test finds a pad among them")
    r = _estop("remote", "--host", "127.0.0.1", "--gamepad")
    assert r.returncode == 3, r
    assert r.stderr.count("\n") == 1 and "no game controller found" in r.stderr


def test_cli_deadman_needs_gamepad() -> None:
    r = _estop("remote", "--host", "127.0.0.1", "--deadman", "BTN_TL", "--script", "hold")
    assert r.returncode == 2 and "--deadman: only with --gamepad" in r.stderr, r
