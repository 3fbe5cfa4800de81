"""``estop demo``: version 3's story, played against a real ``estopd`` on loopback (no root,
no CAN).

The demo makes a fresh key, starts ``estopd`` with it and the two-stage answer to silence
(by default the issue's figures: SLOWING after S = 200 ms without a valid packet, STOPPED at
T = 1000 ms), free loopback ports and its CAN frames logged to a pipe; beside it a second
estopd run as a version-2 unit (one stage, 200 ms), which hears the operator's packets but
no lift. Then it plays the story of :mod:`estop.demo.story` with the real remote code, its
link model and an attacker without the key. Every logged frame goes through the brake
controller emulation into the vehicle model (:mod:`estop.demo.car`), which the live view
shows; the end prints the timeline (:mod:`estop.demo.report`), the stops with their latencies
and distances, and what did not happen as it should (:mod:`estop.demo.checks`): exit code 1.

This module is the command line (options, the estopd binary, the optional status page); the
run is :mod:`estop.demo.run`, its parts the modules of :mod:`estop.demo`. The daemon runner
lives in :mod:`estop.unit.daemon`, shared with the benchmarks.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any, TextIO

from estop.commands.options import ErrorOnlyParser, parse_listen
from estop.demo.result import TIME_MS_MAX, TIME_MS_MIN, Settings
from estop.demo.run import run_demo
from estop.demo.twin import V2_TIMEOUT_MS
from estop.errors import EXIT_NOT_INSTALLED, EXIT_USAGE, CliError
from estop.model.vehicle import kmh
from estop.unit.daemon import find_estopd
from estop.unit.events import state_changes

__all__ = ["add_parser", "main"]

SPEED_KMH_MIN, SPEED_KMH_MAX = 1.0, 60.0


def time_ms(text: str) -> int:
    """argparse type of ``--slow-ms`` and ``--timeout-ms``: whole ms in estopd's range."""
    want = f"must be whole milliseconds {TIME_MS_MIN}..{TIME_MS_MAX} (estopd's range)"
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{want}, got {text!r}") from None
    if not TIME_MS_MIN <= value <= TIME_MS_MAX:
        raise argparse.ArgumentTypeError(f"{want}, got {value}")
    return value


def speed_kmh(text: str) -> float:
    want = f"must be {SPEED_KMH_MIN:g}..{SPEED_KMH_MAX:g} km/h"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{want}, got {text!r}") from None
    if not SPEED_KMH_MIN <= value <= SPEED_KMH_MAX:  # also refuses NaN
        raise argparse.ArgumentTypeError(f"{want}, got {text}")
    return value


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Listed in ``estop --help``; ``estop demo ...`` is dispatched before parsing (its own
    parser: :func:`main`)."""
    sub.add_parser("demo", help="run estopd on loopback and play a scripted drive "
                   "(estop demo --help)")


def _parser() -> ErrorOnlyParser:
    ap = ErrorOnlyParser(prog="estop demo", description=(
        "Run estopd with a fresh key and the two-stage stop on loopback, beside a version-2 "
        "unit, and play version 3's story with an attacker on the network: release, drive, "
        "the finger lifts (lift datagrams: stopped at once; the version-2 unit waits for its "
        "timeout), a forged RELEASE (NAK 4), a burst of lost packets (SLOWING, then ARMED "
        "again), the Wi-Fi dies while the attacker sends forged and replayed heartbeats "
        "(SLOWING at the slow time, STOPPED at the timeout), the attacker's stop datagram (it "
        "stops: anyone may), the stop button. Prints each stop's latency and the distance the "
        "car rolls. No root, no CAN needed."))
    ap.add_argument("--estopd", metavar="PATH", help="the estopd binary (default: beside "
                    "this Python, on PATH, or firmware/build/estopd)")
    ap.add_argument("--slow-ms", type=time_ms, default=200,
                    help="the unit's slow time S: SLOWING after this long without a valid "
                         "packet (default 200)")
    ap.add_argument("--timeout-ms", type=time_ms, default=1000,
                    help=f"the unit's timeout T, {TIME_MS_MIN}..{TIME_MS_MAX}, at least 200 "
                         f"above S (default 1000)")
    ap.add_argument("--speed-kmh", type=speed_kmh, default=15.0,
                    help=f"the car's speed at each moment that matters, {SPEED_KMH_MIN:g}.."
                         f"{SPEED_KMH_MAX:g} (default 15)")
    ap.add_argument("--dashboard", nargs="?", const="127.0.0.1:8080", metavar="ADDR:PORT",
                    help="also serve the live status page of the unit (estop dashboard) "
                         "while the demo runs, on ADDR:PORT (default 127.0.0.1:8080); the "
                         "address is printed at the start")
    ap.add_argument("--plain", action="store_true",
                    help="plain lines instead of a refreshing status line (default off a TTY)")
    return ap


class _Page:
    """``--dashboard``: the status page, fed the unit's can-log and the ``state`` events of
    its log (the page reads either form of estopd's log)."""

    def __init__(self, thread: Any) -> None:
        self.thread = thread

    def tee(self, stream: str, line: str) -> None:
        if stream == "can_log":
            self.thread.can_line(line)
            return
        if state_changes([line]):
            self.thread.log_line(line)

    def close(self) -> None:
        self.thread.close()


def _start_dashboard(listen: str, out: TextIO) -> _Page | None:
    """Serve the page; None (after one line on stderr) when it cannot."""
    try:
        from estop.dashboard.server import ServerThread

        host, port = parse_listen(listen)
        thread = ServerThread(host, port)
        url = thread.start()
    except (ModuleNotFoundError, OSError, CliError) as exc:
        why = (f"the 'dashboard' extra is missing ({exc.name})"
               if isinstance(exc, ModuleNotFoundError) else str(exc))
        sys.stderr.write(f"estop demo: error: --dashboard: {why}\n")
        return None
    out.write(f"estop demo: dashboard on {url} (the unit's live status page, while the demo "
              f"runs)\n")
    out.flush()
    return _Page(thread)


def main(argv: list[str] | None = None) -> int:
    """Run the demo; return its exit code (0 ok, 1 a problem, 2 usage error, 5 no estopd).
    Usage errors are one line, as for every other ``estop`` tool."""
    ap = _parser()
    try:
        args = ap.parse_args(argv)
        try:
            settings = Settings(args.slow_ms, args.timeout_ms, kmh(args.speed_kmh))
        except ValueError as exc:
            ap.error(str(exc))
    except SystemExit as exc:  # --help (0) or a usage error, already reported in one line
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    out = sys.stdout

    exe = find_estopd(args.estopd)
    if exe is None:
        sys.stderr.write("estop demo: estopd not found (run `make setup`, or build it with "
                         "`make -C firmware`, or pass --estopd PATH)\n")
        return EXIT_NOT_INSTALLED

    live = out.isatty() and not args.plain and os.environ.get("TERM", "") != "dumb"
    out.write(f"estop demo: {exe} on 127.0.0.1 with a fresh key, two stages: SLOWING (brake "
              f"{settings.slow_level} %) after S = {settings.slow_ms} ms without a valid "
              f"packet, STOPPED at T = {settings.timeout_ms} ms; beside it a version-2 unit "
              f"(T = {V2_TIMEOUT_MS} ms, one stage); the car at {args.speed_kmh:g} km/h; CAN "
              f"frames logged to a pipe (no CAN hardware, no root)\n")
    page = None
    if args.dashboard:
        page = _start_dashboard(args.dashboard, out)
        if page is None:
            return 2
    return run_demo(exe, settings, out, live=live, tee=None if page is None else page.tee,
                    on_stopped=None if page is None else page.close)
