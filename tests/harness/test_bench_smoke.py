"""The bench's statistics and reporting helpers, on synthetic data only: summaries, goals,
the report's rows (lift, roll-out, before / after, two-stage), the judging of recorded
can-logs and the roll-out computed from their frames.

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


# --------------------------------------------------------------------------------------------
# Version 3 rows: lift, roll-out, before / after, two-stage (synthetic can-logs, no timing)

V15 = 15 / 3.6  # 15 km/h in m/s


def _part(bench: ModuleType, name: str) -> ModuleType:
    """One of the bench's modules, as stop_latency.py imported it (no second copy)."""
    import importlib

    assert bench.HERE.name == "bench"  # the script put its folder on sys.path
    return importlib.import_module(name)
BRAKING_15 = V15 * V15 / (2 * 8.0)  # full braking alone from 15 km/h at 8 m/s^2


def _frames(t0: float, changes: list[tuple[float, int, int]], end: float) -> list[object]:
    """ESTOP_BRAKE records every 10 ms from t0 to end, as a unit sends them: each change
    (time, state, reason) sent at once, the period restarting there."""
    from estop.protocol import can, canlog

    out = []
    ctr = 0
    state, reason = changes[0][1], changes[0][2]
    pending = list(changes[1:])
    t = t0
    while t <= end + 1e-9:
        if pending and pending[0][0] <= t:
            t, state, reason = pending.pop(0)
        frame = can.BrakeFrame.for_state(state, reason, 0, ctr, slow_level=30)
        out.append(canlog.CanLogRecord.at(t, "estop", can.BRAKE_ID, frame.encode()))
        ctr = (ctr + 1) % 15
        t += 0.010
    return out


def _fed(records: list[object]) -> object:
    """A daemon object that never ran, its can-log queue filled with ``records``."""
    import io

    from estop.protocol import canlog
    from estop.unit.daemon import Daemon

    d = Daemon(["estopd-not-run"])
    d._read_frames(io.StringIO("".join(canlog.format_line(r) + "\n" for r in records)))
    return d


def test_roll_out_from_a_synthetic_can_log(bench: ModuleType) -> None:
    from estop.protocol import can

    S, A = can.State, can.Reason
    t0 = 1000.0
    # single stage: ARMED, the timeout stop 20.3 ms after the last packet at t0 + 0.05
    last = t0 + 0.05
    log = _frames(t0, [(t0, S.ARMED, A.NONE), (last + 0.0203, S.STOPPED, A.UDP_TIMEOUT)],
                  last + 0.2)
    roll = bench.roll_from_record(log, last, 15.0)
    assert roll.distance == pytest.approx(V15 * 0.0203 + BRAKING_15, abs=1e-6)
    assert bench.braking_distance(15.0) == pytest.approx(BRAKING_15)
    # the record may end at the stop frame: the controller brakes fully from there
    cut = [r for r in log if r.timestamp <= last + 0.0203 + 1e-6]
    assert bench.roll_from_record(cut, last, 15.0).distance == pytest.approx(roll.distance)
    # two stages: SLOWING at 30 % from S = 100 ms, STOPPED at T = 200 ms
    two = _frames(t0, [(t0, S.ARMED, A.NONE), (last + 0.100, S.SLOWING, A.NONE),
                       (last + 0.200, S.STOPPED, A.UDP_TIMEOUT)], last + 0.3)
    v1 = V15 - 0.3 * 8.0 * 0.1
    want = V15 * 0.1 + (V15 + v1) / 2 * 0.1 + v1 * v1 / 16.0
    assert bench.roll_from_record(two, last, 15.0).distance == pytest.approx(want, abs=1e-6)
    assert want < V15 * 0.2 + BRAKING_15  # the slow-down shortens the stop at the same T


def test_judge_lift_and_two_stage_silence_from_recorded_logs(bench: ModuleType) -> None:
    import time

    from estop.protocol import can

    S, A = can.State, can.Reason
    t0 = time.time() - 5.0
    t_lift = t0 + 0.0405
    log = _frames(t0 - 0.03, [(t0 - 0.03, S.STOPPED, A.BOOT), (t0, S.ARMED, A.NONE),
                              (t_lift + 0.0002, S.STOPPED, A.LIFT)], t_lift + 0.05)
    r = bench.RunResult("estopd", "idle", 20, metrics=bench.PLAIN_METRICS)
    trials = bench.Trials(_fed(log), None, 20, 0.001, r)
    m0 = time.monotonic()
    assert trials.judge_lift(bench.LiftSent(m0, t0 + 0.001, t_lift - 0.001, t_lift))
    assert r.samples["lift"] == [pytest.approx(0.2, abs=1e-3)]
    assert r.distances["lift"] == [pytest.approx(V15 * 0.0002 + BRAKING_15, abs=1e-5)]
    # a lift trial the timeout stopped first: discarded with its reason, not timed
    log = _frames(t0, [(t0, S.ARMED, A.NONE), (t_lift + 0.02, S.STOPPED, A.UDP_TIMEOUT)],
                  t_lift + 0.05)
    trials = bench.Trials(_fed(log), None, 20, 0.001, r)
    assert not trials.judge_lift(bench.LiftSent(m0, t0 + 0.001, t_lift - 0.001, t_lift))
    assert r.discards_for("lift", "the timeout stopped it first") == 1
    # two-stage silence: SLOWING 0.1 ms after S, STOPPED 0.3 ms after T
    last = t0 + 0.012
    log = _frames(t0, [(t0, S.ARMED, A.NONE), (last + 0.1001, S.SLOWING, A.NONE),
                       (last + 0.2003, S.STOPPED, A.UDP_TIMEOUT)], last + 0.3)
    r2 = bench.RunResult("estopd 2-stage", "idle", 200, metrics=bench.TWO_STAGE_METRICS,
                         slow_ms=100)
    trials = bench.Trials(_fed(log), None, 200, 0.001, r2, slow_ms=100)
    assert trials.judge_timeout(bench.TimeoutSent(m0, t0 + 0.001, last))
    assert r2.samples["slowing"] == [pytest.approx(0.1, abs=1e-3)]
    assert r2.samples["overshoot"] == [pytest.approx(0.3, abs=1e-3)]
    assert 1.7 < r2.distances["overshoot"][0] < V15 * 0.2003 + BRAKING_15
    # the same log judged as a single-stage unit: no slow-down metric, one sample
    r1 = bench.RunResult("estopd", "idle", 200, metrics=("overshoot",))
    trials = bench.Trials(_fed(log), None, 200, 0.001, r1)
    assert trials.judge_timeout(bench.TimeoutSent(m0, t0 + 0.001, last))
    assert r1.samples["slowing"] == [] and len(r1.samples["overshoot"]) == 1


def test_settle_drops_the_distances_with_their_samples(bench: ModuleType) -> None:
    r = bench.RunResult("estopd", "idle", 20, metrics=bench.PLAIN_METRICS)
    for i in range(3):
        span = ((float(i), i + 0.1), (10.0 + i, 10.1 + i))
        r.add_sample("lift", 0.01 * i, span, 1.085 + i)
    assert r.settle(lambda real, mono: int(real[0] == 1.0)) == 1
    assert r.samples["lift"] == [0.0, 0.02] and r.distances["lift"] == [1.085, 3.085]


def _v3_run(bench: ModuleType, daemon: str, load: str, role: str, overshoot: list[float],
            lift: list[float] | None = None, drops: int | None = None,
            rcvbuf: int | None = None, metrics: tuple[str, ...] | None = None) -> object:
    r = bench.RunResult(daemon, load, 20, role=role,
                        metrics=metrics or (bench.PLAIN_METRICS if lift else bench.V2_METRICS))
    r.samples["overshoot"] = list(overshoot)
    r.distances["overshoot"] = [BRAKING_15 + V15 * (0.020 + v / 1000) for v in overshoot]
    r.samples["tcp_stop"] = [0.05] * len(overshoot)
    if lift:
        r.samples["lift"] = list(lift)
        r.distances["lift"] = [BRAKING_15 + V15 * v / 1000 for v in lift]
    r.udp_rcvbuf = rcvbuf
    if load == "flood":
        r.flood = bench.FloodStats(target_rate=8e4, sent=800_000, elapsed_s=10.0,
                                   kernel_drops=drops, forged=True)
    return r


def test_lift_roll_and_before_after_rows(bench: ModuleType) -> None:
    report = _part(bench, "latency_report")
    after = _v3_run(bench, "estopd+key", "flood", "main", [0.05] * 99 + [0.2],
                    lift=[0.02] * 99 + [0.4], drops=0, rcvbuf=8_388_608)
    before = _v3_run(bench, "estopd+key v2", "flood", "before", [0.06] * 99 + [0.3],
                     drops=1234)
    peer = _v3_run(bench, "estopd", "flood", "keyless", [0.04] * 100, lift=[0.08] * 100)
    meta = {"date": "today", "host": "h", "cpus": 2, "python": "3.11", "timeout_ms": 20,
            "trials": 100, "flood_rate": 8e4, "auth": True, "speed_kmh": 15.0,
            "decel_ms2": 8.0, "braking_m": BRAKING_15,
            "timer_floor_ms": bench.summarize([0.03] * 99 + [0.09])}
    runs = [after, before, peer]
    md = bench.markdown(runs, meta, bench.check_goals(runs, auth=True, floor_p999=0.09))
    rows = md.splitlines()
    lift = next(ln for ln in rows if ln.startswith("| estopd+key | flood | 100 |"))
    assert "| 0.030 / 0.084 | 0.2x | 0 |" in lift  # timer floor, peer ratio, timeout first
    ba = next(ln for ln in rows if ln.startswith("| flood | 80,000 / 80,000 |"))
    assert "| 1,234 / 0 | default / 8,388,608 | 100 / 100 | 0.060 / 0.050 |" in ba
    roll = [ln for ln in rows if "| first lift datagram |" in ln]
    assert len(roll) == 2 and "| 1.085 |" in roll[0]
    assert "| estopd+key v2 | flood | lift stop latency |" not in md  # a v2 unit: no lift
    assert report.before_after_table([after], meta) == []  # nothing to pair
    # the floor measured before the run's own blocks wins over the one before the start
    after.floor_ms = [0.01] * 9 + [0.5]
    assert report.floor_cell(after, meta) == "0.010 / 0.496"
    assert report.floor_cell(before, meta) == "0.030 / 0.084"
    goals = dict(bench.check_goals(runs, auth=True, floor_p999=0.09))
    assert any("unchanged from estopd+key v2" in g and ok for g, ok in goals.items())
    assert any("lift stop latency flood" in g and ok for g, ok in goals.items())
    worse = _v3_run(bench, "estopd+key", "flood", "main", [0.05] * 98 + [0.9, 0.9],
                    lift=[0.02] * 100, drops=0)
    goals = dict(bench.check_goals([worse, before], auth=True, floor_p999=0.09))
    assert any("unchanged from" in g and not ok for g, ok in goals.items())


def test_two_stage_rows_and_goals(bench: ModuleType) -> None:
    two = _v3_run(bench, "estopd 2-stage", "idle", "main", [0.05] * 10,
                  metrics=bench.TWO_STAGE_METRICS)
    two.slow_ms, two.timeout_ms = 100, 200
    two.samples["slowing"] = [0.04] * 9
    two.missed["slowing"] = 1
    two.distances["overshoot"] = [1.785] * 10
    one = _v3_run(bench, "estopd 1-stage", "idle", "single-stage", [0.05] * 10,
                  metrics=("overshoot",))
    one.timeout_ms = 200
    one.distances["overshoot"] = [1.919] * 10
    meta = {"date": "today", "host": "h", "cpus": 2, "python": "3.11", "timeout_ms": 200,
            "trials": 10, "flood_rate": 8e4, "slow_ms": 100, "slow_level": 30}
    goals = bench.check_goals([two, one])
    md = bench.markdown([two, one], meta, goals)
    row = next(ln for ln in md.splitlines() if ln.startswith("| estopd 2-stage | idle | 100 |"))
    assert "| 9 of 10 | 0.040 / 0.040 | 0.050 / 0.050 | 1.785 / 1.785 |" in row
    verdict = dict(goals)
    assert any("rolls no farther" in g and ok for g, ok in verdict.items())
    assert any("every trial stopped" in g and not ok for g, ok in verdict.items())  # 1 missed
    one.distances["overshoot"] = [1.7] * 10
    assert any("rolls no farther" in g and not ok for g, ok in bench.check_goals([two, one]))


def test_receive_buffer_and_drops_from_the_daemon_log(bench: ModuleType) -> None:
    flood = _part(bench, "latency_flood")
    v3 = ["estopd 1.0 start udp=127.0.0.1:1 tcp=127.0.0.1:2 udp_rcvbuf=8388608 rt_prio=0",
          "estopd 11.0 udp_drops dropped=5 total=5", "estopd 21.0 udp_drops dropped=2 total=7"]
    assert flood.start_rcvbuf(v3) == 8_388_608 and flood.reported_udp_drops(v3) == 7
    assert flood.reported_udp_drops(v3[:1]) == 0  # reports its buffer, no drop yet
    js = ['{"t_mono":1.0,"event":"start","udp":"127.0.0.1:1","udp_rcvbuf":425984}',
          '{"t_mono":2.0,"event":"udp_drops","dropped":3,"total":3}']
    assert flood.start_rcvbuf(js) == 425_984 and flood.reported_udp_drops(js) == 3
    v2 = ["estopd 1.0 start udp=127.0.0.1:1 tcp=127.0.0.1:2 timeout_ms=20 version_major=2"]
    assert flood.start_rcvbuf(v2) is None and flood.reported_udp_drops(v2) is None


def test_runs_come_back_from_json_for_the_tables(bench: ModuleType) -> None:
    import json

    result = _part(bench, "latency_result")
    r = _v3_run(bench, "estopd+key", "flood", "main", [0.05, 0.07], lift=[0.02, 0.03],
                drops=0, rcvbuf=8_388_608)
    doc = json.loads(json.dumps(bench.document([r], {}, [])))
    back = result.from_document(doc["runs"][0])
    assert back.samples == r.samples and back.distances == r.distances
    assert back.metrics == r.metrics and back.role == "main"
    assert back.flood is not None and back.flood.kernel_drops == 0
    old = doc["runs"][0]
    for key in ("distances", "metrics", "role"):
        del old[key]
    del old["samples"]["lift"]
    back = result.from_document(old)  # a report from before the lift rows
    assert back.samples["lift"] == [] and back.metrics == ("overshoot", "tcp_stop")
