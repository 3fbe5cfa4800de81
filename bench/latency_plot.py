"""The stop-latency histogram (PNG): one row per metric measured, one column per load, every
daemon's samples on a log scale, the machine's timer wake-up beside the idle timeout stops."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from latency_goals import GOAL_P999_MS
from latency_result import METRIC_TITLES, METRICS, ROLE_BASELINE, ROLE_BEFORE, RunResult
from latency_stats import fmt_ms, log_bins, summarize

TIMER_METRICS = ("overshoot", "slowing")  # stops at a deadline: the timer floor applies


def _color(r: RunResult, index: int) -> str:
    palette = ["tab:blue", "tab:green", "tab:purple", "tab:brown"]
    if r.role == ROLE_BASELINE:
        return "tab:orange"
    if r.role == ROLE_BEFORE:
        return "tab:red"
    return palette[index % len(palette)]


def plot(results: list[RunResult], path: Path, timeout_ms: int,
         floor_samples: Sequence[float] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 0.001
    metrics = [m for m in METRICS if any(r.samples[m] for r in results)] or ["overshoot"]
    names = list(dict.fromkeys(r.daemon for r in results))
    fig, axes = plt.subplots(len(metrics), 2, figsize=(12, 3.75 * len(metrics)),
                             squeeze=False)
    for row, m in enumerate(metrics):
        for col, load in enumerate(("idle", "flood")):
            ax = axes[row][col]
            runs = [r for r in results if r.load == load and r.samples[m]]
            allv = [max(v, floor) for r in runs for v in r.samples[m]]
            with_floor = m in TIMER_METRICS and load == "idle" and bool(floor_samples)
            if with_floor and allv:
                allv += [max(v, floor) for v in floor_samples]
            if not allv:
                ax.set_axis_off()
                continue
            bins = log_bins(allv, floor)
            for r in runs:
                vals = [max(v, floor) for v in r.samples[m]]
                s = summarize(r.samples[m])
                ax.hist(vals, bins=bins, alpha=0.6, color=_color(r, names.index(r.daemon)),
                        label=f"{r.daemon} (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if with_floor:
                s = summarize(floor_samples)
                ax.hist([max(v, floor) for v in floor_samples], bins=bins, histtype="step",
                        color="k", lw=1,
                        label=f"machine timer wake (p99.9 {fmt_ms(s['p99.9'])} ms)")
            if m != "tcp_stop":  # the TCP stop has no goal of its own
                ax.axvline(GOAL_P999_MS[load], color="k", ls="--", lw=1,
                           label=f"goal p99.9 < {GOAL_P999_MS[load]:g} ms")
            ax.set_xscale("log")
            ax.set_xlabel("ms (log; values <= 0.001 ms drawn at 0.001)")
            ax.set_ylabel("trials")
            ax.set_title(f"{METRIC_TITLES[m]}, {load}")
            # a fixed corner: matplotlib's "best" searches the samples, slow on large runs
            # (it warned so in make test's untimed tests)
            ax.legend(fontsize=8, loc="upper right")
    fig.suptitle(f"estop stop latency, timeout {timeout_ms} ms")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
