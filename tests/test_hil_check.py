"""The HIL harness's pure parts (no vcan, no VM): brake-controller emulator, candump
cross-check, statistics, test protocol, and the hil/run command line."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest

HIL = Path(__file__).resolve().parent.parent / "hil"
sys.path.insert(0, str(HIL))

import hilcheck  # noqa: E402
import hilreport  # noqa: E402
from estop.protocol.can import BrakeFrame, StatusFrame  # noqa: E402
from hilcheck import BrakeController, Frame, crosscheck, read_candump, replay, summary  # noqa: E402

BOOT = bytes.fromhex("016400010000009C")  # spec section 4 examples
ARMED7 = bytes.fromhex("0000010000000718")
TIMEOUT14 = bytes.fromhex("0164000300000E1D")


def armed(counter: int) -> bytes:
    return BrakeFrame.for_state(1, 0, 0, counter).encode()


def stopped(counter: int, reason: int = 2) -> bytes:
    return BrakeFrame.for_state(0, reason, 0, counter).encode()


def test_spec_examples_are_good_frames() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(0.0, 0x050, BOOT))
    assert ctl.good == 1 and ctl.braking and not ctl.issues
    ctl2 = BrakeController()
    ctl2.on_frame(Frame(0.0, 0x050, ARMED7))
    assert ctl2.good == 1 and not ctl2.braking
    ctl3 = BrakeController()
    ctl3.on_frame(Frame(0.0, 0x050, TIMEOUT14))
    assert ctl3.good == 1 and ctl3.braking


def test_releases_on_armed_frames_and_brakes_on_stop() -> None:
    ctl = BrakeController()
    for i in range(5):
        ctl.on_frame(Frame(i * 0.01, 0x050, armed(i)))
    assert not ctl.braking
    ctl.on_frame(Frame(0.05, 0x050, stopped(5)))
    assert ctl.braking
    assert [c.cause for c in ctl.changes] == ["frame", "frame"]
    assert not ctl.issues


def test_bad_crc_is_not_a_good_frame() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(0.0, 0x050, armed(0)))
    bad = bytearray(armed(1))
    bad[7] ^= 0x01
    ctl.on_frame(Frame(0.01, 0x050, bytes(bad)))
    assert ctl.good == 1
    assert [i.kind for i in ctl.issues] == ["bad_crc"]
    # the watchdog still counts from the last good frame
    ctl.on_tick(0.0499)
    assert not ctl.trips
    ctl.on_tick(0.050)
    assert len(ctl.trips) == 1 and ctl.braking


def test_inconsistent_content_rejected() -> None:
    raw = BrakeFrame(0, 100, 1, 0, 0, 3).encode(validate=False)  # release with level 100
    ctl = BrakeController()
    ctl.on_frame(Frame(0.0, 0x050, raw))
    assert ctl.good == 0 and ctl.issues[0].kind == "bad_content"


def test_counter_repeat_is_stale_and_jump_is_reported() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, armed(3)))
    ctl.on_frame(Frame(0.01, 0x050, armed(3)))  # repeated: stale, not good
    assert ctl.good == 1 and ctl.issues[-1].kind == "repeat"
    ctl.on_frame(Frame(0.02, 0x050, armed(6)))  # 4 and 5 lost: still good, reported
    assert ctl.good == 2 and ctl.issues[-1].kind == "jump"
    ctl.on_frame(Frame(0.03, 0x050, armed(7)))
    assert ctl.good == 3 and len(ctl.issues) == 2


def test_counter_wraps_at_15() -> None:
    ctl = BrakeController()
    for i in range(40):
        ctl.on_frame(Frame(i * 0.01, 0x050, armed(i % 15)))
    assert ctl.good == 40 and not ctl.issues


def test_counter_resyncs_after_a_silence() -> None:
    # 15 frames lost in an outage bring the counter back to the same value: not a repeat
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, armed(0)))
    ctl.on_frame(Frame(0.16, 0x050, stopped(0, reason=4)))
    assert ctl.good == 2 and [i.kind for i in ctl.issues] == ["resync"]
    ctl.on_frame(Frame(0.17, 0x050, stopped(1, reason=4)))
    assert ctl.good == 3 and len(ctl.issues) == 1
    status = [StatusFrame(0, 0, 0, 0, 0xFFFF, c).encode() for c in (3, 3, 4)]
    ctl.on_frame(Frame(0.1, 0x051, status[0]))
    ctl.on_frame(Frame(0.4, 0x051, status[1]))  # 300 ms later: starts over
    ctl.on_frame(Frame(0.5, 0x051, status[2]))
    assert ctl.status_good == 3 and [i.kind for i in ctl.issues] == ["resync", "resync"]


def test_new_sender_resets_counters() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(0.0, 0x050, armed(9)))
    ctl.expect_new_sender()
    ctl.on_frame(Frame(0.01, 0x050, BOOT))
    assert not ctl.issues and ctl.good == 2


def test_status_frames_checked() -> None:
    ctl = BrakeController()
    good = StatusFrame(5, 0, 0, 0, 12, 0).encode()
    ctl.on_frame(Frame(0.0, 0x051, good))
    ctl.on_frame(Frame(0.1, 0x051, good[:7] + bytes((good[7] ^ 0xFF,))))
    assert ctl.status_good == 1 and ctl.issues[0].kind == "bad_crc"


def test_silence_trips_once_and_any_frame_advances_time() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(1.000, 0x050, armed(0)))
    ctl.on_frame(Frame(1.030, 0x7FF, b"other"))
    assert not ctl.trips
    ctl.on_frame(Frame(1.060, 0x7FF, b"other"))  # a later frame proves 50 ms of silence
    assert len(ctl.trips) == 1 and ctl.braking
    assert ctl.trips[0].detected == pytest.approx(1.060)
    ctl.on_tick(1.2)
    assert len(ctl.trips) == 1
    ctl.on_frame(Frame(1.3, 0x050, armed(1)))
    assert not ctl.braking and not ctl.tripped


def test_replay_places_trips_at_the_deadline() -> None:
    t0 = 1_700_000_000.0  # wall-clock magnitude: float rounding must not hide a trip
    frames = [Frame(t0 + i * 0.01, 0x050, armed(i % 15)) for i in range(10)]
    frames.append(Frame(t0 + 0.09 + 0.050, 0x050, armed(10)))  # exactly 50 ms later
    frames.append(Frame(t0 + 0.30, 0x050, armed(11)))
    ctl = replay(frames, end=t0 + 1.0)
    assert len(ctl.trips) == 3
    assert ctl.trips[0].detected == pytest.approx(t0 + 0.14, abs=1e-6)
    assert ctl.trips[1].last_good == pytest.approx(t0 + 0.14)
    assert ctl.trips[2].detected == pytest.approx(t0 + 0.35, abs=1e-6)


def test_read_candump_and_crosscheck() -> None:
    lines = [
        "(1700000000.000100) vcan0 050#016400010000009C",
        "(1700000000.010100) vcan0 051#0000000000FFFF00",
        "garbage",
        "(1700000000.020100) vcan0 050#016400010000019C",
        "",
    ]
    cd, bad = read_candump(lines)
    assert len(cd) == 3 and bad == ["garbage"]
    assert cd[0].can_id == 0x050 and cd[0].data == BOOT
    py = [Frame(f.ts + 3e-7, f.can_id, f.data) for f in cd]  # float noise below 1 us
    assert crosscheck(cd, py).ok
    # python-can started later and stopped earlier: the edges do not count
    assert crosscheck(cd, py[1:2]).ok
    missing = crosscheck(cd, [py[0], py[2]], window=(cd[0].ts, cd[2].ts))
    assert not missing.ok and len(missing.only_candump) == 1
    changed = [py[0], Frame(py[1].ts, 0x051, b"\x01" * 8), py[2]]
    cc = crosscheck(cd, changed)
    assert not cc.ok and len(cc.data_mismatch) == 1
    assert not crosscheck([], py).ok


def test_summary_and_gaps() -> None:
    assert summary([]) == {"n": 0}
    s = summary([1.0, 2.0, 3.0, 4.0])
    assert s["n"] == 4 and s["p50"] == 2.5 and s["max"] == 4.0 and s["mean"] == 2.5
    frames = [Frame(0.0, 0x050, BOOT), Frame(0.005, 0x051, b""), Frame(0.01, 0x050, BOOT)]
    assert hilcheck.frame_gaps(frames) == pytest.approx([0.01])
    assert hilcheck.in_windows(1.5, [(1.0, 2.0)]) and not hilcheck.in_windows(3, [(1, 2)])


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


def test_scenario_criteria_format_in_both_profiles() -> None:
    import scenarios

    for profile in ("strict", "tcg"):
        lim = scenarios.Limits.for_profile(profile)
        for sid, _title, crit, _fn in scenarios.SCENARIOS + scenarios.GLOBAL:
            text = crit.format(**asdict(lim))
            assert "{" not in text, sid
    assert scenarios.Limits.for_profile("tcg").max > scenarios.Limits.for_profile("strict").max


def test_invalid_packets_really_are_invalid() -> None:
    import scenarios
    from estop.protocol import udp

    assert not any(udp.is_valid(p) for p in scenarios.INVALID_PACKETS)
    assert udp.is_valid(scenarios.NEUTRAL) and udp.is_valid(scenarios.DRIVE_GAS)


def test_run_command_line() -> None:
    run = HIL / "run"
    assert subprocess.run(["bash", "-n", str(run)]).returncode == 0
    res = subprocess.run([str(run), "--help"], capture_output=True, text=True, timeout=10)
    assert res.returncode == 0 and "hil/run" in res.stdout
    res = subprocess.run([str(run), "--bogus"], capture_output=True, text=True, timeout=10)
    assert res.returncode != 0 and "unknown option" in res.stderr
    res = subprocess.run([str(run), "--mode", "x"], capture_output=True, text=True, timeout=10)
    assert res.returncode != 0 and "--mode" in res.stderr


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
