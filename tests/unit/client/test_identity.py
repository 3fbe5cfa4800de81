"""A remote is one keyed identity (estop.client.identity): its stop channel, its stop and lift
datagrams and its control packets carry one key, one remote id and the session last learnt,
and draw from one counter."""

from __future__ import annotations

import pytest

from estop.client.identity import Identity, MessageCounter
from estop.client.sender import Remote
from estop.protocol import auth
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
        packet = auth.AuthControlPacket.decode(r.identity.control_packet(ControlPacket()), KEY)
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
