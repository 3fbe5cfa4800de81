"""A remote is one keyed identity (estop.client.identity): its stop channel, its stop and lift
datagrams and its control packets carry one key, one remote id and the session last learnt,
and draw from one counter."""

from __future__ import annotations

import time

import pytest

from estop.client.channel import StopChannelError
from estop.client.identity import Identity, MessageCounter
from estop.client.sender import Remote
from estop.protocol import auth, tcp
from estop.protocol.udp import ControlPacket
from net_util import unused_tcp_port

KEY = bytes(range(32))


def test_every_channel_of_a_remote_speaks_as_one_identity() -> None:
    r = Remote("127.0.0.1", unused_tcp_port(), unused_tcp_port(), key=KEY, remote_id=9)
    try:
        assert r.channel.identity is r.identity is r.datagram.identity \
            is r.lift_datagram.identity
        r.identity.session = 0x0123456789ABCDEF  # as a verified reply teaches the channel
        stop = auth.AuthRequest.decode(r.datagram.encode(1), KEY)
        lift = auth.AuthRequest.decode(r.lift_datagram.encode(2), KEY)
        made = r.identity.control_packet(ControlPacket())
        assert made is not None
        packet = auth.AuthControlPacket.decode(made, KEY)
        assert {(m.remote_id, m.session) for m in (stop, lift, packet)} == \
            {(9, 0x0123456789ABCDEF)}
        assert stop.counter < lift.counter < packet.counter == r.identity.counter.last
        assert r.channel.session == 0x0123456789ABCDEF
    finally:
        r.close(flush=False)


def test_without_a_key_the_frames_have_zero_tags_and_no_control_packet() -> None:
    ident = Identity(counter=MessageCounter(start=41))
    frame = ident.request_frame(1, seq=5)
    assert frame[32:] == bytes(16) and auth.AuthRequest.decode(frame, None).counter == 41
    with pytest.raises(ValueError, match="needs a key"):
        ident.control_packet(ControlPacket())


# -- the quiet of a RELEASE in flight (issue 25; docs/REMOTE.md section 4) ----------------------
def _keyed(quiet: float = 0.05) -> Identity:
    return Identity(KEY, 3, MessageCounter(start=100), release_quiet_s=quiet)


def test_a_release_in_flight_holds_back_every_control_packet_until_its_reply() -> None:
    ident = _keyed(quiet=1.0)
    ended: list[float] = []
    ident.on_quiet_end = lambda: ended.append(ident.quiet_until())
    assert ident.control_packet(ControlPacket()) is not None  # counter 100
    release = ident.request(tcp.RELEASE, seq=1)  # counter 101: the quiet begins
    assert release.counter == 101 and ident.quiet_until() > time.monotonic()
    assert ident.control_packet(ControlPacket()) is None  # nothing above 101 is made
    stop = ident.request(tcp.DEFAULT_STOP_ID, seq=2)  # stop requests are never held back
    assert stop.counter == 102
    ident.answered(stop.counter)  # another request's reply ends nothing
    assert ident.control_packet(ControlPacket()) is None and ended == []
    ident.answered(release.counter)
    assert ended == [0.0] and ident.quiet_until() == 0.0
    packet = ident.control_packet(ControlPacket())
    assert packet is not None and auth.AuthControlPacket.decode(packet, KEY).counter == 103


def test_the_quiet_ends_at_its_bound_without_a_reply() -> None:
    """The dead-man's silence rules come first: a RELEASE whose reply does not come holds the
    control packets back for release_quiet_s at most (then it may be refused, NAK 4)."""
    ident = _keyed(quiet=0.05)
    ended: list[int] = []
    ident.on_quiet_end = lambda: ended.append(1)
    t0 = time.monotonic()
    release = ident.request(tcp.RELEASE, seq=1)
    assert t0 + 0.05 <= ident.quiet_until() <= time.monotonic() + 0.05
    time.sleep(0.06)
    assert ident.quiet_until() == 0.0 and ident.control_packet(ControlPacket()) is not None
    ident.answered(release.counter)  # a late reply: the quiet was over already
    assert ended == []


@pytest.mark.parametrize("msg_id", [tcp.STATUS, tcp.LIFT, tcp.DEFAULT_STOP_ID])
def test_only_a_keyed_release_starts_a_quiet(msg_id: int) -> None:
    ident = _keyed()
    ident.request(msg_id, seq=1)
    assert ident.quiet_until() == 0.0
    plain = Identity(release_quiet_s=0.05)
    plain.request(tcp.RELEASE, seq=1)  # no key: no counter is checked, nothing to hold back
    assert plain.quiet_until() == 0.0
    none = _keyed(quiet=0.0)
    none.request(tcp.RELEASE, seq=1)
    assert none.quiet_until() == 0.0


@pytest.mark.parametrize("bad", [-0.01, 1.5, float("nan"), float("inf"), "0.05"])
def test_a_bad_quiet_bound_is_refused_in_one_line(bad: object) -> None:
    with pytest.raises(ValueError, match=r"^release quiet must be 0\.\.1 s, got "):
        Identity(KEY, release_quiet_s=bad)  # type: ignore[arg-type]


def test_a_closed_stop_channel_ends_the_quiet_of_its_release() -> None:
    """A connection closed with the RELEASE unanswered: the unit has read it or never will
    (it handles every frame it received before closing), so the quiet ends at once."""
    r = Remote("127.0.0.1", unused_tcp_port(), unused_tcp_port(), key=KEY,
               release_quiet_s=1.0)
    try:
        with pytest.raises(StopChannelError, match="cannot connect"):
            r.release()  # the counter is taken, the connect fails
        assert r.identity.quiet_until() == 0.0
    finally:
        r.close(flush=False)


def test_a_packet_held_back_goes_out_when_the_reply_comes() -> None:
    """The touch page's remote (paced=False: one packet per fresh frame of the page): a frame
    while the RELEASE is in flight sends nothing; its packet goes out with the reply, above
    the RELEASE's counter."""
    sent: list[int] = []
    r = Remote("127.0.0.1", unused_tcp_port(), unused_tcp_port(), key=KEY, paced=False,
               release_quiet_s=1.0,
               on_packet=lambda _t, d, _td: sent.append(
                   auth.AuthControlPacket.decode(d, KEY).counter))
    try:
        r.identity.session = 1
        r.hold()
        assert r.pulse() and len(sent) == 1
        release = r.identity.request(tcp.RELEASE, seq=1)  # as the channel makes it
        assert r.pulse() and len(sent) == 1  # held back
        r.identity.answered(release.counter)
        assert len(sent) == 2 and sent[1] > release.counter
    finally:
        r.close(flush=False)
