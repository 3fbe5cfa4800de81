"""One run of ``estop demo``: a fresh key, the unit (estopd with the two-stage answer to
silence) and its version-2 twin on loopback, the story played against them, the report and the
checks. The command line is :mod:`estop.commands.demo`."""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from typing import TextIO

from estop.client.keyfile import write_key_file
from estop.demo.bus import BusWatch
from estop.demo.car import LiveCar
from estop.demo.checks import check
from estop.demo.report import clock, match_causes, write_report
from estop.demo.result import Result, Settings
from estop.demo.story import finish_run, run_story
from estop.demo.twin import V2Twin
from estop.demo.view import View
from estop.protocol import tcp
from estop.unit.canlog import DaemonError
from estop.unit.daemon import Daemon
from estop.unit.events import state_changes

__all__ = ["run_demo"]


def run_demo(exe: str, settings: Settings, out: TextIO, *, live: bool,
             tee: Callable[[str, str], None] | None = None,
             on_stopped: Callable[[], None] | None = None) -> int:
    """Play the demo with the estopd binary ``exe``; write its view and report to ``out``
    (refreshing a status line in place when ``live``); ``tee(stream, line)`` also gets every
    line the unit writes (the dashboard's feed), ``on_stopped()`` is called once the units
    have ended. Returns 0, or 1 when a check failed."""
    started = time.monotonic()
    car = LiveCar(settings.speed)
    view = View(out=out, live=live, t0=time.time(), watch=BusWatch(car), car=car)
    keydir = tempfile.TemporaryDirectory(prefix="estop-demo-")
    key_path = os.path.join(keydir.name, "key")
    key = write_key_file(key_path)  # a fresh key, mode 0600
    unit = Daemon([exe], timeout_ms=settings.timeout_ms, extra_args=settings.unit_args(),
                  key_file=key_path, tee=tee)
    twin = V2Twin(exe, key_path, key)
    res = Result(settings)
    try:
        unit.start()
        view.event(time.time(), f"estopd started (pid {unit.pid}), UDP port {unit.udp_port}, "
                                f"TCP port {unit.tcp_port}")
        twin.start()
        view.event(time.time(), f"v2 unit: estopd started (pid {twin.daemon.pid}), timeout "
                                f"{twin.timeout_ms} ms, no slow stage")
        run_story(unit, view, settings, key, res, twin)
    except (DaemonError, OSError, tcp.FrameError) as exc:
        res.problems.append(f"demo aborted: {exc}")
    finally:
        rc, twin_rc = finish_run(unit, view, res, twin)
        keydir.cleanup()
        if on_stopped is not None:
            on_stopped()
    final = view.watch.brake.brake_request if view.watch.brake is not None else None
    view.event(time.time(), f"estopd ended (pid {unit.pid}, exit code {rc}); its last brake "
                            f"frame: brake_request={final}")
    offset = clock()
    causes = match_causes(view.watch.changes, state_changes(unit.log_lines), offset)
    twin_causes = match_causes(twin.watch.changes, state_changes(twin.daemon.log_lines), offset)
    write_report(out, view, res, causes, (twin.watch, twin_causes), unit.dropped_total)

    res.problems += check(res, view.watch, rc, twin_rc)
    for p in res.problems:
        out.write(f"PROBLEM: {p}\n")
    out.write(f"demo {'FAILED' if res.problems else 'ok'} in "
              f"{time.monotonic() - started:.1f} s\n")
    out.flush()
    return 1 if res.problems else 0


