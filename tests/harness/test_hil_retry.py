"""When the HIL runner gives a row a second try (hilrun.Result.worth_another_try,
scenarios.run_all): only when nothing failed that the environment cannot explain."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

import scenarios
from hilrun import Limits, Result


def _res(*notes: str, inconclusive: str | None = "why", spoiled: bool = False) -> Result:
    r = Result("release", "t", "c", notes=list(notes), inconclusive=inconclusive)
    r.spoiled = spoiled
    return r


def test_only_unjudged_failures_are_worth_another_try() -> None:
    assert _res("FAIL: x: 30 ms > 25 ms (not judged: a CPU stood still 12 ms of it)",
                "FAIL: y: median not judged (...)").worth_another_try()
    # a failure the stalls do not explain decides, whatever else was inconclusive
    assert not _res("FAIL: y: median not judged (...)",
                    "FAIL: x: 30 ms > 25 ms").worth_another_try()
    # the harness itself spoiled the try (its keepalive paused): every failure may be its own
    assert _res("FAIL: y: median not judged (...)", "FAIL: stopped 40 ms early",
                spoiled=True).worth_another_try()
    assert not _res("FAIL: x", inconclusive=None).worth_another_try()
    passed = _res()
    passed.passed = True
    assert not passed.worth_another_try()


class _Run:
    """What scenarios.run_all and run_one use of a Run, without a bus or a daemon."""

    def __init__(self) -> None:
        self.lim = Limits.for_profile("tcg")
        self.results: list[Result] = []
        self.monitor = None
        self.remote = None
        self.windows: list[Any] = []
        self.want_key = False
        self.want_opts: dict[str, Any] = {}

    def ensure_daemon(self) -> None:
        pass


def _run_rows(monkeypatch: pytest.MonkeyPatch,
              tries: list[Callable[[Result], None]]) -> tuple[Result, int]:
    calls = 0

    def row(run: Any, res: Result) -> None:
        nonlocal calls
        tries[calls](res)
        calls += 1

    monkeypatch.setattr(scenarios, "SCENARIOS", [("release", "Release", "crit", row)])
    run = _Run()
    scenarios.run_all(run, None, 600.0)  # type: ignore[arg-type]
    return run.results[0], calls


def _unjudged(res: Result) -> None:
    res.inconclusive = "a CPU stood still"
    res.check(False, "release -> ARMED frame: max not judged (29 ms during a stall)")


def _judged_and_unjudged(res: Result) -> None:
    _unjudged(res)
    res.check(False, "release -> ARMED frame 40 ms > 25 ms")


def _passes(res: Result) -> None:
    res.check(True, "fine")


def test_an_unjudged_try_runs_again_and_the_second_decides(
        monkeypatch: pytest.MonkeyPatch) -> None:
    res, calls = _run_rows(monkeypatch, [_unjudged, _passes])
    assert calls == 2 and res.passed
    assert res.notes[0].startswith("try 2; try 1 was inconclusive")


def test_a_judged_failure_beside_an_unjudged_one_is_not_washed_out(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # before 2026-12-02 the row ran again, and a passing second try alone decided
    res, calls = _run_rows(monkeypatch, [_judged_and_unjudged, _passes])
    assert calls == 1 and not res.passed
    assert "FAIL: release -> ARMED frame 40 ms > 25 ms" in res.notes


def test_unjudged_in_every_try_is_a_failure(monkeypatch: pytest.MonkeyPatch) -> None:
    res, calls = _run_rows(monkeypatch, [_unjudged] * scenarios.TRIES)
    assert calls == scenarios.TRIES == 3 and not res.passed
    assert any("inconclusive 3 times" in n for n in res.notes)


class _JudgeRun:
    """What hiljudge.judge uses of a Run: the limits and the stalls."""

    def __init__(self, stalls: list[tuple[float, float]]) -> None:
        self.lim = Limits.for_profile("tcg")  # p50 5, max 25 ms
        self._stalls = stalls

    def stalls(self) -> list[tuple[float, float]]:
        return self._stalls


def _samples(lat_ms: list[float], stalled: list[bool], t0: float) -> tuple[
        list[tuple[float, float]], list[tuple[float, float]]]:
    """(reference, frame) pairs one second apart from ``t0`` and the stalls that cover the
    ``stalled`` ones."""
    pairs = [(t0 + i, t0 + i + ms / 1000) for i, ms in enumerate(lat_ms)]
    stalls = [(a, b) for (a, b), st in zip(pairs, stalled, strict=True) if st]
    return pairs, stalls


def test_the_samples_of_earlier_tries_count_with_the_last() -> None:
    """A loaded TCG guest stalled most samples of each try; together they decide. A median
    that neither try could judge alone (two clean samples each) fails when pooled."""
    import hiljudge

    def one_try(lat: list[float], stalled: list[bool], earlier: Result | None) -> Result:
        pairs, stalls = _samples(lat, stalled, 1000.0 if earlier is None else 2000.0)
        res = Result("tcp_stop", "t", "c", earlier=earlier.pool if earlier else {})
        hiljudge.judge(_JudgeRun(stalls), res, "lat_ms", "lat", pairs)  # type: ignore[arg-type]
        return res

    # 8 stalled (one of them 40 ms, over the max) and 4 clean: too few to judge the max
    first = one_try([40.0, *[6.0] * 7, 2.0, 2.0, 2.0, 2.0], [True] * 8 + [False] * 4, None)
    assert first.inconclusive and "only 4 of 12 samples without one" in first.inconclusive
    second = one_try([3.0] * 3 + [9.0] * 9, [False] * 3 + [True] * 9, first)
    assert second.inconclusive is None and not any(n.startswith("FAIL") for n in second.notes)
    assert second.figures["lat_ms_judged_with_earlier_tries"] == 24
    # the median: two clean samples a try, each 8 ms (a daemon on its 10 ms tick)
    slow = one_try([8.0, 8.0, 9.0, 9.0, 9.0], [False, False, True, True, True], None)
    assert slow.inconclusive and "only 2 samples without one" in slow.inconclusive
    slow2 = one_try([8.0, 8.0, 9.0, 9.0, 9.0], [False, False, True, True, True], slow)
    assert any("median > 5.0 ms" in n for n in slow2.notes)
    alone = one_try([8.0, 8.0, 9.0, 9.0, 9.0], [False, False, True, True, True], None)
    assert not any("median > 5.0 ms" in n for n in alone.notes)  # what pooling adds
