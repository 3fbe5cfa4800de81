"""Test protocol of a HIL run: Markdown table, the car's roll-outs, and plots from
``results.json``.

    python hil/hilreport.py OUT_DIR [--extra vm.json]

Writes ``OUT_DIR/protocol.md``, ``OUT_DIR/latency.png`` (the latencies and deadline overshoots
measured on the bus) and ``OUT_DIR/distance.png`` (how far the car rolls from the moment that
mattered, by row) and prints the protocol. Exits 1 when the run failed or ``results.json`` is
missing or unreadable (never a silent pass).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap
from pathlib import Path

# The latency plot's series (samples_ms labels), shown in the order of the rows.
PLOTTED = (
    "dead-man overshoot",
    "overshoot under invalid flood",
    "TCP STOP -> stop frame",
    "release -> ARMED frame",
    "lift datagram -> stop frame",
    "TCP LIFT -> stop frame",
    "SLOWING overshoot (burst)",
    "3rd packet -> ARMED frame",
    "SLOWING overshoot (loss)",
    "two-stage timeout overshoot",
    "stop datagram -> stop frame",
)


def fmt(value: object) -> str:
    if isinstance(value, dict):
        if "p50" in value:
            return (f"n={value['n']} min {fmt(value['min'])} / p50 {fmt(value['p50'])} / "
                    f"max {fmt(value['max'])}")
        if value.get("n") == 0:
            return "n=0"
        return ", ".join(f"{k} {fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def figures_text(res: dict) -> str:
    return "; ".join(f"{k}: {fmt(v)}" for k, v in res.get("figures", {}).items())


def protocol_md(doc: dict, extra: dict | None = None) -> str:
    meta = doc.get("meta", {})
    prof = meta.get("timing_profile") or {}
    extra = extra or {}
    lines = [
        f"# estop HIL test protocol, {meta.get('date', '?')}",
        "",
        f"- Device under test: `{meta.get('dut', '?')}`"
        + (f" (sha256 {meta['dut_sha256'][:16]}...)" if meta.get("dut_sha256") else ""),
    ]
    if "standin" in str(meta.get("dut", "")):
        lines.append("- **NOTE: the device under test is the harness's Python stand-in, "
                     "not estopd. This run checks the harness only.**")
    lines += [
        f"- Bus: SocketCAN `{meta.get('iface', '?')}` (vcan), mode **{meta.get('mode', '?')}**"
        f", kernel {meta.get('kernel', '?')}, python-can {meta.get('python_can', '?')}",
        f"- Timing limits: profile **{prof.get('profile', '?')}** (\"at once\" = median <= "
        f"{prof.get('p50', '?')} ms, each <= {prof.get('max', '?')} ms; live emulator "
        f"allowance {prof.get('emu', '?')} ms beyond 50 ms)",
        f"- Daemon timeout {meta.get('timeout_ms', '?')} ms; latency scenarios repeated "
        f"{meta.get('repeat', '?')}x; scenario runtime {meta.get('runtime_s', '?')} s",
    ]
    if meta.get("dut_scheduling"):
        asked = meta.get("dut_rt_prio")
        how = (f"as deployed: chrt -f -R {asked} and --rt-prio {asked} --mlock" if asked
               else "an ordinary process")
        lines.append(f"- Daemon scheduling ({how}): {'; '.join(meta['dut_scheduling'])}")
    if meta.get("two_stage"):
        lines.append(f"- Two-stage daemon: {meta['two_stage']}")
    if meta.get("car"):
        lines.append(f"- Car (vehicle model, docs/VEHICLE.md): {meta['car']}")
    for k, v in extra.items():
        lines.append(f"- {k}: {v}")
    if doc.get("fatal"):
        lines.append(f"- **FATAL: {doc['fatal']}**")
    results = doc.get("results", [])
    npass = sum(1 for r in results if r.get("passed"))
    verdict = "PASSED" if doc.get("passed") else "FAILED"
    lines += [f"- Verdict: **{verdict}** ({npass}/{len(results)} rows passed)", "",
              "| # | Test | Criterion | Result | Measured | Notes |",
              "|---|------|-----------|--------|----------|-------|"]
    for i, r in enumerate(results, 1):
        notes = "; ".join(r.get("notes", []))
        lines.append(f"| {i} | {cell(r.get('title', r.get('id', '?')))} "
                     f"| {cell(r.get('criterion', ''))} "
                     f"| {'PASS' if r.get('passed') else '**FAIL**'} "
                     f"| {cell(figures_text(r))} | {cell(notes)} |")
    lines.append("")
    lines.append("Times are measured on the bus: kernel receive timestamps of the frames "
                 "(python-can) against the harness's own send times, same clock.")
    lines += rollout_md(doc)
    return "\n".join(lines) + "\n"


def rollouts(doc: dict) -> list[tuple[str, dict]]:
    """(label, roll-out record) of every row that measured one, in the order of the rows."""
    return [(label, ro) for r in doc.get("results", [])
            for label, ro in (r.get("rollouts") or {}).items()]


def median(values: list[float]) -> float:
    """The interpolated median, as the rows' figures (hilstats.summary) give it."""
    xs = sorted(values)
    mid = (len(xs) - 1) / 2
    return (xs[math.floor(mid)] + xs[math.ceil(mid)]) / 2 if xs else float("nan")


def _spread(values: list[float], digits: int) -> str:
    """``p50 (min-max)``."""
    if not values:
        return "-"
    xs = sorted(values)
    if len(xs) == 1:
        return f"{xs[0]:.{digits}f}"
    return f"{median(xs):.{digits}f} ({xs[0]:.{digits}f}-{xs[-1]:.{digits}f})"


def rollout_md(doc: dict) -> list[str]:
    """The distances table: how far the car rolled from the moment that mattered."""
    ros = rollouts(doc)
    if not ros:
        return []
    car = doc.get("meta", {}).get("car", "15 km/h, emergency deceleration 8 m/s^2")
    lines = ["", "## How far the car rolls", "",
             f"The car at {car} (the vehicle model's defaults, docs/VEHICLE.md), from the "
             "moment that mattered to standstill: replayed from the frames on the bus through "
             "the brake controller's graded answer (estop.model.rollout; the harness's own "
             "emulator must agree to 1 mm). *Model* is the figure for an ideal unit with the "
             "row's times.",
             "", "| From | n | braking began after, ms: p50 (min-max) | distance, m: p50 "
             "(min-max) | model, m |", "|---|---|---|---|---|"]
    compare: list[list] = []
    for label, ro in ros:
        dist = [float(v) for v in ro.get("distance_m", [])]
        began = [float(v) for v in ro.get("braking_after_ms", []) if v is not None]
        lines.append(f"| {cell(label)} | {len(dist)} | {_spread(began, 1)} | "
                     f"{_spread(dist, 3)} | {float(ro.get('model_m', 0.0)):.3f} "
                     f"({cell(str(ro.get('model', '')))}) |")
        compare += ro.get("compare", [])
    for text, metres, *_ in compare:
        lines.append(f"| {cell(str(text))} | - | - | - | {float(metres):.3f} |")
    return lines


def plot(doc: dict, path: Path) -> bool:
    """Strip plot of the stop latencies; False when there is nothing to plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: list[tuple[str, list[float]]] = []
    for r in doc.get("results", []):
        for name, values in r.get("samples_ms", {}).items():
            if name in PLOTTED and values:
                series.append((name, values))
    if not series:
        return False
    fig, ax = plt.subplots(figsize=(max(9.0, 1.1 * len(series) + 1.5), 5.2), dpi=110)
    for i, (_, values) in enumerate(series):
        xs = [i + 0.08 * ((j % 5) - 2) for j in range(len(values))]
        ax.scatter(xs, values, s=22, alpha=0.8, zorder=3)
        if len(values) > 2:
            ax.boxplot([values], positions=[i], widths=0.5, showfliers=False)
    ax.set_xticks(range(len(series)))
    ax.set_xticklabels([textwrap.fill(n, 14) + f"\n(n={len(v)})" for n, v in series],
                       fontsize=7.5)
    ax.axhline(0, color="grey", lw=0.8)
    prof = doc.get("meta", {}).get("timing_profile") or {}
    for key, style in (("p50", ":"), ("max", "--")):
        if isinstance(prof.get(key), int | float):
            ax.axhline(prof[key], color="tab:red", lw=0.8, ls=style)
            ax.annotate(f"limit {key} {prof[key]:g} ms ({prof.get('profile', '?')})",
                        (len(series) - 0.5, prof[key]), fontsize=7, color="tab:red",
                        ha="right", va="bottom")
    ax.set_ylabel("ms: frame time on the bus - reference time")
    ax.set_xlim(-0.6, len(series) - 0.4)
    meta = doc.get("meta", {})
    ax.set_title(f"estop stop latencies and deadline overshoots on {meta.get('iface', 'vcan')} "
                 f"({meta.get('mode', '?')}, {meta.get('date', '')})", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def plot_distance(doc: dict, path: Path) -> bool:
    """Bars of how far the car rolled (p50, whiskers min-max), split into the metres rolled
    before braking began and the metres braking; the model's figure of each row as a tick, and
    the model-only comparisons in grey. False when no row measured a roll-out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ros = rollouts(doc)
    if not ros:
        return False
    car = doc.get("meta", {}).get("car", "")
    bars: list[tuple[str, float, float, float, float, float | None, bool]] = []
    for label, ro in ros:
        dist = sorted(float(x) for x in ro.get("distance_m", []))
        pre = sorted(float(x) for x in ro.get("before_braking_m", []))
        if not dist:
            continue
        p50 = median(dist)
        before = median(pre) if pre else 0.0
        bars.append((f"{label}\n(n={len(dist)})", p50, before, dist[0], dist[-1],
                     float(ro.get("model_m", 0.0)), True))
        for text, metres, *rest in ro.get("compare", []):
            bars.append((str(text), float(metres), float(rest[0]) if rest else 0.0,
                         float(metres), float(metres), None, False))
    if not bars:
        return False
    fig, ax = plt.subplots(figsize=(9.5, 0.75 * len(bars) + 1.8), dpi=110)
    ys = list(range(len(bars)))[::-1]
    for y, (_, total, before, lo, hi, model, measured) in zip(ys, bars, strict=True):
        color = "tab:blue" if measured else "lightgrey"
        ax.barh(y, before, color=color, alpha=0.45, hatch="//", edgecolor="grey", height=0.6)
        ax.barh(y, total - before, left=before, color=color, height=0.6)
        if measured:
            ax.errorbar(total, y, xerr=[[total - lo], [hi - total]], fmt="none", ecolor="black",
                        capsize=4, lw=1)
            if model is not None:
                ax.plot([model, model], [y - 0.38, y + 0.38], color="tab:red", lw=1.5)
        ax.annotate(f"{total:.2f} m", (total, y), xytext=(26, 0), textcoords="offset points",
                    va="center", fontsize=8)
    ax.set_yticks(ys)
    ax.set_yticklabels([textwrap.fill(b[0], 34) if "\n" not in b[0] else b[0] for b in bars],
                       fontsize=7.5)
    ax.set_xlabel("metres from the moment that mattered to standstill (hatched: before "
                  "braking began)")
    ax.set_xlim(0, max(b[1] for b in bars) * 1.45)
    ax.legend(handles=[
        Patch(color="tab:blue", label="measured on the bus: p50, whiskers min-max"),
        Patch(facecolor="white", edgecolor="grey", hatch="//", label="rolled before braking"),
        Line2D([], [], color="tab:red", lw=1.5, label="model: ideal unit, the row's times"),
        Patch(color="lightgrey", label="model only")], fontsize=7.5, loc="upper right")
    meta = doc.get("meta", {})
    ax.set_title(f"How far the car rolls from the moment that mattered to standstill\n{car}; "
                 f"{meta.get('mode', '?')}, {meta.get('date', '')}", fontsize=9)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out")
    p.add_argument("--extra", help="JSON object of extra header lines (e.g. VM figures)")
    p.add_argument("--no-plot", action="store_true")
    args = p.parse_args(argv)
    out = Path(args.out)
    try:
        doc = json.loads((out / "results.json").read_text())
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"hil: no readable results.json in {out}: {exc}\n")
        return 1
    extra = None
    if args.extra:
        try:
            extra = json.loads(Path(args.extra).read_text())
        except (OSError, ValueError) as exc:
            sys.stderr.write(f"hil: cannot read {args.extra}: {exc}\n")
    ok = bool(doc.get("passed"))
    if not args.no_plot:
        try:
            if plot(doc, out / "latency.png"):
                (extra := extra or {})["Latency plot"] = str(out / "latency.png")
            if plot_distance(doc, out / "distance.png"):
                (extra := extra or {})["Distance plot"] = str(out / "distance.png")
        except Exception as exc:  # noqa: BLE001 - a missing plot fails the run, with reason
            sys.stderr.write(f"hil: latency plot failed: {exc}\n")
            ok = False
    text = protocol_md(doc, extra)
    (out / "protocol.md").write_text(text)
    sys.stdout.write(text)
    sys.stdout.write(failure_summary(doc))
    return 0 if ok else 1


def failure_summary(doc: dict, width: int = 300) -> str:
    """The failed rows again, each with its failures, as the last lines printed: CI keeps only
    the tail of a run's output, and the table's failed row may lie far above it (stop 48's CI
    run showed rows 20 to 24, all passed, and not which row failed)."""
    failed = [r for r in doc.get("results", []) if not r.get("passed")]
    if not failed and not doc.get("fatal"):
        return ""
    lines = ["", "## Failed rows, again (the table above has them in full)", ""]
    if doc.get("fatal"):
        lines.append(f"- FATAL: {str(doc['fatal'])[:width]}")
    for r in failed:
        fails = [n for n in r.get("notes", []) if n.startswith(("FAIL", "try "))]
        lines.append(f"- {r.get('id', '?')} ({r.get('title', '?')}): "
                     f"{len(fails)} failure note(s)")
        lines += [f"  - {n[:width]}" for n in fails[:6]]
        if len(fails) > 6:
            lines.append(f"  - ... and {len(fails) - 6} more")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
