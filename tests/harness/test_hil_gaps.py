"""Gaps of 50 ms in the periodic ESTOP_BRAKE frames, judged beside the CPU stalls
(hilstalls.judge_gaps), and the boot row's verdict on a real TCG run (rows_basic)."""

from __future__ import annotations

import json
from pathlib import Path

import hilstalls
import rows_basic
from hilemu import BRAKE_SILENCE_S, Frame
from hiljudge import apply_gaps
from hilrun import Result


def _grid(t0: float, n: int, period: float = 0.010) -> list[float]:
    return [t0 + i * period for i in range(n)]


def test_a_gap_without_a_stall_fails_and_decides() -> None:
    ts = _grid(10.0, 20) + _grid(10.0 + 19 * 0.010 + 0.060, 20)
    v = hilstalls.judge_gaps(ts, [], BRAKE_SILENCE_S)
    assert len(v.fails) == 1 and "60.0 ms" in v.fails[0] and "not judged" not in v.fails[0]
    assert v.inconclusive is None


def test_a_gap_the_stalls_explain_is_not_judged_and_never_a_pass() -> None:
    ts = _grid(10.0, 20) + _grid(10.0 + 19 * 0.010 + 0.060, 20)
    gap_at = 10.0 + 19 * 0.010
    v = hilstalls.judge_gaps(ts, [(gap_at + 0.005, gap_at + 0.050)], BRAKE_SILENCE_S)
    assert len(v.fails) == 1 and "not judged" in v.fails[0]
    assert v.inconclusive is not None and "45.0 ms" in v.inconclusive


def test_a_gap_the_stalls_explain_does_not_hide_one_they_do_not() -> None:
    # one gap explained, one not: a failure that no run more would change (no retry)
    ts = _grid(10.0, 10) + _grid(10.2, 10) + _grid(10.4, 10)
    v = hilstalls.judge_gaps(ts, [(10.10, 10.19)], BRAKE_SILENCE_S)
    assert len(v.fails) == 2
    assert v.inconclusive is None


def test_short_gaps_and_too_short_a_stall_are_judged_as_they_are() -> None:
    assert hilstalls.judge_gaps(_grid(10.0, 100), [], BRAKE_SILENCE_S).fails == []
    assert hilstalls.judge_gaps([], [], BRAKE_SILENCE_S).fails == []
    # a 70-ms gap with a 20-ms stall: the daemon had 50 ms to send (more than 25): judged
    ts = [10.0, 10.07, 10.08]
    v = hilstalls.judge_gaps(ts, [(10.01, 10.03)], BRAKE_SILENCE_S)
    assert len(v.fails) == 1 and v.inconclusive is None


def _boot_run(name: str) -> tuple[list[Frame], list[tuple[float, float]]]:
    data = json.loads((Path(__file__).parent / "data" / name).read_text())
    frames = [Frame(t / 1e6, can_id, bytes.fromhex(hexdata))
              for t, can_id, hexdata in data["frames"]]
    return frames, [(a / 1e6, b / 1e6) for a, b in data["stalls_us"]]


def test_the_boot_row_runs_again_when_vcpu_stalls_made_the_gaps() -> None:
    # The boot row of a fresh-machine run of a87f13b: ESTOP_BRAKE gaps of 65.8 and 54.0 ms,
    # each inside vCPU stalls (the union over both vCPUs) of as long, the grid 10.014 ms.
    # It failed outright; now the row is inconclusive (it boots the daemon once more, and
    # the second boot decides), and still not a pass.
    frames, stalls = _boot_run("hil_boot_tcg_gaps_a87f13b.json")
    res = Result("boot", "Boot", "")
    rows_basic.judge_boot_frames(res, frames, stalls, 1.0)
    fails = [n for n in res.notes if n.startswith("FAIL")]
    assert len(fails) == 2 and all("not judged" in n for n in fails), res.notes
    assert res.inconclusive is not None and "ESTOP_BRAKE gap" in res.inconclusive
    assert res.figures["brake_grid_period"] == {"gaps": 71, "ms": 10.014}


def test_the_boot_row_fails_a_gap_no_stall_explains() -> None:
    frames, stalls = _boot_run("hil_boot_tcg_gaps_a87f13b.json")
    res = Result("boot", "Boot", "")
    rows_basic.judge_boot_frames(res, frames, [], 1.0)  # the same frames, no stall seen
    assert res.inconclusive is None
    assert sum(1 for n in res.notes if n.startswith("FAIL: ESTOP_BRAKE gap")) == 2
    # the rest of the verdict is the same: the grid judged, the frames good
    assert res.figures["brake_grid_period"] == {"gaps": 71, "ms": 10.014}
    assert len([n for n in res.notes if n.startswith("FAIL")]) == 2, res.notes


def test_apply_gaps_records_every_failure_and_the_reason_to_run_again() -> None:
    res = Result("x", "X", "")
    apply_gaps(res, hilstalls.Verdict(["a", "b"], "why"))
    assert res.notes == ["FAIL: a", "FAIL: b"] and res.inconclusive == "why"
    keep = Result("x", "X", "")
    keep.inconclusive = "earlier"
    apply_gaps(keep, hilstalls.Verdict([], None))
    assert keep.inconclusive == "earlier" and keep.notes == []
