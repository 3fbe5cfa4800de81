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

Exit code (the table of every command: :data:`estop.errors.EXIT_CODES`): 0 no problem
flagged, 1 problems flagged (silence included), 2 usage error, 3 the bus could not be opened,
4 the log or DBC cannot be read (a malformed line included), 5 python-can or cantools missing.
"""

from __future__ import annotations

import argparse
import sys

from estop.commands.canbus import can_bus_config
from estop.commands.options import (
    add_can_options,
    add_frame_id_options,
    non_negative_float,
    positive_float,
)
from estop.commands.output import SUB_EPILOG, out
from estop.errors import EXIT_OK, EXIT_REFUSED, UsageError
from estop.model.brakecheck import BrakeFrameChecker
from estop.model.vehicle import DEFAULT_EMERGENCY_DECEL, VehicleParams, kmh
from estop.monitor.sources import DbcDecoder, read_records
from estop.monitor.watch import Monitor, run_bus, run_log

DESCRIPTION = ("Decode ESTOP_BRAKE / ESTOP_STATUS from a python-can bus, a can-utils log or "
               "any log python-can reads (.asc .blf .csv .trc ...), optionally with a DBC, and "
               "flag what a brake controller would: bad length, CRC or counter, "
               "contradictory fields, counter jumps/repeats, gaps of 50 ms or more. Silence "
               "is a failure: no good ESTOP_BRAKE at all, or none for 50 ms before the end "
               "of the log or of --duration-s, is flagged. Each ESTOP_BRAKE shows what the "
               "brake controller does on it (release, controlled N %, EMERGENCY; an unknown "
               "brake_request is an emergency brake).")

__all__ = ["DESCRIPTION", "add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = sub.add_parser("monitor", help="decode and check ESTOP_BRAKE / ESTOP_STATUS frames",
                            description=DESCRIPTION, epilog=SUB_EPILOG)
    parser.set_defaults(handler=run)
    parser.add_argument("--log", metavar="FILE",
                        help="read a log instead of a bus: python-can's formats by their "
                             "suffix (.asc .blf .csv .db .mf4 .trc), any other file as "
                             "can-utils lines (candump -L); '-': can-utils lines on stdin")
    add_can_options(parser)
    parser.add_argument("--dbc", metavar="PATH", nargs="?", const="", default=None,
                        help="also decode every frame with cantools from this DBC (no PATH: "
                             "the unit's own, estop/dbc); a frame the DBC and estop's "
                             "codecs read differently is flagged")
    add_frame_id_options(parser)
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


def run(args: argparse.Namespace) -> int:
    if args.count is not None and args.count <= 0:
        raise UsageError("--count must be > 0")
    if args.log is not None and (args.interface, args.channel, args.bitrate) != (None,) * 3:
        raise UsageError("--log reads a file: --interface, --channel and --bitrate are for a "
                         "live bus")
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
            run_log(monitor, read_records(args.log, lines), args.count)
        else:
            run_bus(monitor, bus, args.duration, args.count)
    except KeyboardInterrupt:
        pass
    roll_out = monitor.roll_out_line()
    if roll_out is not None:
        out(roll_out)
    out(monitor.commands())
    out(monitor.summary())
    mismatches = dbc.mismatches if dbc is not None else 0
    return EXIT_REFUSED if checker.problems or mismatches else EXIT_OK
