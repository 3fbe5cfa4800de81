"""Stop latency of estopd against a plain asyncio baseline, idle and under a UDP flood.

Two measurements, each over many quick trials, for each daemon (estopd and
``bench/baseline_asyncio.py``), each at idle and while another process floods the daemon's UDP
port with invalid packets (loopback only, bounded in time). Both daemons run at once and the
trials alternate between them in blocks (--block), so background load on the machine falls on
both alike; the one flooder is aimed at the daemon whose block runs. The report also gives the
CPU other processes used meanwhile, hypervisor steal, and a reference measurement of this
machine's own timer wake-up latency, so that a tail can be told apart from the machine's.

- timeout overshoot = first stop frame - (last valid packet sent + timeout)
- TCP stop latency  = first stop frame (brake_request 1) - STOP sent

A trial: pause a random 0..10 ms, send 5 neutral valid packets, RELEASE over TCP (retried
if refused), then either drive 3 packets 1 ms apart and go silent (timeout trial), or drive 1
packet and send STOP (TCP trial). Frame times are the daemon's own can-log stamps
(CLOCK_REALTIME); send times are time.time() taken just before the send call (same clock).
A trial whose send call itself took longer than --send-slack-ms (the bench was descheduled,
so the send time is uncertain), whose packets left gaps over half the timeout, or (TCP trial)
whose link timed out before the STOP was handled is discarded, counted and its reason
reported. Stops with the wrong reason, missing stops and early stops (overshoot < 0) are
counted and reported, never dropped.

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
  session, valid body, wrong tag), each costing the keyed daemon a BLAKE2s.

The bench's parts, each a module beside this script (imports go one way, down this list):
``latency_stats`` (percentiles, summaries), ``latency_flood`` (the flood child, kernel drops),
``latency_machine`` (CPU meter, timer floor, busy loops), ``latency_trials`` (a run's results,
the trials), ``latency_run`` (daemons side by side under one load), ``latency_report`` (goals,
Markdown, JSON, histogram); this script is the command line and re-exports their names.

Outputs: a Markdown table (printed and saved), JSON with the raw samples, and a PNG histogram,
in bench/out/ by default. Goals are checked and printed; the exit code is 0 unless the bench
could not run (or --strict and a goal failed).

    bench/stop_latency.py [--quick] [--trials N] [--timeout-ms 20] [--flood-rate 80000]
                          [--rt-prio N [--bench-rt-prio M]] [--hog N] [--auth]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the bench's modules beside this script (also when imported)
    sys.path.insert(0, str(HERE))

from estop.loopback import Daemon, find_estopd, set_realtime  # noqa: E402
from latency_flood import (  # noqa: E402
    FLOOD_PAYLOADS,
    Flood,
    FloodStats,
    forged_packets,
    udp_drops,
)
from latency_machine import CpuMeter, Hogs, timer_floor  # noqa: E402
from latency_report import KEYED, KEYLESS, check_goals, document, markdown, plot  # noqa: E402
from latency_run import DaemonSpec, make_key_file, run_load  # noqa: E402
from latency_stats import fmt_ms, log_bins, percentile, say, summarize  # noqa: E402
from latency_trials import (  # noqa: E402
    LOST_LINES,
    METRIC_TITLES,
    METRICS,
    RunResult,
    TcpSent,
    TimeoutSent,
    Trials,
)

__all__ = [  # the bench's names, for tests/test_bench_*.py (they load this script)
    "FLOOD_PAYLOADS", "KEYED", "KEYLESS", "LOST_LINES", "METRICS", "METRIC_TITLES", "CpuMeter",
    "DaemonSpec", "Flood", "FloodStats", "Hogs", "RunResult", "TcpSent", "TimeoutSent",
    "Trials", "check_goals", "document", "fmt_ms", "forged_packets", "log_bins", "main",
    "markdown", "percentile", "plot", "run_load", "summarize", "udp_drops",
]

BENCH_BELOW_DAEMON = 10  # default real-time priority of the bench: this far below the daemon's


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
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
        daemons: list[DaemonSpec] = []
        if args.auth:
            assert exe is not None
            key, key_file = make_key_file(Path(tmp))
            daemons.append(DaemonSpec(KEYED, [exe], key, key_file, estopd_extra))
            if args.only is None:
                daemons.append(DaemonSpec(KEYLESS, [exe], extra=estopd_extra))
        else:
            if exe is not None:
                daemons.append(DaemonSpec("estopd", [exe], extra=estopd_extra))
            if args.only != "estopd":
                daemons.append(DaemonSpec("baseline", [*chrt, sys.executable,
                                                       str(HERE / "baseline_asyncio.py")]))
        return _run(args, n, loads, daemons)


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
            say(f"reference: this machine's timer wake-up latency, {n} sleeps of "
                f"{args.timeout_ms} ms ...")
            meter = CpuMeter()
            for pid in hogs.pids if hogs else ():
                meter.watch(pid)
            if args.rt_prio:  # the floor a daemon at its priority could reach
                _prio(args.rt_prio)
            floor_samples = timer_floor(n, args.timeout_ms / 1000.0)
            _prio(0)
            floor["timer_floor_ms"] = summarize(floor_samples)
            floor["timer_floor_prio"] = args.rt_prio
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
                say(f"  {r.daemon}: {len(r.samples['overshoot'])} + "
                    f"{len(r.samples['tcp_stop'])} samples, {lost} trials with log lines "
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
            "commands": {d.name: Daemon(d.command, timeout_ms=args.timeout_ms,
                                        extra_args=d.extra, key_file=d.key_file).argv
                         for d in daemons},
            **floor, "bench_wall_s": round(time.monotonic() - t_start, 1)}
    goals = check_goals(results, auth=args.auth)
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
