"""PROTOCOL.md section 5 through the cffi build of the C core: only the key holder may keep the
unit alive or release it; anyone may stop. Frames are made and checked with estop.protocol.auth
(hashlib), written apart from the C code."""

from __future__ import annotations

import struct

import pytest

from core_util import (
    ARMED,
    BOOT,
    MS,
    STOP_ID,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    Unit,
    packet,
    request,
)
from estop.core import TEST_SESSION, Config, Watchdog, ffi
from estop.protocol import auth
from estop.protocol.udp import ControlPacket, Gear
from vectors import AUTH_CONTROL_EXAMPLE as V_CONTROL  # section 5.4, byte for byte
from vectors import AUTH_RELEASE_EXAMPLE as V_RELEASE
from vectors import AUTH_STATUS_EXAMPLE as V_STATUS
from vectors import AUTH_STATUS_REPLY_EXAMPLE as V_STATUS_REPLY
from vectors import AUTH_STOP_EXAMPLE as V_STOP

K = bytes(range(32))
N = 0x0123456789ABCDEF
RID = 7
RELEASE, STATUS = 2, 1
NAK_NOT_AUTH = 4



class Keyed(Unit):
    """A unit with the key K and session N, and a remote that counts its messages: one counter
    for both channels (section 5), as the unit expects of a RELEASE (issue 25, item 2)."""

    def __init__(self, key: bytes | None = K, session: int = N) -> None:
        super().__init__(Config(key=key, session=session))
        self.key = key
        self.counter = 0

    def heartbeat(self, gas: float = 0.0, *, rid: int = RID, key: bytes | None = K,
                  session: int = N, counter: int | None = None) -> bytes:
        if counter is None:
            self.counter += 1
            counter = self.counter
        body = ControlPacket(gas_brake=gas, gear=Gear.NEUTRAL)
        return auth.AuthControlPacket(rid, session, counter, body).encode(key)

    def drive_auth(self, n: int = 5, gas: float = 0.0, gap: int = 20 * MS) -> None:
        for _ in range(n):
            self.wait(gap)
            self.udp(self.heartbeat(gas))

    def frame(self, msg_id: int, seq: int = 1, *, rid: int = RID, key: bytes | None = K,
              session: int = N, counter: int | None = None) -> bytes:
        if counter is None:
            self.counter += 1
            counter = self.counter
        return auth.AuthRequest(msg_id, seq, rid, session, counter).encode(key)

    def ask_frame(self, frame: bytes) -> auth.AuthReply:
        steps = self.send(frame)
        replies = [s.reply for s in steps if s.reply is not None]
        assert len(replies) == 1 and len(replies[0]) == 48
        # A genuine reply verifies under the key for exactly this request (zero tag: no key).
        return auth.AuthReply.decode(replies[0], self.key, auth.request_tag(frame))


# -- 5.4 test vectors through the core ----------------------------------------------------------
def test_vector_status_reply_from_a_freshly_booted_unit() -> None:
    u = Keyed()
    steps = u.send(V_STATUS)
    assert [s.reply for s in steps if s.reply] == [V_STATUS_REPLY]


def test_vectors_control_packet_release_and_stop() -> None:
    """The vectors are one remote's messages in order (counters 1, 2, 3): its control packet,
    then RELEASE. The live link a RELEASE needs comes from a second remote (id 8), whose
    packets leave remote 7's counters alone."""
    u = Keyed()
    u.wait(20 * MS)
    u.udp(V_CONTROL)  # counter 1, drive with gas 0.3: valid, but not neutral
    assert u.wd.status().counters.udp_valid == 1
    for i in range(5):  # neutral packets of remote 8
        u.wait(20 * MS)
        u.udp(u.heartbeat(rid=8, counter=1 + i))
    reply = u.ask_frame(V_RELEASE)  # counter 2: above remote 7's control packet
    assert (reply.ack, reply.state, reply.session, reply.counter) == (True, ARMED, N, 2)
    reply = u.ask_frame(V_STOP)
    assert (reply.ack, reply.state, reply.reason, reply.counter) == (True, STOPPED, TCP_STOP, 3)


# -- only the key holder may keep the unit alive -----------------------------------------------
def test_authenticated_packets_keep_the_unit_alive_and_plain_ones_do_not() -> None:
    u = Keyed()
    u.drive_auth(5)
    assert u.ask_frame(u.frame(RELEASE)).state == ARMED
    for _ in range(20):  # 400 ms of plain packets, the finger lifted: stop at the deadline
        u.wait(20 * MS)
        u.udp(packet())
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    c = u.wd.status().counters
    assert c.udp_valid == 5 and c.udp_invalid >= 9


@pytest.mark.parametrize("damage", ["key", "tag", "session", "magic", "length", "body"])
def test_forged_control_packets_are_invalid(damage: str) -> None:
    u = Keyed()
    u.drive_auth(5)
    good = u.heartbeat()
    bad = {
        "key": u.heartbeat(key=bytes(32)),
        "tag": good[:-1] + bytes([good[-1] ^ 1]),
        "session": u.heartbeat(session=N + 1),
        "magic": b"ESU3" + good[4:],
        "length": good + b"\x00",
        "body": auth.AuthControlPacket(RID, N, 99, ControlPacket(gear=3)).encode(K, validate=False),
    }[damage]
    before = u.wd.status()
    u.wait(20 * MS)
    u.udp(bad)
    after = u.wd.status()
    assert after.counters.udp_valid == before.counters.udp_valid
    assert after.counters.udp_invalid == before.counters.udp_invalid + 1
    assert after.valid_run == before.valid_run


def test_replayed_and_stale_counters_do_not_keep_the_unit_alive() -> None:
    u = Keyed()
    recording = [u.heartbeat() for _ in range(10)]  # counters 1..10
    for p in recording[5:]:  # 6..10 go through
        u.wait(20 * MS)
        u.udp(p)
    assert u.ask_frame(u.frame(RELEASE)).state == ARMED
    for p in [*recording, recording[-1]]:  # every one old or equal: nothing kept alive
        u.wait(19 * MS)
        u.udp(p)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    c = u.wd.status().counters
    assert c.auth_old_counter == 11 and c.udp_valid == 5


def test_a_recording_from_an_earlier_boot_is_refused() -> None:
    old = Keyed(session=N)
    recording = [old.heartbeat(counter=i) for i in range(1, 20)]
    release = old.frame(RELEASE, counter=100)
    u = Keyed(session=N + 1)  # rebooted: a new session
    for p in recording:
        u.wait(20 * MS)
        u.udp(p)
    steps = u.send(release)
    reply = auth.AuthReply.decode(steps[-1].reply, K, auth.request_tag(release))
    assert (reply.ack, reply.nak_code, reply.state) == (False, NAK_NOT_AUTH, STOPPED)
    assert reply.session == N + 1  # the remote learns the new session from any reply
    c = u.wd.status().counters
    assert c.auth_bad_session == len(recording) + 1 and c.udp_valid == 0


def test_counters_are_kept_per_remote_id_and_per_channel() -> None:
    u = Keyed()
    for i in range(5):
        u.wait(20 * MS)
        u.udp(u.heartbeat(rid=1, counter=100 + i))
        u.udp(u.heartbeat(rid=2, counter=1 + i))  # another remote, its own counter
    assert u.wd.status().counters.udp_valid == 10
    # Remote 2's counter (5) does not bind remote 1: a RELEASE of remote 1 at 105 is fresh.
    assert u.ask_frame(u.frame(RELEASE, rid=1, counter=105)).state == ARMED
    assert u.ask_frame(u.frame(RELEASE, rid=1, counter=105)).nak_code == NAK_NOT_AUTH
    # The TCP channel keeps its own counter for control packets: 106 is still fresh on UDP
    # after a RELEASE at 200 (section 5 keeps one per channel; only RELEASE looks at both).
    assert u.ask_frame(u.frame(RELEASE, rid=1, counter=200)).ack
    before = u.wd.status().counters.udp_valid
    u.udp(u.heartbeat(rid=1, counter=106))
    assert u.wd.status().counters.udp_valid == before + 1


def test_a_release_not_above_the_newest_control_packet_is_stale() -> None:
    """Issue 25, item 2: a RELEASE that never reached the unit (its connection was closed
    first) used to stay valid until the remote's next accepted RELEASE, as the unit kept the
    channels apart while the remote raises one counter for both. Now a RELEASE whose counter
    is not above the newest counter authenticated from its remote on either channel is
    refused (NAK 4, an old counter). Failed before: the RELEASE at counter 3 armed the unit."""
    u = Keyed()
    u.drive_auth(2)  # counters 1, 2
    undelivered = u.frame(RELEASE)  # counter 3: sent, its connection evicted unread
    u.drive_auth(5)  # counters 4..8: the link live, the remote neutral
    before = u.wd.status().counters.auth_old_counter
    reply = u.ask_frame(undelivered)
    assert (reply.ack, reply.nak_code, reply.state) == (False, NAK_NOT_AUTH, STOPPED)
    assert u.wd.status().counters.auth_old_counter == before + 1
    assert u.ask_frame(u.frame(RELEASE)).state == ARMED  # counter 9: fresh


def test_a_ninth_remote_id_is_not_authenticated() -> None:
    u = Keyed()
    for rid in range(8):  # 10 ms apart: within the tag checks for new ids (10 per 100 ms)
        u.wait(10 * MS)
        u.udp(u.heartbeat(rid=rid, counter=1))
    u.wait(10 * MS)
    u.udp(u.heartbeat(rid=8, counter=1))
    c = u.wd.status().counters
    assert (c.udp_valid, c.auth_table_full) == (8, 1)
    u.udp(u.heartbeat(rid=3, counter=2))  # the eight keep working
    assert u.wd.status().counters.udp_valid == 9


def test_forged_packets_from_new_remote_ids_do_not_take_the_places() -> None:
    u = Keyed()
    for rid in range(100, 120):  # wrong key or wrong session: no place given
        u.wait(50 * MS)  # a new window of tag checks for the ids without a place
        u.udp(u.heartbeat(rid=rid, key=bytes(32), counter=1))
        u.udp(u.heartbeat(rid=rid, session=N ^ 1, counter=1))
    for rid in range(8):
        u.wait(10 * MS)
        u.udp(u.heartbeat(rid=rid, counter=1))
    c = u.wd.status().counters
    assert (c.udp_valid, c.auth_table_full, c.auth_bad_tag, c.auth_bad_session) == (8, 0, 20, 20)


def test_unsigned_control_packets_and_release_count_as_authentication_failures() -> None:
    """Issue 16, defect 9: on a unit with a key a plain packet (20 or 16 bytes), a 60-byte
    packet without the ESU2 magic and a plain RELEASE need authentication and lack it: each
    counts as a failure (a bad tag) and in ESTOP_STATUS byte 2, as docs/PROTOCOL.md says.
    The body is checked first (section 5's Choice): junk is only invalid."""
    u = Keyed()
    u.drive_auth(5)
    good = u.heartbeat()
    u.wait(100 * MS)  # a STATUS frame: the window starts empty
    before = u.wd.status().counters
    u.udp(packet())  # plain, 20 bytes
    u.udp(packet(legacy=True))  # plain, 16 bytes
    u.udp(b"ESU3" + good[4:])  # the magic is wrong
    assert u.ask(RELEASE)[0::5] == (0x81, NAK_NOT_AUTH)  # a plain RELEASE
    u.udp(b"junk")  # not a control packet: invalid only
    u.udp(packet(gear=3))  # a plain packet whose body is bad: invalid only
    u.udp(b"ESU3" + good[4:24] + packet(gear=3) + good[44:])  # bad magic and body: invalid
    c = u.wd.status().counters
    assert c.auth_bad_tag - before.auth_bad_tag == 4
    assert c.udp_invalid - before.udp_invalid == 6
    status = [d for (_t, can_id, d) in u.frames if can_id == 0x051]
    u.wait(100 * MS)
    status = [d for (_t, can_id, d) in u.frames if can_id == 0x051][len(status):]
    assert status[0][2] == 4  # ESTOP_STATUS byte 2: authentication failures


# -- only the key holder may release ----------------------------------------------------------
def test_plain_release_on_a_keyed_unit_gets_nak_4_even_with_a_live_link() -> None:
    u = Keyed()
    u.drive_auth(5)
    assert u.ask(RELEASE)[0::5] == (0x81, NAK_NOT_AUTH)
    assert u.state == STOPPED


@pytest.mark.parametrize("forgery", ["key", "session", "replay", "equal_counter"])
def test_forged_or_replayed_release_gets_nak_4(forgery: str) -> None:
    u = Keyed()
    u.drive_auth(5)
    first = u.frame(RELEASE, counter=50)
    assert u.ask_frame(first).state == ARMED
    u.ask_frame(u.frame(STOP_ID, counter=51))
    u.counter = 9
    u.drive_auth(5)  # 10..14: below the RELEASE, so the TCP counter alone judges it
    frame = {
        "key": u.frame(RELEASE, key=bytes(32), counter=500),
        "session": u.frame(RELEASE, session=0, counter=500),
        "replay": first,
        "equal_counter": u.frame(RELEASE, counter=50),
    }[forgery]
    steps = u.send(frame)
    raw = steps[-1].reply
    assert raw is not None
    # A forged request's reply still verifies against that request (the unit answers it).
    reply = auth.AuthReply.decode(raw, K, auth.request_tag(frame))
    assert (reply.ack, reply.nak_code, reply.state) == (False, NAK_NOT_AUTH, STOPPED)


def test_release_checks_come_in_order_auth_link_neutral() -> None:
    u = Keyed()
    assert u.ask_frame(u.frame(RELEASE, key=bytes(32))).nak_code == NAK_NOT_AUTH
    assert u.ask_frame(u.frame(RELEASE)).nak_code == 2  # authenticated, no live link
    u.drive_auth(5, gas=0.4)
    assert u.ask_frame(u.frame(RELEASE)).nak_code == 3
    u.drive_auth(1)
    assert u.ask_frame(u.frame(RELEASE)).state == ARMED
    # While ARMED a RELEASE is ACKed, after the authentication check.
    assert u.ask_frame(u.frame(RELEASE)).ack
    assert u.ask_frame(u.frame(RELEASE, key=bytes(32))).nak_code == NAK_NOT_AUTH
    assert u.state == ARMED


# -- anyone may stop ------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["plain", "garbage_tag", "wrong_session", "datagram"])
def test_anyone_may_stop_a_keyed_unit(how: str) -> None:
    u = Keyed()
    u.drive_auth(5)
    assert u.ask_frame(u.frame(RELEASE)).state == ARMED
    if how == "plain":
        assert u.ask(STOP_ID)[2] == STOPPED
    elif how == "datagram":
        u.udp(auth.stop_datagram(1, 0, key=None))
    else:
        frame = u.frame(STOP_ID, key=bytes(32) if how == "garbage_tag" else K,
                        session=0 if how == "wrong_session" else N)
        assert u.ask_frame(frame).state == STOPPED
    assert (u.state, u.reason) == (STOPPED, TCP_STOP)


def test_status_is_answered_whatever_the_tag_and_teaches_the_session() -> None:
    u = Keyed()
    reply = u.ask_frame(u.frame(STATUS, session=0, key=bytes(32)))
    assert (reply.ack, reply.state, reply.reason, reply.session) == (True, STOPPED, BOOT, N)


def test_reply_tag_binds_the_reply_to_its_request() -> None:
    u = Keyed()
    frame = u.frame(STATUS)
    raw = u.send(frame)[-1].reply
    assert raw is not None
    other = u.frame(STATUS)
    with pytest.raises(auth.TagMismatch):
        auth.AuthReply.decode(raw, K, auth.request_tag(other))


# -- a unit without a key ---------------------------------------------------------------------
def test_keyless_unit_refuses_authenticated_packets_and_request_frame_release() -> None:
    u = Keyed(key=None)
    u.drive_auth(5)  # 60-byte packets: the other form
    c = u.wd.status().counters
    assert (c.udp_valid, c.udp_invalid) == (0, 5)
    u.drive(5)
    steps = u.send(u.frame(RELEASE, key=None))
    raw = steps[-1].reply
    assert raw is not None and raw[32:] == bytes(16)  # zero tag
    reply = auth.AuthReply.decode(raw, None)
    assert (reply.ack, reply.nak_code, reply.session) == (False, NAK_NOT_AUTH, N)
    assert u.ask(RELEASE)[2] == ARMED  # the plain RELEASE is the keyless unit's
    reply = auth.AuthReply.decode(u.send(u.frame(STOP_ID, key=None))[-1].reply or b"", None)
    assert (reply.ack, reply.state, reply.reason) == (True, STOPPED, TCP_STOP)


def test_request_frames_split_anywhere_are_reassembled() -> None:
    u = Keyed()
    stream = u.frame(STATUS, 1) + request(STATUS, 2) + u.frame(STATUS, 3)
    replies = []
    for i in range(len(stream)):
        replies += [s.reply for s in u.send(stream[i:i + 1]) if s.reply is not None]
    assert [len(r) for r in replies] == [48, 16, 48]
    assert [struct.unpack_from("<I", r, 8 if len(r) == 48 else 4)[0] for r in replies] == [1, 2, 3]


def test_unknown_msg_id_in_a_request_frame_is_nak_1_whatever_the_tag() -> None:
    u = Keyed()
    reply = u.ask_frame(u.frame(0x12345678, key=bytes(32)))
    assert (reply.ack, reply.nak_code) == (False, 1)


def test_key_is_not_kept_in_the_core_state() -> None:
    wd = Watchdog(Config(key=K, session=TEST_SESSION))
    raw = bytes(ffi.buffer(wd._core))
    assert K not in raw
