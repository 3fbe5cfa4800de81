"""The HIL harness's test protocol (hil/hilreport.py) and its command line (hil/run, hilrun),
the scenarios' criteria and what the protocol shows of the roll-outs."""

from __future__ import annotations

import json
import subprocess
from dataclasses import asdict
from pathlib import Path

import hilreport
from hilcheck import summary
from repo import ROOT


def _doc(passed: bool) -> dict:
    return {
        "meta": {"date": "2024-01-01 00:00:00 UTC", "mode": "vm-tcg", "dut": "estopd",
                 "timing_profile": {"profile": "tcg", "p50": 5.0, "max": 25.0, "emu": 200.0}},
        "fatal": None,
        "passed": passed,
        "results": [
            {"id": "deadman", "title": "Dead-man | timeout", "criterion": "p50 <= 5",
             "passed": passed, "figures": {"overshoot_ms": summary([0.5, 1.0, 1.5])},
             "samples_ms": {"dead-man overshoot": [0.5, 1.0, 1.5]}, "notes": []},
        ],
    }


def test_protocol_table() -> None:
    text = hilreport.protocol_md(_doc(True), {"VM boot": "20 s"})
    assert "| 1 | Dead-man \\| timeout | p50 <= 5 | PASS |" in text
    assert "n=3 min 0.5 / p50 1 / max 1.5" in text
    assert "Verdict: **PASSED** (1/1" in text and "VM boot: 20 s" in text
    assert "**FAIL**" in hilreport.protocol_md(_doc(False))


def test_report_main(tmp_path: Path) -> None:
    assert hilreport.main([str(tmp_path)]) == 1  # no results.json: a failure, never a pass
    (tmp_path / "results.json").write_text(json.dumps(_doc(True)))
    assert hilreport.main([str(tmp_path)]) == 0
    assert (tmp_path / "protocol.md").exists()
    assert (tmp_path / "latency.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "results.json").write_text(json.dumps(_doc(False)))
    assert hilreport.main([str(tmp_path), "--no-plot"]) == 1


def test_the_failed_rows_come_last() -> None:
    """CI keeps the tail of the output: a failed row's failures are the last lines printed."""
    doc = _doc(False)
    doc["results"][0]["notes"] = ["run 1: not a sample", "FAIL: dead-man overshoot: 12 ms"]
    doc["results"].insert(0, {**_doc(True)["results"][0], "id": "boot"})
    tail = hilreport.failure_summary(doc)
    assert tail.rstrip().splitlines()[-2:] == [
        "- deadman (Dead-man | timeout): 1 failure note(s)",
        "  - FAIL: dead-man overshoot: 12 ms"]
    assert "boot" not in tail
    assert hilreport.failure_summary(_doc(True)) == ""


def test_scenario_criteria_format_in_both_profiles() -> None:
    import hilrun
    import scenarios

    for profile in ("strict", "tcg"):
        lim = hilrun.Limits.for_profile(profile)
        for sid, _title, crit, _fn in scenarios.SCENARIOS + scenarios.GLOBAL:
            text = crit.format(**asdict(lim))
            assert "{" not in text, sid
    assert hilrun.Limits.for_profile("tcg").max > hilrun.Limits.for_profile("strict").max


def test_invalid_packets_really_are_invalid() -> None:
    import flood
    import hilclients
    from estop.protocol import udp

    assert not any(udp.is_valid(p) for p in flood.INVALID_PACKETS)
    assert udp.is_valid(hilclients.NEUTRAL) and udp.is_valid(hilclients.DRIVE_GAS)


def test_run_command_line() -> None:
    run = ROOT / "hil" / "run"
    assert subprocess.run(["bash", "-n", str(run)]).returncode == 0
    res = subprocess.run([str(run), "--help"], capture_output=True, text=True, timeout=10)
    assert res.returncode == 0 and "hil/run" in res.stdout
    res = subprocess.run([str(run), "--bogus"], capture_output=True, text=True, timeout=10)
    assert res.returncode != 0 and "unknown option" in res.stderr
    res = subprocess.run([str(run), "--mode", "x"], capture_output=True, text=True, timeout=10)
    assert res.returncode != 0 and "--mode" in res.stderr


def _doc_v3() -> dict:
    doc = _doc(True)
    doc["meta"]["car"] = "15 km/h, emergency deceleration 8 m/s^2, actuator delay 0 ms"
    doc["meta"]["two_stage"] = "S 150 ms, T 600 ms, L 30 %"
    doc["results"].append({
        "id": "lift", "title": "Lift", "criterion": "at once", "passed": True,
        "figures": {"lift_to_stop_frame_ms": summary([0.5, 0.6, 1.3])},
        "samples_ms": {"lift datagram -> stop frame": [0.5, 0.6, 1.3]}, "notes": [],
        "rollouts": {"lift datagram, from the lift": {
            "distance_m": [1.087, 1.0874, 1.0905], "braking_after_ms": [0.5, 0.6, 1.3],
            "before_braking_m": [0.002, 0.0025, 0.0054], "model_m": 1.0851,
            "model": "full braking at the lift",
            "compare": [["no lift (model)", 1.9184, 0.8333]]}}})
    return doc


def test_protocol_shows_the_roll_outs(tmp_path: Path) -> None:
    text = hilreport.protocol_md(_doc_v3())
    assert "- Two-stage daemon: S 150 ms, T 600 ms, L 30 %" in text
    assert "- Car (vehicle model, docs/VEHICLE.md): 15 km/h" in text
    assert "## How far the car rolls" in text
    assert ("| lift datagram, from the lift | 3 | 0.6 (0.5-1.3) | 1.087 (1.087-1.091) | "
            "1.085 (full braking at the lift) |") in text
    assert "| no lift (model) | - | - | - | 1.918 |" in text
    assert "How far the car rolls" not in hilreport.protocol_md(_doc(True))  # no v3 rows
    assert hilreport.median([4.0, 1.0, 3.0, 2.0]) == 2.5 == summary([1.0, 2.0, 3.0, 4.0])["p50"]
    assert hilreport.median([3.0, 1.0, 2.0]) == 2.0
    (tmp_path / "results.json").write_text(json.dumps(_doc_v3()))
    assert hilreport.main([str(tmp_path)]) == 0
    for name in ("latency.png", "distance.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Distance plot" in (tmp_path / "protocol.md").read_text()
