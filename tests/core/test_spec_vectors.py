"""Every example of PROTOCOL.md is a test vector, checked through the C core (cffi) and
through the independent Python codecs."""

from __future__ import annotations

import hashlib

import pytest

from core_util import (
    ARMED,
    BOOT,
    LIFT,
    MS,
    SLOWING,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    Unit,
    packet,
    reply_fields,
)
from estop.core import Config
from estop.protocol import auth
from estop.protocol.can import BrakeFrame
from estop.protocol.tcp import Reply, Request, lift_request, release_request, stop_request
from estop.protocol.udp import ControlPacket
from vectors import (
    AUTH_CONTROL_EXAMPLE,
    AUTH_LIFT_EXAMPLE,
    AUTH_RELEASE_EXAMPLE,
    AUTH_STATUS_EXAMPLE,
    AUTH_STATUS_REPLY_EXAMPLE,
    AUTH_STOP_EXAMPLE,
    BRAKE_ARMED_7,
    BRAKE_BOOT_0,
    BRAKE_LIFT_9,
    BRAKE_SLOWING_5,
    BRAKE_TIMEOUT_14,
    LIFT_EXAMPLE,
    RELEASE_EXAMPLE,
    RID,
    STOP_EXAMPLE,
    UDP_EXAMPLE,
    K,
    N,
)


# -- section 1 --------------------------------------------------------------------------------
def test_udp_example_through_python_codec() -> None:
    pkt = ControlPacket.decode(UDP_EXAMPLE)
    assert pkt.gas_brake == pytest.approx(0.3) and pkt.steering == -0.25
    assert (pkt.gear, pkt.turn_signal, pkt.horn) == (8, 1, 0)
    assert ControlPacket(0.3, -0.25, 8, 1, 0).encode() == UDP_EXAMPLE
    assert not pkt.is_neutral


def test_udp_example_through_core_is_valid_and_not_neutral() -> None:
    u = Unit()
    for _ in range(5):
        u.wait(20_000)
        u.udp(UDP_EXAMPLE)
    assert u.wd.status().counters.udp_valid == 5
    assert u.ask(2)[5] == 3  # gas 0.3 is not neutral: NAK 3


# -- section 2 --------------------------------------------------------------------------------
def test_stop_example_through_python_codec() -> None:
    assert stop_request(1).encode() == STOP_EXAMPLE
    assert Request.decode(STOP_EXAMPLE) == Request(0xE570E570, 1, 0)


def test_release_example_through_python_codec() -> None:
    assert release_request(2).encode() == RELEASE_EXAMPLE
    assert Request.decode(RELEASE_EXAMPLE) == Request(2, 2, 0)


def test_lift_example_through_python_codec() -> None:
    assert lift_request(5).encode() == LIFT_EXAMPLE
    request = Request.decode(LIFT_EXAMPLE)
    assert request == Request(3, 5, 0) and request.kind() == "lift"


def test_lift_example_through_core() -> None:
    u = Unit()
    u.arm()
    (rep,) = [s.reply for s in u.send(LIFT_EXAMPLE) if s.reply]
    assert reply_fields(rep) == (0x80, 5, STOPPED, LIFT, 0, 0)


def test_stop_and_release_examples_through_core() -> None:
    u = Unit()
    u.arm()
    (rep,) = [s.reply for s in u.send(STOP_EXAMPLE) if s.reply]
    assert reply_fields(rep) == (0x80, 1, STOPPED, TCP_STOP, 0, 0)
    assert Reply.decode(rep) == Reply(True, 1, STOPPED, TCP_STOP, 0, 0)
    u.drive(5)
    (rep,) = [s.reply for s in u.send(RELEASE_EXAMPLE) if s.reply]
    assert reply_fields(rep) == (0x80, 2, ARMED, 0, 0, 0)
    assert Reply.decode(rep).encode() == rep


# -- section 4 --------------------------------------------------------------------------------
@pytest.mark.parametrize(("raw", "state", "reason", "counter"), [
    (BRAKE_BOOT_0, STOPPED, BOOT, 0),
    (BRAKE_ARMED_7, ARMED, 0, 7),
    (BRAKE_TIMEOUT_14, STOPPED, UDP_TIMEOUT, 14),
    (BRAKE_LIFT_9, STOPPED, LIFT, 9),
])
def test_brake_examples_through_python_codec(raw: bytes, state: int, reason: int,
                                             counter: int) -> None:
    assert BrakeFrame.for_state(state, reason, 0, counter).encode() == raw
    frame = BrakeFrame.decode(raw)
    assert (frame.state, frame.reason, frame.counter, frame.brakes) == (
        state, reason, counter, state == STOPPED)


def test_slowing_brake_example_through_python_codec() -> None:
    assert BrakeFrame.for_state(SLOWING, 0, 1, 5, slow_level=30).encode() == BRAKE_SLOWING_5
    frame = BrakeFrame.decode(BRAKE_SLOWING_5)
    assert (frame.brake_request, frame.brake_level, frame.state, frame.flags, frame.counter) == (
        2, 30, SLOWING, 1, 5)
    assert frame.brakes and not frame.emergency and frame.deceleration_share == 0.3


def brake_frames_of(u: Unit) -> list[bytes]:
    return [d for _, d in u.brake_frames()]


def test_brake_examples_through_core() -> None:
    u = Unit()
    assert brake_frames_of(u)[0] == BRAKE_BOOT_0
    # Arm, then let the counter run until an ARMED frame with counter 7 and no flag appears.
    u.arm()
    seen_armed_7 = False
    while not seen_armed_7:
        u.wait(10_000)
        u.udp(bytes(20 * [0])[:8] + bytes([4, 0, 0, 0]) + bytes(8))
        seen_armed_7 = BRAKE_ARMED_7 in brake_frames_of(u)
    # Now stop by silence, and run until counter 14 shows the timeout.
    u.wait(200_000)
    assert u.reason == UDP_TIMEOUT
    while BRAKE_TIMEOUT_14 not in brake_frames_of(u):
        u.wait(10_000)
        assert len(u.frames) < 10_000


def test_slowing_and_lift_brake_examples_through_core() -> None:
    """A two-stage unit (S 100 ms, W 50 ms, T 1 s, L 30 %) slows down whenever the link is
    silent for S, with the link-degraded flag; a LIFT stops it. The counter runs until the
    examples' counters come up (5 while SLOWING, 9 for the lift)."""
    u = Unit(Config(timeout_us=1000 * MS, slow_us=100 * MS, warn_us=50 * MS, slow_level=30))
    u.arm()
    rounds = 0
    while BRAKE_SLOWING_5 not in brake_frames_of(u):
        rounds += 1  # silent past S: SLOWING, flagged; three packets bring it back
        u.wait((101 + 7 * (rounds % 20)) * MS)
        assert u.state == SLOWING
        for _ in range(3):
            u.wait(5 * MS)
            u.udp(packet())
        assert u.state == ARMED and len(u.frames) < 10_000
    u.ask(3)  # LIFT
    u.drive(5)
    while BRAKE_LIFT_9 not in brake_frames_of(u):
        u.wait(10 * MS)
        assert len(u.frames) < 10_000


# -- section 5.4 ------------------------------------------------------------------------------
def spec_mac(message: bytes) -> bytes:
    """MAC(K, m) as section 5 defines it, straight from hashlib."""
    return hashlib.blake2s(message, key=K, digest_size=16).digest()


@pytest.mark.parametrize(("raw", "signed"), [
    (AUTH_CONTROL_EXAMPLE, 44), (AUTH_STATUS_EXAMPLE, 32), (AUTH_RELEASE_EXAMPLE, 32),
    (AUTH_STOP_EXAMPLE, 32), (AUTH_LIFT_EXAMPLE, 32)])
def test_auth_example_tags_are_the_spec_mac(raw: bytes, signed: int) -> None:
    assert len(raw) == signed + 16
    assert raw[signed:] == spec_mac(raw[:signed])


def test_auth_reply_example_tag_covers_the_request_tag() -> None:
    assert AUTH_STATUS_REPLY_EXAMPLE[32:] == spec_mac(AUTH_STATUS_EXAMPLE[32:]
                                                      + AUTH_STATUS_REPLY_EXAMPLE[:32])


def test_auth_control_example_through_python_codec() -> None:
    body = ControlPacket(0.3, -0.25, 8, 1, 0)
    assert auth.AuthControlPacket(RID, N, 1, body).encode(K) == AUTH_CONTROL_EXAMPLE
    pkt = auth.AuthControlPacket.decode(AUTH_CONTROL_EXAMPLE, K)
    assert (pkt.remote_id, pkt.session, pkt.counter) == (RID, N, 1)
    assert pkt.body.encode() == UDP_EXAMPLE  # the body of section 1's example
    with pytest.raises(auth.TagMismatch):
        auth.AuthControlPacket.decode(AUTH_CONTROL_EXAMPLE, bytes(32))


@pytest.mark.parametrize(("raw", "fields"), [
    (AUTH_STATUS_EXAMPLE, (1, 1, 0, 0x1122334455667788)),
    (AUTH_RELEASE_EXAMPLE, (2, 2, N, 2)),
    (AUTH_STOP_EXAMPLE, (0xE570E570, 3, N, 3)),
    (AUTH_LIFT_EXAMPLE, (3, 4, N, 4)),
])
def test_auth_request_examples_through_python_codec(raw: bytes,
                                                     fields: tuple[int, int, int, int]) -> None:
    msg_id, seq, session, counter = fields
    assert auth.AuthRequest(msg_id, seq, RID, session, counter).encode(K) == raw
    assert auth.AuthRequest.decode(raw, K) == auth.AuthRequest(msg_id, seq, RID, session, counter)


def test_auth_status_reply_example_through_python_codec() -> None:
    reply = auth.AuthReply(True, 1, STOPPED, BOOT, session=N, counter=0x1122334455667788)
    request_tag = auth.request_tag(AUTH_STATUS_EXAMPLE)
    assert reply.encode(K, request_tag) == AUTH_STATUS_REPLY_EXAMPLE
    assert auth.AuthReply.decode(AUTH_STATUS_REPLY_EXAMPLE, K, request_tag) == reply
    with pytest.raises(auth.TagMismatch):  # bound to its request: not a reply to the RELEASE
        auth.AuthReply.decode(AUTH_STATUS_REPLY_EXAMPLE, K,
                              auth.request_tag(AUTH_RELEASE_EXAMPLE))


def keyed_unit() -> Unit:
    """A freshly booted unit with the key and session of section 5.4."""
    return Unit(Config(key=K, session=N))


def only_reply(u: Unit, frame: bytes) -> bytes:
    (rep,) = [s.reply for s in u.send(frame) if s.reply is not None]
    return rep


def test_auth_status_and_its_reply_examples_through_core() -> None:
    assert only_reply(keyed_unit(), AUTH_STATUS_EXAMPLE) == AUTH_STATUS_REPLY_EXAMPLE


def test_auth_control_release_and_stop_examples_through_core() -> None:
    u = keyed_unit()
    u.wait(20 * MS)
    u.udp(AUTH_CONTROL_EXAMPLE)  # counter 1: valid (gas 0.3, so not neutral)
    assert u.wd.status().counters.udp_valid == 1
    # The examples are one remote's messages in order (counters 1, 2, 3): the live link the
    # RELEASE needs comes from a second remote (id 8), which leaves remote 7's counters alone
    # (a RELEASE must be above its remote's newest counter on either channel).
    for counter in range(1, 6):
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(RID + 1, N, counter, ControlPacket()).encode(K))
    assert u.wd.status().counters.udp_valid == 6
    rep = auth.AuthReply.decode(only_reply(u, AUTH_RELEASE_EXAMPLE), K,
                                auth.request_tag(AUTH_RELEASE_EXAMPLE))
    assert (rep.ack, rep.seq, rep.state, rep.session, rep.counter) == (True, 2, ARMED, N, 2)
    rep = auth.AuthReply.decode(only_reply(u, AUTH_STOP_EXAMPLE), K,
                                auth.request_tag(AUTH_STOP_EXAMPLE))
    assert (rep.ack, rep.seq, rep.state, rep.reason, rep.counter) == (True, 3, STOPPED, TCP_STOP, 3)
    # Replayed, the same RELEASE is refused: its counter is no longer above the one kept.
    assert only_reply(u, AUTH_RELEASE_EXAMPLE)[15] == 4


def test_auth_stop_example_as_a_stop_datagram_through_core() -> None:
    """Section 1: the same frame over UDP stops the unit (whatever its tag)."""
    u = keyed_unit()
    for counter in range(1, 6):
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(RID, N, counter, ControlPacket()).encode(K))
    assert only_reply(u, auth.AuthRequest(2, 9, RID, N, 6).encode(K))[12] == ARMED
    u.udp(AUTH_STOP_EXAMPLE)
    assert (u.state, u.reason) == (STOPPED, TCP_STOP)
    assert u.wd.status().counters.udp_stops == 1


@pytest.mark.parametrize("channel", ["tcp", "udp"])
def test_auth_lift_example_through_core(channel: str) -> None:
    """Section 5.4's LIFT, as a request on TCP (answered with a tagged reply) and as a lift
    datagram on UDP (no reply): either stops an armed unit with reason lift, and changes no
    counter."""
    u = keyed_unit()
    for counter in range(1, 6):  # the link from remote 8: remote 7 sends only requests
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(RID + 1, N, counter, ControlPacket()).encode(K))
    assert only_reply(u, auth.AuthRequest(2, 9, RID, N, 1).encode(K))[12] == ARMED
    if channel == "tcp":
        rep = auth.AuthReply.decode(only_reply(u, AUTH_LIFT_EXAMPLE), K,
                                    auth.request_tag(AUTH_LIFT_EXAMPLE))
        assert (rep.ack, rep.seq, rep.state, rep.reason, rep.counter) == (True, 4, STOPPED, LIFT, 4)
    else:
        u.udp(AUTH_LIFT_EXAMPLE)
        assert u.wd.status().counters.udp_stops == 1
    assert (u.state, u.reason) == (STOPPED, LIFT)
    # No counter moved: a RELEASE with counter 2 (above the 1 kept, below the LIFT's 4) is
    # still authenticated.
    for counter in range(6, 11):
        u.wait(20 * MS)
        u.udp(auth.AuthControlPacket(RID + 1, N, counter, ControlPacket()).encode(K))
    assert only_reply(u, auth.AuthRequest(2, 10, RID, N, 2).encode(K))[12] == ARMED
