"""The stop-latency report: Markdown and JSON (goals in ``latency_goals``, the histogram in
``latency_plot``). Pure: tests/harness/test_bench_smoke.py formats synthetic runs."""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

from latency_result import (
    METRIC_TITLES,
    METRICS,
    ROLE_BASELINE,
    ROLE_BEFORE,
    ROLE_MAIN,
    ROLE_SINGLE,
    ROLL_METRICS,
    TIMEOUT_FIRST,
    RunResult,
)
from latency_roll import fmt_m
from latency_stats import fmt_ms, summarize

BUSY_CORES = 0.25  # other processes' CPU during a run above which the report warns
BUSY_STEAL = 0.05  # hypervisor steal (cores) above which the report warns
KEYED, KEYLESS = "estopd+key", "estopd"  # the two daemons of --auth
MOMENTS = {"overshoot": "last packet", "lift": "first lift datagram"}


def _title(results: list[RunResult], meta: dict[str, Any]) -> str:
    if meta.get("slow_ms"):
        return "Two-stage stop: estopd with a slow time vs single-stage"
    if meta.get("auth"):
        return "Stop latency: estopd with a key vs without"
    if any(r.role == ROLE_BASELINE for r in results):
        return "Stop latency: estopd vs asyncio baseline"
    return "Stop latency: estopd"


def _header(results: list[RunResult], meta: dict[str, Any]) -> list[str]:
    auth_mode = bool(meta.get("auth"))
    flood_kind = ("forged authenticated packets/s (60 bytes, right session, wrong tag)"
                  if auth_mode else "invalid packets/s")
    lines = [f"# {_title(results, meta)}", "",
             f"{meta['date']} on {meta['host']} ({meta['cpus']} CPUs, Python {meta['python']}); "
             f"timeout {meta['timeout_ms']} ms; {meta['trials']} trials per cell; flood target "
             f"{meta['flood_rate']:,.0f} {flood_kind} on loopback. All times in ms."]
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
    if meta.get("slow_ms"):
        lines += ["", f"Two-stage: slow time S = {meta['slow_ms']} ms, slow level L = "
                  f"{meta.get('slow_level', 30)} %, timeout T = {meta['timeout_ms']} ms; the "
                  f"single-stage unit has T only. Silence trials only: the slow-down overshoot "
                  f"is the first SLOWING frame - (last packet + S), the timeout overshoot the "
                  f"first STOPPED frame - (last packet + T)."]
    before = meta.get("before")
    if before:
        lines += ["", f"Before: {before['label']} = the estopd binary {before['path']} "
                  f"({before.get('version', 'version unknown')}), run side by side with this "
                  f"one (no LIFT there: timeout and TCP trials only)."]
    return lines


def floor_cell(r: RunResult, meta: dict[str, Any]) -> str:
    """The machine's timer wake-up p50 / p99.9 beside a run: measured before each of its
    blocks, else (older runs) once before the daemons started."""
    floor = summarize(r.floor_ms) if r.floor_ms else (meta.get("timer_floor_ms") or {})
    return f"{fmt_ms(floor.get('p50', math.nan))} / {fmt_ms(floor.get('p99.9', math.nan))}"


def _main_table(results: list[RunResult], meta: dict[str, Any]) -> list[str]:
    lines = ["", "| daemon | load | metric | n | p50 | p99 | p99.9 | max | timer floor p50 / "
             "p99.9 | early | missed | wrong | discarded | lines lost |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
             "---: | ---: |"]
    for r in results:
        for m in (m for m in METRICS if m in r.metrics):
            s = summarize(r.samples[m])
            early = str(r.early(m)) if m in ("overshoot", "slowing") else "-"
            lines.append(
                f"| {r.daemon} | {r.load} | {METRIC_TITLES[m]} | {s['n']} | {fmt_ms(s['p50'])} |"
                f" {fmt_ms(s['p99'])} | {fmt_ms(s['p99.9'])} | {fmt_ms(s['max'])} |"
                f" {floor_cell(r, meta)} | {early} | {r.missed[m]} | {r.wrong_reason[m]} |"
                f" {r.discarded[m]} | {r.lost_discards(m)} |")
    return lines


def _floor_line(meta: dict[str, Any]) -> list[str]:
    floor = meta.get("timer_floor_ms")
    if not floor:
        return []
    prio = meta.get("timer_floor_prio")
    at = f", SCHED_FIFO {prio}" if prio else ""
    period = meta.get("timer_floor_period_ms", meta["timeout_ms"])
    return ["", f"Reference, this machine's own timer wake-up latency ({floor['n']} sleeps "
            f"of {period} ms, timer slack 1 ns{at}, before the daemons "
            f"start): p50 {fmt_ms(floor['p50'])}, p99 {fmt_ms(floor['p99'])}, p99.9 "
            f"{fmt_ms(floor['p99.9'])}, max {fmt_ms(floor['max'])} ms (other CPU "
            f"{meta.get('timer_floor_other_cpu', 'n/a')} cores, steal "
            f"{meta.get('timer_floor_steal', 'n/a')}). The column 'timer floor' measures the "
            f"same again before each of the run's blocks (5 sleeps, under that load, the "
            f"flood aimed at the daemon, at the bench's priority). A stop's tail at or below "
            f"it comes from the machine, not the daemon."]


def lift_table(results: list[RunResult], meta: dict[str, Any]) -> list[str]:
    """The lift row: each daemon's lift stop latency, the machine's timer floor beside it and
    the ratio to the baseline (or the keyless unit) under the same load."""
    runs = [r for r in results if r.samples["lift"]]
    if not runs:
        return []
    lines = ["", "Lift (spec sections 1, 8): first lift datagram sent -> first stop frame "
             "with reason lift; the remote's three datagrams 10 ms apart, after 3 drive "
             "packets. Beside it, this run's timer wake-up floor, the peer's p99.9 over "
             "this daemon's, and the trials in which no lift datagram was handled before the "
             "timeout stopped the car (all three lost or queued; discarded, not timed).", "",
             "| daemon | load | n | p50 | p99 | p99.9 | max | timer floor p50 / p99.9 | "
             "peer p99.9 / this | timeout first |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in runs:
        s = summarize(r.samples["lift"])
        peer = next((p for p in runs if p.load == r.load and p is not r
                     and p.role != ROLE_MAIN), None) if r.role == ROLE_MAIN else None
        ratio = "-"
        if peer is not None and s["p99.9"] > 0:
            ratio = f"{summarize(peer.samples['lift'])['p99.9'] / s['p99.9']:.1f}x"
        lines.append(f"| {r.daemon} | {r.load} | {s['n']} | {fmt_ms(s['p50'])} | "
                     f"{fmt_ms(s['p99'])} | {fmt_ms(s['p99.9'])} | {fmt_ms(s['max'])} | "
                     f"{floor_cell(r, meta)} | {ratio} | "
                     f"{r.discards_for('lift', TIMEOUT_FIRST)} |")
    return lines


def roll_table(results: list[RunResult], meta: dict[str, Any]) -> list[str]:
    """Metres rolled from the moment that mattered to standstill, per daemon and trial kind."""
    rows = [(r, m) for r in results for m in ROLL_METRICS if r.distances[m]]
    if not rows:
        return []
    speed = meta.get("speed_kmh", 15.0)
    decel = meta.get("decel_ms2", 8.0)
    braking = meta.get("braking_m")
    lines = ["", f"Roll-out at {speed:g} km/h (estop.model.rollout: the trial's can-log frames "
             f"through the brake controller and the vehicle model, {decel:g} m/s^2 emergency "
             f"deceleration, no actuator delay), metres from the moment that mattered to "
             f"standstill" + (f"; full braking alone takes {braking:.3f} m" if braking else "")
             + ". Discarded trials are not in it.", "",
             "| daemon | load | trials | from | n | p50 | p99 | p99.9 | max |",
             "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r, m in rows:
        s = summarize(r.distances[m])
        kind = "silence" if m == "overshoot" else "lift"
        lines.append(f"| {r.daemon} | {r.load} | {kind} | {MOMENTS[m]} | {s['n']} | "
                     f"{fmt_m(s['p50'])} | {fmt_m(s['p99'])} | {fmt_m(s['p99.9'])} | "
                     f"{fmt_m(s['max'])} |")
    return lines


def _drops(r: RunResult) -> str:
    kd = None if r.flood is None else r.flood.kernel_drops
    return "n/a" if kd is None else f"{kd:,}"


def _rcvbuf(r: RunResult) -> str:
    return "default" if r.udp_rcvbuf is None else f"{r.udp_rcvbuf:,}"


def before_after_table(results: list[RunResult], meta: dict[str, Any]) -> list[str]:
    """The same unit before and after a change, per load: kernel drops, receive buffer and
    timeout overshoot side by side (one row per load)."""
    pairs = []
    for load in ("idle", "flood"):
        by = {r.role: r for r in results if r.load == load}
        if ROLE_MAIN in by and ROLE_BEFORE in by:
            pairs.append((load, by[ROLE_BEFORE], by[ROLE_MAIN]))
    if not pairs:
        return []
    b0, a0 = pairs[0][1], pairs[0][2]
    lines = ["", f"Before / after: {b0.daemon} / {a0.daemon}, side by side in the same run "
             "(same machine, same flood, trials alternating in blocks). Timeout overshoot in "
             "ms.", "",
             "| load | flood/s | kernel drops | udp_rcvbuf (bytes) | overshoot n | p50 | p99 | "
             "p99.9 | max | early | discarded | timer floor p50 / p99.9 |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for load, b, a in pairs:
        sb, sa = summarize(b.samples["overshoot"]), summarize(a.samples["overshoot"])

        def both(key: str, sb: dict[str, float] = sb, sa: dict[str, float] = sa) -> str:
            return f"{fmt_ms(sb[key])} / {fmt_ms(sa[key])}"

        rate = (f"{b.flood.rate:,.0f} / {a.flood.rate:,.0f}"
                if b.flood is not None and a.flood is not None else "-")
        lines.append(f"| {load} | {rate} | {_drops(b)} / {_drops(a)} | {_rcvbuf(b)} / "
                     f"{_rcvbuf(a)} | {sb['n']} / {sa['n']} | {both('p50')} | {both('p99')} | "
                     f"{both('p99.9')} | {both('max')} | {b.early('overshoot')} / "
                     f"{a.early('overshoot')} | {b.discarded['overshoot']} / "
                     f"{a.discarded['overshoot']} | {floor_cell(b, meta)} ; "
                     f"{floor_cell(a, meta)} |")
    return lines


def two_stage_table(results: list[RunResult]) -> list[str]:
    """Two-stage against single-stage at the same T: when the brake began and ended."""
    runs = [r for r in results if r.slow_ms is not None or r.role == ROLE_SINGLE]
    if not runs or all(r.slow_ms is None for r in runs):
        return []
    lines = ["", "Two-stage vs single-stage (silence trials): SLOWING at S, STOPPED at T, and "
             "the distance rolled from the last packet (p50 / p99.9).", "",
             "| daemon | load | S ms | T ms | SLOWING seen | slow-down overshoot p50 / p99.9 "
             "| timeout overshoot p50 / p99.9 | rolled m p50 / p99.9 |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in runs:
        slow, stop = summarize(r.samples["slowing"]), summarize(r.samples["overshoot"])
        dist = summarize(r.distances["overshoot"])
        seen = (f"{slow['n']} of {slow['n'] + r.missed['slowing']}" if r.slow_ms is not None
                else "-")
        lines.append(f"| {r.daemon} | {r.load} | {r.slow_ms or '-'} | {r.timeout_ms} | {seen} "
                     f"| {fmt_ms(slow['p50'])} / {fmt_ms(slow['p99.9'])} | "
                     f"{fmt_ms(stop['p50'])} / {fmt_ms(stop['p99.9'])} | {fmt_m(dist['p50'])} / "
                     f"{fmt_m(dist['p99.9'])} |")
    return lines


def _flood_lines(results: list[RunResult]) -> list[str]:
    lines = ["", "Flood (per run): the sender's count over its own run time; kernel drops: "
             "datagrams the daemon's socket dropped (receive buffer full, /proc/net/udp), and "
             "the daemon's own count where it reports one (udp_drops); udp_rcvbuf: the receive "
             "buffer its start line reports (default: it sets none); STATUS: the daemon's own "
             "ESTOP_STATUS frames whose invalid-packet (or authentication-failure) count per "
             "100 ms saturated at 255, i.e. it saw >= 2,550 such packets/s.", ""]
    for r in results:
        if r.flood is not None:
            f = r.flood
            kind = "forged" if f.forged else "invalid"
            own = "n/a" if r.daemon_udp_drops is None else f"{r.daemon_udp_drops:,}"
            lines.append(f"- {r.daemon}: {f.sent:,} {kind} packets in {f.elapsed_s:.1f} s = "
                         f"{f.rate:,.0f} packets/s; kernel drops {_drops(r)} (the daemon's own "
                         f"count {own}); udp_rcvbuf {_rcvbuf(r)}; STATUS saturated "
                         f"{r.status_invalid_saturated} (invalid), {r.status_auth_saturated} "
                         f"(auth failures) of {r.status_frames}"
                         + ("" if r.deadline_cuts is None else
                            f"; drains cut short by a silence deadline {r.deadline_cuts:,}"))
    return lines


def _run_lines(results: list[RunResult]) -> list[str]:
    lines = ["", "Can-log lines lost (issue 11): frames whose alive counters were followed, "
             "counter jumps (frames missing), and the lines the daemon itself reported "
             "dropped (output_dropped). A trial that lost lines between RELEASE and its stop "
             "frame is discarded, never timed (column 'lines lost').", ""]
    for r in results:
        lines.append(f"- {r.daemon} {r.load}: {r.log_frames:,} frames followed, {r.log_gaps} "
                     f"jumps ({r.log_gap_lines} frames missing), daemon reported "
                     f"{r.daemon_dropped} dropped")
    lines += ["", "Per run: wall time of the load (all daemons); CPU that other processes on "
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
    return lines


def markdown(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> str:
    lines = _header(results, meta) + _main_table(results, meta) + _floor_line(meta)
    lines += lift_table(results, meta) + roll_table(results, meta)
    lines += two_stage_table(results) + before_after_table(results, meta)
    lines += _flood_lines(results) + _run_lines(results)
    lines += ["", "Goals:", ""]
    lines += [f"- {'PASS' if ok else 'FAIL'}: {text}" for text, ok in goals]
    lines += ["", "Columns: early = stop frame before last packet + timeout (safe, but the "
              "daemon's deadline did not come from our last packet: e.g. it was dropped); "
              "missed = no stop frame within 2 s (a two-stage unit: no SLOWING before the "
              "stop); wrong = stopped for another reason; "
              "discarded = the bench's own send was late (descheduled), in a TCP or lift trial "
              "the link timed out before the request was handled, or can-log lines were lost: "
              "sample dropped; lines lost = of those, the trials discarded because can-log "
              "lines were lost (the first stop frame seen may not have been the first sent).",
              ""]
    return "\n".join(lines)


def document(results: list[RunResult], meta: dict[str, Any],
             goals: list[tuple[str, bool]]) -> dict[str, Any]:
    """The JSON report: meta, goals, and per run its raw data and summaries (what
    bench/latency_tables.py reads): ``summary_ms`` per metric, ``summary_m`` (distances) per
    trial kind with a roll-out."""
    runs: list[dict[str, Any]] = []
    for r in results:
        d = asdict(r)
        d["summary_ms"] = {m: summarize(r.samples[m]) for m in METRICS}
        d["summary_m"] = {m: summarize(r.distances[m]) for m in ROLL_METRICS}
        if r.flood is not None:
            d["flood"]["rate"] = r.flood.rate
        runs.append(d)
    return {"meta": meta, "runs": runs, "goals": [{"goal": g, "pass": ok} for g, ok in goals]}
