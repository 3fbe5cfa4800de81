"""The HIL harness's roll-outs (hil/hilroll.py): the model's figures, from a lift, from the last
packet (two stages, dead man), disagreements, the speed after a burst."""

from __future__ import annotations

import pytest
from hil_util import bus_frames

import hilcheck

# --------------------------------------------------------------------------- distances (v3)

def test_model_figures() -> None:
    import hilroll

    v = hilroll.speed()
    assert v == pytest.approx(15 / 3.6)
    assert hilroll.single_stage_distance(0.0) == pytest.approx(v * v / 16)  # 1.085 m
    assert hilroll.single_stage_distance(0.2) == pytest.approx(0.2 * v + v * v / 16)  # 1.918
    assert hilroll.single_stage_distance(0.2) - hilroll.single_stage_distance(0.0) == \
        pytest.approx(0.833, abs=1e-3)
    # two-stage, S = 150 ms, T = 600 ms, L = 30 %: 0.625 m at speed, 450 ms at 2.4 m/s^2,
    # then a full brake from what is left
    v1 = v - 0.45 * 2.4
    want = 0.15 * v + 0.45 * (v + v1) / 2 + v1 * v1 / 16
    assert hilroll.two_stage_distance(0.15, 0.6, 30) == pytest.approx(want)
    assert hilroll.two_stage_distance(0.15, 0.6, 30) < hilroll.single_stage_distance(0.6)
    # S = T: one stage
    assert hilroll.two_stage_distance(0.2, 0.2, 30) == pytest.approx(
        hilroll.single_stage_distance(0.2))


def test_roll_from_a_lift() -> None:
    import hilroll

    # ARMED until the lift at +1.000 s; the stop frame 4 ms later; STOPPED lift from then on
    frames = bus_frames([(0.0, 1.004, "ARMED", 0), (1.004, 1.5, "STOPPED", 5)])
    r = hilroll.roll(frames, 1001.0)
    v = hilroll.speed()
    assert r.agree, r.disagreement()
    assert r.bus.distance == pytest.approx(0.004 * v + v * v / 16, abs=1e-6)
    fig = r.figures()
    assert fig["braking_after_ms"] == pytest.approx(4.0, abs=1e-3)
    assert fig["distance_m"] == pytest.approx(1.102, abs=1e-3)
    assert fig["rolled_before_braking_m"] == pytest.approx(0.017, abs=1e-3)


def test_roll_from_the_last_packet_two_stage_and_dead_man() -> None:
    import hilroll

    # two-stage: last packet at +1.0, SLOWING at +1.152 (S = 150 ms, 2 ms late), STOPPED at
    # +1.601 (T = 600 ms)
    frames = bus_frames([(0.0, 1.152, "ARMED", 0), (1.152, 1.601, "SLOWING", 0),
                   (1.601, 2.5, "STOPPED", 3)])
    r = hilroll.roll(frames, 1001.0)
    assert r.agree, r.disagreement()
    model = hilroll.two_stage_distance(0.152, 0.601, 30)
    assert r.bus.distance == pytest.approx(model, abs=1e-6)
    assert r.figures()["braking_after_ms"] == pytest.approx(152.0, abs=1e-3)
    # single stage at T = 200 ms
    dm = hilroll.roll(bus_frames([(0.0, 1.2005, "ARMED", 0), (1.2005, 2.0, "STOPPED", 3)]), 1001.0)
    assert dm.agree and dm.bus.distance == pytest.approx(
        hilroll.single_stage_distance(0.2005), abs=1e-6)


def test_roll_disagreement_is_reported() -> None:
    import hilroll

    frames = bus_frames([(0.0, 1.0, "ARMED", 0), (1.0, 1.2, "STOPPED", 5)])
    r = hilroll.roll(frames, 1000.5)
    bad = hilroll.Roll(r.moment, r.bus, hilroll.EmulatorRoll(r.bus.distance + 0.01, None, 1.0))
    assert r.agree and not bad.agree
    assert "estop.model.rollout" in bad.disagreement()
    never = hilroll.Roll(r.moment, r.bus, hilroll.EmulatorRoll(r.bus.distance, None, None))
    assert not never.agree and "never stops" in never.disagreement()


def test_speed_after_a_burst() -> None:
    import hilroll

    ch = [hilcheck.BrakeChange(0.0, 0.0, "frame"), hilcheck.BrakeChange(10.15, 0.3, "frame"),
          hilcheck.BrakeChange(10.27, 0.0, "frame")]
    v = hilroll.speed()
    assert hilroll.speed_after(ch, 10.0, 11.0) == pytest.approx(v - 0.12 * 2.4)
    assert hilroll.speed_after(ch, 10.0, 10.2) == pytest.approx(v - 0.05 * 2.4)
