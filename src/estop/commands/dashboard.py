"""``estop dashboard``: the live status page a safety driver keeps open beside the track.

Inputs (:mod:`estop.dashboard.feed`): the bus from python-can (``-i socketcan -c can0``, or
python-can's own configuration, as ``estop monitor`` reads it), or a can-utils log being
written (``--can-log FILE``, followed as ``tail -f`` does; ``-`` for standard input), and
estopd's ``--log-json`` log (``--log FILE`` or ``-``: a file being written, a pipe,
``journalctl -u estopd -o cat -f | estop dashboard --log - ...``). What the page shows is
:mod:`estop.dashboard.model`; the web side :mod:`estop.dashboard.server`.

It listens on 127.0.0.1:8080 unless told otherwise (``--listen``): another address shows
the page to the network, an explicit choice. It can never release or drive the car; with
``--allow-stop`` the page has a STOP button, which does what ``estop stop`` does, to the unit
of the common settings (``--host``, ``ESTOP_HOST`` or the configuration file, as every
command reads them).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
from typing import Any

from estop.commands.canbus import can_bus_config
from estop.commands.configfile import config_path
from estop.commands.options import (
    add_can_options,
    add_frame_id_options,
    add_time_option,
    parse_listen,
)
from estop.commands.output import err, out
from estop.commands.settings import add_settings, key_from_args
from estop.errors import EXIT_OK, ConnectionFailure, NotInstalled, UsageError
from estop.protocol import tcp
from estop.unit.bus import open_bus

__all__ = ["DEFAULT_LISTEN", "DESCRIPTION", "EPILOG", "add_parser", "bus_config", "run"]

DEFAULT_LISTEN = "127.0.0.1:8080"
DESCRIPTION = ("Serve a live status page of the unit: its state (ARMED, SLOWING, STOPPED with "
               "the reason, NO SIGNAL after 50 ms without a good ESTOP_BRAKE), the frames' "
               "health, the ESTOP_STATUS fields, the link from estopd's link_histogram "
               "events, the last state changes and the stops by reason. Inputs: a python-can "
               "bus or a can-utils log being written (--can-log), and estopd's --log-json "
               "log (--log). It never releases or drives the car; --allow-stop adds a STOP "
               "button (as estop stop).")
EPILOG = ("examples: estopd --can-log can.log --log-json 2>estopd.log & estop dashboard "
          "--can-log can.log --log estopd.log | journalctl -u estopd -o cat -f | estop "
          "dashboard -i socketcan -c can0 --log -. Exit codes: 0 ended (Ctrl-C), 2 usage "
          "error, 3 the bus, a file or the listening address cannot be opened.")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = sub.add_parser("dashboard", help="serve the live status page (state, frames, "
                            "link, timeline)", description=DESCRIPTION, epilog=EPILOG)
    parser.set_defaults(handler=run)
    parser.add_argument("--can-log", metavar="FILE",
                        help="a can-utils log being written (estopd --can-log FILE, candump "
                             "-L), followed as tail -f does; '-': standard input (instead of "
                             "a python-can bus)")
    add_can_options(parser)
    parser.add_argument("--log", metavar="FILE",
                        help="estopd's --log-json log: a file being written, a pipe, or '-' "
                             "(standard input, e.g. journalctl -u estopd -o cat -f)")
    parser.add_argument("--listen", default=DEFAULT_LISTEN, metavar="ADDR:PORT",
                        help=f"serve the page here (default {DEFAULT_LISTEN}: this machine "
                             "only; another address is an explicit choice; port 0: any free)")
    add_frame_id_options(parser)
    add_settings(parser, "rate_hz", help={"rate_hz": "the remote's send rate, for the link fit"})
    stop = parser.add_argument_group("the STOP button (only with --allow-stop)")
    stop.add_argument("--allow-stop", action="store_true",
                      help="show a STOP button that presses stop as estop stop does (stop "
                           "datagram and TCP STOP, retried); never a release")
    add_settings(parser, "host", "tcp_port", "udp_port", "stop_id", "key_file", "remote_id",
                 host_required=False, group=stop,
                 help={"host": "the unit the STOP button stops",
                       "udp_port": "the unit's UDP control port, for the stop datagram"})
    add_time_option(stop, "stop-deadline", "stop_deadline", 3.0,
                    "a press tries again until the unit answers or this time passes")


def _check(args: argparse.Namespace) -> None:
    if args.can_log == "-" and args.log == "-":
        raise UsageError("only one of --can-log and --log can read standard input")
    if args.can_log is not None and any(x is not None for x in (args.interface, args.channel,
                                                                 args.bitrate)):
        raise UsageError("--can-log reads a file: --interface, --channel and --bitrate are for "
                         "a live bus")
    if args.allow_stop and not args.host:
        raise UsageError(f"--allow-stop needs the unit to stop: give --host, or set ESTOP_HOST "
                         f"or host in {config_path()}")
    try:
        tcp.check_stop_id(args.stop_id)
    except ValueError as exc:
        raise UsageError(f"--stop-id: {exc}") from None


def bus_config(args: argparse.Namespace) -> dict[str, object] | None:
    """The bus to read, as ``estop monitor`` opens it (the command line over python-can's
    configuration); None with --can-log, and with --log alone where python-can names no bus
    (or is not installed)."""
    if args.can_log is not None:
        return None
    named = any(x is not None for x in (args.interface, args.channel, args.bitrate))
    try:
        return can_bus_config(args)
    except (UsageError, NotInstalled) as exc:
        if args.log is not None and not named:
            return None  # the log alone is an input
        if isinstance(exc, NotInstalled) or named:
            raise
        raise UsageError("name an input: --can-log FILE, a python-can bus (--interface, or "
                         "python-can's configuration: CAN_INTERFACE, ~/.canrc), --log "
                         "FILE") from None


def run(args: argparse.Namespace) -> int:
    _check(args)
    host, listen_port = parse_listen(args.listen)
    try:
        from estop.dashboard.model import DashboardModel
        from estop.dashboard.server import stop_action_for
    except ModuleNotFoundError as exc:
        raise UsageError(f"estop dashboard needs the 'dashboard' extra (pip install "
                         f"'estop[dashboard]'): {exc.name} is missing") from None
    stop_action = None
    if args.allow_stop:
        stop_action = stop_action_for(args.host, args.tcp_port, args.udp_port,
                                      key=key_from_args(args), remote_id=args.remote_id,
                                      stop_id=args.stop_id, timeout=2.0,
                                      deadline=args.stop_deadline)
    config = bus_config(args)
    bus = None if config is None else open_bus(config)
    model = DashboardModel(brake_id=args.brake_id, status_id=args.status_id,
                           rate_hz=args.rate_hz)
    try:
        asyncio.run(_serve(args, model, host, listen_port, bus, stop_action))
    except KeyboardInterrupt:
        pass
    return EXIT_OK


async def _serve(args: argparse.Namespace, model: Any, host: str, listen_port: int, bus: Any,
                 stop_action: Any) -> None:
    from estop.dashboard.feed import BusFeed, open_line_feed
    from estop.dashboard.server import DashboardServer

    loop = asyncio.get_running_loop()
    server = DashboardServer(model, host, listen_port, stop_action=stop_action)
    feeds: list[Any] = []
    try:
        if bus is not None:
            feeds.append(BusFeed(bus, server.frame, server.note))
        try:
            if args.can_log is not None:
                feeds.append(open_line_feed(args.can_log, server.can_line, server.note))
            if args.log is not None:
                feeds.append(open_line_feed(args.log, server.log_line, server.note))
        except OSError as exc:
            raise ConnectionFailure(f"cannot read {exc.filename}: {exc.strerror}") from None
        try:
            await server.start()
        except OSError as exc:
            raise ConnectionFailure(f"cannot listen on {args.listen}: "
                                    f"{exc.strerror or exc}") from None
        shown = f"[{host}]" if ":" in host else host
        default = (" (the default: this machine only; --listen ADDR:PORT for another)"
                   if args.listen == DEFAULT_LISTEN else "")
        out(f"estop dashboard: listening on http://{shown}:{server.port}/{default}")
        if host not in ("127.0.0.1", "localhost", "::1"):
            err(f"estop dashboard: the page is open to the network on {host} (--listen)")
        for feed in feeds:
            feed.start(loop)
        done = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, done.set)
        try:
            await done.wait()
        finally:
            # Ctrl-C is the process's own again (a caller in the same process, tests too,
            # would otherwise find SIGINT still going to this loop's wake-up pipe)
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
    finally:
        for feed in feeds:
            with contextlib.suppress(Exception):
                feed.close()
        await server.close()
