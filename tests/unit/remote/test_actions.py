"""The actions every front-end of ``estop remote`` shares (estop.remote.actions): the gear
cycle, neutral, and the requests' lines when the stop channel fails or the stop button gets
no answer. Against a port nobody listens on (127.0.0.1)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from estop.client.channel import StopChannelError
from estop.client.sender import Remote
from estop.protocol.udp import Gear
from estop.remote import actions
from net_util import unused_tcp_port

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def remote() -> Iterator[Remote]:
    r = Remote("127.0.0.1", unused_tcp_port(), unused_tcp_port(), tcp_timeout=0.2,
               stop_deadline=0.3)
    yield r
    r.close(flush=False)


def test_the_gear_cycles_park_reverse_neutral_drive(remote: Remote) -> None:
    assert remote.control.gear == Gear.NEUTRAL  # what a remote starts with
    seen = [actions.next_gear(remote) for _ in range(5)]
    assert seen == [Gear.DRIVE, Gear.PARK, Gear.REVERSE, Gear.NEUTRAL, Gear.DRIVE]
    remote.set_control(gear=Gear.NEUTRAL, gas_brake=0.4, steering=-0.5)
    actions.neutral(remote)
    c = remote.control
    assert (c.gear, c.gas_brake, c.steering) == (Gear.NEUTRAL, 0.0, 0.0)


def test_requests_say_a_failed_channel_in_their_line_or_raise(remote: Remote) -> None:
    assert actions.try_request(remote, "status").startswith("status -> error: ")
    with pytest.raises(StopChannelError):
        actions.request(remote, "release")
    done = actions.request(remote, "stop")  # the stop button never raises
    assert done.reply is None and done.line.startswith("stop -> no ACK within 0.3 s")
    with pytest.raises(ValueError):
        actions.request(remote, "drive")


def test_hold_and_lift(remote: Remote) -> None:
    assert actions.hold(remote) is None and remote.held
    assert actions.lift(remote) == 3 and not remote.held
    assert actions.lift(remote) == 0
