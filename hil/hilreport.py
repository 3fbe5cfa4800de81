"""Test protocol of a HIL run: Markdown table and latency plot from ``results.json``.

    python hil/hilreport.py OUT_DIR [--extra vm.json]

Writes ``OUT_DIR/protocol.md`` and ``OUT_DIR/latency.png`` and prints the table. Exits 1 when
the run failed or ``results.json`` is missing or unreadable (never a silent pass).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

PLOTTED = (
    "dead-man overshoot",
    "overshoot under invalid flood",
    "TCP STOP -> stop frame",
    "release -> ARMED frame",
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
    return "\n".join(lines) + "\n"


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
    fig, ax = plt.subplots(figsize=(9, 4.8), dpi=110)
    for i, (_, values) in enumerate(series):
        xs = [i + 0.08 * ((j % 5) - 2) for j in range(len(values))]
        ax.scatter(xs, values, s=22, alpha=0.8, zorder=3)
        if len(values) > 2:
            ax.boxplot([values], positions=[i], widths=0.5, showfliers=False)
    ax.set_xticks(range(len(series)))
    ax.set_xticklabels([f"{n}\n(n={len(v)})" for n, v in series], fontsize=8)
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
    ax.set_title(f"estop stop latencies on {meta.get('iface', 'vcan')} "
                 f"({meta.get('mode', '?')}, {meta.get('date', '')})", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
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
        except Exception as exc:  # noqa: BLE001 - a missing plot fails the run, with reason
            sys.stderr.write(f"hil: latency plot failed: {exc}\n")
            ok = False
    text = protocol_md(doc, extra)
    (out / "protocol.md").write_text(text)
    sys.stdout.write(text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
