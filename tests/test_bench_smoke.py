"""The bench's statistics and reporting helpers, on synthetic data only.

No timing is measured or asserted here: the stop-latency goals live in bench/stop_latency.py
(``make bench``), never in unit tests.
"""

from __future__ import annotations

import math
import random
from pathlib import Path
from types import ModuleType

import pytest

from tool_util import load_bench_script


def test_percentile_matches_linear_interpolation(bench: ModuleType) -> None:
    values = [float(v) for v in range(1, 1001)]  # 1..1000
    assert bench.percentile(values, 0) == 1.0
    assert bench.percentile(values, 100) == 1000.0
    assert bench.percentile(values, 50) == pytest.approx(500.5)
    assert bench.percentile(values, 99) == pytest.approx(990.01)
    assert bench.percentile(values, 99.9) == pytest.approx(999.001)
    assert bench.percentile([7.0], 99.9) == 7.0
    assert math.isnan(bench.percentile([], 50))
    with pytest.raises(ValueError):
        bench.percentile(values, 101)


def test_percentile_agrees_with_numpy(bench: ModuleType) -> None:
    np = pytest.importorskip("numpy")
    rng = random.Random(7)
    values = sorted(rng.lognormvariate(0.0, 1.0) for _ in range(1234))
    for q in (0, 1, 50, 90, 99, 99.9, 100):
        assert bench.percentile(values, q) == pytest.approx(float(np.percentile(values, q)))


def test_summarize_is_order_free_and_complete(bench: ModuleType) -> None:
    rng = random.Random(1)
    values = [rng.uniform(-0.5, 10.0) for _ in range(1000)]
    s = bench.summarize(values)
    assert s == bench.summarize(list(reversed(values)))
    assert s["n"] == 1000
    assert s["min"] <= s["p50"] <= s["p99"] <= s["p99.9"] <= s["max"]
    assert s["max"] == max(values) and s["min"] == min(values)
    empty = bench.summarize([])
    assert empty["n"] == 0 and math.isnan(empty["p99.9"])


def test_log_bins_cover_the_data(bench: ModuleType) -> None:
    edges = bench.log_bins([0.02, 0.5, 12.0], floor=0.001, n_bins=30)
    assert len(edges) == 31
    assert edges[0] == pytest.approx(0.001)
    assert edges[-1] > 12.0
    assert all(a < b for a, b in zip(edges, edges[1:], strict=False))
    with pytest.raises(ValueError):
        bench.log_bins([1.0], floor=0.0)


def _run(bench: ModuleType, daemon: str, load: str, overshoot: list[float],
         rate: float | None = None) -> object:
    r = bench.RunResult(daemon, load, 20)
    r.samples["overshoot"] = overshoot
    r.samples["tcp_stop"] = [0.05] * len(overshoot)
    if rate is not None:
        r.flood = bench.FloodStats(target_rate=rate, sent=int(rate * 10), elapsed_s=10.0)
    return r


def test_goals_and_report_on_synthetic_runs(bench: ModuleType, tmp_path: Path) -> None:
    fast = [0.1] * 999 + [0.5]
    slow = [5.0] * 999 + [9.9]
    runs = [_run(bench, "estopd", "idle", fast), _run(bench, "baseline", "idle", slow),
            _run(bench, "estopd", "flood", fast[:-2] + [3.0, 3.0], rate=80_000.0),
            _run(bench, "baseline", "flood", slow, rate=40_000.0)]
    goals = dict(bench.check_goals(runs))
    verdicts = sorted(goals.values())
    assert verdicts.count(False) == 3  # flood p99.9 >= 2 ms, not 5x ahead, flood too slow
    assert any("idle" in g and "< 1.0 ms" in g and ok for g, ok in goals.items())
    assert any("40,000 packets/s" in g and not ok for g, ok in goals.items())

    meta = {"date": "today", "host": "h", "cpus": 2, "python": "3.11", "timeout_ms": 20,
            "trials": 1000, "flood_rate": 80_000.0}
    md = bench.markdown(runs, meta, bench.check_goals(runs))
    assert md.count("| estopd |") == 4 and md.count("| baseline |") == 4
    assert "FAIL:" in md and "PASS:" in md
    pytest.importorskip("matplotlib")
    bench.plot(runs, tmp_path / "h.png", 20)
    assert (tmp_path / "h.png").stat().st_size > 1000


def test_start_line_ports_are_parsed() -> None:
    from estop.loopback import parse_start_ports

    assert parse_start_ports("estopd 0.000001 start udp=127.0.0.1:5700 tcp=127.0.0.1:5701") \
        == (5700, 5701)
    assert parse_start_ports('{"t_mono": 1.5, "event": "start", "udp_port": 40000, '
                             '"tcp_port": 40001}') == (40000, 40001)
    assert parse_start_ports("estopd 1.0 start udp_port=1 tcp_port=2") == (1, 2)
    assert parse_start_ports("estopd 1.0 state ARMED->STOPPED reason=udp_timeout") is None


def test_lost_lines_are_a_column_and_settle_moves_samples(bench: ModuleType) -> None:
    r = _run(bench, "estopd", "idle", [0.1, 0.2, 30.0])
    r.spans["overshoot"] = [((1.0, 1.1), (5.0, 5.1)), ((2.0, 2.1), (6.0, 6.1)),
                            ((3.0, 3.1), (7.0, 7.1))]
    moved = r.settle(lambda real, mono: 1 if real[0] == 3.0 else 0)
    assert moved == 1 and r.samples["overshoot"] == [0.1, 0.2]
    assert r.lost_discards("overshoot") == 1 and r.discarded["overshoot"] == 1
    assert r.settle(lambda real, mono: 0) == 0  # settled once is settled
    meta = {"date": "today", "host": "h", "cpus": 2, "python": "3.11", "timeout_ms": 20,
            "trials": 3, "flood_rate": 80_000.0}
    md = bench.markdown([r], meta, [])
    header = next(ln for ln in md.splitlines() if ln.startswith("| daemon"))
    row = next(ln for ln in md.splitlines() if "| timeout overshoot |" in ln)
    cells = dict(zip(header.split("|"), row.split("|"), strict=True))
    assert cells[" lines lost "].strip() == "1" and cells[" discarded "].strip() == "1"
    assert "timeout overshoot: log lines lost 1" in md


def test_latency_tables_from_synthetic_runs(bench: ModuleType) -> None:
    tables = load_bench_script("latency_tables")
    args = tables.argparse.Namespace(hog=2, rt_prio=50, timeout_ms=20, trials=10,
                                     out=Path("/nonexistent"), estopd=None,
                                     estopd_before=None, before_label="before",
                                     two_stage_ms=(100, 200), two_stage_trials=30)
    names = [c.name for c in tables.configs(["hog", "issue11"], args)]
    assert names == ["hog-normal", "hog-rt-bench-normal", "hog-rt"]
    cmd = tables.command(tables.configs(["issue11"], args)[1], args)
    assert cmd[cmd.index("--bench-rt-prio") + 1] == "0" and "--loads" in cmd

    def doc(rt: int, bench_rt: int, lost: int) -> dict[str, object]:
        r = _run(bench, "estopd", "idle", [0.03] * 9 + [0.9])
        for _ in range(lost):
            r.discard("overshoot", bench.LOST_LINES)
        r.log_gaps, r.log_gap_lines, r.daemon_dropped = lost, 3 * lost, 7 * lost
        meta = {"date": "d", "cpus": 2, "timeout_ms": 20, "trials": 10, "flood_rate": 8e4,
                "priorities": "p", "hog": 2, "hog_cpu_cores": 0.5, "rt_prio": rt,
                "bench_rt_prio": bench_rt}
        return tables.json.loads(tables.json.dumps(bench.document([r], meta, [])))

    docs = {"hog-normal": doc(0, 0, 0), "hog-rt-bench-normal": doc(50, 0, 4),
            "hog-rt": doc(50, 40, 0)}
    md = "\n".join(tables.table_issue11(docs, args) + tables.table_hog(docs, args))
    issue_rows = [ln for ln in md.splitlines() if ln.startswith(("| estopd,", "| estopd `"))]
    assert len(issue_rows) == 3
    bench_normal = next(ln for ln in issue_rows if "bench at normal priority" in ln)
    assert "| 4 | 0 | 4 (12) | 28 |" in bench_normal  # lost-line discards, gaps, reported
    hog_rows = [ln for ln in md.splitlines() if "| idle |" in ln]
    assert hog_rows == [
        "| normal | normal | idle | 10 | 0.030 | 0.822 | 0.892 | 0.900 | 0 | 0 | - | n/a |",
        "| SCHED_FIFO 50 | SCHED_FIFO 40 | idle | 10 | 0.030 | 0.822 | 0.892 | 0.900 | 0 | 0 "
        "| - | n/a |"]
