"""The HIL harness's brake-controller emulator (hil/hilcheck.py), pure: good and bad frames,
alive counters, silences, the candump cross-check, the summary, and graded braking (v3)."""

from __future__ import annotations

import pytest
from hil_util import ARMED7, BOOT, SLOWING5, TIMEOUT14, armed, bus_frames, slowing, stopped

import hilcheck
from estop.protocol.can import BrakeFrame, StatusFrame
from hilcheck import BrakeController, Frame, crosscheck, read_candump, replay, summary


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


def test_replay_starts_the_counters_over_for_a_new_daemon() -> None:
    # CI of 7ea791b: a daemon restarted within one status period; the old one's last
    # ESTOP_STATUS had counter 0, the new one's first has counter 0 (as every daemon's first).
    old_status = StatusFrame(0, 0, 0, 0, 0xFFFF, 0).encode()
    frames = [Frame(0.00, 0x050, armed(13)), Frame(0.01, 0x050, armed(14)),
              Frame(0.015, 0x051, old_status),
              Frame(0.12, 0x050, BOOT), Frame(0.121, 0x051, old_status),
              Frame(0.13, 0x050, stopped(1, reason=1))]
    # Without the restart's time the new daemon's first status frame is a stale repeat.
    assert [i.kind for i in replay(frames).issues if i.kind != "resync"] == ["repeat"]
    # With it (the daemon started at 0.1 s), nothing is wrong; a repeat within one daemon
    # still is.
    assert replay(frames, new_senders=[0.1]).issues == []
    again = [*frames, Frame(0.14, 0x050, stopped(1, reason=1))]
    assert [i.kind for i in replay(again, new_senders=[0.1]).issues] == ["repeat"]


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
    frames = bus_frames([(0.0, 0.5, "ARMED", 0), (0.5, 0.62, "SLOWING", 0), (0.62, 0.9, "ARMED", 0),
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


def test_frames_read_out_of_their_send_order_are_checked_in_it() -> None:
    """vcan hands a frame to the readers from the sending CPU: when that CPU stalls, a frame
    sent later on the other CPU is read first (a local run: counters 14 then 13, read 19.7 ms
    apart). Checked in the order read, that is counter jumps (14 frames "lost"); in the
    order sent (the kernel timestamps), none. A frame really lost is still a jump."""
    from wholerun import sent_order

    ts = [i * 0.01 for i in range(20)]
    read = [Frame(t, 0x050, armed(i % 15)) for i, t in enumerate(ts)]
    read[13], read[14] = read[14], read[13]  # 14 read before 13
    assert [i.kind for i in replay(read).issues] == ["jump"] * 3  # the fault it fixes
    wire, swapped, most = sent_order(read)
    assert swapped == 1 and abs(most - 0.01) < 1e-9
    assert [f.data[6] & 0x0F for f in wire[12:16]] == [12, 13, 14, 0]
    assert replay(wire).issues == []
    lost = wire[:10] + wire[11:]  # frame 10 never sent: still a jump in the order sent
    assert [i.kind for i in replay(sent_order(lost)[0]).issues] == ["jump"]
    # The whole-run row reuses the replay in the order sent, without the marker frames, where
    # nothing was read out of order: the markers change nothing in a replay (trips, commands).
    silent = wire[:8] + [Frame(f.ts + 0.3, f.can_id, f.data) for f in wire[8:]]
    marked = sorted([*silent, *(Frame(i * 0.037, 0x7FF, b"HILSYNC") for i in range(20))],
                    key=lambda f: f.ts)
    a, b = replay(silent, end=0.9), replay(marked, end=0.9)
    assert len(a.trips) == 2 and a.trips == b.trips and a.changes == b.changes
    assert a.issues == b.issues and a.good == b.good
