"""BrakeFrameChecker: what a brake controller accepts, when it brakes, and how hard (the graded
answer of spec section 7)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from estop.model.brakecheck import BRAKE_TIMEOUT, BrakeFrameChecker, grade_kind, grade_text
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.crc import e2e_crc8


def armed(counter: int) -> bytes:
    return BrakeFrame.for_state(1, 0, 0, counter % 15).encode()


def stopped(counter: int, reason: int = 2) -> bytes:
    return BrakeFrame.for_state(0, reason, 0, counter % 15).encode()


def test_defaults() -> None:
    chk = BrakeFrameChecker()
    assert (chk.brake_id, chk.status_id, chk.timeout) == (0x050, 0x051, BRAKE_TIMEOUT)
    assert BRAKE_TIMEOUT == 0.050
    with pytest.raises(ValueError):
        BrakeFrameChecker(timeout=0)


def test_brakes_before_first_frame_and_after_silence() -> None:
    chk = BrakeFrameChecker()
    assert chk.brake_applied(0.0)
    v = chk.feed(1.000, 0x050, armed(0))
    assert v is not None and v.accepted and v.events == ()
    assert not chk.brake_applied(1.049)
    assert chk.brake_applied(1.050)  # 50 ms without a good frame: brake
    chk.feed(1.010, 0x050, stopped(1))
    assert chk.brake_applied(1.011)  # the frame asks for the brake


def test_bad_frames_do_not_count_as_alive() -> None:
    chk = BrakeFrameChecker()
    chk.feed(0.00, 0x050, armed(0))
    bad = bytearray(armed(1))
    bad[7] ^= 0xFF
    v = chk.feed(0.04, 0x050, bytes(bad))
    assert v is not None and not v.accepted and [e.kind for e in v.events] == ["bad_crc"]
    assert chk.brake_applied(0.06)  # the last *good* frame is 60 ms old
    assert chk.last_brake_time == 0.00


def test_repeat_is_rejected_jump_is_accepted_but_flagged() -> None:
    chk = BrakeFrameChecker()
    chk.feed(0.00, 0x050, armed(3))
    v = chk.feed(0.01, 0x050, armed(3))
    assert v is not None and not v.accepted and [e.kind for e in v.events] == ["counter_repeat"]
    v = chk.feed(0.02, 0x050, armed(6))
    assert v is not None and v.accepted and [e.kind for e in v.events] == ["counter_jump"]
    assert "2 lost" in v.events[0].message
    assert chk.counts["counter_repeat"] == 1 and chk.counts["counter_jump"] == 1
    assert chk.problems == 2 and chk.frames == 3 and chk.accepted == 2


def test_gap_and_poll_timeout() -> None:
    chk = BrakeFrameChecker()
    assert chk.poll(5.0) == []  # nothing seen yet: nothing to time out
    chk.feed(0.000, 0x050, armed(0))
    assert chk.poll(0.049) == []
    events = chk.poll(0.050)
    assert [e.kind for e in events] == ["timeout"]
    assert chk.poll(0.2) == []  # reported once per silence
    v = chk.feed(0.300, 0x050, armed(1))
    assert v is not None and [e.kind for e in v.events] == ["gap"]
    assert "300.0 ms" in v.events[0].message
    assert chk.poll(0.340) == [] and len(chk.poll(0.351)) == 1


def test_state_change_and_contradictory_content() -> None:
    chk = BrakeFrameChecker()
    chk.feed(0.00, 0x050, stopped(0, reason=1))
    v = chk.feed(0.01, 0x050, armed(1))
    assert v is not None and v.state_changed and chk.last_brake is not None
    bad = BrakeFrame(0, 100, 1, 0, 0, 2).encode(validate=False)  # released, level 100
    v = chk.feed(0.02, 0x050, bad)
    assert v is not None and not v.accepted and [e.kind for e in v.events] == ["bad_content"]
    v = chk.feed(0.03, 0x050, armed(3))  # the bad frame's counter was followed: no jump
    assert v is not None and v.accepted and v.events == ()


def test_status_frames_and_other_ids() -> None:
    chk = BrakeFrameChecker()
    assert chk.feed(0.0, 0x123, b"\x00") is None
    v = chk.feed(0.0, 0x051, StatusFrame(1, 2, 3, 4, 5, 0).encode())
    assert v is not None and v.accepted and chk.last_status == StatusFrame(1, 2, 3, 4, 5, 0)
    v = chk.feed(0.5, 0x051, StatusFrame(1, 2, 3, 4, 5, 2).encode())
    assert v is not None and [e.kind for e in v.events] == ["counter_jump"]  # no gap check
    v = chk.feed(0.6, 0x051, b"\x00" * 7)
    assert v is not None and v.frame is None and [e.kind for e in v.events] == ["bad_length"]
    assert chk.brake_applied(0.6)  # status frames never release the brake
    chk.reset()
    assert chk.frames == 0 and chk.last_status is None
    no_status = BrakeFrameChecker(status_id=None)
    assert no_status.feed(0.0, 0x051, StatusFrame(0, 0, 0, 0, 0, 0).encode()) is None


@given(st.lists(st.integers(1, 9), min_size=1, max_size=300), st.integers(0, 14))
def test_clean_stream_at_up_to_45ms_has_no_events(steps_ms: list[int], start: int) -> None:
    chk = BrakeFrameChecker()
    t = 0.0
    for i, step in enumerate([0, *steps_ms]):
        t += step * 0.005  # 0..45 ms apart
        v = chk.feed(t, 0x050, armed(start + i))
        assert v is not None and v.accepted and v.events == ()
        assert not chk.brake_applied(t)
    assert chk.problems == 0


@given(st.binary(min_size=0, max_size=10))
def test_random_bytes_never_release_the_brake_unless_valid(data: bytes) -> None:
    chk = BrakeFrameChecker()
    v = chk.feed(0.0, 0x050, data)
    assert v is not None
    assert v.accepted == (BrakeFrame.check(data) == [])
    if not chk.brake_applied(0.0):
        assert v.accepted and not BrakeFrame.decode(data).brakes


# ------------------------------------------------------------ silence is a failure (spec 7)

def test_finish_without_any_frame_is_a_failure() -> None:
    chk = BrakeFrameChecker()
    events = chk.finish(None)
    assert [e.kind for e in events] == ["no_brake_frame"]
    assert "not a working unit" in events[0].message
    assert chk.problems == 1 and chk.counts["no_brake_frame"] == 1
    assert chk.finish(None) == []  # judged once


def test_finish_with_only_bad_or_status_frames_is_a_failure() -> None:
    chk = BrakeFrameChecker()
    bad = bytearray(armed(0))
    bad[7] ^= 1
    chk.feed(0.00, 0x050, bytes(bad))
    for i in range(10):
        chk.feed(0.01 + i * 0.1, 0x051, StatusFrame(1, 0, 0, 0, 5, i).encode())
    events = chk.finish(0.95)
    assert [e.kind for e in events] == ["no_brake_frame"]
    assert "11 frames seen, none a good ESTOP_BRAKE" in events[0].message


def test_finish_judges_the_silence_up_to_the_end() -> None:
    chk = BrakeFrameChecker()
    for i in range(10):
        chk.feed(i * 0.010, 0x050, armed(i))
    assert chk.finish(0.09 + 0.049) == []  # 49 ms: fine
    chk2 = BrakeFrameChecker()
    for i in range(10):
        chk2.feed(i * 0.010, 0x050, armed(i))
    events = chk2.finish(0.09 + 0.9)  # ESTOP_BRAKE stopped, something else went on 0.9 s
    assert [e.kind for e in events] == ["timeout"]
    assert "900.0 ms" in events[0].message and "end" in events[0].message
    assert events[0].t == pytest.approx(0.99)
    assert chk2.problems == 1


def test_finish_does_not_repeat_a_timeout_poll_already_reported() -> None:
    chk = BrakeFrameChecker()
    chk.feed(0.0, 0x050, armed(0))
    assert [e.kind for e in chk.poll(0.06)] == ["timeout"]
    assert chk.finish(0.5) == []
    assert chk.counts["timeout"] == 1


def test_poll_from_the_start_of_the_watch() -> None:
    chk = BrakeFrameChecker()
    chk.begin(10.0)
    assert chk.poll(10.049) == []
    events = chk.poll(10.050)
    assert [e.kind for e in events] == ["timeout"]
    assert "since the watch began" in events[0].message
    assert chk.poll(10.5) == []
    chk.feed(10.6, 0x050, armed(0))  # frames came: the gap from the start is not a "gap"
    assert chk.counts["gap"] == 0
    assert [e.kind for e in chk.finish(10.605)] == []


# ------------------------------------------------------- the graded answer (spec section 7)

def slowing(counter: int, level: int = 30) -> bytes:
    return BrakeFrame.for_state(2, 0, 0, counter % 15, slow_level=level).encode()


def raw_brake(brake_request: int, counter: int, level: int = 0, state: int = 1,
              reason: int = 0) -> bytes:
    """An ESTOP_BRAKE written byte by byte, with a right CRC-8 (data ID 0x0E57)."""
    payload = bytes((brake_request, level, state, reason, 0, 0, counter % 15))
    return payload + bytes((e2e_crc8(0x0E57, payload),))


def test_deceleration_share_follows_the_accepted_frames() -> None:
    chk = BrakeFrameChecker()
    assert chk.deceleration_share(0.0) == 1.0  # nothing accepted yet: brake
    assert chk.silence_deadline is None
    chk.feed(1.000, 0x050, armed(0))
    assert chk.deceleration_share(1.000) == 0.0
    assert chk.silence_deadline == pytest.approx(1.050)
    v = chk.feed(1.010, 0x050, slowing(1, level=30))
    assert v is not None and v.accepted and v.share == pytest.approx(0.30)
    assert chk.deceleration_share(1.011) == pytest.approx(0.30)
    assert chk.brake_applied(1.011)
    chk.feed(1.020, 0x050, slowing(2, level=99))
    assert chk.deceleration_share(1.020) == pytest.approx(0.99)
    chk.feed(1.030, 0x050, stopped(3, reason=5))
    assert chk.deceleration_share(1.030) == 1.0
    chk.feed(1.040, 0x050, armed(4))  # the controller follows the frames; the unit latches
    assert chk.deceleration_share(1.040) == 0.0
    assert dict(chk.grades) == {"release": 2, "controlled": 2, "emergency": 1}


def test_50_ms_without_an_accepted_frame_is_an_emergency_brake_whatever_the_grade() -> None:
    for frame, share in ((armed, 0.0), (slowing, 0.3)):
        chk = BrakeFrameChecker()
        chk.feed(0.0, 0x050, frame(0))
        assert chk.deceleration_share(0.0499) == pytest.approx(share)
        assert chk.deceleration_share(0.050) == 1.0
        assert chk.deceleration_share(7.0) == 1.0


@pytest.mark.parametrize("after", ["release", "controlled"])
@pytest.mark.parametrize("unknown", [3, 255])
def test_an_unknown_brake_request_is_an_emergency_brake_at_once(unknown: int,
                                                                after: str) -> None:
    # a frame from the unit (right CRC, counter in order) whose brake_request the controller
    # does not know: neither a release nor the previous grade held for up to 50 ms
    chk = BrakeFrameChecker()
    chk.feed(0.000, 0x050, armed(0) if after == "release" else slowing(0))
    v = chk.feed(0.010, 0x050, raw_brake(unknown, 1))
    assert v is not None and not v.accepted
    assert [e.kind for e in v.events] == ["bad_content"] and "brake_request" in v.events[0].message
    assert v.share == 1.0
    assert chk.deceleration_share(0.010) == 1.0 and chk.brake_applied(0.010)
    assert chk.deceleration_share(0.049) == 1.0  # the earlier frame is still young: no matter
    assert chk.grades["emergency"] == 1
    v = chk.feed(0.020, 0x050, raw_brake(unknown, 2, level=100, state=0, reason=2))
    assert v is not None and v.share == 1.0  # however its other fields read
    v = chk.feed(0.030, 0x050, armed(3))  # counter in order: accepted, the grade follows it
    assert v is not None and v.accepted and v.events == ()
    assert chk.deceleration_share(0.030) == 0.0


def test_contradictory_frame_from_the_unit_brakes_a_bad_crc_or_a_repeat_changes_nothing() -> None:
    chk = BrakeFrameChecker()
    chk.feed(0.00, 0x050, armed(0))
    bad_crc = bytearray(armed(1))
    bad_crc[7] ^= 0x01
    v = chk.feed(0.01, 0x050, bytes(bad_crc))
    assert v is not None and v.share is None  # not whole from the unit: commands nothing
    assert chk.deceleration_share(0.01) == 0.0  # until the 50 ms run out
    v = chk.feed(0.02, 0x050, armed(0))  # a repeat of counter 0: stale
    assert v is not None and v.share is None and chk.deceleration_share(0.02) == 0.0
    v = chk.feed(0.03, 0x050, raw_brake(0, 1, level=100))  # release at level 100: contradicts
    assert v is not None and not v.accepted and v.share == 1.0
    assert chk.deceleration_share(0.03) == 1.0
    assert chk.deceleration_share(0.06) == 1.0


def test_grade_words() -> None:
    assert [grade_text(s) for s in (0.0, 0.3, 0.99, 1.0)] == [
        "release", "controlled 30 %", "controlled 99 %", "EMERGENCY"]
    assert [grade_kind(s) for s in (0.0, 0.01, 1.0)] == ["release", "controlled", "emergency"]


@given(st.lists(st.tuples(st.integers(1, 60), st.binary(min_size=8, max_size=8)), max_size=40))
def test_the_share_is_a_share_and_releases_only_on_an_accepted_release(
        frames: list[tuple[int, bytes]]) -> None:
    chk = BrakeFrameChecker()
    t = 0.0
    for step_ms, data in frames:
        t += step_ms / 1000
        v = chk.feed(t, 0x050, data)
        assert v is not None
        share = chk.deceleration_share(t)
        assert 0.0 <= share <= 1.0
        if share < 1.0:  # anything short of an emergency brake comes from an accepted frame
            assert chk.last_brake is not None and chk.last_brake.deceleration_share == share
            assert v.share is None or v.accepted


@pytest.mark.parametrize("unknown", [3, 255])
def test_brake_applied_right_after_an_unknown_request_that_follows_a_release(
        unknown: int) -> None:
    # was a hole: the release frame, 10 ms old, still counted, so the controller kept
    # releasing for up to 50 ms after the unit had said something it does not know
    chk = BrakeFrameChecker()
    chk.feed(0.000, 0x050, armed(0))
    chk.feed(0.010, 0x050, raw_brake(unknown, 1))
    assert chk.brake_applied(0.010)
    assert chk.brake_applied(0.030)
