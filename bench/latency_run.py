"""One load of the stop-latency bench: the daemons side by side, trials alternating between
them in blocks, the flood aimed at the daemon whose block runs."""

from __future__ import annotations

import argparse
import gc
import queue
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from estop.client.keyfile import write_key_file
from estop.model.vehicle import VehicleParams
from estop.protocol import tcp
from estop.unit.canlog import DaemonError
from estop.unit.daemon import Daemon
from estop.unit.looplink import Link
from latency_flood import Flood, reported_deadline_cuts, reported_udp_drops, start_rcvbuf
from latency_machine import CpuMeter, timer_floor
from latency_result import PLAIN_METRICS, ROLE_MAIN, RunResult
from latency_trials import Trials

FLOOR_SLEEPS = 5  # timer wake-ups measured before each block
FLOOR_PERIOD_MS = 20  # their period: the bench's timeout, at most this long


@dataclass
class Contender:
    name: str
    daemon: Daemon
    result: RunResult
    link: Link | None = None
    trials: Trials | None = None
    attempts: int = 0


def _drain(daemon: Daemon) -> None:
    while True:
        try:
            daemon.frames.get_nowait()
        except queue.Empty:
            return


@dataclass
class DaemonSpec:
    """One daemon of a run: its name in the report, its command, its key (None: --no-auth),
    extra options, what it is in the run (``ROLE_*``), the metrics it is measured on, and its
    slow time S when it is a two-stage unit."""

    name: str
    command: list[str]
    key: bytes | None = None
    key_file: str | None = None
    extra: list[str] = field(default_factory=list)
    role: str = ROLE_MAIN
    metrics: tuple[str, ...] = PLAIN_METRICS
    slow_ms: int | None = None


def run_load(load: str, daemons: list[DaemonSpec], args: argparse.Namespace, n: int,
             watch_pids: Sequence[int] = ()) -> list[RunResult]:
    """All daemons side by side under one load: they run at once, and trials alternate
    between them in blocks, so background load on the machine falls on both alike. The
    flood (one child) is aimed at the daemon whose block is running. ``watch_pids`` (the
    hogs) count as the bench's own processes in the CPU meter."""
    t0 = time.monotonic()
    cons = [Contender(d.name, Daemon(d.command, timeout_ms=args.timeout_ms, extra_args=d.extra,
                                     key_file=d.key_file, reader_rt_prio=args.bench_rt_prio),
                      RunResult(d.name, load, args.timeout_ms, metrics=d.metrics, role=d.role,
                                slow_ms=d.slow_ms)) for d in daemons]
    vehicle = VehicleParams(emergency_decel=args.decel)
    floor_s = min(args.timeout_ms, FLOOR_PERIOD_MS) / 1000.0
    flood: Flood | None = None
    try:
        for c, spec in zip(cons, daemons, strict=True):
            try:
                c.daemon.start()
                c.link = Link(c.daemon.udp_port, c.daemon.tcp_port, key=spec.key)
                c.trials = Trials(c.daemon, c.link, args.timeout_ms,
                                  args.send_slack_ms / 1000.0, c.result, slow_ms=spec.slow_ms,
                                  speed_kmh=args.speed_kmh, vehicle=vehicle)
                c.result.udp_rcvbuf = start_rcvbuf(c.daemon.log_lines)
            except (DaemonError, OSError, tcp.FrameError) as exc:
                c.result.error = str(exc)
        live = [c for c in cons if c.trials is not None]
        if load == "flood" and live:
            sessions = None
            if args.auth:  # each unit's own session: forgeries that get as far as the tag
                sessions = [(c.link.session if c.link is not None and c.link.session else
                             c.daemon.session or 1) for c in cons]
            flood = Flood([c.daemon.udp_port for c in cons], args.flood_rate,
                          args.max_run_s + 30.0, sessions)
        deadline = time.monotonic() + args.max_run_s
        gc.collect()
        gc.disable()
        try:
            while live and time.monotonic() < deadline:
                for c in list(live):
                    assert c.trials is not None
                    if flood is not None:
                        flood.aim(cons.index(c))
                    # 0.1 s before each block (the daemon under test is in the flood for a
                    # while): the machine's timer wake-up under this load and at this hour,
                    # the floor reported beside the block's latencies
                    c.result.floor_ms += timer_floor(FLOOR_SLEEPS, floor_s)
                    _drain(c.daemon)  # frames logged while the other daemon was tested
                    c.trials.forget_frames()
                    meter = CpuMeter()
                    for other in cons:
                        meter.watch(other.daemon.pid)
                    if flood is not None:
                        meter.watch(flood.pid)
                    for pid in watch_pids:
                        meter.watch(pid)
                    target = min(n, len(c.result.samples["overshoot"]) + args.block)
                    try:
                        c.attempts += c.trials.run(target, deadline, args.block * 3)
                    except (DaemonError, OSError, tcp.FrameError) as exc:
                        c.result.error = str(exc)
                    c.result.add_cpu(meter.finish())
                    c.result.settle(c.daemon.lines_lost)  # losses found since
                    done = all(len(c.result.samples[m]) >= n for m in c.result.trial_kinds)
                    if done or c.result.error or c.attempts > 3 * n:
                        live.remove(c)
        finally:
            gc.enable()
    finally:
        if flood is not None:
            stats = flood.stop()
            for c in cons:
                c.result.flood = stats.get(c.daemon.udp_port)
        for c in cons:
            if c.link is not None:
                c.link.close()
            c.daemon.stop()
            # every line and every drop report is in now: the final word on lost lines
            c.result.settle(c.daemon.lines_lost)
            c.result.log_frames = c.daemon.loss.frames
            c.result.log_gaps = len(c.daemon.loss.gaps)
            c.result.log_gap_lines = c.daemon.loss.lines_lost
            c.result.daemon_dropped = c.daemon.dropped_total
            c.result.daemon_udp_drops = reported_udp_drops(c.daemon.log_lines)
            c.result.deadline_cuts = reported_deadline_cuts(c.daemon.log_lines)
    wall = time.monotonic() - t0
    for c in cons:
        c.result.wall_s = wall
    return [c.result for c in cons]


def make_key_file(directory: Path) -> tuple[bytes, str]:
    """A fresh key in ``directory``/estopd.key, mode 0600 from the start (the package's key
    file writer, as ``estop keygen``)."""
    path = directory / "estopd.key"
    return write_key_file(path), str(path)
