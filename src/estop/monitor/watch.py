"""The watch behind ``estop monitor``: each ESTOP_BRAKE / ESTOP_STATUS frame decoded, checked
as a brake controller checks it (:class:`estop.model.brakecheck.BrakeFrameChecker`) and
written as one line with what the controller does on it; the frames read from a log or a live
python-can bus; the roll-out of a car braking as they command."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from typing import TextIO

from estop.errors import ConnectionFailure
from estop.model.brakecheck import (
    EVENT_KINDS,
    GRADE_KINDS,
    BrakeFrameChecker,
    CheckEvent,
    Verdict,
    grade_text,
)
from estop.model.rollout import RollOutReplay
from estop.model.vehicle import VehicleParams
from estop.monitor.sources import DbcDecoder, Record
from estop.protocol.can import (
    BRAKE_REQUEST_NAMES,
    BrakeFrame,
    StatusFrame,
    flag_names,
    reason_name,
    state_name,
)
from estop.unit.bus import open_bus

__all__ = ["Monitor", "format_frame", "grade_note", "run_bus", "run_log"]


def format_frame(frame: BrakeFrame | StatusFrame) -> str:
    """Decoded fields of one frame, e.g. ``ESTOP_BRAKE STOPPED reason=boot brake=1 ...``."""
    if isinstance(frame, BrakeFrame):
        flags = f"{frame.flags:#04x}"
        names = flag_names(frame.flags)
        if names:
            flags += "(" + ",".join(names) + ")"
        return (f"ESTOP_BRAKE {state_name(frame.state)} reason={reason_name(frame.reason)} "
                f"brake={frame.brake_request} level={frame.brake_level} flags={flags} "
                f"ctr={frame.counter}")
    age = "none" if frame.link_age is None else f"{frame.link_age}ms"
    return (f"ESTOP_STATUS valid={frame.valid_packets} invalid={frame.invalid_packets} "
            f"auth_failures={frame.auth_failures} stops={frame.stops} link_age={age} "
            f"ctr={frame.counter}")


def grade_note(verdict: Verdict) -> str:
    """`` => <grade>`` for an ESTOP_BRAKE that commands (see the module's docstring), with why
    a rejected one brakes; empty for a frame that commands nothing."""
    if verdict.share is None:
        return ""
    note = f" => {grade_text(verdict.share)}"
    frame = verdict.frame
    if not verdict.accepted and isinstance(frame, BrakeFrame):
        if frame.brake_request not in BRAKE_REQUEST_NAMES:
            note += f" (brake_request {frame.brake_request} unknown)"
        else:
            note += " (content rejected)"
    return note


class Monitor:
    """Feeds a :class:`BrakeFrameChecker` and writes the monitor's lines to ``stream``
    (standard output by default). With ``speed`` (m/s) it also replays the frames into the
    vehicle model (:meth:`roll`, :meth:`roll_out_line`)."""

    def __init__(self, checker: BrakeFrameChecker, *, quiet: bool = False,
                 stream: TextIO | None = None, speed: float | None = None,
                 params: VehicleParams | None = None, dbc: DbcDecoder | None = None) -> None:
        self.checker = checker
        self.dbc = dbc
        self.quiet = quiet
        self._stream = stream
        self.speed = speed
        self.params = params or VehicleParams()
        self.rollout: RollOutReplay | None = None

    def _line(self, text: str) -> None:
        stream = sys.stdout if self._stream is None else self._stream
        stream.write(text + "\n")
        stream.flush()

    @staticmethod
    def _stamp(t: float) -> str:
        return f"({t:.6f})"

    def frame(self, t: float, can_id: int, data: bytes) -> Verdict | None:
        verdict = self.checker.feed(t, can_id, data)
        if verdict is None:  # not an estop frame: the DBC may still know it
            self._dbc_line(can_id, data)
            return None
        head = f"{self._stamp(t)} {can_id:03X}"
        if verdict.frame is not None and (not self.quiet or verdict.state_changed):
            mark = "" if verdict.accepted else "  [rejected]"
            if verdict.state_changed:
                mark += "  <- state change"
            self._line(f"{head} {format_frame(verdict.frame)}{grade_note(verdict)}{mark}")
        elif verdict.frame is None and not self.quiet:
            self._line(f"{head} {data.hex().upper()}  [rejected]")
        self._dbc_line(can_id, data)
        for ev in verdict.events:
            self.event(ev)
        return verdict

    def _dbc_line(self, can_id: int, data: bytes) -> None:
        if self.dbc is None:
            return
        before = self.dbc.mismatches
        line = self.dbc.line(can_id, data)
        if line is not None and (not self.quiet or self.dbc.mismatches > before):
            self._line(line)

    def event(self, ev: CheckEvent) -> None:
        self._line(f"{self._stamp(ev.t)} {ev.can_id:03X} ! {ev.kind}: {ev.message}")

    def begin(self, t: float) -> None:
        """The watch starts at ``t``: the moment of the roll-out (with a speed)."""
        if self.speed is not None and self.rollout is None:
            self.rollout = RollOutReplay(t, self.speed, params=self.params,
                                         brake_id=self.checker.brake_id,
                                         timeout=self.checker.timeout)

    def roll(self, t: float, can_id: int, data: bytes) -> None:
        """A record of any ID, for the roll-out (the first one begins the watch)."""
        if self.speed is not None:
            self.begin(t)
            assert self.rollout is not None
            self.rollout.feed(t, can_id, data)

    def roll_out_line(self) -> str | None:
        """``roll-out at 15.0 km/h from the start of the watch (...): ...``, or None without
        a speed."""
        if self.speed is None:
            return None
        if self.rollout is None:
            return "roll-out: nothing was watched"
        out = self.rollout.result()
        return (f"roll-out {out.summary()}, from the start of the watch "
                f"{self._stamp(out.moment)}")

    def commands(self) -> str:
        """``brake commands: release 40, controlled 0, emergency 4``: the ESTOP_BRAKE frames
        that commanded, by grade."""
        grades = self.checker.grades
        return "brake commands: " + ", ".join(f"{k} {grades[k]}" for k in GRADE_KINDS)

    def summary(self) -> str:
        c = self.checker
        found = [f"{k} {c.counts[k]}" for k in EVENT_KINDS if c.counts[k]]
        if self.dbc is not None and self.dbc.mismatches:
            found.append(f"dbc_mismatch {self.dbc.mismatches}")
        return (f"summary: {c.frames} frames, {c.accepted} accepted; problems: "
                + (", ".join(found) if found else "none"))


def run_log(monitor: Monitor, records: Iterable[Record], count: int | None) -> None:
    """Feed the log's frames; then judge the silence up to its last line (any ID)."""
    seen = 0
    end: float | None = None
    for t, can_id, data, extended in records:
        end = t if end is None else max(end, t)
        if extended:
            continue
        monitor.roll(t, can_id, data)
        if monitor.frame(t, can_id, data) is not None:
            seen += 1
            if count is not None and seen >= count:
                break
    for ev in monitor.checker.finish(end):
        monitor.event(ev)


def run_bus(monitor: Monitor, config: dict[str, object], duration: float | None,
             count: int | None) -> None:
    import can  # python-can, imported only when a bus is used

    bus = open_bus(config)
    end = None if duration is None else time.monotonic() + duration
    seen = 0
    began = time.time()
    monitor.checker.begin(began)
    monitor.begin(began)
    try:
        while end is None or time.monotonic() < end:
            try:
                msg = bus.recv(timeout=0.005)
            except can.CanError as exc:
                raise ConnectionFailure(f"reading the bus failed: {exc}") from None
            now = time.time()
            if msg is not None and not (msg.is_error_frame or msg.is_remote_frame
                                        or msg.is_extended_id):
                t = msg.timestamp or now
                monitor.roll(t, msg.arbitration_id, bytes(msg.data))
                if monitor.frame(t, msg.arbitration_id, bytes(msg.data)) is not None:
                    seen += 1
                    if count is not None and seen >= count:
                        break
            for ev in monitor.checker.poll(now):
                monitor.event(ev)
    except KeyboardInterrupt:
        pass  # Ctrl-C ends the watch; it is judged like any other end
    finally:
        bus.shutdown()
    # the silence up to the end of the watch (--duration, --count or Ctrl-C) counts too
    for ev in monitor.checker.finish(time.time()):
        monitor.event(ev)
