"""``estop link`` for protocol version 3: the slow time S and the timeout T.

The model's rate of silences reaching a time reads two ways: brief slow-downs at S, latched
emergency stops at T. The recommended pair is checked against the closed form at the true
parameters of seeded Gilbert traces (tests/link_util.py), the reading as S against the unit's
own rules run on the same traces (SLOWING ends after 3 valid packets, so close silences merge
into one slow-down), and the unit's counts in a version 3 daemon's log against the model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_util import run_cli
from estop import cli
from estop.link.fit import false_stops_per_hour, fit, lost_in_row
from estop.link.gaps import gaps_from_times
from estop.link.histogram import read_histogram_log
from estop.link.poisson import poisson_lower95, poisson_upper95
from estop.link.report import (
    DEFAULT_REACT_MS,
    DEFAULT_SLOW_TARGET,
    DEFAULT_TARGET,
    TIMEOUTS_MS,
    report,
)
from link_util import (
    HOURS10,
    PERIOD_US,
    RATE,
    UnitRun,
    arrivals_us,
    gilbert_lost,
    histogram_log,
    simulate_unit,
    unit_log,
)

pytestmark = pytest.mark.timeout(120)

LOSS = 0.09
BURST = 3.0
IID_BURST = 1.0 / (1.0 - LOSS)  # independent losses: P(bad->good) = 1 - loss
KMH15 = 15.0 / 3.6


@pytest.fixture(scope="module")
def bursty() -> np.ndarray:
    """Arrival times (us) of 10 hours at 50 Hz, 9 % loss in bursts of mean 3."""
    return arrivals_us(gilbert_lost(HOURS10, LOSS, BURST, 12))


@pytest.fixture(scope="module")
def independent() -> np.ndarray:
    """Arrival times (us) of 10 hours at 50 Hz, 9 % independent losses."""
    return arrivals_us(gilbert_lost(HOURS10, LOSS, IID_BURST, 14))


def truth_pair(loss: float, burst: float, target: float = DEFAULT_TARGET,
               slow_target: float = DEFAULT_SLOW_TARGET) -> tuple[int, int]:
    """(S, T) from the closed form at the true parameters, by the rule of PROTOCOL.md 3 read
    as the brief says: T the shortest time below target, S the shortest one longer than a
    send period, not above T, below slow_target."""
    rate = {d: false_stops_per_hour(loss, burst, lost_in_row(d, RATE), RATE)
            for d in TIMEOUTS_MS}
    t = next(d for d in TIMEOUTS_MS if rate[d] < target)
    s = next((d for d in TIMEOUTS_MS if d * 1000 > PERIOD_US and d <= t
              and rate[d] < slow_target), t)
    return s, t


def run_link(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    return run_cli(capsys, "link", *args)


def write_times(path: Path, t_us: np.ndarray) -> str:
    path.write_text("\n".join(f"{x / 1e6:.6f}" for x in t_us) + "\n")
    return str(path)


# --------------------------------------------------------------------------- the pair


def test_bursty_link_gets_two_stages(bursty: np.ndarray, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    # the issue's link: T far out (the bursts' long tail), S short (the rate there is large
    # but only costs slow-downs)
    s_true, t_true = truth_pair(LOSS, BURST)
    assert (s_true, t_true) == (130, 700)
    rep = report(gaps_from_times(bursty / 1e6, RATE), RATE)
    assert (rep.recommended_slow_ms, rep.recommended_ms) == (s_true, t_true)
    assert rep.two_stage
    assert (t_true - s_true) * 1000 >= 25 * PERIOD_US
    # S is the shortest candidate below the slow target, longer than a send period
    below = [r for r in rep.rows if r.timeout_ms < s_true and r.lost_in_row >= 1]
    assert below and all(r.model >= rep.slow_target for r in below)
    assert rep.row(s_true).model < rep.slow_target

    code, text, err = run_link([write_times(tmp_path / "t.txt", bursty)], capsys)
    assert code == 0 and err == ""
    lines = text.splitlines()
    assert next(x for x in lines if x.split()[:2] == ["130", "ms"]).endswith("<- S")
    assert next(x for x in lines if x.split()[:2] == ["700", "ms"]).endswith("<- T")
    assert "estopd options: --slow-ms 130 --timeout-ms 700" in lines
    assert f"the car rolls {0.130 * KMH15:.2f} m before braking begins" in text
    assert f"({0.700 * KMH15:.2f} m with a single-stage stop at T)" in text
    assert "0.54 m" in text

    code, text, _ = run_link([str(tmp_path / "t.txt"), "--json"], capsys)
    rep_j = json.loads(text)
    assert rep_j["recommended_slow_ms"] == 130 and rep_j["recommended_timeout_ms"] == 700
    assert rep_j["recommended_estopd_options"] == ["--slow-ms", "130", "--timeout-ms", "700"]
    assert rep_j["slow_target_per_hour"] == DEFAULT_SLOW_TARGET
    assert rep_j["target_per_hour"] == DEFAULT_TARGET
    for r in rep_j["rows"]:  # one model, read two ways
        assert r["slowdowns_per_hour"] == r["false_stops_per_hour"]
        assert r["slowdowns_per_hour_95"] == r["false_stops_per_hour_95"]
    assert rep_j["unit"] is None


def test_json_gives_every_pair_and_the_recommended_one(bursty: np.ndarray, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """The two-stage contract of ``--json``: ``pairs`` (every S <= T of the grid with the
    model's slow-downs at S and emergency stops at T; none at S = T, one stage) and
    ``recommendation``, beside today's keys."""
    code, text, _ = run_link([write_times(tmp_path / "t.txt", bursty), "--json"], capsys)
    rep_j = json.loads(text)
    assert code == 0 and rep_j["react_ms"] == DEFAULT_REACT_MS
    assert rep_j["recommendation"] == {"slow_ms": 130, "timeout_ms": 700}
    model = {r["timeout_ms"]: r["false_stops_per_hour"] for r in rep_j["rows"]}
    short = {r["timeout_ms"] for r in rep_j["rows"] if r["lost_in_row"] < 1}
    pairs = {(p["slow_ms"], p["timeout_ms"]): p for p in rep_j["pairs"]}
    assert set(pairs) == {(s, t) for s in TIMEOUTS_MS for t in TIMEOUTS_MS
                          if s <= t and s not in short}
    assert set(pairs[130, 700]) == {"slow_ms", "timeout_ms", "slowdowns_per_hour",
                                    "emergency_stops_per_hour"}
    for (s, t), p in pairs.items():
        assert p["emergency_stops_per_hour"] == model[t]
        assert p["slowdowns_per_hour"] == (model[s] if s < t else 0.0)


@pytest.mark.parametrize("react_ms", [50, 90, 100, 129, 130, 200, 700, 2000])
def test_the_slow_time_never_exceeds_react_ms(bursty: np.ndarray, react_ms: int) -> None:
    rep = report(gaps_from_times(bursty / 1e6, RATE), RATE, react_ms=react_ms)
    assert rep.recommended_ms == 700  # T is the target's alone
    s = rep.recommended_slow_ms
    assert s is not None and s <= react_ms and rep.recommendation == (s, 700)
    # within the reaction: the shortest time below the slow target (130 ms), else the longest
    # one the reaction allows (the fewest slow-downs)
    assert s == (130 if react_ms >= 130 else max(d for d in TIMEOUTS_MS if d <= react_ms))
    assert rep.slow_target_met == (react_ms >= 130)


def test_react_ms_on_the_command_line(bursty: np.ndarray, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    times = write_times(tmp_path / "t.txt", bursty)
    code, text, _ = run_link([times, "--react-ms", "100"], capsys)
    assert code == 0
    assert "slow time: S 100 ms, the longest within --react-ms 100: no slow time up to it " \
           "keeps slow-downs below 1000 per hour" in text
    assert "estopd options: --slow-ms 100 --timeout-ms 700" in text
    code, text, _ = run_link([times, "--react-ms", "10", "--json"], capsys)
    rep_j = json.loads(text)
    assert code == 0 and rep_j["recommendation"] is None and rep_j["recommended_slow_ms"] is None
    assert rep_j["recommended_timeout_ms"] == 700 and rep_j["recommended_estopd_options"] is None
    code, text, _ = run_link([times, "--react-ms", "10"], capsys)
    assert "slow time: none within --react-ms 10 (the shortest time longer than one send " \
           "period is 50 ms): no options for estopd recommended" in text
    code, _, err = run_link([times, "--react-ms", "0"], capsys)
    assert code == 2 and "--react-ms" in err


def test_independent_losses_need_almost_no_second_stage(independent: np.ndarray,
                                                        bursty: np.ndarray) -> None:
    # without bursts the rate falls by 1/loss = 11 per packet: from 1000 slow-downs to 0.01
    # stops per hour takes 5 packets, not the 28 of bursts of 3
    s_true, t_true = truth_pair(LOSS, IID_BURST)
    assert (s_true, t_true) == (70, 150)
    rep = report(gaps_from_times(independent / 1e6, RATE), RATE)
    assert rep.fit.mean_burst == pytest.approx(IID_BURST, rel=0.02)
    assert (rep.recommended_slow_ms, rep.recommended_ms) == (s_true, t_true)
    s, t = rep.recommended_slow_ms, rep.recommended_ms
    assert s is not None and t is not None
    gap_iid = t - s
    b = report(gaps_from_times(bursty / 1e6, RATE), RATE)
    assert b.recommended_ms is not None and b.recommended_slow_ms is not None
    gap_bursty = b.recommended_ms - b.recommended_slow_ms
    assert gap_iid * 1000 <= 5 * PERIOD_US and gap_bursty >= 6 * gap_iid


def test_one_stage_when_no_shorter_time_meets_the_slow_target(
        bursty: np.ndarray, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_times(tmp_path / "t.txt", bursty[:360_000])  # 2 hours
    # slow-downs held to the stop target: only T itself meets it, so S = T where the reaction
    # allows T (here any time of the grid)
    code, text, _ = run_link([path, "--slow-target", "0.01", "--react-ms", "2000"], capsys)
    assert code == 0
    assert "the link needs no two-stage stop" in text
    t_line = next(x for x in text.splitlines() if x.endswith("<- S = T"))
    t_ms = int(t_line.split()[0])
    assert f"estopd options: --timeout-ms {t_ms}" in text.splitlines()
    assert "--slow-ms" not in text
    assert f"the emergency brake starts T = {t_ms} ms after the last packet" in text
    code, text, _ = run_link([path, "--slow-target", "0.01", "--react-ms", "2000", "--json"],
                             capsys)
    rep = json.loads(text)
    assert rep["recommended_slow_ms"] == rep["recommended_timeout_ms"] == t_ms
    assert rep["recommended_estopd_options"] == ["--timeout-ms", str(t_ms)]


def test_slow_time_is_never_above_the_timeout(bursty: np.ndarray) -> None:
    gaps = gaps_from_times(bursty[:360_000] / 1e6, RATE)
    for slow_target in (1e-9, 1e-3, 0.01, 1.0, 100.0, 1e4, 1e9):
        rep = report(gaps, RATE, slow_target=slow_target, react_ms=2000)
        assert rep.recommended_ms is not None and rep.recommended_slow_ms is not None
        assert rep.recommended_slow_ms <= rep.recommended_ms
        if rep.recommended_slow_ms < rep.recommended_ms:
            assert rep.row(rep.recommended_slow_ms).meets(slow_target)
        # with the default reaction, S is within it whatever the slow target
        s = report(gaps, RATE, slow_target=slow_target).recommended_slow_ms
        assert s is not None and s <= DEFAULT_REACT_MS
    # a laxer slow target never lengthens S
    s = [report(gaps, RATE, slow_target=x).recommended_slow_ms for x in (10.0, 300.0, 3000.0)]
    assert s == sorted(s, reverse=True) and s[0] != s[-1]  # type: ignore[type-var]


def test_slow_time_is_longer_than_one_send_period(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    # at 10 Hz every time up to 100 ms is a deadline at or before the next packet: the unit
    # would slow at every packet, whatever the slow target allows
    lost = gilbert_lost(40_000, 0.05, 2.0, 33)
    path = tmp_path / "slow.txt"
    path.write_text("\n".join(f"{x:.6f}" for x in np.flatnonzero(~lost) / 10.0) + "\n")
    code, text, _ = run_link([str(path), "--json", "--rate-hz", "10", "--slow-target", "1e9"],
                            capsys)
    rep = json.loads(text)
    assert code == 0 and rep["recommended_slow_ms"] == 110
    assert next(r for r in rep["rows"] if r["timeout_ms"] == 100)["lost_in_row"] == 0


def test_no_timeout_meets_the_target(bursty: np.ndarray, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    path = write_times(tmp_path / "t.txt", bursty[:360_000])
    code, text, _ = run_link([path, "--target", "1e-40"], capsys)
    assert code == 0 and "no timeout up to 2000 ms" in text
    assert "slow time: S 130 ms" in text  # S still told: the table holds it
    assert "no options for estopd recommended" in text and "estopd options:" not in text
    code, text, _ = run_link([path, "--target", "1e-40", "--json"], capsys)
    rep = json.loads(text)
    assert rep["recommended_timeout_ms"] is None and rep["recommended_slow_ms"] == 130
    assert rep["recommended_estopd_options"] is None


def test_no_loss_recommends_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "clean.txt"
    path.write_text("\n".join(f"{i / 50:.6f}" for i in range(5000)) + "\n")
    code, text, _ = run_link([str(path), "--json"], capsys)
    rep = json.loads(text)
    assert code == 0 and rep["recommended_slow_ms"] is None
    assert rep["recommended_estopd_options"] is None
    code, text, _ = run_link([str(path)], capsys)
    assert "slow time:" not in text and "estopd options" not in text


# --------------------------------------------------------------------------- read as S


@pytest.mark.parametrize("slow_ms, timeout_ms", [(100, 700), (130, 700), (200, 1000)])
def test_slowdowns_of_the_units_rules_follow_the_model_at_s(bursty: np.ndarray, slow_ms: int,
                                                           timeout_ms: int) -> None:
    # The unit's slow-downs are the silences reaching S less those that begin while it is
    # still SLOWING (within 2 packets of the last one): the model's rate at S counts every
    # silence, so it is at most a few per cent high, never low. Measured on this trace:
    # 100 ms 1.8 %, 130 ms 0.6 %, 200 ms 0.1 % more silences than slow-downs.
    unit = simulate_unit(bursty, slow_ms * 1000, timeout_ms * 1000)
    gaps = np.diff(bursty)
    silences = int((gaps >= slow_ms * 1000).sum())
    assert silences * 0.97 <= len(unit.slowdowns_us) <= silences
    hours = unit.moving_us / 3.6e9
    f = fit(gaps_from_times(bursty / 1e6, RATE), RATE)
    n = lost_in_row(slow_ms, RATE)
    lo, hi = f.interval95(n)
    per_h = len(unit.slowdowns_us) / hours
    assert per_h == pytest.approx(f.false_stops(n), rel=0.04)
    assert poisson_lower95(len(unit.slowdowns_us)) / hours <= hi
    assert lo * 0.96 <= poisson_upper95(len(unit.slowdowns_us)) / hours
    assert len(unit.timeouts_us) == int((gaps >= timeout_ms * 1000).sum())  # all while moving


# --------------------------------------------------------------------------- the unit's counts


def two_runs(t_us: np.ndarray, slow_us: int, timeout_us: int,
             release_second: bool = True) -> list[tuple[np.ndarray, UnitRun]]:
    half = t_us.size // 2
    return [(t_us[:half], simulate_unit(t_us[:half], slow_us, timeout_us)),
            (t_us[half:], simulate_unit(t_us[half:], slow_us, timeout_us,
                                        release=release_second))]


def test_unit_counts_are_read_from_a_v3_daemon_log(bursty: np.ndarray, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    runs = two_runs(bursty[:720_000], 200_000, 1_000_000)  # 4.4 hours
    log = tmp_path / "estopd.jsonl"
    log.write_text(unit_log(runs))
    h = read_histogram_log(str(log))
    u = h.unit
    assert h.runs == 2 and u is not None and h.unit_note == ""
    assert u.slowdowns == sum(len(r.slowdowns_us) for _, r in runs)
    assert u.timeouts == sum(len(r.timeouts_us) for _, r in runs)
    assert (u.slow_us, u.timeout_us) == (200_000, 1_000_000) and u.slowdowns > 500
    moving_s = sum(r.moving_us for _, r in runs) / 1e6
    assert u.moving_s == pytest.approx(moving_s, abs=1e-3)

    code, text, err = run_link([str(log), "--json"], capsys)
    assert code == 0 and err == ""
    rep = json.loads(text)
    unit = rep["unit"]
    assert unit["slowdowns"] == u.slowdowns and unit["timeouts"] == u.timeouts
    assert (unit["slow_ms"], unit["timeout_ms"]) == (200, 1000)
    assert unit["hours_from"] == "state events"
    assert unit["hours"] == pytest.approx(moving_s / 3600)
    assert rep["input"]["slowdowns"] == u.slowdowns and rep["input"]["slow_us"] == 200_000
    s, t = unit["slowdowns_check"], unit["timeouts_check"]
    assert s["verdict"] == t["verdict"] == "agrees"
    assert s["recorded"] == u.slowdowns and s["lost_in_row"] == 9
    assert s["model_per_hour"] == next(r["slowdowns_per_hour"] for r in rep["rows"]
                                       if r["timeout_ms"] == 200)
    assert s["per_hour"] == pytest.approx(u.slowdowns / (moving_s / 3600))
    assert t["model_per_hour"] < 1e-3 and t["recorded"] == 0

    code, text, _ = run_link([str(log)], capsys)
    assert "unit: slow time S 200 ms, timeout T 1000 ms" in text
    block = text[text.index("the unit's own counts"):].splitlines()
    assert "per hour moving (ARMED or SLOWING" in block[0]
    assert block[1].lstrip().startswith(f"slow-downs    {u.slowdowns:6d}:".lstrip())
    assert block[1].endswith("agrees") and block[2].endswith("agrees")
    assert "model at 200 ms" in block[1] and "model at 1000 ms" in block[2]


def test_time_stopped_does_not_count_against_the_model(bursty: np.ndarray, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    # the second run never leaves STOPPED: the unit counts nothing there. Per hour moving the
    # counts agree with the model; a log cut so that the runs' starts are missing cannot tell
    # the time moving, and per hour recorded they look too few (and the report says why)
    runs = two_runs(bursty[:720_000], 150_000, 300_000, release_second=False)
    assert not runs[1][1].states
    log = tmp_path / "estopd.jsonl"
    log.write_text(unit_log(runs))
    code, text, _ = run_link([str(log), "--json"], capsys)
    unit = json.loads(text)["unit"]
    assert unit["hours"] == pytest.approx(runs[0][1].moving_us / 3.6e9)  # the first run only
    assert unit["hours"] == pytest.approx((runs[0][0][-1] - runs[0][0][0]) / 3.6e9, rel=0.01)
    assert unit["slowdowns_check"]["verdict"] == "agrees"
    assert unit["timeouts_check"]["verdict"] == "agrees"
    assert unit["timeouts"] > 20  # 300 ms: 27 per hour

    cut = tmp_path / "cut.jsonl"
    cut.write_text(unit_log(runs, start=False))
    code, text, _ = run_link([str(cut), "--json"], capsys)
    unit = json.loads(text)["unit"]
    assert code == 0 and unit["hours_from"] == "recording"
    span = sum(int(t[-1] - t[0]) for t, _ in runs) / 3.6e9
    assert unit["hours"] == pytest.approx(span, rel=0.01)
    assert unit["slowdowns_check"]["verdict"] == "fewer_than_model"
    code, text, _ = run_link([str(cut)], capsys)
    assert "the time the unit moved is unknown" in text
    assert "a unit STOPPED part of the recording counts none there" in text


def test_unit_that_never_moved(bursty: np.ndarray, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    t = bursty[:90_000]
    log = tmp_path / "estopd.jsonl"
    log.write_text(unit_log([(t, simulate_unit(t, 200_000, 1_000_000, release=False))]))
    code, text, _ = run_link([str(log), "--json"], capsys)
    unit = json.loads(text)["unit"]
    assert code == 0 and unit["hours"] == 0
    assert unit["slowdowns_check"]["verdict"] == "never_moving"
    assert unit["slowdowns_check"]["per_hour"] is None
    code, text, _ = run_link([str(log)], capsys)
    assert "the unit never moved" in text


def test_unit_counts_the_model_cannot_explain_are_flagged(bursty: np.ndarray, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    runs = two_runs(bursty[:720_000], 200_000, 1_000_000)
    lines = []
    for line in unit_log(runs).splitlines():
        ev = json.loads(line)
        if ev["event"] == "link_histogram":  # a unit that slowed twice as often as its gaps
            ev["slowdowns"] *= 2
        lines.append(json.dumps(ev))
    log = tmp_path / "estopd.jsonl"
    log.write_text("\n".join(lines) + "\n")
    code, text, _ = run_link([str(log), "--json"], capsys)
    unit = json.loads(text)["unit"]
    assert unit["slowdowns_check"]["verdict"] == "more_than_model"
    assert unit["timeouts_check"]["verdict"] == "agrees"
    code, text, _ = run_link([str(log)], capsys)
    assert "! more than the model allows: trust the unit's count" in text


def test_unit_at_s_equal_t_has_no_slowdown_check(bursty: np.ndarray, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    t = bursty[:360_000]
    log = tmp_path / "estopd.jsonl"
    log.write_text(unit_log([(t, simulate_unit(t, 200_000, 200_000))]))
    code, text, _ = run_link([str(log), "--json"], capsys)
    unit = json.loads(text)["unit"]
    assert unit["slowdowns"] == 0 and unit["slowdowns_check"] is None
    assert unit["timeouts"] > 300 and unit["timeouts_check"]["verdict"] == "agrees"
    code, text, _ = run_link([str(log)], capsys)
    assert "slow-downs: none possible, the unit ran with S = T" in text


# --------------------------------------------------------------------------- compatibility


def test_older_daemon_logs_have_no_unit_row(bursty: np.ndarray, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    t = bursty[:360_000]
    for name, text in (("v2.jsonl", histogram_log([t[:180_000], t[180_000:]])),
                       ("v2-states.jsonl", unit_log([(t, simulate_unit(t, 200_000, 200_000))],
                                                    unit_keys=False))):
        log = tmp_path / name
        log.write_text(text)
        h = read_histogram_log(str(log))
        assert h.unit is None and h.unit_note == ""
        code, out, err = run_link([str(log), "--json"], capsys)
        rep = json.loads(out)
        assert code == 0 and err == "" and rep["unit"] is None
        assert "slowdowns" not in rep["input"] and rep["notes"] == []
        assert rep["recommended_slow_ms"] is not None
        code, out, err = run_link([str(log)], capsys)
        assert code == 0 and err == ""
        assert "own counts" not in out and "unit:" not in out


def test_runs_that_cannot_be_added_up_leave_a_note(bursty: np.ndarray, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    a, b = bursty[:90_000], bursty[90_000:180_000]
    new = unit_log([(a, simulate_unit(a, 200_000, 1_000_000))])
    old = unit_log([(b, simulate_unit(b, 200_000, 1_000_000))], unit_keys=False)
    other = unit_log([(b, simulate_unit(b, 150_000, 1_000_000))])
    for text, says in ((new + old, "1 of 2 run(s) lack the unit's own counts"),
                       (new + other, "the runs used different slow times or timeouts "
                                     "(S 150 ms T 1000 ms, S 200 ms T 1000 ms)")):
        log = tmp_path / "mixed.jsonl"
        log.write_text(text)
        code, out, err = run_link([str(log), "--json"], capsys)
        rep = json.loads(out)
        assert code == 0 and err == "" and rep["unit"] is None
        assert any(says in n for n in rep["notes"]), rep["notes"]


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("key, value, message", [
    ("slowdowns", -1, "'slowdowns' is not a count"),
    ("timeouts", 1.5, "'timeouts' is not a count"),
    ("slow_us", "200", "'slow_us' is not a count"),
    ("slow_us", 0, "break 0 < S <= T"),
    ("slow_us", 2_000_000, "break 0 < S <= T"),
])
def test_bad_unit_keys_are_one_line_exit_4(bursty: np.ndarray, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str], key: str,
                                           value: object, message: str) -> None:
    t = bursty[:3000]
    lines = []
    for line in unit_log([(t, simulate_unit(t, 200_000, 1_000_000))]).splitlines():
        ev = json.loads(line)
        if ev["event"] == "link_histogram":
            ev[key] = value
        lines.append(json.dumps(ev))
    log = tmp_path / "bad.jsonl"
    log.write_text("\n".join(lines) + "\n")
    code, out, err = run_link([str(log)], capsys)
    assert code == 4 and out == "" and err.count("\n") == 1  # a file not understood
    assert err.startswith("estop: error: ") and message in err, err


@pytest.mark.parametrize("value", ["0", "-5", "-0.01", "nan", "inf", "lots"])
def test_bad_slow_target_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            value: str) -> None:
    ok = tmp_path / "t.txt"
    ok.write_text("0\n0.02\n0.06\n")
    code, out, err = run_link([str(ok), f"--slow-target={value}"], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("estop: error: ") and "--slow-target" in err, err


def test_cli_defaults_are_the_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the command cannot import the analysis (numpy) to parse its options: same numbers
    lost = gilbert_lost(50_000, 0.09, 3.0, 3)
    path = write_times(tmp_path / "t.txt", arrivals_us(lost))
    code, out, _ = run_link([path, "--json"], capsys)
    rep = json.loads(out)
    assert rep["target_per_hour"] == DEFAULT_TARGET
    assert rep["slow_target_per_hour"] == DEFAULT_SLOW_TARGET
    assert cli.main(["link", "--help"]) == 0
    assert "--slow-target" in capsys.readouterr().out


def test_dropped_log_lines_are_noted(bursty: np.ndarray, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    # a daemon whose log reader was slow drops lines: state events may be among them
    t = bursty[:90_000]
    text = unit_log([(t, simulate_unit(t, 200_000, 1_000_000))])
    lines = text.splitlines()
    lines.insert(len(lines) // 2, json.dumps({"t_mono": 5000.0, "event": "output_dropped",
                                              "stream": "log", "dropped": 3, "total": 3,
                                              "err": "full"}))
    log = tmp_path / "estopd.jsonl"
    log.write_text("\n".join(lines) + "\n")
    code, out, _ = run_link([str(log), "--json"], capsys)
    unit = json.loads(out)["unit"]
    assert code == 0 and unit["hours_from"] == "state events"
    assert any("dropped log lines" in n for n in unit["notes"])
    code, out, _ = run_link([str(log)], capsys)
    assert "note: the daemon dropped log lines" in out
