"""The stop-latency report: goals, Markdown, JSON and the histogram."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from latency_stats import fmt_ms, log_bins, summarize
from latency_trials import METRIC_TITLES, METRICS, RunResult

GOAL_FLOOD_RATE = 50_000.0
GOAL_P999_MS = {"idle": 1.0, "flood": 2.0}
GOAL_AHEAD_FACTOR = 5.0
BUSY_CORES = 0.25  # other processes' CPU during a run above which the report warns
BUSY_STEAL = 0.05  # hypervisor steal (cores) above which the report warns
KEYED, KEYLESS = "estopd+key", "estopd"  # the two daemons of --auth


def check_goals(results: list[RunResult], auth: bool = False) -> list[tuple[str, bool]]:
    """Goals of the run. Plain: estopd's p99.9 overshoot (idle < 1 ms, flood < 2 ms), every
    trial stopped with the right reason, 5x ahead of the baseline, the flood fast enough.
    --auth (issue 8): the keyed estopd under the forged flood, p99.9 < 2 ms, no kernel drops,
    and the release/heartbeat path still working (every trial armed)."""
    by = {(r.daemon, r.load): r for r in results}
    main_name = KEYED if auth else "estopd"
    goals: list[tuple[str, bool]] = []
    for load in ("idle", "flood"):
        e, b = by.get((main_name, load)), by.get(("baseline", load))
        if e is None:
            continue
        ok_run = e.error is None and len(e.samples["overshoot"]) > 0
        p = summarize(e.samples["overshoot"])["p99.9"]
        lim = GOAL_P999_MS[load]
        goals.append((f"{main_name} p99.9 timeout overshoot {load}: {fmt_ms(p)} ms < {lim} ms",
                      ok_run and p < lim))
        missing = sum(e.missed.values()) + sum(e.wrong_reason.values())
        goals.append((f"{main_name} {load}: every trial stopped, with the right reason "
                      f"({missing} missed or wrong)", ok_run and missing == 0))
        if auth:
            goals.append((f"{main_name} {load}: the release/heartbeat path works (every trial "
                          f"armed: {e.release_failures} release failures, {e.release_naks} "
                          f"NAKs retried)", ok_run and e.release_failures == 0))
        if b is not None and b.samples["overshoot"]:
            pb = summarize(b.samples["overshoot"])["p99.9"]
            goals.append((f"estopd p99.9 overshoot {load} at most 1/{GOAL_AHEAD_FACTOR:g} of "
                          f"the baseline's ({fmt_ms(p)} vs {fmt_ms(pb)} ms)",
                          ok_run and p * GOAL_AHEAD_FACTOR <= pb))
        if load == "flood":
            if auth and e.flood is not None:
                kd = e.flood.kernel_drops
                goals.append((f"{main_name} under the forged flood: no kernel drops "
                              f"({'n/a' if kd is None else f'{kd:,}'})", kd == 0))
            for r in (e, b):
                if r is not None and r.flood is not None:
                    goals.append((f"flood at {r.daemon}: {r.flood.rate:,.0f} packets/s while "
                                  f"aimed at it >= {GOAL_FLOOD_RATE:,.0f}",
                                  r.flood.rate >= GOAL_FLOOD_RATE))
    return goals


def markdown(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> str:
    auth_mode = bool(meta.get("auth"))
    title = ("Stop latency: estopd with a key vs without" if auth_mode
             else "Stop latency: estopd vs asyncio baseline"
             if any(r.daemon == "baseline" for r in results) else "Stop latency: estopd")
    flood_kind = ("forged authenticated packets/s (60 bytes, right session, wrong tag)"
                  if auth_mode else "invalid packets/s")
    lines = [
        f"# {title}",
        "",
        f"{meta['date']} on {meta['host']} ({meta['cpus']} CPUs, Python {meta['python']}); "
        f"timeout {meta['timeout_ms']} ms; {meta['trials']} trials per cell; flood target "
        f"{meta['flood_rate']:,.0f} {flood_kind} on loopback. All times in ms.",
    ]
    if meta.get("priorities"):
        lines += ["", f"Priorities: {meta['priorities']}."]
    if meta.get("hog"):
        used = meta.get("hog_cpu_cores")
        lines += ["", f"CPU contention: {meta['hog']} busy-loop processes at normal priority "
                  f"ran throughout" + (f" (they used {used:.2f} cores)" if used is not None
                                       else "") + "."]
    if auth_mode:
        lines += ["", f"{KEYED}: estopd --key-file (a fresh key, mode 0600); the bench's link "
                  f"sends authenticated 60-byte packets and 48-byte request frames (session "
                  f"learnt with a STATUS, rising counters) and verifies every reply. "
                  f"{KEYLESS}: estopd --no-auth, plain link, the same flood (to it the forged "
                  f"packets are merely invalid)."]
    lines += [
        "",
        "| daemon | load | metric | n | p50 | p99 | p99.9 | max | early | missed | wrong | "
        "discarded | lines lost |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
        "---: |",
    ]
    for r in results:
        for m in METRICS:
            s = summarize(r.samples[m])
            early = str(r.early(m)) if m == "overshoot" else "-"
            lines.append(
                f"| {r.daemon} | {r.load} | {METRIC_TITLES[m]} | {s['n']} | {fmt_ms(s['p50'])} |"
                f" {fmt_ms(s['p99'])} | {fmt_ms(s['p99.9'])} | {fmt_ms(s['max'])} | {early} |"
                f" {r.missed[m]} | {r.wrong_reason[m]} | {r.discarded[m]} |"
                f" {r.lost_discards(m)} |")
    floor = meta.get("timer_floor_ms")
    if floor:
        prio = meta.get("timer_floor_prio")
        at = f", SCHED_FIFO {prio}" if prio else ""
        lines += ["", f"Reference, this machine's own timer wake-up latency ({floor['n']} sleeps "
                  f"of {meta['timeout_ms']} ms, timer slack 1 ns{at}, before the daemons "
                  f"start): p50 {fmt_ms(floor['p50'])}, p99 {fmt_ms(floor['p99'])}, p99.9 "
                  f"{fmt_ms(floor['p99.9'])}, max {fmt_ms(floor['max'])} ms (other CPU "
                  f"{meta.get('timer_floor_other_cpu', 'n/a')} cores, steal "
                  f"{meta.get('timer_floor_steal', 'n/a')}). A timeout stop's tail at or below "
                  f"this comes from the machine, not the daemon."]
    lines += ["", "Flood (per run): the sender's count over its own run time; kernel drops: "
              "datagrams the daemon's socket dropped (receive buffer full, /proc/net/udp); "
              "STATUS: the daemon's own ESTOP_STATUS frames whose invalid-packet (or "
              "authentication-failure) count per 100 ms saturated at 255, i.e. it saw >= 2,550 "
              "such packets/s.", ""]
    for r in results:
        if r.flood is not None:
            f = r.flood
            drops = "n/a" if f.kernel_drops is None else f"{f.kernel_drops:,}"
            kind = "forged" if f.forged else "invalid"
            lines.append(f"- {r.daemon}: {f.sent:,} {kind} packets in {f.elapsed_s:.1f} s = "
                         f"{f.rate:,.0f} packets/s; kernel drops {drops}; STATUS saturated "
                         f"{r.status_invalid_saturated} (invalid), {r.status_auth_saturated} "
                         f"(auth failures) of {r.status_frames}")
    lines += ["", "Can-log lines lost (issue 11): frames whose alive counters were followed, "
              "counter jumps (frames missing), and the lines the daemon itself reported "
              "dropped (output_dropped). A trial that lost lines between RELEASE and its stop "
              "frame is discarded, never timed (column 'lines lost').", ""]
    for r in results:
        lines.append(f"- {r.daemon} {r.load}: {r.log_frames:,} frames followed, {r.log_gaps} "
                     f"jumps ({r.log_gap_lines} frames missing), daemon reported "
                     f"{r.daemon_dropped} dropped")
    lines += ["", "Per run: wall time of the load (both daemons); CPU that other processes on "
              "this machine used meanwhile (cores, averaged over the daemon's blocks; not the "
              "bench, its daemons, its flooder or its busy loops) and hypervisor "
              "steal: numbers taken on a busy machine have fatter tails; RELEASE refusals "
              "(retried) and failures; errors.", ""]
    for r in results:
        err = f"; ERROR {r.error}" if r.error else ""
        other = "n/a" if r.other_cpu is None else f"{r.other_cpu:.2f}"
        steal = "n/a" if r.steal_cpu is None else f"{r.steal_cpu:.2f}"
        peak = max((b["other"] + b["steal"] for b in r.blocks), default=math.nan)
        lines.append(f"- {r.daemon} {r.load}: {r.wall_s:.1f} s; other CPU {other} cores, "
                     f"steal {steal} (busiest block: {fmt_ms(peak)} cores); RELEASE NAKs "
                     f"{r.release_naks}, release failures {r.release_failures}{err}")
        if r.discard_reasons:
            lines.append("  - discarded: " + ", ".join(
                f"{k} {v}" for k, v in sorted(r.discard_reasons.items())))
    busy = [r for r in results if (r.other_cpu or 0.0) > BUSY_CORES
             or (r.steal_cpu or 0.0) > BUSY_STEAL]
    if busy:
        lines += ["", "WARNING: the machine was busy with other work (or the hypervisor stole "
                  "CPU) during " + ", ".join(f"{r.daemon} {r.load} (other {r.other_cpu or 0:.2f}"
                                             f", steal {r.steal_cpu or 0:.2f} cores)"
                                             for r in busy)
                  + ": their tails show that load as much as the daemon under test; rerun on "
                  "a quiet machine for numbers to compare against the goals."]
    lines += ["", "Goals:", ""]
    lines += [f"- {'PASS' if ok else 'FAIL'}: {text}" for text, ok in goals]
    lines += ["", "Columns: early = stop frame before last packet + timeout (safe, but the "
              "daemon's deadline did not come from our last packet: e.g. it was dropped); "
              "missed = no stop frame within 2 s; wrong = stopped for another reason; "
              "discarded = the bench's own send was late (descheduled), in a TCP trial the "
              "link timed out before the STOP was handled, or can-log lines were lost: sample "
              "dropped; lines lost = of those, the trials discarded because can-log lines "
              "were lost (the first stop frame seen may not have been the first sent).", ""]
    return "\n".join(lines)


def document(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> dict[str, Any]:
    """The JSON report: meta, goals, and per run its raw data and summaries (what
    bench/latency_tables.py reads)."""
    runs: list[dict[str, Any]] = []
    for r in results:
        d = asdict(r)
        d["summary_ms"] = {m: summarize(r.samples[m]) for m in METRICS}
        if r.flood is not None:
            d["flood"]["rate"] = r.flood.rate
        runs.append(d)
    return {"meta": meta, "runs": runs, "goals": [{"goal": g, "pass": ok} for g, ok in goals]}


def plot(results: list[RunResult], path: Path, timeout_ms: int,
         floor_samples: Sequence[float] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 0.001
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), squeeze=False)
    colors = {"estopd": "tab:blue", "baseline": "tab:orange", KEYED: "tab:green"}
    for row, m in enumerate(METRICS):
        for col, load in enumerate(("idle", "flood")):
            ax = axes[row][col]
            runs = [r for r in results if r.load == load and r.samples[m]]
            allv = [max(v, floor) for r in runs for v in r.samples[m]]
            if m == "overshoot" and load == "idle" and allv:
                allv += [max(v, floor) for v in floor_samples]
            if not allv:
                ax.set_axis_off()
                continue
            bins = log_bins(allv, floor)
            for r in runs:
                vals = [max(v, floor) for v in r.samples[m]]
                s = summarize(r.samples[m])
                ax.hist(vals, bins=bins, alpha=0.6, color=colors.get(r.daemon),
                        label=f"{r.daemon} (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if m == "overshoot" and load == "idle" and floor_samples:
                s = summarize(floor_samples)
                ax.hist([max(v, floor) for v in floor_samples], bins=bins, histtype="step",
                        color="k", lw=1,
                        label=f"machine timer wake (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if m == "overshoot":
                ax.axvline(GOAL_P999_MS[load], color="k", ls="--", lw=1,
                           label=f"goal p99.9 < {GOAL_P999_MS[load]:g} ms")
            ax.set_xscale("log")
            ax.set_xlabel("ms (log; values <= 0.001 ms drawn at 0.001)")
            ax.set_ylabel("trials")
            ax.set_title(f"{METRIC_TITLES[m]}, {load}")
            ax.legend(fontsize=8)
    fig.suptitle(f"estop stop latency, timeout {timeout_ms} ms")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
