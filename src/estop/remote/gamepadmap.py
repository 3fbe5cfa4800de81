"""What a game controller's events mean to the remote: pure logic, no device, no evdev.

:class:`PadMapper` turns Linux input events (type, code, value, as evdev reports them) into
:class:`Action` s for :class:`estop.client.sender.Remote`:

- the **dead-man**: a trigger or button that must be held. Held: the remote sends control
  packets (``HOLD``); released: ``LIFT`` at once (the remote sends the lift datagrams). An
  analog trigger counts as held from half way (:data:`PRESS_AT`) and as released below
  :data:`RELEASE_BELOW` (a little hysteresis, so a finger resting at the threshold does not
  chatter). A dead-man already held when the pad is opened does nothing until it has been
  let go once: a stuck trigger or a pad on a seat never starts sending.
- the **sticks**: left stick across = steering (-1 left .. 1 right), right stick up/down =
  gas/brake (up = gas, down = brake); a dead zone around the centre (the axis's own ``flat``
  or :data:`DEAD_ZONE`, whichever is larger) reads as 0.
- the **buttons**: B (east) the stop button, START release, SELECT status, Y (north) next
  gear (park, reverse, neutral, drive), X (west) horn while held; the D-pad across sets the
  turn signal (left, right; down: off).
- ``SYN_DROPPED`` (the kernel's event buffer overflowed, events were lost): the mapper says
  ``RESYNC``, and the reader feeds it the device's current state (:meth:`PadMapper.sync`),
  which lifts if the dead-man is no longer held.

Event codes are the kernel's (``linux/input-event-codes.h``), written out here so that this
module runs without python-evdev (the tests check them against evdev where it is installed).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field

from estop.protocol.udp import TurnSignal

__all__ = [
    "ABS_NAMES",
    "BUTTON_ACTIONS",
    "DEAD_ZONE",
    "KEY_NAMES",
    "PRESS_AT",
    "RELEASE_BELOW",
    "Act",
    "Action",
    "AxisRange",
    "Control",
    "PadLayout",
    "PadMapper",
    "choose_deadman",
    "parse_control",
]

# event types and codes (linux/input-event-codes.h)
EV_SYN, EV_KEY, EV_ABS = 0x00, 0x01, 0x03
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_NAMES: Mapping[str, int] = {
    "ABS_X": 0x00, "ABS_Y": 0x01, "ABS_Z": 0x02, "ABS_RX": 0x03, "ABS_RY": 0x04,
    "ABS_RZ": 0x05, "ABS_GAS": 0x09, "ABS_BRAKE": 0x0A, "ABS_HAT0X": 0x10, "ABS_HAT0Y": 0x11,
}
KEY_NAMES: Mapping[str, int] = {
    "BTN_SOUTH": 0x130, "BTN_EAST": 0x131, "BTN_NORTH": 0x133, "BTN_WEST": 0x134,
    "BTN_TL": 0x136, "BTN_TR": 0x137, "BTN_TL2": 0x138, "BTN_TR2": 0x139,
    "BTN_SELECT": 0x13A, "BTN_START": 0x13B,
}

PRESS_AT = 0.5  # an analog dead-man counts as held from this far pressed (0..1)
RELEASE_BELOW = 0.4  # ... and as released below this
DEAD_ZONE = 0.05  # stick readings nearer the centre than this are 0

# The dead-man, in order of preference, by what the pad has: the left analog trigger, the
# left digital trigger, the left bumper.
DEADMAN_PREFERENCE = ("ABS_Z", "BTN_TL2", "BTN_TL")


class Act(enum.Enum):
    HOLD = "hold"
    LIFT = "lift"
    CONTROL = "control"  # new values of some control packet fields
    NEXT_GEAR = "next_gear"
    STOP = "stop"
    RELEASE = "release"
    STATUS = "status"
    RESYNC = "resync"  # events were lost: read the device's state and sync()


@dataclass(frozen=True, slots=True)
class Action:
    act: Act
    fields: Mapping[str, float | int] = field(default_factory=dict)


BUTTON_ACTIONS: Mapping[str, Act] = {
    "BTN_EAST": Act.STOP, "BTN_START": Act.RELEASE, "BTN_SELECT": Act.STATUS,
    "BTN_NORTH": Act.NEXT_GEAR,
}
_HORN = "BTN_WEST"


@dataclass(frozen=True, slots=True)
class Control:
    """One input of the pad: an EV_KEY button or an EV_ABS axis."""

    ev_type: int
    code: int
    name: str


def parse_control(name: str) -> Control:
    """``BTN_TL2`` or ``ABS_Z`` (the kernel's names, case-insensitive) as a :class:`Control`;
    ValueError with a one-line message for an unknown name."""
    upper = name.strip().upper()
    if upper in KEY_NAMES:
        return Control(EV_KEY, KEY_NAMES[upper], upper)
    if upper in ABS_NAMES:
        return Control(EV_ABS, ABS_NAMES[upper], upper)
    known = ", ".join([*KEY_NAMES, *ABS_NAMES])
    raise ValueError(f"unknown control {name!r} (one of {known})")


@dataclass(frozen=True, slots=True)
class AxisRange:
    """An absolute axis as the device reports it (evdev's absinfo)."""

    minimum: int
    maximum: int
    flat: int = 0

    def stick(self, value: int) -> float:
        """-1.0 .. 1.0 from the axis's range; 0 inside the dead zone."""
        span = self.maximum - self.minimum
        if span <= 0:
            return 0.0
        x = 2.0 * (value - self.minimum) / span - 1.0
        x = max(-1.0, min(1.0, x))
        zone = max(DEAD_ZONE, 2.0 * self.flat / span)
        if abs(x) < zone:
            return 0.0
        return round(x, 3)

    def trigger(self, value: int) -> float:
        """0.0 (not pressed) .. 1.0 (fully pressed)."""
        span = self.maximum - self.minimum
        if span <= 0:
            return 0.0
        return max(0.0, min(1.0, (value - self.minimum) / span))


@dataclass(frozen=True, slots=True)
class PadLayout:
    """Which inputs do what, and the ranges of the axes the pad has."""

    deadman: Control
    axes: Mapping[int, AxisRange]
    steering_axis: int = ABS_NAMES["ABS_X"]
    gas_axis: int = ABS_NAMES["ABS_RY"]  # up (negative) = gas

    def describe(self) -> str:
        return (f"dead-man {self.deadman.name} (hold to drive), left stick steering, right "
                f"stick gas/brake, B stop, START release, SELECT status, Y gear, X horn")


def choose_deadman(keys: set[int], axes: Mapping[int, AxisRange],
                   wanted: str | None = None) -> Control:
    """The dead-man: ``wanted`` (a control name) if given and the pad has it, else the first
    of :data:`DEADMAN_PREFERENCE` the pad has. ValueError when there is none."""
    names = [wanted] if wanted else list(DEADMAN_PREFERENCE)
    for name in names:
        control = parse_control(name)
        if control.ev_type == EV_KEY and control.code in keys:
            return control
        if control.ev_type == EV_ABS and control.code in axes:
            return control
    raise ValueError(f"the pad has no {' or '.join(names)} for the dead-man")


class PadMapper:
    """Events in, actions out; it remembers whether the dead-man is held and whether it has
    been let go since the pad was opened (only then may a press start sending)."""

    def __init__(self, layout: PadLayout) -> None:
        self.layout = layout
        self.held = False  # the dead-man, as last seen
        self.armed = False  # the dead-man has been seen released since the start
        self.horn = False
        self._keys = {code: name for name, code in KEY_NAMES.items()}

    # --------------------------------------------------------------------- state

    def sync(self, keys_down: set[int], abs_values: Mapping[int, int]) -> list[Action]:
        """The device's whole state (at the start, and after lost events): the sticks'
        values, and HOLD/LIFT as the dead-man now is."""
        actions = [self._axis_action(code, value) for code, value in abs_values.items()]
        out = [a for a in actions if a is not None]
        dm = self.layout.deadman
        if dm.ev_type == EV_KEY:
            pressed = dm.code in keys_down
        else:
            rng = self.layout.axes.get(dm.code)
            level = rng.trigger(abs_values.get(dm.code, rng.minimum)) if rng else 0.0
            pressed = level >= (RELEASE_BELOW if self.held else PRESS_AT)
        out.extend(self._deadman(pressed))
        return out

    def _deadman(self, pressed: bool) -> list[Action]:
        if not pressed:
            self.armed = True
            if self.held:
                self.held = False
                return [Action(Act.LIFT)]
            return []
        if self.held or not self.armed:
            return []
        self.held = True
        return [Action(Act.HOLD)]

    # -------------------------------------------------------------------- events

    def event(self, ev_type: int, code: int, value: int) -> list[Action]:
        """The actions one input event asks for (often none)."""
        if ev_type == EV_SYN:
            return [Action(Act.RESYNC)] if code == SYN_DROPPED else []
        dm = self.layout.deadman
        if ev_type == dm.ev_type and code == dm.code:
            if ev_type == EV_KEY:
                return self._deadman(value != 0)
            level = self.layout.axes[code].trigger(value)
            return self._deadman(level >= (RELEASE_BELOW if self.held else PRESS_AT))
        if ev_type == EV_KEY:
            return self._button(code, value)
        if ev_type == EV_ABS:
            action = self._axis_action(code, value)
            return [action] if action is not None else []
        return []

    def _button(self, code: int, value: int) -> list[Action]:
        name = self._keys.get(code)
        if name == _HORN:
            horn = value != 0
            if horn == self.horn:
                return []
            self.horn = horn
            return [Action(Act.CONTROL, {"horn": int(horn)})]
        if name is not None and name in BUTTON_ACTIONS and value == 1:  # the press only
            return [Action(BUTTON_ACTIONS[name])]
        return []

    def _axis_action(self, code: int, value: int) -> Action | None:
        layout = self.layout
        rng = layout.axes.get(code)
        if code == layout.steering_axis and rng is not None:
            return Action(Act.CONTROL, {"steering": rng.stick(value)})
        if code == layout.gas_axis and rng is not None:
            return Action(Act.CONTROL, {"gas_brake": -rng.stick(value) or 0.0})
        if code == ABS_NAMES["ABS_HAT0X"] and value != 0:  # D-pad left/right
            return Action(Act.CONTROL, {"turn_signal": int(TurnSignal.LEFT if value < 0
                                                           else TurnSignal.RIGHT)})
        if code == ABS_NAMES["ABS_HAT0Y"] and value > 0:  # D-pad down: signal off
            return Action(Act.CONTROL, {"turn_signal": int(TurnSignal.OFF)})
        return None
