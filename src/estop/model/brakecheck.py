"""What a brake controller checks on ESTOP_BRAKE (and ESTOP_STATUS) frames.

A brake controller accepts an ESTOP_BRAKE frame only if it is 8 bytes, its CRC-8 (data ID
0x0E57) is right, its alive counter is legal and new (not a repeat), and its fields agree with
each other. It brakes when the accepted frame asks for it, and by itself when no accepted
frame arrived for 50 ms (``timeout``), and before the first one.

Silence is a failure (spec section 7): no good ESTOP_BRAKE frame for 50 ms means brake, and a
watch that saw no good ESTOP_BRAKE frame at all has not seen a working unit. So a watch ends
with :meth:`BrakeFrameChecker.finish` at the end of what it watched (the end of ``--duration``,
the last line of a log): it judges the silence up to then.

The graded answer (spec section 7), :meth:`BrakeFrameChecker.deceleration_share`: the share of
the emergency deceleration the controller brakes with at a moment. 1.0 before the first
accepted ESTOP_BRAKE and when none was accepted for 50 ms; else what the latest frame that
*commands* asks for: an accepted frame its :attr:`~estop.protocol.can.BrakeFrame.
deceleration_share` (0 release, brake_level/100 for a controlled stop, 1.0 emergency). A frame
that really came from the unit (right CRC, legal and new counter) but fails the content check
also commands: 1.0, an emergency brake. That is how a brake_request the controller does not
know (3, 255, ...) ends up, and any frame whose fields contradict each other: the unit said
something, and it is not a release or a grade the controller can trust (when in doubt, the car
stops). Frames that did not come whole from the unit (bad length, CRC or counter) or that
repeat the previous counter command nothing: the controller goes on with what it had until
the 50 ms run out.

:class:`BrakeFrameChecker` is that logic without the brake: feed it frames with their times,
read back verdicts, events and the deceleration share. ``estop monitor`` prints them, the
vehicle model (:mod:`estop.model.rollout`) brakes with the share; a brake controller emulator uses
:meth:`BrakeFrameChecker.brake_applied` or :meth:`BrakeFrameChecker.deceleration_share`.

Event kinds: ``bad_length``, ``bad_crc``, ``bad_counter``, ``bad_content``,
``counter_repeat``, ``counter_jump`` (frames lost in between), ``gap`` (two accepted frames
``timeout`` or more apart; reported when the second arrives), ``timeout`` (no good frame for
``timeout``: reported by :meth:`BrakeFrameChecker.poll` while the silence lasts, or by
:meth:`BrakeFrameChecker.finish` for the silence at the end) and ``no_brake_frame`` (the watch
ended without one good ESTOP_BRAKE frame; :meth:`BrakeFrameChecker.finish`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace

from estop.protocol.can import (
    BRAKE_ID,
    STATUS_ID,
    BrakeFrame,
    CounterChecker,
    CounterResult,
    CrcError,
    LengthError,
    StatusFrame,
)

__all__ = ["BRAKE_TIMEOUT", "EMERGENCY", "EVENT_KINDS", "GRADE_KINDS", "BrakeFrameChecker",
           "CheckEvent", "Verdict", "grade_kind", "grade_text"]

BRAKE_TIMEOUT = 0.050  # seconds without an accepted ESTOP_BRAKE before a controller brakes
EMERGENCY = 1.0  # the deceleration share of an emergency brake
GRADE_KINDS = ("release", "controlled", "emergency")  # tallies of commanding ESTOP_BRAKE frames
EVENT_KINDS = ("bad_length", "bad_crc", "bad_counter", "bad_content", "counter_repeat",
               "counter_jump", "gap", "timeout", "no_brake_frame")


@dataclass(frozen=True, slots=True)
class CheckEvent:
    t: float  # seconds, on the clock the frames were fed with
    can_id: int
    kind: str  # one of EVENT_KINDS
    message: str  # one line

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"


@dataclass(frozen=True, slots=True)
class Verdict:
    """The outcome for one fed frame."""

    t: float
    can_id: int
    data: bytes
    frame: BrakeFrame | StatusFrame | None  # fields as read (None if the length was wrong)
    accepted: bool  # a receiver would use this frame
    events: tuple[CheckEvent, ...] = field(default=())
    state_changed: bool = False  # accepted ESTOP_BRAKE whose state/reason differs from before
    # the deceleration share this ESTOP_BRAKE commands from its arrival (see the module's
    # docstring); None when it commands nothing (not whole from the unit, a repeat, or not
    # an ESTOP_BRAKE)
    share: float | None = None


def grade_kind(share: float) -> str:
    """``release``, ``controlled`` or ``emergency`` (one of :data:`GRADE_KINDS`)."""
    if share <= 0.0:
        return "release"
    return "emergency" if share >= EMERGENCY else "controlled"


def grade_text(share: float) -> str:
    """A deceleration share as words: ``release``, ``controlled 30 %``, ``EMERGENCY``."""
    kind = grade_kind(share)
    if kind == "controlled":
        return f"controlled {share * 100:g} %"
    return "EMERGENCY" if kind == "emergency" else kind


class _Stream:
    """Counter and time of one frame type."""

    def __init__(self) -> None:
        self.counter = CounterChecker()
        self.last_accepted_t: float | None = None
        self.timeout_reported = False


class BrakeFrameChecker:
    """Check a stream of ESTOP_BRAKE / ESTOP_STATUS frames as a brake controller would.

    Times are seconds on any one clock (log timestamps, ``time.monotonic()``...), fed in order.
    Frames with other IDs are ignored (``feed`` returns None).
    """

    def __init__(self, *, brake_id: int = BRAKE_ID, status_id: int | None = STATUS_ID,
                 timeout: float = BRAKE_TIMEOUT) -> None:
        if timeout <= 0:
            raise ValueError("timeout must be > 0")
        self.brake_id = brake_id
        self.status_id = status_id
        self.timeout = timeout
        self.reset()

    def reset(self) -> None:
        """Forget everything seen so far (counters, times, tallies)."""
        self._brake = _Stream()
        self._status = _Stream()
        self.last_brake: BrakeFrame | None = None  # last accepted ESTOP_BRAKE
        self.last_status: StatusFrame | None = None  # last accepted ESTOP_STATUS
        self.counts: Counter[str] = Counter()  # events by kind
        self.grades: Counter[str] = Counter()  # commanding ESTOP_BRAKE frames by grade kind
        self._share: float | None = None  # what the latest commanding ESTOP_BRAKE asked for
        self.frames = 0
        self.accepted = 0
        self._began: float | None = None
        self._finished = False

    def begin(self, t: float) -> None:
        """The watch starts at ``t`` (live use): from then on :meth:`poll` reports a silence
        even before the first good frame."""
        self._began = t

    # --------------------------------------------------------------------------- feeding

    def feed(self, t: float, can_id: int, data: bytes | bytearray | memoryview) -> Verdict | None:
        """Check one frame received at time ``t``; None if ``can_id`` is neither frame's."""
        raw = bytes(data)
        if can_id == self.brake_id:
            verdict, fresh = self._feed(t, can_id, raw, BrakeFrame, self._brake, gap_check=True)
            frame = verdict.frame
            share: float | None = None
            changed = False
            if verdict.accepted:
                assert isinstance(frame, BrakeFrame)
                prev = self.last_brake
                changed = prev is not None and (prev.state, prev.reason) != (frame.state,
                                                                             frame.reason)
                self.last_brake = frame
                share = frame.deceleration_share
            elif fresh:
                share = EMERGENCY  # from the unit, but not a command to trust: brake
            if share is not None:
                self._share = share
                self.grades[grade_kind(share)] += 1
            verdict = replace(verdict, state_changed=changed, share=share)
        elif self.status_id is not None and can_id == self.status_id:
            verdict, _ = self._feed(t, can_id, raw, StatusFrame, self._status, gap_check=False)
            if verdict.accepted:
                assert isinstance(verdict.frame, StatusFrame)
                self.last_status = verdict.frame
        else:
            return None
        self.frames += 1
        self.accepted += verdict.accepted
        for ev in verdict.events:
            self.counts[ev.kind] += 1
        return verdict

    def _feed(self, t: float, can_id: int, raw: bytes,
              kind: type[BrakeFrame] | type[StatusFrame], stream: _Stream,
              gap_check: bool) -> tuple[Verdict, bool]:
        """The verdict, and whether the frame came whole and new from the unit (right CRC,
        legal counter, not a repeat), whatever its content."""
        events: list[CheckEvent] = []
        problems = kind.check(raw)
        for p in problems:
            events.append(CheckEvent(t, can_id, p.kind, str(p)))
        if any(isinstance(p, LengthError) for p in problems):
            return Verdict(t, can_id, raw, None, False, tuple(events)), False
        frame = kind.parse(raw)
        crc_ok = not any(isinstance(p, CrcError) for p in problems)
        accepted = not problems
        fresh = False
        if crc_ok and not any(p.kind == "bad_counter" for p in problems):
            # the frame really was sent: follow its counter even if its content is bad
            status = stream.counter.check(frame.counter)
            fresh = status.result is not CounterResult.REPEAT
            if status.result is CounterResult.REPEAT:
                events.append(CheckEvent(t, can_id, "counter_repeat",
                                         f"counter {frame.counter} repeated"))
                accepted = False
            elif status.result is CounterResult.JUMP:
                events.append(CheckEvent(t, can_id, "counter_jump",
                                         f"counter {status.expected} expected, got "
                                         f"{frame.counter} ({status.lost} lost)"))
        if accepted:
            last = stream.last_accepted_t
            if gap_check and last is not None and t - last >= self.timeout:
                events.append(CheckEvent(t, can_id, "gap",
                                         f"{(t - last) * 1000:.1f} ms without a good frame "
                                         f"(limit {self.timeout * 1000:g} ms)"))
            stream.last_accepted_t = t
            stream.timeout_reported = False
        return Verdict(t, can_id, raw, frame, accepted, tuple(events)), fresh

    def poll(self, now: float) -> list[CheckEvent]:
        """Live use: a ``timeout`` event once when ``timeout`` passes without a good
        ESTOP_BRAKE frame (again only after good frames came back); before the first good
        frame, counted from :meth:`begin` (nothing without it)."""
        stream = self._brake
        if stream.timeout_reported:
            return []
        last = stream.last_accepted_t
        since = last if last is not None else self._began
        if since is None or now - since < self.timeout:
            return []
        stream.timeout_reported = True
        if last is None:
            text = (f"no good ESTOP_BRAKE since the watch began {(now - since) * 1000:.1f} ms "
                    f"ago: a brake controller brakes")
        else:
            text = (f"no good ESTOP_BRAKE for {(now - since) * 1000:.1f} ms: a brake "
                    f"controller brakes now")
        return [self._event(CheckEvent(now, self.brake_id, "timeout", text))]

    def finish(self, end: float | None) -> list[CheckEvent]:
        """The watch is over at ``end`` (the end of a live watch, the last record of a log of
        any ID; None if there was nothing at all). Judge its silence, once:

        - ``no_brake_frame`` when not one good ESTOP_BRAKE frame came: no working unit seen;
        - ``timeout`` when the last good one is ``timeout`` or more older than ``end`` (unless
          :meth:`poll` already reported this silence).
        """
        if self._finished:
            return []
        self._finished = True
        stream = self._brake
        last = stream.last_accepted_t
        t = end if end is not None else (last if last is not None else 0.0)
        if last is None:
            seen = (f" ({self.frames} frames seen, none a good ESTOP_BRAKE)"
                    if self.frames else "")
            return [self._event(CheckEvent(
                t, self.brake_id, "no_brake_frame",
                f"no good ESTOP_BRAKE frame at all{seen}: not a working unit"))]
        if end is None or stream.timeout_reported or end - last < self.timeout:
            return []
        stream.timeout_reported = True
        return [self._event(CheckEvent(
            end, self.brake_id, "timeout",
            f"no good ESTOP_BRAKE for {(end - last) * 1000:.1f} ms up to the end of the "
            f"record (limit {self.timeout * 1000:g} ms)"))]

    def _event(self, ev: CheckEvent) -> CheckEvent:
        self.counts[ev.kind] += 1
        return ev

    # ------------------------------------------------------------------------- reading

    def deceleration_share(self, now: float) -> float:
        """The share of its emergency deceleration a brake controller brakes with at ``now``
        (spec section 7; ``now`` not before the last frame fed): 1.0 before the first
        accepted ESTOP_BRAKE and once none was accepted for ``timeout``; else what the latest
        commanding frame asks for (see the module's docstring): 0 release, brake_level/100
        for a controlled stop, 1.0 for an emergency brake, an unknown brake_request or any
        frame from the unit that fails the content check."""
        last = self._brake.last_accepted_t
        if last is None or self._share is None or now - last >= self.timeout:
            return EMERGENCY
        return self._share

    def brake_applied(self, now: float) -> bool:
        """Whether a brake controller brakes at all at ``now``: unless the latest commanding
        ESTOP_BRAKE asked for release and the last accepted one is younger than ``timeout``
        (:meth:`deceleration_share` > 0)."""
        return self.deceleration_share(now) > 0.0

    @property
    def commanded_share(self) -> float | None:
        """What the latest commanding ESTOP_BRAKE asked for, however old (None before any);
        :meth:`deceleration_share` adds the silence rule."""
        return self._share

    @property
    def silence_deadline(self) -> float | None:
        """When the 50 ms rule brakes unless another ESTOP_BRAKE is accepted first: the last
        accepted one's time plus ``timeout`` (None before the first)."""
        last = self._brake.last_accepted_t
        return None if last is None else last + self.timeout

    @property
    def last_brake_time(self) -> float | None:
        return self._brake.last_accepted_t

    @property
    def problems(self) -> int:
        """Number of events flagged so far (all kinds)."""
        return sum(self.counts[k] for k in EVENT_KINDS)
