"""What the demo reads from a unit's bus: its logged CAN frames (:class:`BusWatch`, checked
frame by frame as a receiver would). The unit's own account, the ``state`` events of its log,
is :func:`estop.unit.events.state_changes`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from estop.demo.car import LiveCar
from estop.model.brakecheck import grade_text
from estop.protocol import can, canlog
from estop.unit.canlog import stamp

__all__ = ["BusWatch", "Change", "grade", "is_state"]


@dataclass(frozen=True, slots=True)
class Change:
    """An ESTOP_BRAKE frame whose state, reason or flags differ from the one before it."""

    t: float  # its can-log stamp (realtime seconds)
    frame: can.BrakeFrame
    flags_only: bool = False  # the same state and reason, other flags

    @property
    def state(self) -> int:
        return self.frame.state

    @property
    def reason(self) -> int:
        return self.frame.reason

    def text(self) -> str:
        """``STOPPED reason=lift brake_request=1 EMERGENCY (counter 9)``."""
        b = self.frame
        if self.flags_only:
            return "flags " + (",".join(can.flag_names(b.flags)) or "none")
        return (f"{can.state_name(b.state)} reason={can.reason_name(b.reason)} "
                f"brake_request={b.brake_request} {grade(b)} (counter {b.counter})")


def grade(frame: can.BrakeFrame) -> str:
    """What a brake controller does on the frame: ``release``, ``controlled 30 %``,
    ``EMERGENCY``."""
    return grade_text(frame.deceleration_share)


@dataclass
class BusWatch:
    """Follows one unit's can-log: every record (for the roll-outs), the checks, the latest
    ESTOP_BRAKE and ESTOP_STATUS, every change; feeds ``car`` when given."""

    car: LiveCar | None = None
    records: list[canlog.CanLogRecord] = field(default_factory=list)
    changes: list[Change] = field(default_factory=list)
    brake: can.BrakeFrame | None = None
    link_age_ms: int | None = None
    auth_failures: int = 0  # ESTOP_STATUS byte 2, the latest window
    frames: int = 0
    bad_frames: int = 0
    counter_jumps: int = 0
    _brake_ctr: can.CounterChecker = field(default_factory=can.CounterChecker)
    _status_ctr: can.CounterChecker = field(default_factory=can.CounterChecker)

    def take(self, rec: canlog.CanLogRecord) -> Change | None:
        """One logged frame; the change it shows, if any."""
        self.records.append(rec)
        self.frames += 1
        if self.car is not None and not rec.extended:
            self.car.feed(stamp(rec), rec.can_id, rec.data)
        if rec.can_id == can.STATUS_ID:
            if can.StatusFrame.check(rec.data):
                self.bad_frames += 1
                return None
            status = can.StatusFrame.parse(rec.data)
            self.counter_jumps += not self._status_ctr.check(status.counter).ok
            self.link_age_ms = status.link_age
            self.auth_failures = status.auth_failures
            return None
        if rec.can_id != can.BRAKE_ID:
            return None
        if can.BrakeFrame.check(rec.data):
            self.bad_frames += 1
            return None
        b = can.BrakeFrame.parse(rec.data)
        self.counter_jumps += not self._brake_ctr.check(b.counter).ok
        prev, self.brake = self.brake, b
        if prev is not None and (prev.state, prev.reason, prev.flags) == (b.state, b.reason,
                                                                           b.flags):
            return None
        change = Change(stamp(rec), b, flags_only=prev is not None and
                        (prev.state, prev.reason) == (b.state, b.reason))
        self.changes.append(change)
        return change

    def first(self, after: float, test: Callable[[Change], bool]) -> Change | None:
        """The first change of state or reason at or after ``after`` that passes ``test``."""
        return next((c for c in self.changes
                     if c.t >= after and not c.flags_only and test(c)), None)

    def states(self, after: float, before: float) -> list[Change]:
        """The changes of state or reason in [after, before)."""
        return [c for c in self.changes if after <= c.t < before and not c.flags_only]

    @property
    def state(self) -> int | None:
        return None if self.brake is None else self.brake.state


def is_state(state: int, reason: int | None = None) -> Callable[[Change], bool]:
    """A test for :meth:`BusWatch.first`: into ``state`` (with ``reason``, when given)."""
    return lambda c: c.state == state and (reason is None or c.reason == reason)
