"""One test per rule that protocol version 3 added to section 3: LIFT (a stop request with its
own reason, by TCP and by lift datagram) and the two-stage answer to silence (SLOWING at the
slow time S, not latched; STOPPED at the timeout T), through the cffi build of the C core."""

from __future__ import annotations

import struct

import pytest

from core_util import (
    ARMED,
    BOOT,
    BRAKE_ID,
    FAULT,
    LIFT,
    LIFT_ID,
    MS,
    NONE,
    SLOWING,
    STATUS_ID,
    STOP_ID,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    Unit,
    packet,
    request,
)
from estop.core import Config, Watchdog, default_warn_us
from estop.protocol import auth
from estop.protocol.udp import ControlPacket

ACK, NAK = 0x80, 0x81
RELEASE, STATUS = 2, 1
S, T, W = 200 * MS, 1000 * MS, 100 * MS
TWO_STAGE = Config(timeout_us=T, slow_us=S, warn_us=W, slow_level=30)


def lift_datagram(tail: bytes = bytes(40)) -> bytes:
    return b"ESQ2" + struct.pack("<I", LIFT_ID) + tail


def armed(config: Config = TWO_STAGE) -> Unit:
    u = Unit(config)
    u.arm()
    return u


def brake_bytes(u: Unit, since: int = 0) -> list[tuple[int, bytes]]:
    return [(t, d[:5]) for t, d in u.brake_frames(since)]


# -- LIFT (msg_id 3, reason 5): a stop request anyone may send ---------------------------------
def test_lift_frame_stops_an_armed_unit_with_reason_lift() -> None:
    u = armed(Config())
    n = len(u.frames)
    msg, seq, state, reason, _flags, nak = u.ask(LIFT_ID, seq=4)
    assert (msg, seq, state, reason, nak) == (ACK, 4, STOPPED, LIFT, 0)
    t, can_id, data = u.frames[n]
    assert (t, can_id) == (u.t, BRAKE_ID) and data[:4] == bytes([1, 100, STOPPED, LIFT])
    st = u.wd.status()
    assert st.counters.stops[LIFT] == 1 and st.counters.tcp_unknown_id == 0
    assert st.valid_run == 0  # like every stop, it restarts the release count


@pytest.mark.parametrize("tail", [bytes(40), bytes(range(40)), b"\xff" * 40])
@pytest.mark.parametrize("key", [None, bytes(range(32))])
def test_lift_datagram_stops_whatever_its_tag(tail: bytes, key: bytes | None) -> None:
    u = Unit(Config(key=key))
    if key is None:
        u.arm()
    else:
        for counter in range(1, 6):
            u.wait(20 * MS)
            u.udp(auth.AuthControlPacket(7, u.wd.config.session, counter,
                                         ControlPacket()).encode(key))
        u.send(auth.AuthRequest(RELEASE, 1, 7, u.wd.config.session, 6).encode(key))
        assert u.state == ARMED
    step = u.udp(lift_datagram(tail))
    assert step.state_changed and step.reply is None
    assert (u.state, u.reason) == (STOPPED, LIFT)
    assert u.wd.status().counters.udp_stops == 1


@pytest.mark.parametrize("key", [None, bytes(range(32))])
def test_lift_request_frame_with_a_forged_tag_stops(key: bytes | None) -> None:
    u = armed(Config()) if key is None else Unit(Config(key=key))
    if key is not None:  # a keyed unit can only be stopped here, from boot: the reason stays
        u.send(auth.AuthRequest(LIFT_ID, 1, 9, 0, 1).encode(bytes(32)))
        assert (u.state, u.reason) == (STOPPED, BOOT)
        return
    steps = u.send(auth.AuthRequest(LIFT_ID, 1, 9, 0, 1).encode(bytes(32)))
    assert [s.reply for s in steps if s.reply][0][15] == 0  # ACK, nak code 0
    assert (u.state, u.reason) == (STOPPED, LIFT)


def test_lift_while_stopped_is_acked_and_keeps_the_first_reason() -> None:
    u = armed(Config())
    u.ask(STOP_ID)
    assert u.ask(LIFT_ID)[0:4] == (ACK, 1, STOPPED, TCP_STOP)
    u.udp(lift_datagram())
    assert (u.state, u.reason) == (STOPPED, TCP_STOP)
    assert Unit().ask(LIFT_ID)[2:4] == (STOPPED, BOOT)


def test_stop_id_may_not_be_lift() -> None:
    with pytest.raises(Exception, match="bad_stop_id"):
        Watchdog(Config(stop_id=LIFT_ID))


# -- the defaults keep version 2: S = T, W = S/2 ------------------------------------------------
def test_default_slow_time_is_the_timeout_and_never_slows() -> None:
    u = armed(Config())
    last = u.t
    states = []
    while u.t < last + 200 * MS:
        u.wait(MS)
        states.append(u.state)
    assert set(states[:-1]) == {ARMED} and (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    assert all(d[0] != 2 for _, d in u.brake_frames())
    assert u.wd.status().counters.slowdowns == 0


@pytest.mark.parametrize(("slow_us", "warn_us"), [
    (200_000, 100_000), (201_000, 100_000), (200_999, 100_000), (3_000, 1_000),
    (1_999, 1_000), (1_000, 1_000), (999, 999), (1, 1)])
def test_default_warn_time_is_half_the_slow_time_in_whole_ms(slow_us: int, warn_us: int) -> None:
    """Half the slow time, rounded down to a whole millisecond; where that is 0 ms (a slow
    time under 2 ms) it would break 0 < W, so it is 1 ms or the slow time if that is shorter."""
    assert default_warn_us(slow_us) == warn_us
    cfg = Config(timeout_us=max(slow_us, 1000), slow_us=slow_us)
    assert cfg.effective_warn_us == warn_us
    Watchdog(cfg)  # the core accepts it


# -- ARMED -> SLOWING at the slow time, at the deadline itself ---------------------------------
def test_slowing_starts_at_the_slow_time_itself() -> None:
    u = armed()
    last = u.t
    assert u.wd.tick(u.t).next_call_us <= last + S
    u.at(last + S - 1)
    assert u.state == ARMED
    n = len(u.brake_frames())
    step = u.wd.tick(last + S)
    u.t = last + S
    assert step.state_changed and step.changed_by_clock
    assert (step.state, step.reason, step.flags) == (SLOWING, NONE, 1)
    assert step.frames[0].data[:5] == bytes([2, 30, SLOWING, NONE, 1])
    assert len(u.brake_frames()) == n
    assert u.wd.status().counters.slowdowns == 1


def test_slowing_deadline_is_a_call_time_the_core_asks_for() -> None:
    u = armed()
    last = u.t
    times = []
    while u.state != STOPPED:
        nxt = u.wd.tick(u.t).next_call_us
        times.append(nxt)
        u.t = nxt
        u.wd.tick(nxt)
    assert last + S in times and last + T in times


def test_a_packet_at_exactly_the_slow_time_is_too_late() -> None:
    u = armed()
    last = u.t
    u.at(last + S - 1)
    u.t = last + S
    step = u.udp(packet())
    assert step.state_changed and step.state == SLOWING  # slowed first, then counted 1 of 3
    assert [f.data[0] for f in step.frames if f.can_id == BRAKE_ID] == [2]


@pytest.mark.parametrize("level", [1, 30, 99])
def test_slowing_brakes_at_the_slow_level(level: int) -> None:
    u = armed(Config(timeout_us=T, slow_us=S, slow_level=level))
    u.wait(S + 50 * MS)
    frames = [d for t, d in u.brake_frames() if d[2] == SLOWING]
    assert len(frames) >= 5
    assert all((d[0], d[1], d[3]) == (2, level, NONE) for d in frames)


# -- SLOWING -> ARMED after 3 valid packets, however far apart ---------------------------------
def test_three_valid_packets_end_slowing() -> None:
    u = armed()
    u.wait(S + 10 * MS)
    assert u.state == SLOWING
    for expected in (SLOWING, SLOWING, ARMED):
        u.wait(20 * MS)
        step = u.udp(packet())
        assert u.state == expected
    assert step.state_changed and not step.changed_by_clock
    assert step.frames[-1].data[:4] == bytes([0, 0, ARMED, NONE])
    counters = u.wd.status().counters
    assert (counters.slowdowns, counters.rearms, counters.releases_accepted) == (1, 1, 1)


def test_packets_toward_armed_count_together_however_far_apart() -> None:
    u = armed()
    u.wait(S)
    for _ in range(2):
        u.udp(packet())
        u.wait(S + 100 * MS)  # silent for longer than S again, still shorter than T
        assert u.state == SLOWING
    u.udp(packet())
    assert u.state == ARMED
    assert u.wd.status().counters.slowdowns == 1  # one controlled stop, never left


def test_invalid_and_forged_packets_do_not_end_slowing() -> None:
    key = bytes(range(32))
    u = Unit(Config(timeout_us=T, slow_us=S, key=key))
    session = u.wd.config.session
    for counter in range(1, 6):
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(7, session, counter, ControlPacket()).encode(key))
    u.send(auth.AuthRequest(RELEASE, 1, 7, session, 6).encode(key))
    assert u.state == ARMED
    u.wait(S)
    forged = [packet(), b"junk", auth.AuthControlPacket(7, session, 99, ControlPacket())
              .encode(bytes(32)), auth.AuthControlPacket(7, session, 5, ControlPacket())
              .encode(key)]  # plain, garbage, wrong key, replayed counter
    for datagram in forged * 3:
        u.wait(MS)
        u.udp(datagram)
    assert u.state == SLOWING
    # The forgeries spent remote 7's tag checks for their window (docs/PROTOCOL.md 5, bounded
    # cost): the remote's own packets, at its rate, are checked from the next window on.
    for counter in range(7, 10):
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(7, session, counter, ControlPacket()).encode(key))
    assert u.state == ARMED


def test_slowing_again_counts_afresh() -> None:
    u = armed()
    u.wait(S)
    u.udp(packet())
    u.udp(packet())
    u.udp(packet())
    assert u.state == ARMED
    u.wait(S)
    assert u.state == SLOWING
    u.udp(packet())
    u.udp(packet())
    assert u.state == SLOWING  # 2 of 3 since this SLOWING began
    u.udp(packet())
    assert u.state == ARMED
    assert u.wd.status().counters.slowdowns == 2


# -- SLOWING -> STOPPED: the timeout, a stop request, a fault ----------------------------------
def test_timeout_stops_a_slowing_unit_at_the_deadline_itself() -> None:
    u = armed()
    last = u.t
    u.at(last + T - 1)
    assert u.state == SLOWING
    u.at(last + T)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    stops = [t for t, d in u.brake_frames() if d[3] == UDP_TIMEOUT]
    assert stops[0] == last + T
    ls = u.wd.link_stats()
    assert (ls.slowdowns, ls.timeouts) == (1, 1)


def test_a_packet_while_slowing_moves_the_timeout() -> None:
    u = armed()
    u.wait(S + MS)
    u.udp(packet())
    last = u.t
    u.at(last + T - 1)
    assert u.state == SLOWING
    u.at(last + T)
    assert u.reason == UDP_TIMEOUT


@pytest.mark.parametrize(("how", "reason"), [
    ("stop", TCP_STOP), ("lift", LIFT), ("lift_datagram", LIFT), ("fault", FAULT)])
def test_stop_requests_and_faults_stop_a_slowing_unit(how: str, reason: int) -> None:
    u = armed()
    u.wait(S + 5 * MS)
    assert u.state == SLOWING
    if how == "stop":
        assert u.ask(STOP_ID)[2:4] == (STOPPED, TCP_STOP)
    elif how == "lift":
        assert u.ask(LIFT_ID)[2:4] == (STOPPED, LIFT)
    elif how == "lift_datagram":
        u.udp(lift_datagram())
    else:
        u.frames += [(u.t, f.can_id, f.data) for f in u.wd.fault(u.t).frames]
    assert (u.state, u.reason) == (STOPPED, reason)
    assert u.brake_frames()[-1][1][:4] == bytes([1, 100, STOPPED, reason])


def test_a_late_call_past_both_deadlines_goes_straight_to_stopped() -> None:
    u = armed()
    last = u.t
    step = u.wd.tick(last + T + 5 * MS)
    u.t = last + T + 5 * MS
    assert step.changed_by_clock and (step.state, step.reason) == (STOPPED, UDP_TIMEOUT)
    assert [f.data[0] for f in step.frames if f.can_id == BRAKE_ID] == [1]
    assert u.wd.status().counters.slowdowns == 0


def test_stopped_never_slows() -> None:
    u = Unit(TWO_STAGE)
    u.drive(5)
    u.wait(S + 10 * MS)
    assert (u.state, u.reason) == (STOPPED, BOOT)


# -- RELEASE and STATUS while SLOWING ----------------------------------------------------------
def test_release_while_slowing_is_acked_and_changes_nothing() -> None:
    u = armed()
    u.wait(S + 5 * MS)
    msg, _seq, state, reason, flags, nak = u.ask(RELEASE)
    assert (msg, state, reason, flags, nak) == (ACK, SLOWING, NONE, 1, 0)
    assert u.state == SLOWING
    assert u.wd.status().counters.releases_accepted == 1  # only the one that armed it


def test_a_stop_in_the_call_that_slows_the_unit_reports_both_changes() -> None:
    """Issue 25, item 5: a stop datagram whose call is the first past S: the clock moves the
    unit ARMED -> SLOWING, then the datagram SLOWING -> STOPPED. The core tells both (the state
    after the clock's part, then the state after the input), so that a host logs two changes,
    each with its cause, and sends both brake frames."""
    u = armed()
    u.t += S + 5 * MS  # no tick in between
    step = u.udp(auth.stop_datagram(1, 0, key=None))
    assert step.changed_by_clock and (step.clock_state, step.clock_reason) == (SLOWING, NONE)
    assert (step.state, step.reason) == (STOPPED, TCP_STOP)
    assert [f.data[2] for f in step.frames if f.can_id == BRAKE_ID] == [SLOWING, STOPPED]
    step = u.udp(auth.stop_datagram(1, 0, key=None))  # nothing changes: the clock's is the end
    assert (step.clock_state, step.clock_reason) == (step.state, step.reason) == (STOPPED, TCP_STOP)


def test_a_release_in_the_call_that_slows_the_unit_is_not_counted_as_accepted() -> None:
    """Issue 25, item 5: the RELEASE's own call moves the clock past S (ARMED -> SLOWING, a
    change from the clock), then the RELEASE finds the unit SLOWING: acknowledged, nothing
    more changes. It was counted as accepted (the state had changed in that call)."""
    u = armed()
    u.t += S + 5 * MS  # no tick in between: the RELEASE's call is the first past S
    steps = u.send(request(RELEASE))
    assert steps[-1].changed_by_clock and steps[-1].state == SLOWING
    c = u.wd.status().counters
    assert (c.releases_accepted, c.releases_refused, c.slowdowns) == (1, 0, 1)


def test_status_reports_state_2_with_the_degraded_flag() -> None:
    u = armed()
    u.wait(S + 5 * MS)
    assert u.ask(STATUS)[2:5] == (SLOWING, NONE, 1)


def test_link_degraded_flag_while_slowing_with_warn_after_slow() -> None:
    """W = S: the flag and the slow-down start together."""
    u = armed(Config(timeout_us=T, slow_us=S, warn_us=S))
    u.at(u.t + S - 1)
    assert u.wd.status().flags == 0
    u.wait(1)
    assert (u.state, u.wd.status().flags) == (SLOWING, 1)


# -- ESTOP_STATUS byte 3: stops (bits 0-3) and slow-downs (bits 4-7) per window ----------------
def test_status_frame_counts_slowdowns_and_stops_per_window() -> None:
    u = Unit(Config(timeout_us=T, slow_us=20 * MS, warn_us=10 * MS))
    u.at(60 * MS)
    u.drive(5, gap=5 * MS)
    u.ask(RELEASE)
    u.at(100 * MS)  # status frame: the window held no stop and no slow-down
    for _ in range(2):  # two slow-downs within the next window (at 105 and 141 ms), a stop
        u.wait(21 * MS)
        for _ in range(3):
            u.udp(packet())
    u.ask(STOP_ID)
    u.at(200 * MS)
    status = [d for t, i, d in u.frames if i == STATUS_ID]
    assert status[-2][3] == 0
    assert status[-1][3] == 0x21  # slow-downs 2 (high nibble), stops 1 (low nibble)
    u.at(300 * MS)
    assert [d for t, i, d in u.frames if i == STATUS_ID][-1][3] == 0


def test_status_frame_nibbles_saturate_at_15() -> None:
    u = Unit(Config(timeout_us=T, slow_us=MS, warn_us=MS))
    u.at(5 * MS)
    u.drive(5, gap=MS // 2)
    u.ask(RELEASE)
    for _ in range(20):  # 20 slow-downs and a stop before the next status frame
        u.wait(MS)
        for _ in range(3):
            u.udp(packet())
    u.ask(STOP_ID)
    assert u.t < 100 * MS
    u.at(100 * MS)
    assert [d for t, i, d in u.frames if i == STATUS_ID][-1][3] == 0xF1
    assert u.wd.status().counters.slowdowns == 20


def test_release_of_a_link_older_than_the_slow_time_goes_straight_to_slowing() -> None:
    """The link check of a RELEASE looks at the timeout, so a link silent for longer than the
    slow time (but less than the timeout) passes it; its slow-down is then already due. The
    unit goes from STOPPED straight to SLOWING: no frame ever releases the brake for a link
    that has been silent for S (found by the fuzzer: ARMED past the slow time)."""
    u = Unit(TWO_STAGE)
    u.drive(5)
    u.wait(S + 50 * MS)
    n = len(u.frames)
    msg, _seq, state, reason, flags, nak = u.ask(RELEASE)
    assert (msg, state, reason, flags, nak) == (ACK, SLOWING, NONE, 1, 0)
    new = [d for _t, i, d in u.frames[n:] if i == BRAKE_ID]
    assert [d[:3] for d in new] == [bytes([2, 30, SLOWING])]  # one frame, never a release
    counters = u.wd.status().counters
    assert (counters.releases_accepted, counters.slowdowns) == (1, 1)
    for _ in range(3):
        u.udp(packet())
    assert u.state == ARMED


@pytest.mark.parametrize(("age", "state"), [(S - 1, ARMED), (S, SLOWING)])
def test_release_at_the_edge_of_the_slow_time(age: int, state: int) -> None:
    """A link exactly S old has been silent for the slow time: the RELEASE arms into SLOWING;
    a microsecond younger, into ARMED."""
    u = Unit(TWO_STAGE)
    u.drive(5)
    u.wait(age)
    assert u.ask(RELEASE)[2] == state
