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


def test_new_sender_from_a_time() -> None:
    # a lagging receiver still reads the old daemon's frames after the new one was started
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, armed(9)))
    ctl.expect_new_sender(0.05)
    ctl.on_frame(Frame(0.01, 0x050, armed(10)))  # the old one, read late: still followed
    ctl.on_frame(Frame(0.02, 0x050, armed(12)))
    assert [i.kind for i in ctl.issues] == ["jump"]
    ctl.on_frame(Frame(0.06, 0x050, BOOT))  # the new one: counter 0, no continuity expected
    ctl.on_frame(Frame(0.07, 0x050, stopped(1, reason=1)))
    assert len(ctl.issues) == 1 and ctl.good == 5


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
    # another ID in the other frame's place is no match either
    other = crosscheck(cd, [py[0], Frame(py[1].ts, 0x7FF, py[1].data), py[2]])
    assert not other.ok and len(other.only_candump) == len(other.only_pycan) == 1


def test_crosscheck_order_is_per_sender() -> None:
    # Seen in a run: the daemon's stop frame and the harness's marker 155 us later, on two
    # CPUs, reached candump's socket in one order and python-can's in the other.
    stop = Frame(1795599529.515946, 0x050, bytes.fromhex("01640005000001CF"))
    marker = Frame(1795599529.516101, 0x7FF, b"HILSYNC")
    before = Frame(1795599529.505946, 0x050, bytes.fromhex("01640005000000E0"))
    cc = crosscheck([before, marker, stop], [before, stop, marker], (before.ts, marker.ts))
    assert cc.ok and cc.matched == 3
    # within one ID the order still counts: two frames swapped do not match
    late = Frame(stop.ts + 0.01, 0x050, bytes.fromhex("016400050000023A"))
    swapped = crosscheck([before, stop, late], [before, Frame(stop.ts, 0x050, late.data),
                                               Frame(late.ts, 0x050, stop.data)])
    assert not swapped.ok and len(swapped.data_mismatch) == 2


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


PROC_NET_UDP = """\
   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout \
inode ref pointer drops
11060: 0100007F:D252 00000000:0000 07 00000000:007FFE80 00:00000000 00000000     0        0 \
201297 2 0000000020bb6bc2 226942
14081: 0100007F:9E1F 0100007F:D252 01 00000000:00000000 00:00000000 00000000     0        0 \
201301 2 00000000afdcb09b 7
"""


def test_udp_socket_drops() -> None:
    assert hilcheck.udp_socket_drops(PROC_NET_UDP, 0xD252) == (0x7FFE80, 226942)
    # the flooder's own connected socket (remote port set) is not the daemon's
    assert hilcheck.udp_socket_drops(PROC_NET_UDP, 0x9E1F) is None
    assert hilcheck.udp_socket_drops("header only\n", 5700) is None


def _status(ts: float, valid: int, invalid: int, auth: int, ctr: int) -> Frame:
    return Frame(ts, 0x051, StatusFrame(valid, invalid, auth, 0, 0xFFFF, ctr).encode())


def test_status_windows() -> None:
    frames = [_status(1.0, 0, 0, 0, 0), Frame(1.05, 0x050, BOOT), _status(1.1, 5, 12, 3, 1),
              _status(1.2, 0, 255, 0, 2)]
    ws = hilcheck.status_windows(frames)
    assert [(w.start, w.end, w.valid, w.invalid, w.auth_failures) for w in ws] == [
        (1.0, 1.1, 5, 12, 3), (1.1, 1.2, 0, 255, 0)]
    bad = bytearray(frames[2].data)
    bad[7] ^= 1
    ws2 = hilcheck.status_windows([frames[0], Frame(1.1, 0x051, bytes(bad)), frames[3]])
    assert ws2 == []  # a bad frame loses its window and the one after (unknown start)


def test_sent_between() -> None:
    series = [[10.0, 0], [10.005, 100], [10.010, 200], [10.015, 300]]
    assert hilcheck.sent_between(series, 10.005, 10.010) == (100, 100)
    lo, hi = hilcheck.sent_between(series, 10.002, 10.012)
    assert (lo, hi) == (100, 300)
    assert hilcheck.sent_between(series, 9.0, 11.0) == (300, 300)


def test_flooder_counts_what_it_sends() -> None:
    """flood.py against a real socket on loopback: a burst is exactly N, cycling the kinds."""
    import socket
    import time

    import flood

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    port = rx.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-B", str(HIL / "flood.py"), str(port),
                             "--rate", "2000"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        def ask(line: str) -> dict:
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.write(line + "\n")
            proc.stdin.flush()
            return json.loads(proc.stdout.readline())

        assert json.loads(proc.stdout.readline())["ready"] is True  # unasked, once up
        assert ask("ready?")["ready"] is True
        burst = ask("burst 30")
        assert burst["sent"] == 30 and burst["errors"] == 0
        rx.settimeout(2.0)
        got = [rx.recv(128) for _ in range(30)]
        assert got == (flood.INVALID_PACKETS * 3)[:30]
        proc.stdin.write("flood\n")
        proc.stdin.flush()
        time.sleep(0.3)
        res = ask("stop")
        span = res["t1"] - res["t0"]
        assert 0 < res["sent"] <= 2000 * span + 64  # the rate limit holds (one GSO send over)
        assert res["series"][0][1] == 0 and res["series"][-1][1] == res["sent"]
        # UDP GSO cuts the flood's sends apart: each kind arrives as datagrams of its own, in
        # equal numbers, and every one that was counted as sent arrives (no drops here)
        assert res["gso"] is True and res["errors"] == 0
        rx.settimeout(0.5)
        flooded = [rx.recv(128) for _ in range(res["sent"])]
        kinds = {p: flooded.count(p) for p in flood.INVALID_PACKETS}
        assert sum(kinds.values()) == res["sent"]
        assert max(kinds.values()) - min(kinds.values()) <= 8
        with pytest.raises(TimeoutError):
            rx.recv(128)
        assert "error" in ask("bogus")
    finally:
        proc.stdin.write("quit\n")
        proc.stdin.close()
        proc.wait(timeout=10)
        rx.close()


def test_judge_latencies_counts_stalled_samples_as_upper_bounds() -> None:
    jl = hilcheck.judge_latencies
    # all within the limits, stalls or not: met (a stall can only delay)
    v = jl([1.0, 2.0, 4.0, 11.0], [True, True, True, True], 5.0, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    # a slow daemon fails on its clean samples
    v = jl([7.0, 8.0, 9.0, 30.0], [False, False, False, True], 5.0, 25.0, "x")
    assert v.fails == ["x: median > 5.0 ms (waits for the 10 ms tick?)"]
    assert v.inconclusive is None
    # the median over the limit only with stalled samples in it, too few clean ones: undecided
    v = jl([1.0, 8.0, 8.0, 9.0], [False, True, True, True], 5.0, 25.0, "x")
    assert v.inconclusive is not None and v.fails[0].startswith("x: median not judged")
    # enough clean samples decide, the stalled ones aside
    v = jl([1.0, 1.5, 2.0, 8.0, 9.0, 9.5], [False] * 3 + [True] * 3, 5.0, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    # over the max without a stall: a failure; with one: not judged if most samples stalled
    assert jl([1.0, 26.0], [False, False], None, 25.0, "x").fails == ["x: 26.0 ms > 25.0 ms"]
    v = jl([1.0, 26.0, 2.0], [True, True, False], None, 25.0, "x")
    assert v.inconclusive is not None and v.fails[0].startswith("x: max not judged")
    v = jl([1.0, 26.0, 2.0], [False, True, False], None, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    assert jl([], [], 5.0, 25.0, "x") == hilcheck.Verdict([])


def test_keyed_rows_run_last() -> None:
    import scenarios

    ids = [sid for sid, *_ in scenarios.SCENARIOS]
    keyed = [i for i, sid in enumerate(ids) if sid in scenarios.KEYED]
    assert len(keyed) == len(scenarios.KEYED) == 4
    assert keyed == list(range(len(ids) - 4, len(ids)))
    assert scenarios.KEYED <= scenarios.RETRYABLE


def test_attack_packets_are_made_without_the_key() -> None:
    from types import SimpleNamespace

    import rows_keyed
    from estop.protocol import auth, udp
    from hilclients import NEUTRAL

    key = bytes(range(32))
    remote = SimpleNamespace(remote_id=7, session=0x0123456789ABCDEF, udp_counter=41)
    genuine = [auth.AuthControlPacket(7, remote.session, c, udp.decode(NEUTRAL))
               .encode(key) for c in (40, 41)]
    pkts = rows_keyed.attack_packets(remote, key, genuine)  # type: ignore[arg-type]
    assert [k for k, _ in pkts] == ["plain", "wrong_key", "replay"] * 2
    for kind, data in pkts:
        if kind == "plain":
            assert data == NEUTRAL and udp.is_valid(data)
        elif kind == "replay":
            assert data in genuine
        else:
            # the right session and remote id, a counter above the remote's, a wrong tag
            with pytest.raises(auth.TagMismatch):
                auth.AuthControlPacket.decode(data, key)
            p = auth.AuthControlPacket.decode(data, None)
            assert p.session == remote.session and p.remote_id == 7 and p.counter > 41


# --------------------------------------------------------------------------- graded braking (v3)

SLOWING5 = bytes.fromhex("021E02000100053E")  # spec section 4 example


def slowing(counter: int, level: int = 30, flags: int = 1) -> bytes:
    return BrakeFrame.for_state(2, 0, flags, counter, slow_level=level).encode()


def _bus(segments: list[tuple[float, float, str, int]], t0: float = 1000.0) -> list[Frame]:
    """ESTOP_BRAKE every 10 ms: (start, end, state name, reason) relative to ``t0``; a change
    of state sends at once (the period starts over), as the unit does."""
    make = {"ARMED": lambda c, r: armed(c), "SLOWING": lambda c, r: slowing(c),
            "STOPPED": lambda c, r: stopped(c, r)}
    out: list[Frame] = []
    ctr = 0
    for start, end, state, reason in segments:
        t = start
        while t < end - 1e-9:
            out.append(Frame(t0 + t, 0x050, make[state](ctr, reason)))
            ctr = (ctr + 1) % 15
            t += 0.010
    return out


def test_spec_slowing_example_grades_the_brake() -> None:
    assert SLOWING5 == slowing(5)
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, armed(4)))
    assert ctl.share == 0.0 and not ctl.braking
    ctl.on_frame(Frame(0.01, 0x050, SLOWING5))
    assert ctl.share == pytest.approx(0.3) and ctl.braking and not ctl.issues
    ctl.on_frame(Frame(0.02, 0x050, slowing(6, level=55)))  # the unit's own slow level
    assert ctl.share == pytest.approx(0.55)
    ctl.on_frame(Frame(0.03, 0x050, armed(7)))
    ctl.on_frame(Frame(0.04, 0x050, stopped(8, reason=5)))  # lift
    assert [(c.share, c.cause) for c in ctl.changes] == [
        (0.0, "frame"), (0.3, "frame"), (0.55, "frame"), (0.0, "frame"), (1.0, "frame")]
    assert ctl.good == 5 and not ctl.issues


def test_unknown_brake_request_is_an_emergency_brake() -> None:
    # right CRC, a new counter, brake_request 3: the unit said something no controller knows
    unknown = BrakeFrame(3, 30, 2, 0, 0, 1).encode(validate=False)
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, armed(0)))
    ctl.on_frame(Frame(0.01, 0x050, unknown))
    assert ctl.share == 1.0 and ctl.changes[-1].cause == "frame"
    assert ctl.good == 1 and ctl.issues[-1].kind == "bad_content"  # not a good frame
    # a frame that did not come whole from the unit commands nothing: still the emergency
    bad = bytearray(armed(2))
    bad[7] ^= 0xFF
    ctl.on_frame(Frame(0.02, 0x050, bytes(bad)))
    assert ctl.share == 1.0
    ctl.on_frame(Frame(0.03, 0x050, armed(3)))  # a good release releases
    assert ctl.share == 0.0
    # the silence watchdog still counts from the last good frame, not from the unknown one
    ctl2 = BrakeController()
    ctl2.on_frame(Frame(0.00, 0x050, slowing(0)))
    ctl2.on_frame(Frame(0.01, 0x050, BrakeFrame(7, 0, 1, 0, 0, 1).encode(validate=False)))
    ctl2.on_tick(0.0499)
    assert not ctl2.trips
    ctl2.on_tick(0.05)
    assert len(ctl2.trips) == 1 and ctl2.trips[0].last_good == 0.0 and ctl2.share == 1.0
    assert [c.cause for c in ctl2.changes] == ["frame", "frame"]  # braking since the unknown


def test_grading_starts_over_after_a_silence_and_a_new_sender() -> None:
    ctl = BrakeController()
    ctl.on_frame(Frame(0.00, 0x050, slowing(0)))
    ctl.on_tick(0.06)
    assert ctl.share == 1.0 and ctl.changes[-1].cause == "silence"
    # 15 frames lost: the counter is back at 0, which is no repeat after a silence
    ctl.on_frame(Frame(0.16, 0x050, slowing(0)))
    assert ctl.share == pytest.approx(0.3) and ctl.changes[-1].cause == "frame"
    ctl.expect_new_sender()
    ctl.on_frame(Frame(0.17, 0x050, BOOT))  # counter 0 again: a new daemon, graded at once
    assert ctl.share == 1.0 and ctl.changes[-1] == hilcheck.BrakeChange(0.17, 1.0, "frame")


def test_live_and_replayed_grades_agree() -> None:
    frames = _bus([(0.0, 0.5, "ARMED", 0), (0.5, 0.62, "SLOWING", 0), (0.62, 0.9, "ARMED", 0),
                   (0.9, 1.0, "SLOWING", 0), (1.0, 1.2, "STOPPED", 3)])
    live = BrakeController()
    for f in frames:
        live.on_frame(f)
        live.on_tick(f.ts + 0.001)
    off = replay(frames)
    assert hilcheck.frame_commands(live.changes) == hilcheck.frame_commands(off.changes)
    cmds = hilcheck.frame_commands(off.changes, 1000.4, 1001.5)
    assert [s for _, s in cmds] == [0.3, 0.0, 0.3, 1.0]
    assert cmds[0][0] == pytest.approx(1000.5)


def test_share_at_and_shares_between() -> None:
    ch = [hilcheck.BrakeChange(1.0, 0.0, "frame"), hilcheck.BrakeChange(2.0, 0.3, "frame"),
          hilcheck.BrakeChange(2.5, 0.0, "frame"), hilcheck.BrakeChange(3.0, 1.0, "silence")]
    assert hilcheck.share_at(ch, 0.5) == 1.0  # powers up braking
    assert hilcheck.share_at(ch, 2.0) == 0.3 and hilcheck.share_at(ch, 2.49) == 0.3
    assert hilcheck.share_at([], 5.0, initial=0.0) == 0.0
    assert hilcheck.shares_between(ch, 2.0, 2.5) == [0.3]  # while SLOWING: only 0.3
    assert hilcheck.shares_between(ch, 1.5, 2.6) == [0.0, 0.3, 0.0]
    assert hilcheck.shares_between(ch, 2.1, 3.5) == [0.3, 0.0, 1.0]


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
    frames = _bus([(0.0, 1.004, "ARMED", 0), (1.004, 1.5, "STOPPED", 5)])
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
    frames = _bus([(0.0, 1.152, "ARMED", 0), (1.152, 1.601, "SLOWING", 0),
                   (1.601, 2.5, "STOPPED", 3)])
    r = hilroll.roll(frames, 1001.0)
    assert r.agree, r.disagreement()
    model = hilroll.two_stage_distance(0.152, 0.601, 30)
    assert r.bus.distance == pytest.approx(model, abs=1e-6)
    assert r.figures()["braking_after_ms"] == pytest.approx(152.0, abs=1e-3)
    # single stage at T = 200 ms
    dm = hilroll.roll(_bus([(0.0, 1.2005, "ARMED", 0), (1.2005, 2.0, "STOPPED", 3)]), 1001.0)
    assert dm.agree and dm.bus.distance == pytest.approx(
        hilroll.single_stage_distance(0.2005), abs=1e-6)


def test_roll_disagreement_is_reported() -> None:
    import hilroll

    frames = _bus([(0.0, 1.0, "ARMED", 0), (1.0, 1.2, "STOPPED", 5)])
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


# --------------------------------------------------------------------------- states and logs (v3)

def test_state_changes_on_the_bus() -> None:
    import hilstates

    frames = _bus([(0.0, 0.5, "ARMED", 0), (0.5, 0.62, "SLOWING", 0), (0.62, 0.9, "ARMED", 0),
                   (0.9, 1.0, "SLOWING", 0), (1.0, 1.2, "STOPPED", 3)])
    bad = bytearray(stopped(3, reason=5))
    bad[7] ^= 1
    frames.insert(30, Frame(frames[29].ts + 0.001, 0x050, bytes(bad)))  # not a change: bad CRC
    frames.insert(10, Frame(frames[9].ts + 0.001, 0x051, StatusFrame(0, 0, 0, 0, 5, 0).encode()))
    ch = hilstates.state_changes(frames, 1000.45)
    assert [(c.state, c.reason) for c in ch] == [(2, 0), (1, 0), (2, 0), (0, 3)]
    assert ch[0].ts == pytest.approx(1000.5) and ch[0].data[:4] == bytes((2, 30, 2, 0))
    assert ch[-1].text() == "STOPPED/udp_timeout"
    # the state before the window counts: no change at the window's start
    assert [(c.state, c.reason) for c in hilstates.state_changes(frames, 1000.7, 1000.95)] == \
        [(2, 0)]
    # with nothing before, the first frame in the window is a change
    late = [f for f in frames if f.ts > 1000.7]
    assert [c.text() for c in hilstates.state_changes(late, 0.0, 1000.89)] == ["ARMED/none"]


def test_sequence_and_frame_problems() -> None:
    import hilstates

    frames = _bus([(0.0, 0.1, "ARMED", 0), (0.1, 0.2, "STOPPED", 5)])
    ch = hilstates.state_changes(frames, 1000.05)
    assert hilstates.sequence_problem(ch, [(0, 5)], "run 0") is None
    text = hilstates.sequence_problem(ch, [(2, 0), (0, 5)], "run 0")
    assert text == "run 0: the bus showed STOPPED/lift, want SLOWING/none -> STOPPED/lift"
    assert "showed none" in str(hilstates.sequence_problem([], [(0, 5)], "x"))
    assert hilstates.frame_problem(ch[0].data, bytes((1, 100, 0, 5)), "stop") is None
    assert "want 01 64 00 03" in str(hilstates.frame_problem(ch[0].data, bytes((1, 100, 0, 3)),
                                                             "stop"))
    bad = bytearray(ch[0].data)
    bad[7] ^= 1
    assert "fails the frame checks" in str(hilstates.frame_problem(bytes(bad), b"", "stop"))


def _state(frm: str, to: str, reason: str, cause: str | None, src: str = "-") -> dict:
    rec = {"t_mono": 1.0, "event": "state", "from": frm, "to": to, "reason": reason, "src": src}
    return rec if cause is None else {**rec, "cause": cause}


def test_log_changes_and_problems() -> None:
    import hilstates

    recs = [{"event": "start"}, _state("ARMED", "SLOWING", "none", "udp_silence"),
            _state("SLOWING", "ARMED", "none", "link_back", "127.0.0.1:5")]
    got = hilstates.log_changes(recs)
    assert [c.text() for c in got] == ["ARMED->SLOWING none cause=udp_silence",
                                       "SLOWING->ARMED none cause=link_back"]
    assert got[1].src == "127.0.0.1:5"
    want = [("ARMED", "SLOWING", "none", "udp_silence"), ("SLOWING", "ARMED", "none",
                                                          "link_back")]
    assert hilstates.log_problem(got, want, "run 1") is None
    text = hilstates.log_problem(got[:1], want, "run 1")
    assert text is not None and text.startswith("run 1: log ARMED->SLOWING none cause=")
    assert "log none" in str(hilstates.log_problem([], want[:1], "x"))


@pytest.mark.parametrize("rec,ok", [
    (_state("ARMED", "STOPPED", "lift", "lift_datagram"), True),
    (_state("SLOWING", "STOPPED", "lift", "lift"), True),
    (_state("ARMED", "STOPPED", "tcp_stop", "stop_datagram"), True),
    (_state("SLOWING", "STOPPED", "udp_timeout", "udp_timeout"), True),
    (_state("ARMED", "STOPPED", "fault", "clock_backwards"), True),
    (_state("ARMED", "SLOWING", "none", "udp_silence"), True),
    (_state("SLOWING", "ARMED", "none", "link_back"), True),
    (_state("STOPPED", "SLOWING", "none", "release"), True),
    (_state("ARMED", "STOPPED", "lift", "tcp_stop"), False),
    (_state("ARMED", "STOPPED", "udp_timeout", "lift"), False),
    (_state("ARMED", "SLOWING", "none", "link_back"), False),
    (_state("SLOWING", "ARMED", "none", "release"), False),
    (_state("ARMED", "ARMED", "none", "release"), False),
    (_state("ARMED", "STOPPED", "lift", None), False),
])
def test_cause_fits_the_change(rec: dict, ok: bool) -> None:
    import hilstates

    (change,) = hilstates.log_changes([rec])
    assert (hilstates.cause_problem(change) is None) is ok


def test_bus_transitions_count_slowing() -> None:
    import hilstates

    frames = _bus([(0.0, 0.1, "STOPPED", 1), (0.1, 0.3, "ARMED", 0), (0.3, 0.4, "SLOWING", 0),
                   (0.4, 0.5, "ARMED", 0), (0.5, 0.6, "SLOWING", 0), (0.6, 0.7, "STOPPED", 3)])
    assert hilstates.bus_transitions(frames) == {
        "STOPPED->ARMED": 1, "ARMED->SLOWING": 2, "SLOWING->ARMED": 1, "SLOWING->STOPPED": 1}


def test_judge_drops() -> None:
    assert hilcheck.judge_drops(0, 0.5, "the flood") == hilcheck.Verdict([])
    v = hilcheck.judge_drops(12, 0.0, "the flood")
    assert v.fails == ["the kernel dropped 12 datagrams of the flood"] and v.inconclusive is None
    v = hilcheck.judge_drops(12, 0.004, "the flood")  # a CPU stood still: never a pass
    assert v.inconclusive is not None and v.fails[0].startswith("kernel drops not judged")
    assert hilcheck.judge_drops(None, 0.0, "the flood").fails


def test_judge_rolls_and_state_lines() -> None:
    from types import SimpleNamespace

    import hiljudge
    import hilroll
    from hilrun import Result

    frames = _bus([(0.0, 1.004, "ARMED", 0), (1.004, 1.5, "STOPPED", 5)])
    good = hilroll.roll(frames, 1001.0)
    bad = hilroll.Roll(good.moment, good.bus, hilroll.EmulatorRoll(2.0, None, 1.0))
    res = Result("lift", "t", "c")
    hiljudge.judge_rolls(res, "distance_m", "from the lift", [good, good], 1.085, "ideal",
                         [("no lift", 1.918, 0.833)])
    assert res.rollouts == {"from the lift": {
        "distance_m": [1.1017, 1.1017], "braking_after_ms": [4.0, 4.0],
        "before_braking_m": [0.0167, 0.0167], "model_m": 1.085,
        "model": "ideal", "compare": [["no lift", 1.918, 0.833]]}}
    assert not res.notes
    assert res.figures["distance_m"]["p50"] == pytest.approx(1.102, abs=1e-3)
    hiljudge.judge_rolls(res, "distance_m", "from the lift", [bad], 1.085, "ideal")
    assert res.figures["distance_m"] == pytest.approx(1.102, abs=1e-3)
    assert res.notes[0].startswith("FAIL: from the lift: the two ways to the distance disagree")
    d = SimpleNamespace(events=lambda name=None, since=0.0: [
        {**_state("STOPPED", "ARMED", "none", "release"), "t_mono": 5.0},
        {**_state("ARMED", "STOPPED", "lift", "lift_datagram"), "t_mono": 7.0}])
    lines = hiljudge.wait_state_lines(d, 6.0, 1, timeout=0.1)  # type: ignore[arg-type]
    assert [c.text() for c in lines] == ["ARMED->STOPPED lift cause=lift_datagram"]
    assert len(hiljudge.wait_state_lines(d, 6.0, 2, timeout=0.05)) == 1  # type: ignore[arg-type]


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


def test_standin_reads_datagrams_in_batches() -> None:
    """The stand-in's recvmmsg (ctypes): in order, at most n a call, long ones cut at 64."""
    import socket
    import time

    import standin_estopd

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.bind(("127.0.0.1", 0))
        rx.setblocking(False)
        batch = standin_estopd.BatchReceiver(rx, n=8)
        assert batch.recv() == []
        tx.connect(rx.getsockname())
        sent = [b"", b"a" * 19, b"b" * 20, b"c" * 100] + [bytes([i]) * 5 for i in range(10)]
        for m in sent:
            tx.send(m)
        got: list[bytes] = []
        end = time.monotonic() + 2.0
        while len(got) < len(sent) and time.monotonic() < end:
            more = batch.recv()
            assert len(more) <= 8
            got += more
        assert got == [m[:64] for m in sent]
    finally:
        rx.close()
        tx.close()


def test_storm_holds_every_place_and_closes_an_idle_client() -> None:
    """storm.py against a loopback server that keeps 8 connections and closes the one quiet
    longest (as the unit does, docs/PROTOCOL.md section 2): its busy connections get their
    replies, a client that connected first and stays idle is closed, and it counts what it
    did."""
    import selectors
    import socket
    import threading
    import time

    from estop.protocol import tcp

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(64)
    srv.setblocking(False)
    port = srv.getsockname()[1]
    done = threading.Event()

    def serve() -> None:  # the unit's rule for making room, and a reply per request
        sel = selectors.DefaultSelector()
        sel.register(srv, selectors.EVENT_READ)
        quiet: dict[socket.socket, float] = {}
        while not done.is_set():
            for key, _ in sel.select(0.01):
                if key.fileobj is not srv and key.fileobj not in quiet:
                    continue  # closed earlier in this round to make room: its event is stale
                if key.fileobj is srv:
                    conn, _addr = srv.accept()
                    if len(quiet) >= 8:
                        victim = min(quiet, key=quiet.__getitem__)
                        sel.unregister(victim)
                        del quiet[victim]
                        victim.close()
                    conn.setblocking(False)
                    quiet[conn] = time.monotonic()
                    sel.register(conn, selectors.EVENT_READ)
                    continue
                conn = key.fileobj  # type: ignore[assignment]
                try:
                    data = conn.recv(4096)
                except OSError:
                    data = b""
                if not data:
                    sel.unregister(conn)
                    quiet.pop(conn, None)
                    conn.close()
                    continue
                quiet[conn] = time.monotonic()
                try:
                    conn.send(bytes(tcp.FRAME_SIZE) * (len(data) // tcp.FRAME_SIZE))
                except OSError:
                    pass
        for c in quiet:
            c.close()

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    idle = socket.create_connection(("127.0.0.1", port))
    proc = subprocess.Popen([sys.executable, "-B", str(HIL / "storm.py"), str(port)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        assert json.loads(proc.stdout.readline())["ready"] is True
        proc.stdin.write("storm\n")
        proc.stdin.flush()
        busy = json.loads(proc.stdout.readline())
        assert busy["busy"] is True
        time.sleep(0.3)
        idle.settimeout(2.0)
        assert idle.recv(16) == b""  # the idle client was the quietest: closed
        proc.stdin.write("stop\n")
        proc.stdin.flush()
        res = json.loads(proc.stdout.readline())
        assert res["connects"] > 0 and res["refused"] == 0
        assert res["status_sent"] > 0 and 0 < res["replies"] <= res["status_sent"]
        assert res["busy_closed_by_unit"] > 0  # every new connect closes someone
    finally:
        proc.stdin.write("quit\n")
        proc.stdin.close()
        proc.wait(timeout=10)
        done.set()
        server.join(timeout=2)
        idle.close()
        srv.close()


def test_sched_text_and_the_stop_datagram_the_storm_row_looks_for() -> None:
    import os

    import hildaemon
    import rows_storm
    from estop.protocol import auth, tcp

    me = hildaemon.threads_sched(os.getpid())
    assert me and me[0].tid == os.getpid()  # the main thread first
    assert hildaemon.sched_text(me).startswith(f"loop {me[0].policy}")
    fifo = hildaemon.ThreadSched(1, "estopd", "FIFO", 50, True)
    out = hildaemon.ThreadSched(2, "estopd-out", "OTHER", 0, False)
    assert hildaemon.sched_text([fifo, out, out]) == \
        "loop FIFO 50 reset-on-fork; 2 other threads OTHER"
    assert hildaemon.sched_text([]).startswith("unknown")
    assert rows_storm.is_stop_datagram(auth.stop_datagram(1, 1))
    assert not rows_storm.is_stop_datagram(auth.stop_datagram(1, 1, stop_id=0x12345678))
    assert not rows_storm.is_stop_datagram(tcp.Request(tcp.DEFAULT_STOP_ID, 1).encode())


def test_udp_tap_times_only_the_datagrams_asked_for() -> None:
    """hilload.UdpTap (a packet socket on lo, root only): the kernel's time of each datagram of
    the size asked for to the port asked for; the others (a keepalive's 20-byte packets, in
    thousands) never reach its queue."""
    import socket
    import time

    from estop.protocol import auth
    from hilload import UdpTap

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    port = rx.getsockname()[1]
    try:
        tap = UdpTap(port, auth.REQUEST_SIZE)
    except PermissionError:
        rx.close()
        pytest.skip("a packet socket needs root")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(3000):
            tx.sendto(bytes(20), ("127.0.0.1", port))
        t0 = time.time()
        tx.sendto(auth.stop_datagram(1, 1), ("127.0.0.1", port))
        t1 = time.time()
        tx.sendto(bytes(auth.REQUEST_SIZE), ("127.0.0.1", port + 1 if port < 65535 else 1))
        got = tap.read()
        assert [p for _, p in got][:1] == [auth.stop_datagram(1, 1)]
        assert all(p == auth.stop_datagram(1, 1) for _, p in got)  # sent, maybe received too
        assert t0 - 1e-3 <= got[0][0] <= t1 + 1e-3
    finally:
        tap.close()
        tx.close()
        rx.close()
