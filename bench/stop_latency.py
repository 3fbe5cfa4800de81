"""Stop latency of estopd against a plain asyncio baseline, idle and under a UDP flood.

Three measurements, each over many quick trials, for each daemon (estopd and
``bench/baseline_asyncio.py``), each at idle and while another process floods the daemon's UDP
port with invalid packets (loopback only, bounded in time). The daemons run at once and the
trials alternate between them in blocks (--block), so background load on the machine falls on
all alike; the one flooder is aimed at the daemon whose block runs. The report also gives the
CPU other processes used meanwhile, hypervisor steal, and a reference measurement of this
machine's own timer wake-up latency, so that a tail can be told apart from the machine's.

- timeout overshoot = first stop frame - (last valid packet sent + timeout)
- TCP stop latency  = first stop frame (brake_request 1) - STOP sent
- lift stop latency = first stop frame with reason lift - first lift datagram sent (the
  remote's three lift datagrams 10 ms apart, spec section 8)

A trial: pause a random 0..10 ms, send 5 neutral valid packets, RELEASE over TCP (retried
if refused), then either drive 3 packets 1 ms apart and go silent (timeout trial), drive 1
packet and send STOP (TCP trial), or drive 3 packets 1 ms apart and lift (lift trial). Frame
times are the daemon's own can-log stamps (CLOCK_REALTIME); send times are time.time() taken
just before the send call (same clock). A trial whose send call itself took longer than
--send-slack-ms (the bench was descheduled, so the send time is uncertain), whose packets left
gaps over half the timeout, or (TCP, lift trial) whose link timed out before the request was
handled is discarded, counted and its reason reported. Stops with the wrong reason, missing
stops and early stops (overshoot < 0) are counted and reported, never dropped.

Roll-out: for every timeout and lift trial, the distance the car rolled at --speed-kmh (15)
from the moment that mattered (the last packet, the first lift datagram) to standstill, from
the trial's can-log frames through ``estop.model.rollout`` (docs/VEHICLE.md), as percentiles.

Lost log lines (issue 11): the daemon writes its can-log through a queue and drops lines when
its reader is slow, so a lost first stop frame would make the next one look like a late stop.
A trial is discarded with the reason "log lines lost" when the alive counters of ESTOP_BRAKE
or ESTOP_STATUS jump between RELEASE and the stop frame, or when the daemon's own
``output_dropped`` report (up to a second late) covers the trial: samples stay provisional
and are checked again after every block and once the daemon has exited.

Options for the closing notes (``bench/latency_tables.py`` runs them all):

- ``--rt-prio N``: estopd's own ``--rt-prio N`` (SCHED_FIFO for its loop; its output threads
  stay at normal priority), the baseline under ``chrt -f N``; the bench's sender and can-log
  readers then run under SCHED_FIFO too, a little below (``--bench-rt-prio``, default N - 10;
  0 keeps the bench at normal priority);
- ``--hog N``: N busy-loop processes at normal priority for the whole run (CPU contention);
- ``--auth``: estopd with a fresh key (``--key-file``, mode 0600, in a temporary directory)
  against estopd without one; the bench's link sends authenticated packets and request frames
  (learning the session with a STATUS), and the flood is forged authenticated packets (right
  session, valid body, wrong tag), each costing the keyed daemon a BLAKE2s;
- ``--estopd-before PATH``: a previous estopd binary (e.g. built from git history) runs side
  by side as the same unit "before" (``--before-label``): kernel drops, receive buffer and
  overshoot before / after from the same run (a version 2 binary gets no lift trials);
- ``--slow-ms S``: the two-stage configuration: estopd ``--slow-ms S --timeout-ms T`` against
  a single-stage estopd at the same T and the baseline with the same S and T, silence trials
  only: SLOWING at S, STOPPED at T and the distance rolled.

The bench's parts, each a module beside this script (imports go one way, down this list):
``latency_stats`` (percentiles, summaries), ``latency_flood`` (the flood child, kernel drops,
the daemon's receive buffer), ``latency_machine`` (CPU meter, timer floor, busy loops),
``latency_roll`` (the roll-out of a trial), ``latency_result`` (what a run measured),
``latency_trials`` (the trials), ``latency_run`` (daemons side by side under one load),
``latency_goals``, ``latency_report`` (Markdown, JSON), ``latency_plot`` (histogram); this
script is the command line and re-exports their names.

Outputs: a Markdown table (printed and saved), JSON with the raw samples, and a PNG histogram,
in bench/out/ by default. Goals are checked and printed; the exit code is 0 unless the bench
could not run (or --strict and a goal failed).

    bench/stop_latency.py [--quick] [--trials N] [--timeout-ms 20] [--flood-rate 80000]
                          [--rt-prio N [--bench-rt-prio M]] [--hog N] [--auth]
                          [--estopd-before PATH [--before-label v2]]
                          [--slow-ms S [--slow-level 30]] [--speed-kmh 15]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the bench's modules beside this script (also when imported)
    sys.path.insert(0, str(HERE))

from estop.model.vehicle import VehicleParams  # noqa: E402
from estop.unit.daemon import Daemon, find_estopd, set_realtime  # noqa: E402
from latency_flood import (  # noqa: E402
    FLOOD_PAYLOADS,
    FORGED_REMOTE_ID,
    Flood,
    FloodStats,
    forged_packets,
    udp_drops,
)
from latency_goals import check_goals  # noqa: E402
from latency_machine import CpuMeter, Hogs, timer_floor  # noqa: E402
from latency_plot import plot  # noqa: E402
from latency_report import KEYED, KEYLESS, document, markdown  # noqa: E402
from latency_result import (  # noqa: E402
    LOST_LINES,
    METRIC_TITLES,
    METRICS,
    PLAIN_METRICS,
    ROLE_BASELINE,
    ROLE_BEFORE,
    ROLE_KEYLESS,
    ROLE_SINGLE,
    TWO_STAGE_METRICS,
    V2_METRICS,
    RunResult,
)
from latency_roll import DEFAULT_SPEED_KMH, braking_distance, roll_from_record  # noqa: E402
from latency_run import FLOOR_PERIOD_MS, DaemonSpec, make_key_file, run_load  # noqa: E402
from latency_stats import fmt_ms, log_bins, percentile, say, summarize  # noqa: E402
from latency_trials import LiftSent, TcpSent, TimeoutSent, Trials  # noqa: E402

__all__ = [  # the bench's names, for tests/harness/test_bench_*.py (they load this script)
    "FLOOD_PAYLOADS", "FORGED_REMOTE_ID", "KEYED", "KEYLESS", "LOST_LINES", "METRICS",
    "METRIC_TITLES", "CpuMeter", "PLAIN_METRICS", "TWO_STAGE_METRICS", "V2_METRICS",
    "DaemonSpec", "Flood", "FloodStats", "Hogs", "LiftSent", "RunResult", "TcpSent",
    "TimeoutSent", "Trials", "braking_distance", "check_goals", "document", "fmt_ms",
    "forged_packets", "log_bins", "main", "markdown", "percentile", "plot", "roll_from_record",
    "run_load", "summarize", "udp_drops",
]

BENCH_BELOW_DAEMON = 10  # default real-time priority of the bench: this far below the daemon's


# --------------------------------------------------------------------------------------------


def _exit_on_term(_sig: int, _frame: object) -> None:
    # SIGTERM unwinds like an error, so the daemons, the flood and the busy loops are ended
    # (the default action left them running)
    raise SystemExit(128 + signal.SIGTERM)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    signal.signal(signal.SIGTERM, _exit_on_term)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000, help="trials per metric and run")
    ap.add_argument("--quick", action="store_true", help="smoke run: 100 trials")
    ap.add_argument("--timeout-ms", type=int, default=20)
    ap.add_argument("--flood-rate", type=float, default=80_000.0,
                    help="invalid packets/s sent during the flood runs (goal: >= 50,000)")
    ap.add_argument("--send-slack-ms", type=float, default=0.25,
                    help="discard a trial whose send call took longer than this")
    ap.add_argument("--block", type=int, default=50,
                    help="trials per daemon before switching to the other one")
    ap.add_argument("--max-run-s", type=float, default=300.0,
                    help="time limit of one load (both daemons)")
    ap.add_argument("--rt-prio", type=int, default=0, metavar="PRIO",
                    help="real-time daemons, as a deployment would run them: estopd with its "
                         "own --rt-prio PRIO (SCHED_FIFO loop, output threads normal), the "
                         "baseline under `chrt -f PRIO` (needs CAP_SYS_NICE); 0 = off")
    ap.add_argument("--bench-rt-prio", type=int, default=None, metavar="PRIO",
                    help="SCHED_FIFO priority of the bench's sender and can-log readers "
                         f"(default: --rt-prio minus {BENCH_BELOW_DAEMON}, at least 1, when "
                         "--rt-prio is set; 0 = normal priority)")
    ap.add_argument("--hog", type=int, default=0, metavar="N",
                    help="run N busy-loop processes at normal priority throughout (CPU "
                         "contention; 2 = one per core here)")
    ap.add_argument("--auth", action="store_true",
                    help="estopd with a fresh key (--key-file) against estopd without one; "
                         "authenticated link, flood of forged authenticated packets")
    ap.add_argument("--estopd", metavar="PATH", help="estopd binary (default: found like "
                    "`estop demo` does)")
    ap.add_argument("--estopd-before", metavar="PATH",
                    help="a previous estopd binary (e.g. built from git history) run side by "
                         "side as the same unit before a change: drops, receive buffer and "
                         "overshoot before / after in one run")
    ap.add_argument("--before-label", default="before",
                    help="its name in the report, after the unit's (default: before)")
    ap.add_argument("--slow-ms", type=int, default=None, metavar="S",
                    help="the two-stage configuration: estopd --slow-ms S beside a "
                         "single-stage estopd and the baseline with the same S, silence "
                         "trials only (S < --timeout-ms)")
    ap.add_argument("--slow-level", type=int, default=30, metavar="L",
                    help="brake level while SLOWING, percent (with --slow-ms; default 30)")
    ap.add_argument("--speed-kmh", type=float, default=DEFAULT_SPEED_KMH,
                    help="speed of the car for the roll-out distances (default 15 km/h)")
    ap.add_argument("--decel", type=float, default=8.0, metavar="M_S2",
                    help="the car's emergency deceleration for the roll-out (default 8 m/s^2, "
                         "docs/VEHICLE.md)")
    ap.add_argument("--only", choices=("estopd", "baseline"), help="run one daemon only "
                    "(with --auth: estopd = the keyed one)")
    ap.add_argument("--loads", default="idle,flood", help="comma-separated: idle,flood")
    ap.add_argument("--out", type=Path, default=HERE / "out")
    ap.add_argument("--no-floor", action="store_true",
                    help="skip the reference measurement of the machine's timer wake-up")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a goal fails")
    args = ap.parse_args(argv)
    n = 100 if args.quick else args.trials
    if not 0 <= args.rt_prio <= 99:
        ap.error("--rt-prio takes 1..99 (0 = off)")
    if args.bench_rt_prio is None:
        args.bench_rt_prio = max(1, args.rt_prio - BENCH_BELOW_DAEMON) if args.rt_prio else 0
    if not 0 <= args.bench_rt_prio <= 99:
        ap.error("--bench-rt-prio takes 1..99 (0 = normal priority)")
    if args.hog < 0:
        ap.error("--hog takes a number of busy loops >= 0")
    if args.auth and args.only == "baseline":
        ap.error("--auth compares estopd with and without a key; the baseline has no key")
    if args.slow_ms is not None:
        if not 0 < args.slow_ms < args.timeout_ms:
            ap.error("--slow-ms takes 1 .. --timeout-ms minus 1 (a two-stage unit)")
        if args.auth or args.estopd_before:
            ap.error("--slow-ms is a configuration of its own (no --auth, --estopd-before)")
    if not 1 <= args.slow_level <= 99:
        ap.error("--slow-level takes 1..99")
    if not (args.speed_kmh > 0 and args.decel > 0):
        ap.error("--speed-kmh and --decel take values > 0")
    before = None
    if args.estopd_before:
        before = find_estopd(args.estopd_before)
        if before is None:
            ap.error(f"--estopd-before: no such binary {args.estopd_before}")
    loads = [x for x in args.loads.split(",") if x]
    if any(x not in ("idle", "flood") for x in loads):
        ap.error("--loads takes idle and/or flood")

    exe = None
    if args.only != "baseline":
        exe = find_estopd(args.estopd)
        if exe is None:
            sys.stderr.write("stop_latency: estopd not found (make setup, or make -C firmware,"
                             " or --estopd PATH)\n")
            return 2
    estopd_extra = ["--rt-prio", str(args.rt_prio)] if args.rt_prio else []
    chrt: list[str] = []
    if args.rt_prio and args.only != "estopd" and not args.auth:
        found = shutil.which("chrt")
        if found is None:
            ap.error("--rt-prio needs chrt (util-linux) for the baseline")
        chrt = [found, "-f", str(args.rt_prio)]

    with tempfile.TemporaryDirectory(prefix="estop-bench-") as tmp:
        daemons = daemon_specs(args, exe, before, Path(tmp), estopd_extra, chrt)
        return _run(args, n, loads, daemons)


def binary_version(exe: str) -> str | None:
    """``estopd 3.0`` from ``exe --version``; None when it does not say."""
    try:
        out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return None
    text = out.stdout.strip().splitlines()
    return text[0] if out.returncode == 0 and text else None


def daemon_specs(args: argparse.Namespace, exe: str | None, before: str | None, tmp: Path,
                 estopd_extra: list[str], chrt: list[str]) -> list[DaemonSpec]:
    """The daemons of the run, the unit under test first."""
    baseline = [*chrt, sys.executable, str(HERE / "baseline_asyncio.py")]
    if args.slow_ms is not None:  # two-stage: silence trials only
        two = ["--slow-ms", str(args.slow_ms), "--slow-level", str(args.slow_level)]
        specs = []
        if exe is not None:
            specs += [DaemonSpec("estopd 2-stage", [exe], extra=[*two, *estopd_extra],
                                 metrics=TWO_STAGE_METRICS, slow_ms=args.slow_ms),
                      DaemonSpec("estopd 1-stage", [exe], extra=estopd_extra,
                                 role=ROLE_SINGLE, metrics=("overshoot",))]
        if args.only != "estopd":
            specs.append(DaemonSpec("baseline 2-stage", baseline, extra=two,
                                    role=ROLE_BASELINE, metrics=TWO_STAGE_METRICS,
                                    slow_ms=args.slow_ms))
        return specs
    key, key_file = make_key_file(tmp) if args.auth else (None, None)
    main_name = KEYED if args.auth else "estopd"
    specs = []
    if exe is not None:
        specs.append(DaemonSpec(main_name, [exe], key, key_file, estopd_extra))
    if before is not None:
        version = binary_version(before) or ""
        lift = version.split(" ")[-1][:1] not in ("1", "2")  # LIFT came with version 3
        specs.append(DaemonSpec(f"{main_name} {args.before_label}", [before], key, key_file,
                                estopd_extra, role=ROLE_BEFORE,
                                metrics=PLAIN_METRICS if lift else V2_METRICS))
    if args.auth and args.only is None:
        specs.append(DaemonSpec(KEYLESS, [exe or ""], extra=estopd_extra, role=ROLE_KEYLESS))
    elif not args.auth and args.only != "estopd":
        specs.append(DaemonSpec("baseline", baseline, role=ROLE_BASELINE))
    return specs


def before_meta(args: argparse.Namespace, daemons: Sequence[DaemonSpec]
                ) -> dict[str, Any] | None:
    """The previous estopd of the run, for the report: label, path, version."""
    spec = next((d for d in daemons if d.role == ROLE_BEFORE), None)
    if spec is None:
        return None
    return {"label": spec.name, "path": spec.command[0],
            "version": binary_version(spec.command[0])}


def priorities(args: argparse.Namespace, names: Sequence[str] = ()) -> str:
    """One sentence on who ran at which priority, for the report."""
    if args.rt_prio:
        base = "; the baseline under chrt -f" if "baseline" in names else ""
        daemon = (f"daemons SCHED_FIFO {args.rt_prio} (estopd: its own --rt-prio {args.rt_prio}"
                  f", its loop only, its output threads at normal priority{base})")
    else:
        daemon = "daemons at normal priority"
    if args.bench_rt_prio:
        bench = (f"the bench's sender and can-log readers SCHED_FIFO {args.bench_rt_prio}"
                 + (" (below the daemons, so the reader keeps up on a busy machine)"
                    if args.rt_prio else ""))
    else:
        bench = "the bench (sender and can-log readers) at normal priority"
    return f"{daemon}; {bench}"


class PrioError(Exception):
    """The bench could not change its own scheduling. ``str()`` is one line."""


def _prio(prio: int) -> None:
    """The calling thread to SCHED_FIFO ``prio`` (0: normal priority)."""
    try:
        set_realtime(prio)
    except OSError as exc:
        raise PrioError(f"cannot run the bench at real-time priority {prio} ({exc.strerror}; "
                        f"needs CAP_SYS_NICE or RLIMIT_RTPRIO)") from None


def _run(args: argparse.Namespace, n: int, loads: list[str], daemons: list[DaemonSpec]) -> int:
    t_start = time.monotonic()
    hogs = Hogs(args.hog) if args.hog else None
    results: list[RunResult] = []
    floor: dict[str, Any] = {}
    floor_samples: list[float] = []
    try:
        if not args.no_floor:
            period_ms = min(args.timeout_ms, FLOOR_PERIOD_MS)
            say(f"reference: this machine's timer wake-up latency, {n} sleeps of "
                f"{period_ms} ms ...")
            meter = CpuMeter()
            for pid in hogs.pids if hogs else ():
                meter.watch(pid)
            if args.rt_prio:  # the floor a daemon at its priority could reach
                _prio(args.rt_prio)
            floor_samples = timer_floor(n, period_ms / 1000.0)
            _prio(0)
            floor["timer_floor_ms"] = summarize(floor_samples)
            floor["timer_floor_prio"] = args.rt_prio
            floor["timer_floor_period_ms"] = period_ms
            cpu = meter.finish()
            if cpu is not None:
                floor["timer_floor_other_cpu"] = round(cpu[0], 2)
                floor["timer_floor_steal"] = round(cpu[1], 2)
        if args.bench_rt_prio:
            _prio(args.bench_rt_prio)  # reset on fork: daemons, flood, hogs stay normal
        names = [d.name for d in daemons]
        say(f"priorities: {priorities(args, names)}"
            + (f"; {args.hog} busy loops" if hogs else ""))
        for load in loads:
            say(f"{load}: {' and '.join(d.name for d in daemons)} side by side, {n} trials per "
                f"metric each, alternating in blocks of {args.block} ...")
            for r in run_load(load, daemons, args, n, hogs.pids if hogs else ()):
                results.append(r)
                extra = f", flood {r.flood.rate:,.0f}/s" if r.flood else ""
                err = f", ERROR {r.error}" if r.error else ""
                lost = sum(r.lost_discards(m) for m in METRICS)
                counts = " + ".join(f"{len(r.samples[m])} {m}" for m in r.metrics)
                say(f"  {r.daemon}: {counts} samples, {lost} trials with log lines "
                    f"lost{extra}{err}")
            say(f"  {load} done in {results[-1].wall_s:.1f} s")
    except PrioError as exc:
        sys.stderr.write(f"stop_latency: {exc}\n")
        return 2
    finally:
        if hogs is not None:
            hogs.stop()
        with contextlib.suppress(OSError):
            set_realtime(0)

    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "host": platform.node(),
            "cpus": os.cpu_count(), "python": platform.python_version(),
            "timeout_ms": args.timeout_ms, "trials": n, "flood_rate": args.flood_rate,
            "send_slack_ms": args.send_slack_ms, "block": args.block,
            "rt_prio": args.rt_prio, "bench_rt_prio": args.bench_rt_prio,
            "priorities": priorities(args, [d.name for d in daemons]), "hog": args.hog,
            "hog_cpu_cores": None if hogs is None or hogs.cpu_cores is None
            else round(hogs.cpu_cores, 2),
            "auth": args.auth, "argv": sys.argv[1:],
            "speed_kmh": args.speed_kmh, "decel_ms2": args.decel,
            "braking_m": round(braking_distance(args.speed_kmh,
                                                VehicleParams(emergency_decel=args.decel)), 4),
            "slow_ms": args.slow_ms, "slow_level": args.slow_level if args.slow_ms else None,
            "before": before_meta(args, daemons),
            "commands": {d.name: Daemon(d.command, timeout_ms=args.timeout_ms,
                                        extra_args=d.extra, key_file=d.key_file).argv
                         for d in daemons},
            **floor, "bench_wall_s": round(time.monotonic() - t_start, 1)}
    floor_p999 = floor["timer_floor_ms"]["p99.9"] if floor else None
    goals = check_goals(results, auth=args.auth, floor_p999=floor_p999)
    md = markdown(results, meta, goals)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stop_latency.md").write_text(md)
    doc = document(results, meta, goals)
    doc["timer_floor_samples_ms"] = floor_samples
    (args.out / "stop_latency.json").write_text(json.dumps(doc, indent=1, allow_nan=True))
    plot(results, args.out / "stop_latency.png", args.timeout_ms, floor_samples)
    say()
    say(md)
    say(f"bench wall time {meta['bench_wall_s']} s; wrote {args.out}/stop_latency.md, "
        f".json, .png")
    if args.strict and not all(ok for _, ok in goals):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
