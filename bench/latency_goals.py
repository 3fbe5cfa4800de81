"""The goals of the stop-latency bench, checked on a run's results (pure).

Plain: the unit under test's p99.9 timeout overshoot (idle < 1 ms, flood < 2 ms), every trial
stopped with the right reason, 5x ahead of the baseline, the flood fast enough; its p99.9 lift
stop latency under the same limits. --auth (issue 8): the keyed estopd under the forged flood,
no kernel drops, the release/heartbeat path still working (every trial armed). With a previous
estopd beside it (--estopd-before): the forged flood's overshoot unchanged. Two-stage
(--slow-ms): SLOWING at S and STOPPED at T within the same limits, and the car rolled no
farther than with the single-stage unit at the same T.
"""

from __future__ import annotations

from latency_result import ROLE_BASELINE, ROLE_BEFORE, ROLE_MAIN, ROLE_SINGLE, RunResult
from latency_stats import fmt_ms, summarize

GOAL_FLOOD_RATE = 50_000.0
GOAL_P999_MS = {"idle": 1.0, "flood": 2.0}
GOAL_AHEAD_FACTOR = 5.0

Goal = tuple[str, bool]


def _p(r: RunResult, metric: str, q: str = "p99.9") -> float:
    return summarize(r.samples[metric])[q]


def _latency_goals(e: RunResult, load: str, auth: bool) -> list[Goal]:
    """The unit under test alone under one load."""
    goals: list[Goal] = []
    ok_run = e.error is None and len(e.samples["overshoot"]) > 0
    lim = GOAL_P999_MS[load]
    p = _p(e, "overshoot")
    # the machine's own timer wake-up under the same load, beside each latency goal
    floor = (f" (timer floor p99.9 {fmt_ms(summarize(e.floor_ms)['p99.9'])} ms)"
             if e.floor_ms else "")
    goals.append((f"{e.daemon} p99.9 timeout overshoot {load}: {fmt_ms(p)} ms < {lim} ms"
                  f"{floor}", ok_run and p < lim))
    for m, what in (("slowing", "slow-down overshoot (SLOWING at S)"),
                    ("lift", "lift stop latency")):
        if m in e.metrics:
            pm = _p(e, m)
            goals.append((f"{e.daemon} p99.9 {what} {load}: {fmt_ms(pm)} ms < {lim} ms{floor}",
                          ok_run and len(e.samples[m]) > 0 and pm < lim))
    missing = (sum(e.missed[m] for m in e.metrics)
               + sum(e.wrong_reason[m] for m in e.metrics))
    goals.append((f"{e.daemon} {load}: every trial stopped, with the right reason "
                  f"({missing} missed or wrong)", ok_run and missing == 0))
    if auth:
        goals.append((f"{e.daemon} {load}: the release/heartbeat path works (every trial "
                      f"armed: {e.release_failures} release failures, {e.release_naks} NAKs "
                      f"retried)", ok_run and e.release_failures == 0))
    return goals


def _peer_goals(e: RunResult, by_role: dict[str, RunResult], load: str,
                floor_p999: float | None) -> list[Goal]:
    """The unit under test against its peers under one load."""
    goals: list[Goal] = []
    ok_run = e.error is None and len(e.samples["overshoot"]) > 0
    p = _p(e, "overshoot")
    b = by_role.get(ROLE_BASELINE)
    if b is not None and b.samples["overshoot"]:
        pb = _p(b, "overshoot")
        goals.append((f"{e.daemon} p99.9 overshoot {load} at most 1/{GOAL_AHEAD_FACTOR:g} of "
                      f"the baseline's ({fmt_ms(p)} vs {fmt_ms(pb)} ms)",
                      ok_run and p * GOAL_AHEAD_FACTOR <= pb))
    s = by_role.get(ROLE_SINGLE)
    if s is not None and e.distances["overshoot"] and s.distances["overshoot"]:
        d2 = summarize(e.distances["overshoot"])["p50"]
        d1 = summarize(s.distances["overshoot"])["p50"]
        goals.append((f"{e.daemon} {load}: the two-stage unit rolls no farther after the last "
                      f"packet than the single-stage unit at the same T (p50 {d2:.3f} vs "
                      f"{d1:.3f} m)", ok_run and d2 <= d1))
    before = by_role.get(ROLE_BEFORE)
    if load == "flood" and before is not None and before.samples["overshoot"]:
        pb = _p(before, "overshoot")
        # the machine's own noise under this load: the larger floor of the two runs' blocks
        # (else the one before the daemons started)
        floors = [summarize(r.floor_ms)["p99.9"] for r in (e, before) if r.floor_ms]
        slack = max(floors) if floors else floor_p999 or 0.0
        slack = 0.0 if slack != slack else slack  # NaN: no allowance
        goals.append((f"{e.daemon} flood: overshoot unchanged from {before.daemon} (p99.9 "
                      f"{fmt_ms(p)} vs {fmt_ms(pb)} ms; allowed: + this machine's timer "
                      f"wake-up p99.9 {fmt_ms(slack)} ms)", ok_run and p <= pb + slack))
    return goals


def check_goals(results: list[RunResult], auth: bool = False,
                floor_p999: float | None = None) -> list[Goal]:
    """Every goal of the run: per load, the unit under test alone, then against its peers;
    the flood's own goals. ``floor_p999``: the machine's timer wake-up p99.9 in the same run
    (ms), the noise allowed when comparing with the previous estopd."""
    goals: list[Goal] = []
    for load in ("idle", "flood"):
        here = [r for r in results if r.load == load]
        by_role = {r.role: r for r in here}
        e = by_role.get(ROLE_MAIN)
        if e is None:
            continue
        goals += _latency_goals(e, load, auth)
        goals += _peer_goals(e, by_role, load, floor_p999)
        if load == "flood":
            if auth and e.flood is not None:
                kd = e.flood.kernel_drops
                goals.append((f"{e.daemon} under the forged flood: no kernel drops "
                              f"({'n/a' if kd is None else f'{kd:,}'})", kd == 0))
            for r in here:
                if r.flood is not None and r.role in (ROLE_MAIN, ROLE_BASELINE):
                    goals.append((f"flood at {r.daemon}: {r.flood.rate:,.0f} packets/s while "
                                  f"aimed at it >= {GOAL_FLOOD_RATE:,.0f}",
                                  r.flood.rate >= GOAL_FLOOD_RATE))
    return goals
