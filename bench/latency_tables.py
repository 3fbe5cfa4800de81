"""The stop-latency figures for the closing notes, as Markdown tables.

Runs ``bench/stop_latency.py`` once per configuration (a fresh process each, so each sets its
own scheduling), reads back its JSON, and prints:

1. plain: estopd against the asyncio baseline, idle and under the invalid-packet flood; its
   lift row (first lift datagram to the stop frame, the timer floor beside it) and the
   roll-out at 15 km/h of the timeout and lift trials;
2. auth (issue 8): estopd with a key against estopd without one, idle and under a flood of
   forged authenticated packets; kernel drops and whether every trial still armed; with
   ``--estopd-before PATH`` (a previous estopd, e.g. built from git history) beside them, the
   forged-flood row before / after: drops, receive buffer, overshoot; auth-rt: the same with
   ``--rt-prio`` (SCHED_FIFO, as deploy/estopd.service runs it);
3. hog: estopd under CPU contention (``--hog``: busy loops at normal priority, one per core
   here), without and with ``--rt-prio``, idle and flooded: p50, p99, p99.9, max overshoot;
4. issue11: the three rows of issue 11 under the same contention: estopd at normal priority;
   estopd ``--rt-prio`` with the bench at normal priority; both real-time (the bench a little
   below). Each with the trials discarded because can-log lines were lost;
5. two-stage: estopd ``--slow-ms S --timeout-ms T`` beside a single-stage estopd at the same
   T and the baseline with S and T (--two-stage-ms S,T, default 100,200; idle, silence trials,
   --two-stage-trials): SLOWING at S, STOPPED at T, metres rolled from the last packet.

Every command run is printed first, so any one can be re-run by hand. Each run's own report
(stop_latency.md/.json/.png) stays in --out/<name>/.

    bench/latency_tables.py [--sets plain,auth,auth-rt,hog,issue11,two-stage] [--trials 1000]
                            [--timeout-ms 20] [--rt-prio 50] [--hog 2]
                            [--estopd-before PATH [--before-label v2]]
                            [--two-stage-ms 100,200] [--two-stage-trials 300]
                            [--out bench/out/tables] [--dry-run]
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the bench's modules beside this script (also when imported)
    sys.path.insert(0, str(HERE))

from latency_report import (  # noqa: E402
    before_after_table,
    lift_table,
    roll_table,
    two_stage_table,
)
from latency_result import RunResult, from_document  # noqa: E402

STOP_LATENCY = HERE / "stop_latency.py"
SETS = ("plain", "auth", "auth-rt", "hog", "issue11", "two-stage")


@dataclass
class Config:
    name: str
    args: list[str]
    what: str  # how the tables call it
    timeout_ms: int | None = None  # its own timeout (else --timeout-ms)
    trials: int | None = None  # its own trials per cell (else --trials)


def configs(sets: list[str], a: argparse.Namespace) -> list[Config]:
    """The runs the chosen sets need, each once (hog and issue11 share two)."""
    hog = ["--hog", str(a.hog), "--only", "estopd"]
    rt = ["--rt-prio", str(a.rt_prio)]
    need_flood = "hog" in sets
    loads = [] if need_flood else ["--loads", "idle"]
    out: list[Config] = []
    if "plain" in sets:
        out.append(Config("plain", [], "estopd vs baseline"))
    before = (["--estopd-before", a.estopd_before, "--before-label", a.before_label]
              if a.estopd_before else [])
    if "auth" in sets:
        out.append(Config("auth", ["--auth", *before], "estopd with a key vs without"
                          + (f", and {a.before_label} beside them" if before else "")))
    if "auth-rt" in sets:
        out.append(Config("auth-rt", ["--auth", *rt],
                          f"estopd with a key vs without, --rt-prio {a.rt_prio} as deployed"))
    if "hog" in sets or "issue11" in sets:
        out.append(Config("hog-normal", [*hog, *loads], "estopd normal priority"))
    if "issue11" in sets:
        out.append(Config("hog-rt-bench-normal",
                          [*hog, *rt, "--bench-rt-prio", "0", "--loads", "idle"],
                          f"estopd --rt-prio {a.rt_prio}, bench at normal priority"))
    if "hog" in sets or "issue11" in sets:
        below = max(1, a.rt_prio - 10)
        out.append(Config("hog-rt", [*hog, *rt, *loads],
                          f"estopd --rt-prio {a.rt_prio}, bench also real-time "
                          f"(SCHED_FIFO {below})"))
    if "two-stage" in sets:
        slow, timeout = a.two_stage_ms
        out.append(Config("two-stage", ["--slow-ms", str(slow), "--loads", "idle"],
                          f"estopd two-stage S {slow} ms, T {timeout} ms vs single-stage",
                          timeout_ms=timeout, trials=a.two_stage_trials))
    return out


def command(c: Config, a: argparse.Namespace) -> list[str]:
    cmd = [sys.executable, str(STOP_LATENCY), *c.args, "--trials", str(c.trials or a.trials),
           "--timeout-ms", str(c.timeout_ms or a.timeout_ms), "--out", str(a.out / c.name)]
    if a.estopd:
        cmd += ["--estopd", a.estopd]
    return cmd


# --------------------------------------------------------------------------------------------
# Tables from the runs' JSON


def ms(v: float | None) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def _lost(run: dict[str, Any], metric: str) -> int:
    title = {"overshoot": "timeout overshoot", "tcp_stop": "TCP stop latency",
             "lift": "lift stop latency", "slowing": "slow-down overshoot"}[metric]
    return int(run["discard_reasons"].get(f"{title}: log lines lost", 0))


def _results(doc: dict[str, Any]) -> list[RunResult]:
    return [from_document(r) for r in doc["runs"]]


def table_new_rows(doc: dict[str, Any], title: str, goals: bool = False) -> list[str]:
    """The version 3 rows of one run: lift (timer floor beside it), roll-out, before / after,
    two-stage; the run's own report formats them the same way. ``goals``: the run's goals
    after them (for a run without a table_daemons table)."""
    results, meta = _results(doc), doc["meta"]
    body = (lift_table(results, meta) + roll_table(results, meta)
            + before_after_table(results, meta) + two_stage_table(results))
    if not body:
        return []
    if goals:
        body += ["", "Goals: " + "; ".join(f"{'PASS' if g['pass'] else 'FAIL'} {g['goal']}"
                                           for g in doc["goals"])]
    return [f"### {title}", "", _meta_line(doc), *body, ""]


def _other_discards(run: dict[str, Any], metric: str) -> int:
    return int(run["discarded"][metric]) - _lost(run, metric)


def _rate(flood: dict[str, Any]) -> str:
    return "-" if not flood else f"{flood['rate']:,.0f}"


def _busy(run: dict[str, Any]) -> str:
    other = run.get("other_cpu")
    return "n/a" if other is None else f"{other:.2f}"


def table_daemons(doc: dict[str, Any], title: str) -> list[str]:
    """plain and auth: one row per daemon and load, both metrics."""
    lines = [f"### {title}", "", _meta_line(doc), "",
             "| daemon | load | overshoot n | p50 | p99 | p99.9 | max | TCP stop n | p50 | "
             "p99.9 | missed/wrong | discarded (lines lost) | flood/s | kernel drops | "
             "release failures |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
             "| ---: | ---: | ---: |"]
    for r in doc["runs"]:
        o, t = r["summary_ms"]["overshoot"], r["summary_ms"]["tcp_stop"]
        fl = r.get("flood") or {}
        kd = fl.get("kernel_drops")
        bad = sum(r["missed"].values()) + sum(r["wrong_reason"].values())
        disc = sum(r["discarded"].values())
        lost = sum(_lost(r, m) for m in r["discarded"])
        lines.append(
            f"| {r['daemon']} | {r['load']} | {o['n']} | {ms(o['p50'])} | {ms(o['p99'])} | "
            f"{ms(o['p99.9'])} | {ms(o['max'])} | {t['n']} | {ms(t['p50'])} | "
            f"{ms(t['p99.9'])} | {bad} | {disc} ({lost}) | "
            f"{_rate(fl)} | "
            f"{'-' if kd is None else f'{kd:,}'} | {r['release_failures']} |")
    lines += ["", "Goals: " + "; ".join(f"{'PASS' if g['pass'] else 'FAIL'} {g['goal']}"
                                         for g in doc["goals"]), ""]
    return lines


def _meta_line(doc: dict[str, Any]) -> str:
    m = doc["meta"]
    floor = m.get("timer_floor_ms") or {}
    parts = [f"{m['date']}, {m['cpus']} CPUs, timeout {m['timeout_ms']} ms, "
             f"{m['trials']} trials per cell, flood target {m['flood_rate']:,.0f}/s",
             f"priorities: {m.get('priorities', '?')}"]
    if m.get("hog"):
        parts.append(f"{m['hog']} busy loops at normal priority (used "
                     f"{m.get('hog_cpu_cores') or 0:.2f} cores)")
    if floor:
        parts.append(f"machine timer wake-up p99.9 {ms(floor.get('p99.9'))} ms")
    others = [r.get("other_cpu") for r in doc["runs"] if r.get("other_cpu") is not None]
    if others:
        parts.append(f"other processes' CPU {max(others):.2f} cores at most")
    return "; ".join(parts) + "."


def table_hog(docs: dict[str, dict[str, Any]], a: argparse.Namespace) -> list[str]:
    lines = [f"### estopd under CPU contention ({a.hog} busy loops at normal priority), "
             f"without and with --rt-prio {a.rt_prio}", "",
             "| estopd priority | bench priority | load | n | p50 | p99 | p99.9 | max | "
             "discarded | lines lost | flood/s | other CPU |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name in ("hog-normal", "hog-rt"):
        doc = docs.get(name)
        if doc is None:
            continue
        m = doc["meta"]
        dprio = f"SCHED_FIFO {m['rt_prio']}" if m["rt_prio"] else "normal"
        bprio = f"SCHED_FIFO {m['bench_rt_prio']}" if m["bench_rt_prio"] else "normal"
        for r in doc["runs"]:
            o = r["summary_ms"]["overshoot"]
            fl = r.get("flood") or {}
            lines.append(f"| {dprio} | {bprio} | {r['load']} | {o['n']} | {ms(o['p50'])} | "
                         f"{ms(o['p99'])} | {ms(o['p99.9'])} | {ms(o['max'])} | "
                         f"{r['discarded']['overshoot']} | {_lost(r, 'overshoot')} | "
                         f"{_rate(fl)} | {_busy(r)} |")
    lines += ["", "Timeout overshoot in ms. " + " ".join(
        f"{n}: {_meta_line(d)}" for n, d in docs.items() if n in ("hog-normal", "hog-rt")), ""]
    return lines


def table_issue11(docs: dict[str, dict[str, Any]], a: argparse.Namespace) -> list[str]:
    lines = [f"### Issue 11: estopd only, idle, {a.hog} busy loops, timeout {a.timeout_ms} ms",
             "",
             "| run | n | p50 | p99 | p99.9 | max | discarded: log lines lost | other "
             "discards | counter jumps (frames) | daemon reported dropped |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    rows = [("hog-normal", "estopd, normal priority"),
            ("hog-rt-bench-normal", f"estopd `--rt-prio {a.rt_prio}`, bench at normal "
                                    f"priority"),
            ("hog-rt", f"estopd `--rt-prio {a.rt_prio}`, bench also real-time (SCHED_FIFO "
                       f"{max(1, a.rt_prio - 10)})")]
    for name, label in rows:
        doc = docs.get(name)
        if doc is None:
            continue
        r = next((x for x in doc["runs"] if x["load"] == "idle"), None)
        if r is None:
            continue
        o = r["summary_ms"]["overshoot"]
        lines.append(f"| {label} | {o['n']} | {ms(o['p50'])} | {ms(o['p99'])} | "
                     f"{ms(o['p99.9'])} | {ms(o['max'])} | {_lost(r, 'overshoot')} | "
                     f"{_other_discards(r, 'overshoot')} | {r['log_gaps']} "
                     f"({r['log_gap_lines']}) | {r['daemon_dropped']} |")
    lines += ["", "Timeout overshoot in ms; discards and lost lines of the timeout trials "
              "(counter jumps and the daemon's count cover the whole run, TCP trials "
              "included)."]
    lines += [f"- {name}: {_meta_line(docs[name])}" for name, _ in rows if name in docs]
    lines.append("")
    return lines


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default=",".join(SETS),
                    help=f"comma-separated, of {', '.join(SETS)} (default: all)")
    ap.add_argument("--trials", type=int, default=1000, help="trials per metric and cell")
    ap.add_argument("--timeout-ms", type=int, default=20)
    ap.add_argument("--rt-prio", type=int, default=50)
    ap.add_argument("--hog", type=int, default=2, help="busy loops (one per core here)")
    ap.add_argument("--estopd", metavar="PATH")
    ap.add_argument("--estopd-before", metavar="PATH",
                    help="a previous estopd beside the auth run (before / after)")
    ap.add_argument("--before-label", default="before")
    ap.add_argument("--two-stage-ms", default="100,200", metavar="S,T",
                    help="slow time and timeout of the two-stage set (default 100,200)")
    ap.add_argument("--two-stage-trials", type=int, default=300,
                    help="trials per cell of the two-stage set (each waits T: default 300)")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "tables")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    a = ap.parse_args(argv)
    sets = [s for s in a.sets.split(",") if s]
    if not sets or any(s not in SETS for s in sets):
        ap.error(f"--sets takes some of {', '.join(SETS)}")
    if not 1 <= a.rt_prio <= 99:
        ap.error("--rt-prio takes 1..99")
    if a.hog < 1:
        ap.error("--hog takes at least 1")
    try:
        slow, timeout = (int(x) for x in a.two_stage_ms.split(","))
    except ValueError:
        ap.error("--two-stage-ms takes S,T in ms, e.g. 100,200")
    if not 0 < slow < timeout:
        ap.error("--two-stage-ms: 0 < S < T")
    a.two_stage_ms = (slow, timeout)
    runs = configs(sets, a)
    print("Runs (each can be re-run alone):")
    for c in runs:
        print("  " + shlex.join(command(c, a)))
    if a.dry_run:
        return 0
    docs: dict[str, dict[str, Any]] = {}
    failed = []
    t0 = time.monotonic()
    for c in runs:
        print(f"\n== {c.name}: {c.what}", flush=True)
        rc = subprocess.run(command(c, a), stdin=subprocess.DEVNULL).returncode
        path = a.out / c.name / "stop_latency.json"
        if rc != 0 or not path.is_file():
            failed.append(f"{c.name} (exit code {rc})")
            continue
        docs[c.name] = json.loads(path.read_text())
    md = [f"# Stop-latency tables ({time.strftime('%Y-%m-%d %H:%M:%S %Z')}, "
          f"{time.monotonic() - t0:.0f} s)", "", "Commands:", ""]
    md += [f"    {shlex.join(command(c, a))}" for c in runs]
    md.append("")
    if "plain" in sets and "plain" in docs:
        md += table_daemons(docs["plain"], "Plain: estopd vs the asyncio baseline")
        md += table_new_rows(docs["plain"], "Plain: lift and roll-out")
    if "auth" in sets and "auth" in docs:
        md += table_daemons(docs["auth"], "Auth (issue 8): estopd with a key vs without, "
                                          "flood of forged authenticated packets")
        md += table_new_rows(docs["auth"], "Auth: forged flood before / after, lift and "
                                           "roll-out")
    if "auth-rt" in sets and "auth-rt" in docs:
        md += table_daemons(docs["auth-rt"], f"Auth (issue 8) as deployed: both daemons "
                                             f"--rt-prio {a.rt_prio}, the bench SCHED_FIFO "
                                             f"{max(1, a.rt_prio - 10)}")
    if "hog" in sets:
        md += table_hog(docs, a)
    if "issue11" in sets:
        md += table_issue11(docs, a)
    if "two-stage" in sets and "two-stage" in docs:
        md += table_new_rows(docs["two-stage"], "Two-stage: SLOWING at S, STOPPED at T, "
                                                "distance rolled", goals=True)
    if failed:
        md += ["", "Runs that failed: " + ", ".join(failed), ""]
    text = "\n".join(md)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "tables.md").write_text(text + "\n")
    print("\n" + text)
    print(f"wrote {a.out / 'tables.md'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
