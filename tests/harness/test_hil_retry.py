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
    assert res.notes[0].startswith("second try; the first was inconclusive")


def test_a_judged_failure_beside_an_unjudged_one_is_not_washed_out(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # before 2026-12-02 the row ran again, and a passing second try alone decided
    res, calls = _run_rows(monkeypatch, [_judged_and_unjudged, _passes])
    assert calls == 1 and not res.passed
    assert "FAIL: release -> ARMED frame 40 ms > 25 ms" in res.notes


def test_twice_unjudged_is_a_failure(monkeypatch: pytest.MonkeyPatch) -> None:
    res, calls = _run_rows(monkeypatch, [_unjudged, _unjudged])
    assert calls == 2 and not res.passed
    assert any("inconclusive twice" in n for n in res.notes)
