"""The brake-controller emulator of the HIL harness (pure logic: no sockets, no threads).

:class:`BrakeController` emulates the brake controller that receives ESTOP_BRAKE (spec
sections 4 and 7): it accepts only frames with a good CRC, a legal alive counter that moved
on, and consistent fields, and it brakes by itself when no good frame has arrived for 50 ms.
It grades its braking as a real controller does (section 7): the share of the emergency
deceleration is estop.model.brakecheck's answer (0 release, brake_level/100 for brake_request 2,
1 for an emergency brake and for any brake_request it does not know).
Frame checks use the project's codecs in ``estop.protocol.can`` (``BrakeFrame.check``,
``StatusFrame.check``, ``CounterChecker``), which are written independently of the C core.
:func:`replay` runs it offline on a bus record.

Times are float seconds on the wall clock (CLOCK_REALTIME) that SocketCAN uses to timestamp
frames, so frame times and the harness's own send times can be subtracted directly.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from estop.model.brakecheck import EMERGENCY, BrakeFrameChecker
from estop.protocol.can import (
    BRAKE_ID,
    STATUS_ID,
    BrakeFrame,
    CounterChecker,
    CounterResult,
    StatusFrame,
)

BRAKE_SILENCE_S = 0.050  # spec section 4: brake when no good ESTOP_BRAKE for 50 ms
STATUS_RESYNC_S = 0.200  # two ESTOP_STATUS periods without one: its counter starts over
_EPS = 1e-6  # float seconds near 1.7e9 carry ~0.2 us of rounding


@dataclass(frozen=True, slots=True)
class Frame:
    """One CAN frame as a receiver saw it (kernel timestamp, seconds)."""

    ts: float
    can_id: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Issue:
    """A frame a brake controller must not accept, or a counter anomaly."""

    ts: float
    can_id: int
    kind: str  # bad_length, bad_crc, bad_counter, bad_content, repeat, jump, resync
    detail: str


@dataclass(frozen=True, slots=True)
class Trip:
    """The 50 ms silence watchdog fired: no good frame since ``last_good``."""

    last_good: float
    detected: float  # when the emulator noticed (live: its own clock; offline: deadline)

    @property
    def deadline(self) -> float:
        return self.last_good + BRAKE_SILENCE_S


@dataclass(frozen=True, slots=True)
class BrakeChange:
    """The controller's braking changed at ``ts``: from then on it decelerates the car at
    ``share`` of its emergency deceleration (spec section 7)."""

    ts: float
    share: float
    cause: str  # "frame" (a frame from the unit commanded it) or "silence" (watchdog)

    @property
    def braking(self) -> bool:
        return self.share > 0.0


@dataclass
class BrakeController:
    """Brake-controller emulator for ESTOP_BRAKE (and an integrity checker for ESTOP_STATUS).

    Feed it every frame with :meth:`on_frame` (in time order) and call :meth:`on_tick` with the
    current time whenever possible; it brakes when no good ESTOP_BRAKE frame arrived for
    ``silence_s``. It powers up braking, as a real one would.

    How hard it brakes (:attr:`share`, every change in :attr:`changes`) is
    :class:`estop.model.brakecheck.BrakeFrameChecker`'s graded answer: what the latest frame
    from the unit commands (a frame with a right CRC and a new counter whose content is wrong,
    e.g. an unknown brake_request, commands an emergency brake), or 1 after the silence. The grader
    starts over whenever this controller's counter does (a new sender, a silence), so both
    agree on which frames came from the unit.
    """

    silence_s: float = BRAKE_SILENCE_S
    share: float = EMERGENCY
    last_good: float | None = None
    last_frame: BrakeFrame | None = None
    good: int = 0
    status_good: int = 0
    issues: list[Issue] = field(default_factory=list)
    trips: list[Trip] = field(default_factory=list)
    changes: list[BrakeChange] = field(default_factory=list)
    tripped: bool = False
    last_status: float | None = None
    _brake_ctr: CounterChecker = field(default_factory=CounterChecker)
    _status_ctr: CounterChecker = field(default_factory=CounterChecker)
    _new_sender_at: float | None = None
    _grader: BrakeFrameChecker = field(
        default_factory=lambda: BrakeFrameChecker(status_id=None))

    @property
    def braking(self) -> bool:
        """Whether it brakes at all (any share above 0)."""
        return self.share > 0.0

    def expect_new_sender(self, since: float | None = None) -> None:
        """A new daemon starts: its counters start over, so no continuity is expected. With
        ``since``, from its first frame stamped at or after that time (a receiver that lags
        behind the bus may still be reading the previous daemon's last frames)."""
        if since is None:
            self._brake_ctr.reset()
            self._status_ctr.reset()
            self._grader.reset()
        self._new_sender_at = since

    def _set(self, ts: float, share: float, cause: str) -> None:
        if share != self.share:
            self.share = share
            self.changes.append(BrakeChange(ts, share, cause))

    def on_frame(self, frame: Frame) -> None:
        """Any frame (of any ID) proves that time has reached ``frame.ts`` on the bus."""
        self.on_tick(frame.ts)
        if self._new_sender_at is not None and frame.can_id in (BRAKE_ID, STATUS_ID) \
                and frame.ts >= self._new_sender_at:
            self._new_sender_at = None
            self._brake_ctr.reset()
            self._status_ctr.reset()
            self._grader.reset()
        if frame.can_id == BRAKE_ID:
            self._on_brake(frame)
        elif frame.can_id == STATUS_ID:
            self._on_status(frame)

    def _counter(self, checker: CounterChecker, frame: Frame, counter: int,
                 resync: bool) -> bool:
        if resync and checker.last is not None:
            # After a silence the counter cannot be followed (15 lost frames look like a
            # repeat): start over, as an E2E receiver does after a timeout, and report it.
            self.issues.append(Issue(frame.ts, frame.can_id, "resync",
                                     f"counter {counter} after a silence, was {checker.last}"))
            checker.reset()
        status = checker.check(counter)
        if status.result is CounterResult.REPEAT:
            self.issues.append(Issue(frame.ts, frame.can_id, "repeat",
                                     f"counter {counter} repeated (stale frame)"))
            return False
        if status.result is CounterResult.JUMP:
            self.issues.append(Issue(frame.ts, frame.can_id, "jump",
                                     f"counter {counter}, expected {status.expected} "
                                     f"({status.lost} lost)"))
        return True

    def _on_brake(self, frame: Frame) -> None:
        if self.tripped:
            self._grader.reset()  # after a silence its counter starts over, as ours does
        verdict = self._grader.feed(frame.ts, frame.can_id, frame.data)
        if verdict is not None and verdict.share is not None:
            self._set(frame.ts, verdict.share, "frame")
        problems = BrakeFrame.check(frame.data)
        if problems:
            for p in problems:
                self.issues.append(Issue(frame.ts, frame.can_id, p.kind, str(p)))
            return
        parsed = BrakeFrame.parse(frame.data)
        if not self._counter(self._brake_ctr, frame, parsed.counter, self.tripped):
            return
        self.good += 1
        self.last_good = frame.ts
        self.last_frame = parsed
        self.tripped = False

    def _on_status(self, frame: Frame) -> None:
        problems = StatusFrame.check(frame.data)
        if problems:
            for p in problems:
                self.issues.append(Issue(frame.ts, frame.can_id, p.kind, str(p)))
            return
        resync = self.last_status is not None and frame.ts - self.last_status >= STATUS_RESYNC_S
        self.last_status = frame.ts
        if self._counter(self._status_ctr, frame, StatusFrame.parse(frame.data).counter, resync):
            self.status_good += 1

    def on_tick(self, now: float) -> None:
        """Apply the silence watchdog at time ``now`` (live: the emulator's clock)."""
        if self.last_good is None or self.tripped:
            return
        if now - self.last_good >= self.silence_s - _EPS:
            self.tripped = True
            self.trips.append(Trip(self.last_good, now))
            self._set(now, EMERGENCY, "silence")


def replay(frames: Iterable[Frame], silence_s: float = BRAKE_SILENCE_S,
           end: float | None = None, new_senders: Iterable[float] = ()) -> BrakeController:
    """Offline emulator run: watchdog trips are placed exactly at their deadlines.
    ``new_senders`` are the times a new daemon was started (each daemon's t_start): from the
    first frame at or after each, the counters start over, as in the live emulator (the run's
    start_daemon). Without them a restart quicker than a status period read the new daemon's
    first ESTOP_STATUS (counter 0) as a repeat when the old one's last had counter 0 too (CI
    of 7ea791b: two such repeats failed the whole-run row, 1 in 15 a restart)."""
    ctl = BrakeController(silence_s=silence_s)
    starts = sorted(new_senders)
    for fr in frames:
        while starts and starts[0] <= fr.ts:
            ctl.expect_new_sender(starts.pop(0))
        if ctl.last_good is not None and fr.ts - ctl.last_good >= silence_s - _EPS:
            ctl.on_tick(ctl.last_good + silence_s)
        ctl.on_frame(fr)
    if end is not None and ctl.last_good is not None and end - ctl.last_good >= silence_s - _EPS:
        ctl.on_tick(ctl.last_good + silence_s)
    return ctl


def share_at(changes: Sequence[BrakeChange], t: float, initial: float = EMERGENCY) -> float:
    """The share the controller braked with at ``t`` (``initial`` before its first change; it
    powers up braking)."""
    share = initial
    for c in changes:
        if c.ts > t:
            break
        share = c.share
    return share


def shares_between(changes: Sequence[BrakeChange], t0: float, t1: float,
                   initial: float = EMERGENCY) -> list[float]:
    """Every share the controller braked with in ``[t0, t1)``, in order (no repeats)."""
    out = [share_at(changes, t0, initial)]
    for c in changes:
        if t0 < c.ts < t1 and c.share != out[-1]:
            out.append(c.share)
    return out


def frame_commands(changes: Iterable[BrakeChange], t0: float = -math.inf,
                   t1: float = math.inf) -> list[tuple[float, float]]:
    """(time, share) of the changes frames commanded in ``[t0, t1]``: the same for the live
    controller and a replay of the bus record, as both see the same kernel timestamps (the
    silence watchdog's changes differ: live they come when it looked)."""
    return [(c.ts, c.share) for c in changes if c.cause == "frame" and t0 <= c.ts <= t1]
