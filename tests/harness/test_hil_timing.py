"""The HIL harness's judging of time (hil/hilstalls.py, hilstats): stall intervals, the periods
a stall stretched, late frames and enough frames."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

import hilcheck


def test_stall_intervals() -> None:
    lines = ["# cpu 0 rt 1 pid 5", "10.000 10.040", "bad line", "10.030 10.050", "11.0 11.01"]
    stalls = hilcheck.merge(hilcheck.read_stalls(lines))
    assert stalls == [(10.0, 10.05), (11.0, 11.01)]
    assert hilcheck.overlap(stalls, 10.02, 11.005) == pytest.approx(0.035)
    # a 54 ms gap of which the CPU stood still 45 ms: the environment's
    assert hilcheck.excused(10.0, 10.054, stalls) == pytest.approx(0.05)
    # a 60 ms gap with only a 10 ms stall in it: the daemon had 50 ms to send
    assert hilcheck.excused(10.995, 11.055, stalls) is None
    assert hilcheck.excused(12.0, 12.06, stalls) is None


def test_overlap_is_a_binary_search_over_merged_intervals() -> None:
    stalls = hilcheck.merge([(float(i), i + 0.5) for i in range(0, 20000, 2)])
    assert hilcheck.overlap(stalls, 10.25, 12.25) == pytest.approx(0.25 + 0.25)
    assert hilcheck.overlap(stalls, -5.0, 0.1) == pytest.approx(0.1)
    assert hilcheck.overlap(stalls, 19998.4, 30000.0) == pytest.approx(0.1)
    assert hilcheck.overlap(stalls, 1.0, 1.9) == 0.0
    assert hilcheck.overlap([], 0.0, 1.0) == 0.0
    # the same answer as the plain sum it replaces
    for t0, t1 in ((3.7, 9.1), (0.0, 0.5), (4.49, 4.51), (7.0, 7.0)):
        plain = sum(max(0.0, min(b, t1) - max(a, t0)) for a, b in stalls)
        assert hilcheck.overlap(stalls, t0, t1) == pytest.approx(plain)


def test_merge_more_equals_a_full_merge() -> None:
    cpu0 = [(10.0, 10.01), (10.05, 10.06), (10.2, 10.3)]
    cpu1 = [(10.005, 10.02), (10.25, 10.4), (10.5, 10.6)]
    full = hilcheck.merge(cpu0 + cpu1)
    # read in pieces, the files interleaved in time (cpu1 read on after cpu0's later lines)
    part = hilcheck.merge_more(hilcheck.merge(cpu0[:2] + cpu1[:1]), cpu0[2:] + cpu1[1:])
    assert part == full == [(10.0, 10.02), (10.05, 10.06), (10.2, 10.4), (10.5, 10.6)]
    assert hilcheck.merge_more(full, []) is full


def _grid(t0: float, n: int, period: float = 0.010) -> list[float]:
    return [t0 + i * period for i in range(n)]


def test_periods_without_stalls_judge_every_gap() -> None:
    p = hilcheck.periods(_grid(100.0, 101), [], 0.010)
    assert len(p.gaps) == len(p.judged) == 100 and p.stretches == 1
    assert p.mean_judged == pytest.approx(0.010)
    assert p.left_out_text() == "none"


def test_periods_leave_out_what_a_stall_stretched() -> None:
    # The boot row's failure: stalls of 15-30 ms push frames late; after a delay of a whole
    # period the daemon starts its grid over, so slots are lost and the mean of all gaps grows
    # (here by 0.23 ms; the boot row's 1 s had 70 such stalls). Judged on the stall-free
    # stretches, the period is the grid's.
    ts = _grid(100.0, 30)  # 100.00 .. 100.29
    stall1 = (100.295, 100.320)  # 25 ms: the frame due at 100.30 goes out at 100.321
    ts += [100.321 + i * 0.010 for i in range(30)]  # grid restarted: 100.321 .. 100.611
    stall2 = (100.6115, 100.6255)  # 14 ms: 100.621 goes out at 100.626, then the grid again
    ts += [100.626, 100.631] + [100.641 + i * 0.010 for i in range(30)]
    stalls = [stall1, stall2]
    p = hilcheck.periods(ts, stalls, 0.010)
    assert p.mean_all is not None and p.mean_all > 0.0102  # what the old check judged
    assert p.mean_judged == pytest.approx(0.010, abs=1e-4)
    assert p.splits == 2 and p.stretches == 3
    left = len(p.gaps) - len(p.judged)
    # the two stalled gaps, and the gaps from frames a stall may have delayed (within 20 ms)
    assert 2 < left < 10
    text = p.left_out_text()
    assert text.startswith(f"{left} of {len(p.gaps)} gaps (2 held a CPU stall")
    assert "max 31.0 ms" in text


def test_periods_do_not_hide_a_slow_daemon() -> None:
    # a daemon that sends every 11 ms is judged 11 ms with or without stalls elsewhere
    ts = _grid(200.0, 200, 0.011)
    stalls = [(200.5, 200.53), (201.2, 201.25)]
    p = hilcheck.periods(ts, stalls, 0.010)
    assert p.mean_judged == pytest.approx(0.011, abs=1e-6)
    assert len(p.judged) > 150
    # and a frame that is late without a stall stays in: it is the daemon's own
    ts2 = _grid(300.0, 50)
    ts2[25] += 0.007
    p2 = hilcheck.periods(ts2, [], 0.010)
    assert len(p2.judged) == 49 and max(p2.judged) == pytest.approx(0.017)
    assert min(p2.judged) == pytest.approx(0.003)


def test_periods_status_period_ignores_short_stalls() -> None:
    # ESTOP_STATUS (100 ms) with a 10 ms stall in most gaps: too short to cost it a slot, so
    # the stretch goes on; only frames right after a stall do not start or end one
    ts = _grid(50.0, 21, 0.100)
    stalls = [(50.0 + i * 0.1 + 0.04, 50.0 + i * 0.1 + 0.05) for i in range(20)]
    p = hilcheck.periods(ts, stalls, 0.100)
    assert len(p.judged) == 20 and p.splits == 0
    assert p.mean_judged == pytest.approx(0.100)
    late_ts = list(ts)
    late_ts[10] += 0.008  # delayed by a stall that ends right before it
    p2 = hilcheck.periods(late_ts, [*stalls[:9], (50.995, 51.007), *stalls[10:]], 0.100)
    assert p2.mean_judged == pytest.approx(0.100, abs=1e-3)


def _boot_tcg_run(name: str) -> tuple[list[float], list[tuple[float, float]]]:
    data = json.loads((Path(__file__).parent / "data" / name).read_text())
    return ([t / 1e6 for t in data["brake_us"]],
            [(a / 1e6, b / 1e6) for a, b in data["stalls_us"]])


def test_the_grid_period_of_a_tcg_run_whose_stretch_mean_failed() -> None:
    # The boot row of a HIL run of fe6fa73 failed on the mean of the stall-free stretches,
    # 9.22 ms: 22 gaps in 8 stretches of 1 to 5, whose first frames a vCPU delay the stall
    # monitor did not see had made late (a late start shortens a short stretch's mean).
    ts, stalls = _boot_tcg_run("hil_boot_tcg_fe6fa73.json")
    p = hilcheck.periods(ts, stalls, 0.010)
    assert p.mean_judged == pytest.approx(0.00922, abs=1e-5)
    assert p.grid == pytest.approx(0.010, abs=5e-5)
    assert p.grid_gaps >= 100


def test_the_grid_period_of_a_loaded_tcg_run_is_not_cut_at_stalls() -> None:
    # A run with a WP run beside it on the host: 59 of the first 90 gaps held a stall of half
    # a period. Fitted to runs cut at those stalls, the grid came out 9.59 ms (26 gaps in 60
    # runs of a few frames, each tilted by its own delays); cut at the long gaps only, 10.01.
    ts, stalls = _boot_tcg_run("hil_boot_tcg_loaded_5f2ba15.json")
    p = hilcheck.periods(ts, stalls, 0.010)
    assert p.grid == pytest.approx(0.010, abs=5e-5)
    first_s = [t for t in ts if t <= ts[0] + 1.0]
    assert hilcheck.periods(first_s, stalls, 0.010).grid == pytest.approx(0.010, abs=5e-5)


def _delayed(ts: list[float], seed: int, most_s: float) -> list[float]:
    rng = random.Random(seed)
    out = [t + (rng.uniform(0.0, most_s) if rng.random() < 0.4 else 0.0) for t in ts]
    return sorted(out)


@pytest.mark.parametrize("period", [0.0095, 0.010, 0.0106, 0.011])
def test_the_grid_period_under_delays_unseen(period: float) -> None:
    # frames delayed by up to 0.8 of a period, without any stall recorded: the grid's period
    # is found, a wrong one too (a daemon off by 0.6 ms fails the row's 0.5 ms)
    ts = _delayed(_grid(10.0, 200, period), 7, 0.8 * period)
    p = hilcheck.periods(ts, [], 0.010)
    assert p.grid == pytest.approx(period, abs=2e-5)
    assert p.grid_gaps > 100


def test_the_grid_period_across_a_restarted_grid() -> None:
    # after a stall the daemon starts its grid over, 4 ms later in phase: two runs, each with
    # its own line, one period
    ts = _delayed(_grid(20.0, 60), 3, 0.004)
    ts += _delayed(_grid(20.0 + 60 * 0.010 + 0.034, 60), 4, 0.004)
    p = hilcheck.periods(ts, [(20.59, 20.63)], 0.010)
    assert p.grid == pytest.approx(0.010, abs=2e-5)
    # unseen, the restart is still a gap of 1.5 periods or more: a run of its own
    q = hilcheck.periods(ts, [], 0.010)
    assert q.grid == pytest.approx(0.010, abs=2e-5)


def test_the_grid_period_wants_runs_of_three_frames() -> None:
    assert hilcheck.grid_period([[1.0, 1.01]], 0.010) == (None, 0)
    assert hilcheck.grid_period([], 0.010) == (None, 0)
    period, gaps = hilcheck.grid_period([[1.0, 1.01, 1.02], [2.0, 2.011]], 0.010)
    assert period == pytest.approx(0.010, abs=1e-6) and gaps == 2


def test_late_and_enough_frames() -> None:
    stalls = [(10.0, 10.03)]
    ok = hilcheck.late(9.99, 10.02, 0.05, stalls)
    assert ok.ok and ok.stall is None
    excusable = hilcheck.late(9.99, 10.06, 0.05, stalls)
    assert not excusable.ok and excusable.stall == pytest.approx(0.03)
    plain = hilcheck.late(11.0, 11.06, 0.05, stalls)
    assert not plain.ok and plain.stall is None
    ts = [10.0 + i * 0.01 for i in range(30)]
    assert hilcheck.enough_frames(ts, 10.0, 10.3, 20, 0.01, []) == (30, True)
    few = ts[:5] + ts[20:]  # 15 frames: 150 ms without any
    assert hilcheck.enough_frames(few, 10.0, 10.3, 20, 0.01, []) == (15, False)
    assert hilcheck.enough_frames(few, 10.0, 10.3, 20, 0.01, [(10.05, 10.2)]) == (15, None)
    assert hilcheck.enough_frames(few, 10.0, 10.3, 20, 0.01, [(10.05, 10.07)]) == (15, False)
