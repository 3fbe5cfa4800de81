"""The dead-man across the touch page's hop (estop.remote.touch.hold), on made-up times."""

from __future__ import annotations

import pytest

from estop.remote.touch.hold import DRIFT, STALE_PERIODS, DeadMan, Verdict

P = 0.020  # the control period


def stream(dm: DeadMan, conn: int, t0: float, n: int, *, delay: float = 0.001,
           page0: float = 100.0) -> list[Verdict]:
    """n frames one period apart from ``t0``, each ``delay`` on its way."""
    return [dm.frame(conn, (page0 + t0 + i * P) * 1000, t0 + i * P + delay) for i in range(n)]


def test_a_steady_hold_sends_one_packet_per_frame() -> None:
    dm = DeadMan(P)
    assert stream(dm, 1, 10.0, 50) == [Verdict.SEND] * 50
    assert dm.holder == 1 and dm.stats.missed == 0 and dm.stats.late == 0


def test_jitter_costs_no_packet_and_a_gap_counts_as_missed() -> None:
    dm = DeadMan(P)
    verdicts = [dm.frame(1, (100 + i * P) * 1000, i * P + (0.015 if i % 2 else 0.001))
                for i in range(20)]
    assert verdicts == [Verdict.SEND] * 20  # 15 ms of jitter, one frame 6 ms after another
    dm.frame(1, (100 + 25 * P) * 1000, 25 * P + 0.001)  # frames 20..24 never came
    assert dm.stats.missed == 5


def test_a_backlog_is_stale_and_never_a_burst() -> None:
    dm = DeadMan(P)
    stream(dm, 1, 0.0, 10)
    assert dm.stalled(1.0)  # the network stalls: no fresh frame for two periods, said once
    assert not dm.stalled(1.1)
    # the 50 frames sent meanwhile arrive together at t = 1.2
    verdicts = [dm.frame(1, (100 + 0.2 + i * P) * 1000, 1.2 + i * 1e-5) for i in range(50)]
    assert verdicts.count(Verdict.SEND) <= 2
    assert all(v is Verdict.STALE for v in verdicts[:45])


def test_a_page_sending_too_fast_does_not_raise_the_rate() -> None:
    dm = DeadMan(P)
    verdicts = [dm.frame(1, (100 + i * 0.001) * 1000, i * 0.001 + 0.001) for i in range(100)]
    assert verdicts.count(Verdict.SEND) <= 100 * 0.001 / (P / 2) + 1


def test_one_page_holds_at_a_time() -> None:
    dm = DeadMan(P)
    assert stream(dm, 1, 0.0, 3) == [Verdict.SEND] * 3
    assert dm.frame(2, 7_070.0, 0.07) is Verdict.OTHER
    assert not dm.end(2)  # another page's finger leaving lifts nothing
    assert dm.holder == 1
    assert dm.end(1) and dm.holder is None
    assert not dm.end(1)  # once
    assert stream(dm, 2, 1.0, 2, page0=7.0) == [Verdict.SEND] * 2
    assert dm.holder == 2 and dm.stats.holds == 2


def test_a_lasting_change_of_delay_rebaselines_within_seconds() -> None:
    dm = DeadMan(P)
    stream(dm, 1, 0.0, 50)
    step = 0.100  # the route changes: every frame 100 ms later from now on
    verdicts = [dm.frame(1, (100 + 1.0 + i * P) * 1000, 1.0 + i * P + step)
                for i in range(int(10 / P))]
    first_fresh = verdicts.index(Verdict.SEND) * P
    assert verdicts[0] is Verdict.STALE
    assert first_fresh <= (step - STALE_PERIODS * P) / DRIFT + 0.1
    assert all(v is Verdict.SEND for v in verdicts[int((first_fresh + 0.1) / P):])


def test_a_stall_is_said_once_and_ends_with_a_fresh_frame() -> None:
    dm = DeadMan(P)
    stream(dm, 1, 0.0, 5)
    last = 4 * P + 0.001
    assert not dm.stalled(last + STALE_PERIODS * P - 0.001)
    assert dm.stalled(last + STALE_PERIODS * P + 0.001) and dm.is_stalled
    assert not dm.stalled(last + 1.0)
    assert dm.frame(1, (100 + 1.0) * 1000, 1.0 + 0.001) is Verdict.SEND
    assert not dm.is_stalled and dm.stats.stalls == 1
    with pytest.raises(ValueError):
        DeadMan(0.0)
