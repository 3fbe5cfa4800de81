"""``estop monitor``: decode ESTOP_BRAKE / ESTOP_STATUS and flag what a brake controller would.

Sources: any python-can bus (``--interface socketcan --channel vcan0 --bitrate 500000``,
``--interface virtual``, ...; what is not given comes from python-can's own configuration:
``CAN_INTERFACE``, ``~/.canrc``), or a log (``--log FILE``): can-utils lines, or any format
python-can reads (.asc .blf .csv .db .mf4 .trc ...), or can-utils lines on standard input
(``--log -``, e.g. ``candump -L vcan0 | estop monitor --log -``). ``--dbc`` decodes every frame
with cantools as well (the unit's own DBC, or another) and flags a frame the DBC and estop's
codecs read differently.

Flags bad lengths, bad CRCs, illegal or repeated alive counters, counter jumps, fields that
contradict each other, and gaps of 50 ms (``--brake-timeout-ms``) or more between good ESTOP_BRAKE
frames (live buses also get a ``timeout`` line while the silence lasts).

Each ESTOP_BRAKE line ends with what a brake controller does on it (spec section 7):
``=> release``, ``=> controlled 30 %``, ``=> EMERGENCY``. A frame from the unit (right CRC,
legal new counter) that the controller must reject for its content, an unknown brake_request
above all, is an emergency brake too: ``=> EMERGENCY (brake_request 3 unknown)  [rejected]``;
frames that did not come whole from the unit command nothing and get no grade. Before the
summary a ``brake commands:`` line counts the frames that commanded, by grade.

``--speed-kmh V`` adds the roll-out of a car driving at V when the watch began (the first
record of a log, or the start of a live watch), braking as the frames command
(docs/VEHICLE.md): when braking began, when it stood still, how far it rolled.

Silence is a failure (spec section 7): a watch with no good ESTOP_BRAKE frame at all has not
seen a working unit (``no_brake_frame``), and the silence at the end counts (``timeout``): in
a log, from the last good ESTOP_BRAKE to the last line (a frame of any ID); on a live bus, up
to the end of ``--duration-s`` (or Ctrl-C).

Exit code (the table of every command: :data:`estop.cliutil.EXIT_CODES`): 0 no problem
flagged, 1 problems flagged (silence included), 2 usage error, 3 the bus could not be opened,
4 the log or DBC cannot be read (a malformed line included), 5 python-can or cantools missing.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterable
from typing import TextIO

from estop.brakecheck import (
    EVENT_KINDS,
    GRADE_KINDS,
    BrakeFrameChecker,
    CheckEvent,
    Verdict,
    grade_text,
)
from estop.cliutil import (
    EXIT_OK,
    EXIT_PROBLEM,
    ConnectionFailure,
    UsageError,
    add_can_options,
    can_bus_config,
    non_negative_float,
    out,
    parse_u32,
    positive_float,
)
from estop.monitorsource import DbcDecoder, Record, read_records
from estop.protocol.can import (
    BRAKE_ID,
    BRAKE_REQUEST_NAMES,
    STATUS_ID,
    BrakeFrame,
    StatusFrame,
    flag_names,
    reason_name,
    state_name,
)
from estop.rollout import RollOutReplay
from estop.vehicle import DEFAULT_EMERGENCY_DECEL, VehicleParams, kmh

DESCRIPTION = ("Decode ESTOP_BRAKE / ESTOP_STATUS from a python-can bus, a can-utils log or "
               "any log python-can reads (.asc .blf .csv .trc ...), optionally with a DBC, and "
               "flag what a brake controller would: bad length, CRC or counter, "
               "contradictory fields, counter jumps/repeats, gaps of 50 ms or more. Silence "
               "is a failure: no good ESTOP_BRAKE at all, or none for 50 ms before the end "
               "of the log or of --duration-s, is flagged. Each ESTOP_BRAKE shows what the "
               "brake controller does on it (release, controlled N %, EMERGENCY; an unknown "
               "brake_request is an emergency brake).")

__all__ = ["DESCRIPTION", "Monitor", "add_arguments", "format_frame", "grade_note", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log", metavar="FILE",
                        help="read a log instead of a bus: python-can's formats by their "
                             "suffix (.asc .blf .csv .db .mf4 .trc), any other file as "
                             "can-utils lines (candump -L); '-': can-utils lines on stdin")
    add_can_options(parser)
    parser.add_argument("--dbc", metavar="PATH", nargs="?", const="", default=None,
                        help="also decode every frame with cantools from this DBC (no PATH: "
                             "the unit's own, estop/dbc); a frame the DBC and estop's "
                             "codecs read differently is flagged")
    parser.add_argument("--brake-id", type=parse_u32, default=BRAKE_ID, metavar="ID",
                        help=f"ESTOP_BRAKE CAN ID (default {BRAKE_ID:#05x})")
    parser.add_argument("--status-id", type=parse_u32, default=STATUS_ID, metavar="ID",
                        help=f"ESTOP_STATUS CAN ID (default {STATUS_ID:#05x})")
    # the brake controller's own timeout (spec section 7); --timeout-ms is its older name here
    parser.add_argument("--brake-timeout-ms", dest="brake_timeout_ms",
                        type=positive_float, default=50.0, metavar="MS",
                        help="the brake controller's timeout: flag gaps of this many ms "
                             "between good ESTOP_BRAKE frames (default 50)")
    parser.add_argument("--timeout-ms", dest="brake_timeout_ms", type=positive_float,
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    parser.add_argument("--duration-s", dest="duration", type=non_negative_float, default=None,
                        metavar="S", help="live bus: stop after this many seconds")
    parser.add_argument("--duration", dest="duration", type=non_negative_float,
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    parser.add_argument("--count", type=int, default=None, metavar="N",
                        help="stop after this many ESTOP frames")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="print only problems, state changes and the summary")
    parser.add_argument("--speed-kmh", type=non_negative_float, default=None, metavar="KMH",
                        help="also print how far a car at this speed when the watch began "
                             "rolls, braking as the frames command (docs/VEHICLE.md)")
    parser.add_argument("--decel-ms2", type=positive_float, default=None, metavar="MS2",
                        help="with --speed-kmh: the car's emergency deceleration, m/s^2 "
                             f"(default {DEFAULT_EMERGENCY_DECEL:g})")
    parser.add_argument("--actuator-delay-ms", type=non_negative_float, default=None,
                        metavar="MS",
                        help="with --speed-kmh: the brake acts this long after the controller "
                             "(default 0)")


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
        if self._stream is None:
            out(text)
        else:
            self._stream.write(text + "\n")

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


def _run_log(monitor: Monitor, records: Iterable[Record], count: int | None) -> None:
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


def _run_bus(monitor: Monitor, config: dict[str, object], duration: float | None,
             count: int | None) -> None:
    import can  # python-can, imported only when a bus is used

    try:
        bus = can.Bus(**config)  # type: ignore[arg-type]
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConnectionFailure(f"cannot open {config.get('interface')} bus "
                                f"{config.get('channel') or ''}: {why}") from None
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


def run(args: argparse.Namespace) -> int:
    if args.count is not None and args.count <= 0:
        raise UsageError("--count must be > 0")
    if args.log is not None and (args.interface, args.channel, args.bitrate) != (None,) * 3:
        raise UsageError("--log reads a file: --interface, --channel and --bitrate are for a "
                         "live bus")
    if args.brake_id > 0x7FF or args.status_id > 0x7FF:
        raise UsageError("CAN IDs must be 11-bit (0..0x7FF)")
    checker = BrakeFrameChecker(brake_id=args.brake_id, status_id=args.status_id,
                                timeout=args.brake_timeout_ms / 1000.0)
    if args.speed_kmh is None and (args.decel_ms2, args.actuator_delay_ms) != (None, None):
        raise UsageError("--decel-ms2 and --actuator-delay-ms need --speed-kmh")
    speed = None if args.speed_kmh is None else kmh(args.speed_kmh)
    params = VehicleParams(
        emergency_decel=DEFAULT_EMERGENCY_DECEL if args.decel_ms2 is None else args.decel_ms2,
        actuator_delay=(args.actuator_delay_ms or 0.0) / 1000.0)
    bus = None if args.log is not None else can_bus_config(args)
    dbc = None if args.dbc is None else DbcDecoder(args.dbc or None)
    monitor = Monitor(checker, quiet=args.quiet, speed=speed, params=params, dbc=dbc)
    try:
        if bus is None:
            lines = sys.stdin if args.log == "-" else None
            _run_log(monitor, read_records(args.log, lines), args.count)
        else:
            _run_bus(monitor, bus, args.duration, args.count)
    except KeyboardInterrupt:
        pass
    roll_out = monitor.roll_out_line()
    if roll_out is not None:
        out(roll_out)
    out(monitor.commands())
    out(monitor.summary())
    mismatches = dbc.mismatches if dbc is not None else 0
    return EXIT_PROBLEM if checker.problems or mismatches else EXIT_OK
