"""One test per rule of PROTOCOL.md section 3 (and the timing rules of section 4), run
through the cffi build of the C core. Names follow the rules."""

from __future__ import annotations

import math
import struct

import pytest

from core_util import (
    ARMED,
    BOOT,
    BRAKE_ID,
    FAULT,
    MS,
    NONE,
    STATUS_ID,
    STOP_ID,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    Unit,
    packet,
    reply_fields,
    request,
)
from estop.core import Config

ACK, NAK = 0x80, 0x81
RELEASE, STATUS = 2, 1


# -- 3. The unit boots STOPPED with reason boot ---------------------------------------------
def test_boots_stopped_with_reason_boot() -> None:
    u = Unit()
    assert (u.state, u.reason) == (STOPPED, BOOT)
    (t, first), = u.brake_frames()[:1]
    assert t == 0 and first[:4] == bytes([1, 100, STOPPED, BOOT])
    assert u.wd.status().counters.stops[BOOT] == 1


# -- 3. STOPPED is latched: nothing but an accepted RELEASE leaves it -------------------------
def test_stopped_is_latched_against_everything_but_release() -> None:
    u = Unit()
    u.drive(10)  # live, neutral link
    u.ask(STATUS)
    u.ask(STOP_ID)
    u.wait(5 * 1000 * MS)
    u.wd.fault(u.t)
    for gas in (0.0, -1.0, 1.0):
        u.udp(packet(gas))
    assert u.state == STOPPED
    u.drive(5)
    assert u.ask(RELEASE)[5] == 0
    assert u.state == ARMED


# -- 3. RELEASE needs a live link ... otherwise NAK 2 -----------------------------------------
def test_release_refused_without_any_packet_nak_2() -> None:
    u = Unit()
    assert u.ask(RELEASE)[0::5] == (NAK, 2)
    assert u.state == STOPPED


def test_release_refused_with_fewer_than_five_packets_since_boot_nak_2() -> None:
    u = Unit()
    u.drive(4)
    assert u.ask(RELEASE)[5] == 2
    u.drive(1)
    assert u.ask(RELEASE)[5] == 0


def test_release_refused_when_last_packet_is_timeout_old_nak_2() -> None:
    u = Unit()
    u.drive(5)
    u.wait(200 * MS)  # exactly the timeout: no longer "less than the timeout ago"
    assert u.ask(RELEASE)[5] == 2
    u2 = Unit()
    u2.drive(5)
    u2.wait(200 * MS - 1)
    assert u2.ask(RELEASE)[5] == 0


def test_release_count_restarts_after_every_stop() -> None:
    u = Unit()
    u.arm()
    u.ask(STOP_ID)
    u.drive(4)
    assert u.ask(RELEASE)[5] == 2
    u.drive(1)
    assert u.ask(RELEASE)[5] == 0


def test_release_needs_five_packets_since_the_link_was_last_silent() -> None:
    """Version 2: 5 packets, 10 s of silence, 1 packet, RELEASE must be NAK 2 (it was ACKed)."""
    u = Unit()
    u.drive(5)
    u.wait(10 * 1000 * MS)
    u.drive(1)
    assert u.ask(RELEASE)[0::5] == (NAK, 2)
    assert u.wd.status().valid_run == 1
    u.drive(3)
    assert u.ask(RELEASE)[5] == 2
    u.drive(1)
    assert u.ask(RELEASE)[0::5] == (ACK, 0)


def test_silence_just_short_of_the_timeout_keeps_the_count() -> None:
    u = Unit()
    u.drive(4)
    u.drive(1, gap=200 * MS - 1)
    assert u.ask(RELEASE)[5] == 0


def test_silence_of_exactly_the_timeout_restarts_the_count() -> None:
    u = Unit()
    u.drive(4)
    u.drive(1, gap=200 * MS)
    assert u.ask(RELEASE)[5] == 2
    assert u.wd.status().valid_run == 1


# -- 3. ... and a neutral latest packet (gas_brake <= 0), otherwise NAK 3 ---------------------
@pytest.mark.parametrize("gas", [1e-45, 0.01, 0.5, 1.0])
def test_release_refused_when_latest_packet_not_neutral_nak_3(gas: float) -> None:
    u = Unit()
    u.drive(5)
    u.udp(packet(gas))
    assert u.ask(RELEASE)[0::5] == (NAK, 3)
    assert u.state == STOPPED


@pytest.mark.parametrize("gas", [0.0, -0.0, -1e-45, -0.5, -1.0])
def test_release_accepted_when_live_and_neutral(gas: float) -> None:
    u = Unit()
    u.drive(5, gas=0.8)
    u.udp(packet(gas))
    msg, seq, state, reason, flags, nak = u.ask(RELEASE, seq=77)
    assert (msg, seq, state, reason, flags, nak) == (ACK, 77, ARMED, NONE, 0, 0)


def test_no_live_link_is_checked_before_neutral() -> None:
    u = Unit()
    u.drive(3, gas=0.5)
    assert u.ask(RELEASE)[5] == 2


# -- 3. A RELEASE while ARMED is acknowledged and changes nothing -----------------------------
def test_release_while_armed_is_acked_and_changes_nothing() -> None:
    u = Unit()
    u.arm()
    u.udp(packet(0.9))  # not neutral: still just an ACK
    n = len(u.frames)
    assert u.ask(RELEASE)[0::5] == (ACK, 0)
    assert u.state == ARMED and len(u.frames) == n


# -- 3. ARMED -> STOPPED, reason tcp stop ---------------------------------------------------
def test_stop_frame_stops_armed_unit_with_reason_tcp_stop() -> None:
    u = Unit()
    u.arm()
    n = len(u.frames)
    msg, seq, state, reason, _flags, nak = u.ask(STOP_ID, seq=9)
    assert (msg, seq, state, reason, nak) == (ACK, 9, STOPPED, TCP_STOP, 0)
    t, i, data = u.frames[n]
    assert (t, i) == (u.t, BRAKE_ID) and data[:4] == bytes([1, 100, STOPPED, TCP_STOP])


def stop_datagram(msg_id: int = STOP_ID, tail: bytes = bytes(40)) -> bytes:
    """A 48-byte request frame (PROTOCOL.md 5.2) as sent over UDP; the tail is everything after
    the msg_id (seq, remote id, session, counter, tag), here whatever the caller likes."""
    return b"ESQ2" + struct.pack("<I", msg_id) + tail


@pytest.mark.parametrize("tail", [bytes(40), bytes(range(40)), b"\xff" * 40])
def test_stop_datagram_stops_an_armed_unit_whatever_its_tag(tail: bytes) -> None:
    u = Unit()
    u.arm()
    step = u.udp(stop_datagram(tail=tail))
    assert step.state_changed and (u.state, u.reason) == (STOPPED, TCP_STOP)
    assert step.frames[-1].data[:4] == bytes([1, 100, STOPPED, TCP_STOP])
    assert step.reply is None  # no reply over UDP
    st = u.wd.status()
    assert st.counters.udp_stops == 1 and st.counters.udp_invalid == 0
    assert st.valid_run == 0  # like every stop, it restarts the release count


def test_stop_datagram_while_stopped_keeps_the_first_reason() -> None:
    u = Unit()
    u.udp(stop_datagram())
    assert (u.state, u.reason) == (STOPPED, BOOT)


@pytest.mark.parametrize("frame", [
    stop_datagram(msg_id=1), stop_datagram(msg_id=2), stop_datagram(msg_id=0xE570E571),
    stop_datagram()[:47], stop_datagram() + b"\x00", b"ESQ3" + stop_datagram()[4:],
])
def test_other_request_datagrams_are_invalid_and_do_not_stop(frame: bytes) -> None:
    u = Unit()
    u.arm()
    u.udp(frame)
    assert u.state == ARMED
    counters = u.wd.status().counters
    assert (counters.udp_invalid, counters.udp_stops) == (1, 0)


def test_stop_id_is_configurable() -> None:
    u = Unit(Config(stop_id=0x12345678))
    u.arm()
    assert u.ask(STOP_ID)[5] == 1  # the default id is now unknown
    assert u.ask(0x12345678)[2:4] == (STOPPED, TCP_STOP)


# -- 3. ARMED -> STOPPED, reason udp timeout, at the deadline itself --------------------------
def test_timeout_stops_at_the_deadline_itself() -> None:
    u = Unit()
    u.arm()
    last = u.t
    step = u.wd.tick(u.t)
    assert step.next_call_us <= last + 200 * MS
    u.at(last + 200 * MS - 1)
    assert u.state == ARMED
    u.at(last + 200 * MS)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    stop_frames = [t for t, d in u.brake_frames() if d[3] == UDP_TIMEOUT]
    assert stop_frames[0] == last + 200 * MS


def test_deadline_is_a_call_time_the_core_asks_for() -> None:
    u = Unit()
    u.arm()
    last = u.t
    times = []
    while u.state == ARMED:
        nxt = u.wd.tick(u.t).next_call_us
        times.append(nxt)
        u.t = nxt
        u.wd.tick(nxt)
    assert last + 200 * MS in times


@pytest.mark.parametrize("timeout_ms", [1, 20, 200, 1000])
def test_timeout_follows_configuration(timeout_ms: int) -> None:
    u = Unit(Config(timeout_us=timeout_ms * MS))
    u.drive(5, gap=timeout_ms * MS // 2)
    assert u.ask(RELEASE)[5] == 0
    last = u.t
    u.at(last + timeout_ms * MS)
    assert u.reason == UDP_TIMEOUT


def test_only_valid_packets_keep_the_unit_alive() -> None:
    u = Unit()
    u.arm()
    last = u.t
    bad = [b"", b"\x00" * 19, packet() + b"\x00", packet(gas=math.nan), packet(gear=3),
           packet(turn=4), packet(horn=2), packet(steer=math.inf)]
    t = last
    while t < last + 200 * MS - 10 * MS:
        t += 5 * MS
        u.at(t)
        for b in bad:
            u.udp(b)
    u.at(last + 200 * MS)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    assert u.wd.status().counters.udp_invalid >= 30 * len(bad)


@pytest.mark.parametrize("length", [0, 1, 8, 15, 17, 18, 19, 21, 24, 64])
def test_packets_of_other_lengths_are_invalid(length: int) -> None:
    good = packet() + packet()  # every prefix starts like a valid neutral packet
    u = Unit()
    u.udp(good[:length])
    counters = u.wd.status().counters
    assert (counters.udp_valid, counters.udp_invalid) == (0, 1)


def test_old_16_byte_packet_keeps_the_unit_alive() -> None:
    u = Unit()
    u.arm()
    legacy = struct.pack("<ffii", 0.0, 0.0, 4, 0)
    for _ in range(10):
        u.wait(100 * MS)
        u.udp(legacy)
    assert u.state == ARMED


# -- 3. ARMED -> STOPPED, reason fault ------------------------------------------------------
def test_fault_stops_armed_unit_with_reason_fault() -> None:
    u = Unit()
    u.arm()
    step = u.wd.fault(u.t)
    assert step.state_changed and (step.state, step.reason) == (STOPPED, FAULT)
    assert step.frames[0].data[:4] == bytes([1, 100, STOPPED, FAULT])


def test_fault_while_stopped_keeps_the_first_reason() -> None:
    u = Unit()
    u.arm()
    u.ask(STOP_ID)
    u.wd.fault(u.t)
    assert u.reason == TCP_STOP and u.wd.status().counters.faults == 1


# -- 3. A STOP while already STOPPED is acknowledged and keeps the first reason ---------------
def test_stop_while_stopped_is_acked_and_keeps_first_reason() -> None:
    u = Unit()
    assert u.ask(STOP_ID)[0:4:2] == (ACK, STOPPED) and u.reason == BOOT
    u.arm()
    u.wait(200 * MS)
    assert u.reason == UDP_TIMEOUT
    assert u.ask(STOP_ID)[2:] == (STOPPED, UDP_TIMEOUT, 0, 0)


# -- 3. Flags: link degraded at the warn time -----------------------------------------------
def test_link_degraded_flag_at_warn_time() -> None:
    u = Unit()
    u.arm()
    last = u.t
    u.at(last + 100 * MS - 1)
    assert u.ask(STATUS)[4] == 0
    u.at(last + 100 * MS)
    assert u.ask(STATUS)[4] == 1
    u.at(last + 110 * MS)
    assert u.brake_frames()[-1][1][4] == 1
    u.udp(packet())
    assert u.ask(STATUS)[4] == 0


def test_link_degraded_flag_is_never_set_while_stopped() -> None:
    u = Unit()
    u.drive(1)
    u.wait(150 * MS)
    assert u.ask(STATUS)[4] == 0


# -- 2. TCP framing -------------------------------------------------------------------------
def test_unknown_msg_id_is_answered_with_nak_1() -> None:
    u = Unit()
    u.arm()
    for msg_id in (0, 4, 0x80, 0x81, 0xFFFFFFFF):
        assert u.ask(msg_id, seq=msg_id)[0:2] + u.ask(msg_id)[5:] == (NAK, msg_id, 1)
    assert u.state == ARMED and u.wd.status().counters.tcp_unknown_id == 10


def test_bad_crc_closes_the_connection_and_is_counted() -> None:
    u = Unit()
    u.arm()
    bad = bytearray(request(STOP_ID))
    bad[12] ^= 0xFF
    steps = u.send(bytes(bad) + request(STOP_ID))
    assert steps[-1].close and all(s.reply is None for s in steps)
    assert u.state == ARMED  # a broken frame is no stop: the stream lost framing
    assert u.wd.status().counters.tcp_bad_crc == 1


def test_frames_split_byte_by_byte_are_reassembled() -> None:
    u = Unit()
    u.arm()
    frame = request(STOP_ID, seq=5)
    replies = []
    for b in frame:
        replies += [s.reply for s in u.send(bytes([b])) if s.reply]
    assert len(replies) == 1 and reply_fields(replies[0])[1:4] == (5, STOPPED, TCP_STOP)


def test_several_frames_in_one_read_each_get_one_reply() -> None:
    u = Unit()
    u.drive(5)
    steps = u.send(request(STATUS, 1) + request(RELEASE, 2) + request(STOP_ID, 3) + b"\x01")
    replies = [reply_fields(s.reply) for s in steps if s.reply]
    assert [(r[1], r[2], r[3]) for r in replies] == [
        (1, STOPPED, BOOT), (2, ARMED, NONE), (3, STOPPED, TCP_STOP)]


def test_request_arg_is_ignored() -> None:
    u = Unit()
    u.arm()
    u.send(request(STOP_ID, arg=0xDEAD))
    assert u.reason == TCP_STOP


def test_any_of_several_clients_may_stop() -> None:
    u = Unit()
    for slot in range(1, 8):
        u.wd.tcp_open(slot, u.t)
    u.arm()
    steps = u.wd.tcp_data(6, request(STOP_ID), u.t)
    assert steps[-1].state == STOPPED


# -- 4. CAN timing --------------------------------------------------------------------------
def test_brake_frame_every_period_in_every_state() -> None:
    u = Unit()
    u.wait(95 * MS)
    u.arm()
    u.wait(100 * MS)
    times = [t for t, _ in u.brake_frames()]
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert max(gaps) <= 10 * MS and len(times) >= 20


def test_brake_frame_at_once_on_state_change_restarts_period() -> None:
    u = Unit()
    u.drive(5, gap=7 * MS)
    before = len(u.brake_frames())
    t0 = u.t
    u.ask(RELEASE)
    frames = u.brake_frames()
    assert frames[before][0] == t0 and frames[before][1][2] == ARMED
    u.wait(10 * MS)
    assert [t for t, _ in u.brake_frames(t0 + 1)] == [t0 + 10 * MS]


def test_status_frame_every_100_ms_with_own_counter() -> None:
    u = Unit()
    u.wait(1000 * MS)
    status = [(t, d) for t, i, d in u.frames if i == STATUS_ID]
    assert [t for t, _ in status] == [k * 100 * MS for k in range(11)]
    assert [d[6] for _, d in status] == list(range(11))


def test_alive_counter_runs_0_to_14_then_back_to_0() -> None:
    u = Unit()
    u.wait(400 * MS)
    counters = [d[6] for _, d in u.brake_frames()]
    assert counters[:17] == list(range(15)) + [0, 1]
    assert 15 not in counters


def test_status_frame_reports_window_counts_and_link_age() -> None:
    u = Unit()
    u.at(20 * MS)
    for _ in range(3):
        u.udp(packet())
    u.udp(b"junk")
    u.at(100 * MS)
    data = [d for t, i, d in u.frames if i == STATUS_ID][-1]
    assert data[0:4] == bytes([3, 1, 0, 0])
    assert struct.unpack("<H", data[4:6])[0] == 80
    u.at(400 * MS)
    data = [d for t, i, d in u.frames if i == STATUS_ID][-1]
    assert data[0:2] == bytes([0, 0]) and data[4:6] == b"\xff\xff"


def test_next_call_is_never_later_than_the_next_brake_frame() -> None:
    u = Unit()
    for k in range(50):
        step = u.wd.tick(u.t)
        assert step.next_call_us - u.t <= 10 * MS
        u.wait((k * 7919) % (10 * MS) + 1)
