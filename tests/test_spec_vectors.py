"""Every example of PROTOCOL.md is a test vector, checked through the C core (cffi) and
through the independent Python codecs."""

from __future__ import annotations

import pytest

from core_util import ARMED, BOOT, STOPPED, TCP_STOP, UDP_TIMEOUT, Unit, reply_fields
from estop.protocol.can import BrakeFrame
from estop.protocol.tcp import Reply, Request, release_request, stop_request
from estop.protocol.udp import ControlPacket

UDP_EXAMPLE = bytes.fromhex("9A 99 99 3E 00 00 80 BE 08 00 00 00 01 00 00 00 00 00 00 00")
STOP_EXAMPLE = bytes.fromhex("70 E5 70 E5 01 00 00 00 00 00 00 00 DC 09 BF 43")
RELEASE_EXAMPLE = bytes.fromhex("02 00 00 00 02 00 00 00 00 00 00 00 8D 5F CB D5")
BRAKE_BOOT_0 = bytes.fromhex("01 64 00 01 00 00 00 9C")
BRAKE_ARMED_7 = bytes.fromhex("00 00 01 00 00 00 07 18")
BRAKE_TIMEOUT_14 = bytes.fromhex("01 64 00 03 00 00 0E 1D")


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
])
def test_brake_examples_through_python_codec(raw: bytes, state: int, reason: int,
                                             counter: int) -> None:
    assert BrakeFrame.for_state(state, reason, 0, counter).encode() == raw
    frame = BrakeFrame.decode(raw)
    assert (frame.state, frame.reason, frame.counter, frame.brakes) == (
        state, reason, counter, state == STOPPED)


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
