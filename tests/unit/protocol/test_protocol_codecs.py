"""The pure-Python codecs (estop.protocol) against the spec's examples and properties."""

from __future__ import annotations

import dataclasses
import io
import math
import struct
import zlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from estop.protocol import can, canlog, crc, tcp, udp
from estop.protocol.can import BrakeFrame, CounterChecker, CounterResult, StatusFrame
from estop.protocol.tcp import FrameAssembler, Reply, Request
from estop.protocol.udp import ControlPacket, InvalidPacket

# ---------------------------------------------------------------- spec examples (test vectors)

SPEC_UDP_DRIVE = "9A 99 99 3E 00 00 80 BE 08 00 00 00 01 00 00 00 00 00 00 00"
SPEC_TCP_STOP = "70 E5 70 E5 01 00 00 00 00 00 00 00 DC 09 BF 43"
SPEC_TCP_RELEASE = "02 00 00 00 02 00 00 00 00 00 00 00 8D 5F CB D5"
SPEC_CAN_BRAKE = [
    # (hex, state, reason, counter)
    ("01 64 00 01 00 00 00 9C", 0, 1, 0),  # boot, counter 0
    ("00 00 01 00 00 00 07 18", 1, 0, 7),  # armed, counter 7
    ("01 64 00 03 00 00 0E 1D", 0, 3, 14),  # udp timeout, counter 14
]
SPEC_LOG_LINE = "(1700000000.123456) estop 050#016400010000009C"


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def test_crc8_catalogue_check_value() -> None:
    assert crc.crc8_j1850(b"123456789") == 0x4B
    assert crc.crc8_j1850(b"") == 0x00  # init 0xFF, xorout 0xFF


def test_crc8_init_parameter() -> None:
    # continuing a CRC: feeding the un-xored register back as init gives the same result
    whole = crc.crc8_j1850(b"\x57\x0e\x01\x64")
    part = crc.crc8_j1850(b"\x57\x0e") ^ 0xFF
    assert crc.crc8_j1850(b"\x01\x64", init=part) == whole
    with pytest.raises(ValueError):
        crc.crc8_j1850(b"", init=256)


def test_crc32_is_zlib() -> None:
    assert crc.crc32(b"123456789") == 0xCBF43926 == zlib.crc32(b"123456789")


def test_spec_udp_example() -> None:
    pkt = udp.decode(h(SPEC_UDP_DRIVE))
    assert pkt.gas_brake == struct.unpack("<f", struct.pack("<f", 0.3))[0]
    assert pkt.steering == -0.25
    assert pkt.gear == udp.Gear.DRIVE
    assert pkt.turn_signal == udp.TurnSignal.LEFT
    assert pkt.horn == 0
    assert ControlPacket(0.3, -0.25, udp.Gear.DRIVE, udp.TurnSignal.LEFT, 0).encode() == h(
        SPEC_UDP_DRIVE)
    assert udp.encode(pkt) == h(SPEC_UDP_DRIVE)
    assert udp.is_valid(h(SPEC_UDP_DRIVE))
    assert not pkt.is_neutral


def test_spec_udp_example_old_form() -> None:
    short = h(SPEC_UDP_DRIVE)[:16]
    pkt = udp.decode(short)
    assert pkt.horn == 0 and pkt.gear == 8 and pkt.turn_signal == 1
    assert pkt.encode(legacy=True) == short
    with pytest.raises(InvalidPacket, match="horn"):
        ControlPacket(0.0, 0.0, 4, 0, 1).encode(legacy=True)


def test_spec_tcp_examples() -> None:
    assert tcp.stop_request(1).encode() == h(SPEC_TCP_STOP)
    assert Request(tcp.DEFAULT_STOP_ID, 1).encode() == h(SPEC_TCP_STOP)
    assert tcp.release_request(2).encode() == h(SPEC_TCP_RELEASE)
    stop = Request.decode(h(SPEC_TCP_STOP))
    assert stop == Request(0xE570E570, 1, 0) and stop.kind() == "stop"
    rel = Request.decode(h(SPEC_TCP_RELEASE))
    assert rel == Request(tcp.RELEASE, 2, 0) and rel.kind() == "release"
    assert tcp.status_request(3).kind() == "status"
    assert Request(0x1234, 1).kind() == "unknown"
    assert Request(0x1234, 1).kind(stop_id=0x1234) == "stop"


@pytest.mark.parametrize(("text", "state", "reason", "counter"), SPEC_CAN_BRAKE)
def test_spec_can_examples(text: str, state: int, reason: int, counter: int) -> None:
    frame = BrakeFrame.decode(h(text))
    assert (frame.state, frame.reason, frame.counter, frame.flags) == (state, reason, counter, 0)
    assert frame.brake_request == (1 if state == 0 else 0)
    assert frame.brake_level == (100 if state == 0 else 0)
    assert frame.brakes == (state == 0)
    assert BrakeFrame.for_state(state, reason, 0, counter).encode() == h(text)
    assert crc.e2e_crc8(0x0E57, h(text)[:7]) == h(text)[7]


def test_spec_log_line() -> None:
    rec = canlog.parse_line(SPEC_LOG_LINE)
    assert rec.timestamp_us == 1_700_000_000_123_456
    assert rec.interface == "estop" and rec.can_id == can.BRAKE_ID and not rec.extended
    assert rec.data == h("01 64 00 01 00 00 00 9C")
    assert canlog.format_line(rec) == SPEC_LOG_LINE
    assert abs(rec.timestamp - 1700000000.123456) < 1e-6


def test_constants() -> None:
    assert (can.BRAKE_ID, can.STATUS_ID) == (0x050, 0x051)
    assert (can.BRAKE_DATA_ID, can.STATUS_DATA_ID) == (0x0E57, 0x0E58)
    assert (tcp.STATUS, tcp.RELEASE, tcp.LIFT, tcp.ACK, tcp.NAK) == (1, 2, 3, 0x80, 0x81)
    assert tcp.DEFAULT_STOP_ID == 0xE570E570
    assert [int(c) for c in tcp.NakCode] == [0, 1, 2, 3, 4]
    assert (udp.DEFAULT_PORT, tcp.DEFAULT_PORT) == (5700, 5701)
    assert can.STATE_NAMES == {0: "STOPPED", 1: "ARMED", 2: "SLOWING"}
    assert can.REASON_NAMES == {0: "none", 1: "boot", 2: "tcp_stop", 3: "udp_timeout",
                                4: "fault", 5: "lift"}
    assert can.BRAKE_REQUEST_NAMES == {0: "release", 1: "emergency_brake",
                                       2: "controlled_stop"}
    assert can.brake_request_name(3) == "request?3"
    assert can.flag_names(1) == ["link_degraded"] and can.flag_names(0) == []
    assert can.state_name(7) == "state?7" and can.reason_name(9) == "reason?9"


# ----------------------------------------------------------------------------- UDP boundaries

F32_MAX_BELOW_1 = struct.unpack("<f", struct.pack("<I", 0x3F7FFFFF))[0]
F32_MIN_ABOVE_1 = struct.unpack("<f", struct.pack("<I", 0x3F800001))[0]
F32_DENORMAL = struct.unpack("<f", struct.pack("<I", 0x00000001))[0]


def raw_packet(gas: float, steer: float, gear: int = 4, turn: int = 0, horn: int = 0) -> bytes:
    return struct.pack("<ffiii", gas, steer, gear, turn, horn)


@pytest.mark.parametrize("value", [1.0, -1.0, 0.0, -0.0, F32_MAX_BELOW_1, -F32_MAX_BELOW_1,
                                   F32_DENORMAL, -F32_DENORMAL, 1e-40, -1e-45])
def test_udp_valid_float_boundaries(value: float) -> None:
    for data in (raw_packet(value, 0.0), raw_packet(0.0, value)):
        assert udp.is_valid(data)
        assert udp.encode(udp.decode(data)) == data  # bit-exact, keeps -0.0 and denormals


def test_udp_negative_zero_kept() -> None:
    pkt = udp.decode(raw_packet(-0.0, -0.0))
    assert math.copysign(1.0, pkt.gas_brake) == -1.0 and pkt.is_neutral


@pytest.mark.parametrize("value", [math.nan, -math.nan, math.inf, -math.inf, F32_MIN_ABOVE_1,
                                   -F32_MIN_ABOVE_1, 2.0, -1.5, 3.0e38])
def test_udp_invalid_floats(value: float) -> None:
    for data in (raw_packet(value, 0.0), raw_packet(0.0, value)):
        assert not udp.is_valid(data)
        with pytest.raises(InvalidPacket):
            udp.decode(data)


def test_udp_nan_payloads_and_signalling_nan() -> None:
    for bits in (0x7FC00000, 0xFFC00000, 0x7F800001, 0x7FBFFFFF, 0xFF800001):
        gas = struct.pack("<I", bits)
        assert not udp.is_valid(gas + raw_packet(0.0, 0.0)[4:])


def test_udp_encode_rounds_to_float32() -> None:
    # 1.00000001 becomes exactly 1.0 on the wire: valid
    assert udp.decode(ControlPacket(1.00000001, 0.0).encode()).gas_brake == 1.0
    with pytest.raises(InvalidPacket, match="gas_brake"):
        ControlPacket(1.0001, 0.0).encode()
    with pytest.raises(InvalidPacket, match="not finite"):
        ControlPacket(0.0, 1e300).encode()


@pytest.mark.parametrize("gear", [0, 3, 5, 6, 7, 9, 16, -1, -8, 2**31 - 1, -(2**31)])
def test_udp_unknown_gear(gear: int) -> None:
    assert not udp.is_valid(raw_packet(0.0, 0.0, gear=gear))
    with pytest.raises(InvalidPacket, match="gear"):
        udp.decode(raw_packet(0.0, 0.0, gear=gear))


@pytest.mark.parametrize("gear", [1, 2, 4, 8])
@pytest.mark.parametrize("turn", [0, 1, 2, 3])
@pytest.mark.parametrize("horn", [0, 1])
def test_udp_all_codes_valid(gear: int, turn: int, horn: int) -> None:
    assert udp.is_valid(raw_packet(0.5, -0.5, gear, turn, horn))


@pytest.mark.parametrize("turn", [-1, 4, 255, 2**31 - 1])
def test_udp_unknown_turn(turn: int) -> None:
    assert not udp.is_valid(raw_packet(0.0, 0.0, turn=turn))


@pytest.mark.parametrize("horn", [-1, 2, 256, 2**31 - 1, -(2**31)])
def test_udp_bad_horn(horn: int) -> None:
    assert not udp.is_valid(raw_packet(0.0, 0.0, horn=horn))


@pytest.mark.parametrize("length", [0, 1, 4, 12, 15, 17, 18, 19, 21, 24, 32, 1400])
def test_udp_bad_lengths(length: int) -> None:
    data = (raw_packet(0.0, 0.0) * 100)[:length]
    assert not udp.is_valid(data)
    with pytest.raises(InvalidPacket, match=f"length {length}"):
        udp.decode(data)


def test_udp_error_messages_are_one_line() -> None:
    for data in (b"", raw_packet(math.nan, 0), raw_packet(0, 0, gear=3), raw_packet(0, 0, horn=2)):
        with pytest.raises(InvalidPacket) as info:
            udp.decode(data)
        assert "\n" not in str(info.value) and str(info.value)
        assert isinstance(info.value, ValueError)


def test_udp_encode_without_validation_builds_invalid_packets() -> None:
    data = ControlPacket(math.nan, 0.0, 3, 9, 2).encode(validate=False)
    assert len(data) == 20 and not udp.is_valid(data)
    with pytest.raises(InvalidPacket):
        ControlPacket(0.0, 0.0, 2**40).encode(validate=False)


# --------------------------------------------------------------------- UDP hypothesis properties

def f32_bits_valid(bits: int) -> bool:
    """Independent statement of the float rule on the raw bits: finite and |x| <= 1.0."""
    return (bits & 0x7FFFFFFF) <= 0x3F800000


def reference_valid(data: bytes) -> bool:
    if len(data) not in (16, 20):
        return False
    gas_bits, steer_bits = struct.unpack_from("<II", data)
    gear, turn = struct.unpack_from("<ii", data, 8)
    horn = struct.unpack_from("<i", data, 16)[0] if len(data) == 20 else 0
    return (f32_bits_valid(gas_bits) and f32_bits_valid(steer_bits) and gear in (1, 2, 4, 8)
            and turn in (0, 1, 2, 3) and horn in (0, 1))


axis = st.floats(min_value=-1.0, max_value=1.0, width=32, allow_subnormal=True)
valid_packets = st.builds(ControlPacket, axis, axis, st.sampled_from([1, 2, 4, 8]),
                          st.integers(0, 3), st.integers(0, 1))


@given(valid_packets)
def test_udp_roundtrip_packet(pkt: ControlPacket) -> None:
    data = pkt.encode()
    assert len(data) == 20 and udp.is_valid(data)
    back = udp.decode(data)
    assert back == pkt
    assert math.copysign(1, back.gas_brake) == math.copysign(1, pkt.gas_brake)
    if pkt.horn == 0:
        assert udp.decode(pkt.encode(legacy=True)) == pkt


@given(st.binary(min_size=20, max_size=20) | st.binary(min_size=16, max_size=16))
def test_udp_validity_matches_reference_on_random_bytes(data: bytes) -> None:
    assert udp.is_valid(data) == reference_valid(data)
    if udp.is_valid(data):
        assert udp.encode(udp.decode(data), legacy=len(data) == 16) == data


@given(valid_packets, st.integers(0, 19), st.integers(0, 255))
def test_udp_validity_matches_reference_after_byte_change(
        pkt: ControlPacket, pos: int, value: int) -> None:
    data = bytearray(pkt.encode())
    data[pos] = value
    assert udp.is_valid(bytes(data)) == reference_valid(bytes(data))


@given(st.binary(max_size=64).filter(lambda b: len(b) not in (16, 20)))
def test_udp_rejects_other_lengths(data: bytes) -> None:
    assert not udp.is_valid(data)


@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32).filter(
    lambda x: not -1.0 <= x <= 1.0)), st.booleans())
def test_udp_rejects_bad_floats(value: float, on_steering: bool) -> None:
    data = raw_packet(0.0, value) if on_steering else raw_packet(value, 0.0)
    assert not udp.is_valid(data)


@given(st.integers(-(2**31), 2**31 - 1).filter(lambda g: g not in (1, 2, 4, 8)))
def test_udp_rejects_bad_gear(gear: int) -> None:
    assert not udp.is_valid(raw_packet(0.0, 0.0, gear=gear))


# ------------------------------------------------------------------------------------- TCP

u32 = st.integers(0, 2**32 - 1)


@given(u32, u32, u32)
def test_tcp_request_roundtrip(msg_id: int, seq: int, arg: int) -> None:
    req = Request(msg_id, seq, arg)
    data = req.encode()
    assert len(data) == 16
    assert struct.unpack("<I", data[12:])[0] == zlib.crc32(data[:12])
    assert Request.decode(data) == req


@given(u32, u32, st.integers(0, 127))
def test_tcp_single_bit_flip_is_detected(msg_id: int, seq: int, bit: int) -> None:
    data = bytearray(Request(msg_id, seq).encode())
    data[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(tcp.CrcMismatch):
        Request.decode(bytes(data))
    with pytest.raises(tcp.FrameError):
        Reply.decode(bytes(data))


valid_replies = st.one_of(
    st.builds(Reply, st.just(True), u32, st.just(0), st.integers(1, 4), st.just(0), st.just(0)),
    st.builds(Reply, st.just(True), u32, st.just(1), st.just(0), st.integers(0, 1), st.just(0)),
    st.builds(Reply, st.just(False), u32, st.just(0), st.integers(1, 4), st.just(0),
              st.integers(1, 4)),
    st.builds(Reply, st.just(False), u32, st.just(1), st.just(0), st.integers(0, 1),
              st.integers(1, 4)),
)


@given(valid_replies)
def test_tcp_reply_roundtrip(reply: Reply) -> None:
    data = reply.encode()
    assert len(data) == 16
    assert data[:4] == struct.pack("<I", 0x80 if reply.ack else 0x81)
    assert Reply.decode(data) == reply


def test_tcp_reply_layout() -> None:
    data = Reply(False, 0x01020304, 0, 1, 0, tcp.NakCode.NO_LIVE_LINK).encode()
    assert data[:12] == h("81 00 00 00 04 03 02 01 00 01 00 02")
    assert data[12:] == struct.pack("<I", zlib.crc32(data[:12]))


@pytest.mark.parametrize(("reply", "match"), [
    (Reply(True, 1, 3, 0), "state"),
    (Reply(True, 1, 0, 6), "reason"),
    (Reply(True, 1, 1, 2), "while ARMED"),
    (Reply(True, 1, 2, 5), "while SLOWING"),
    (Reply(True, 1, 0, 0), "none while STOPPED"),
    (Reply(True, 1, 1, 0, 2), "flags"),
    (Reply(True, 1, 0, 1, 1), "link_degraded"),
    (Reply(True, 1, 0, 1, 0, 1), "ACK with nak"),
    (Reply(False, 1, 0, 1, 0, 0), "NAK with nak code 0"),
    (Reply(False, 1, 0, 1, 0, 5), "nak code 5"),
])
def test_tcp_reply_invalid(reply: Reply, match: str) -> None:
    with pytest.raises(tcp.FrameError, match=match):
        reply.validate()
    data = reply.encode(validate=False)
    with pytest.raises(tcp.FrameError, match=match):
        Reply.decode(data)
    assert Reply.decode(data, strict=False) == reply


def test_tcp_reply_unknown_msg_id() -> None:
    body = struct.pack("<IIBBBB", 0x82, 1, 0, 1, 0, 0)
    frame = body + struct.pack("<I", zlib.crc32(body))
    with pytest.raises(tcp.FrameError, match="neither ACK"):
        Reply.decode(frame, strict=False)


def test_tcp_wrong_length_and_bad_values() -> None:
    with pytest.raises(tcp.FrameError, match="16 bytes"):
        Request.decode(h(SPEC_TCP_STOP)[:15])
    with pytest.raises(ValueError, match="u32"):
        Request(2**32, 0).encode()
    with pytest.raises(ValueError, match="u32"):
        Request(1, -1).encode()
    for bad in (0, 1, 2, 3):
        with pytest.raises(ValueError, match="0, 1, 2, 3 or 0x32515345"):
            tcp.stop_request(1, bad)
    assert tcp.check_stop_id(4) == 4


def test_frame_assembler_example_split_everywhere() -> None:
    stream = h(SPEC_TCP_STOP) + h(SPEC_TCP_RELEASE)
    for cut in range(len(stream) + 1):
        asm = FrameAssembler()
        frames = asm.feed(stream[:cut]) + asm.feed(stream[cut:])
        assert frames == [h(SPEC_TCP_STOP), h(SPEC_TCP_RELEASE)]
        assert asm.pending == 0


@given(st.lists(st.tuples(u32, u32), max_size=8), st.lists(st.integers(0, 200), max_size=10))
def test_frame_assembler_any_split(reqs: list[tuple[int, int]], cuts: list[int]) -> None:
    frames = [Request(m, s).encode() for m, s in reqs]
    stream = b"".join(frames)
    points = sorted({min(c, len(stream)) for c in cuts} | {0, len(stream)})
    asm = FrameAssembler()
    got: list[bytes] = []
    for a, b in zip(points, points[1:], strict=False):
        got += asm.feed(stream[a:b])
    assert got == frames and asm.pending == 0
    assert [Request.decode(f) for f in got] == [Request(m, s) for m, s in reqs]


def test_frame_assembler_keeps_partial_and_resets() -> None:
    asm = FrameAssembler()
    assert asm.feed(b"\x00" * 20) == [b"\x00" * 16]
    assert asm.pending == 4
    asm.reset()
    assert asm.pending == 0
    assert asm.feed(memoryview(b"\x01" * 16)) == [b"\x01" * 16]


# ------------------------------------------------------------------------------------- CAN

def all_valid_brake_frames() -> list[BrakeFrame]:
    frames = []
    for counter in range(15):
        for reason in range(1, 5):
            frames.append(BrakeFrame.for_state(0, reason, 0, counter))
        for flags in (0, 1):
            frames.append(BrakeFrame.for_state(1, 0, flags, counter))
    return frames


def test_can_brake_every_valid_frame_roundtrips() -> None:
    for frame in all_valid_brake_frames():
        data = frame.encode()
        assert len(data) == 8 and data[5] == 0 and data[6] == frame.counter
        assert data[7] == crc.crc8_j1850(b"\x57\x0e" + data[:7])
        assert BrakeFrame.decode(data) == frame
        assert BrakeFrame.check(data) == []


@given(st.sampled_from(all_valid_brake_frames()), st.integers(0, 63))
def test_can_single_bit_flip_is_detected(frame: BrakeFrame, bit: int) -> None:
    data = bytearray(frame.encode())
    data[bit // 8] ^= 1 << (bit % 8)
    problems = BrakeFrame.check(bytes(data))
    assert any(isinstance(p, can.CrcError) for p in problems)
    with pytest.raises(can.FrameError):
        BrakeFrame.decode(bytes(data))


def test_can_data_id_matters() -> None:
    brake = BrakeFrame.for_state(0, 1).encode()
    # the same payload sealed with the STATUS data ID is not a good brake frame
    other = brake[:7] + bytes((crc.e2e_crc8(can.STATUS_DATA_ID, brake[:7]),))
    assert other != brake
    assert [p.kind for p in BrakeFrame.check(other)] == ["bad_crc"]


def seal(payload7: bytes, data_id: int = can.BRAKE_DATA_ID) -> bytes:
    return payload7 + bytes((crc.e2e_crc8(data_id, payload7),))


@pytest.mark.parametrize(("payload", "kind", "match"), [
    ("01 64 00 01 00 00 0F", "bad_counter", "15"),
    ("01 64 00 01 00 00 10", "bad_counter", "bits 4-7"),
    ("01 64 00 01 00 01 00", "bad_content", "byte 5"),
    ("00 64 00 01 00 00 00", "bad_content", "brake_request 0 while STOPPED"),
    ("01 00 01 00 00 00 00", "bad_content", "brake_request 1 while ARMED"),
    ("01 32 00 01 00 00 00", "bad_content", "brake_level 50"),
    ("00 64 01 00 00 00 00", "bad_content", "brake_level 100"),
    ("02 64 00 01 00 00 00", "bad_content", "brake_request 2 while STOPPED"),
    ("03 64 00 01 00 00 00", "bad_content", "brake_request 3"),
    ("01 64 03 01 00 00 00", "bad_content", "state 3"),
    ("01 64 00 06 00 00 00", "bad_content", "reason 6"),
    ("01 64 02 00 00 00 00", "bad_content", "brake_request 1 while SLOWING"),
    ("00 00 02 00 00 00 00", "bad_content", "brake_request 0 while SLOWING"),
    ("02 00 02 00 00 00 00", "bad_content", "brake_level 0 while SLOWING"),
    ("02 64 02 00 00 00 00", "bad_content", "brake_level 100 while SLOWING"),
    ("02 1E 02 05 00 00 00", "bad_content", "while SLOWING"),
    ("02 1E 01 00 00 00 00", "bad_content", "brake_request 2 while ARMED"),
    ("01 64 00 00 00 00 00", "bad_content", "none while STOPPED"),
    ("00 00 01 02 00 00 00", "bad_content", "while ARMED"),
    ("00 00 01 00 02 00 00", "bad_content", "flags"),
    ("01 64 00 01 01 00 00", "bad_content", "link_degraded"),
])
def test_can_brake_bad_frames_with_good_crc(payload: str, kind: str, match: str) -> None:
    data = seal(h(payload))
    problems = BrakeFrame.check(data)
    assert [p.kind for p in problems] == [kind]
    with pytest.raises(can.FrameError, match=match):
        BrakeFrame.decode(data)
    BrakeFrame.parse(data)  # lenient parse still reads the fields


def test_can_wrong_dlc() -> None:
    for data in (b"", h("01 64 00 01 00 00 00"), h("01 64 00 01 00 00 00 9C 00")):
        assert [p.kind for p in BrakeFrame.check(data)] == ["bad_length"]
        assert [p.kind for p in StatusFrame.check(data)] == ["bad_length"]
        with pytest.raises(can.LengthError):
            BrakeFrame.parse(data)
        with pytest.raises(can.LengthError):
            StatusFrame.decode(data)


def test_can_encode_refuses_invalid_frames() -> None:
    with pytest.raises(can.CounterError):
        BrakeFrame.for_state(0, 1, 0, 15).encode()
    with pytest.raises(can.ContentError):
        BrakeFrame(0, 100, 0, 1, 0, 0).encode()
    with pytest.raises(can.ContentError):
        BrakeFrame(0, 0, 1, 0, 0, 0, reserved=256).encode(validate=False)
    # validate=False still puts the right CRC on a contradictory frame
    data = BrakeFrame(0, 100, 0, 1, 0, 0).encode(validate=False)
    assert [p.kind for p in BrakeFrame.check(data)] == ["bad_content"]


status_frames = st.builds(StatusFrame, st.integers(0, 255), st.integers(0, 255),
                          st.integers(0, 255), st.integers(0, 15), st.integers(0, 0xFFFF),
                          st.integers(0, 14), st.integers(0, 15))


@given(status_frames)
def test_can_status_roundtrip(frame: StatusFrame) -> None:
    data = frame.encode()
    assert data[3] == frame.stops | frame.slowdowns << 4
    assert data[4:6] == struct.pack("<H", frame.link_age_ms)
    assert data[6] == frame.counter
    assert data[7] == crc.crc8_j1850(b"\x58\x0e" + data[:7])
    assert StatusFrame.decode(data) == frame


def test_can_status_layout_and_link_age() -> None:
    frame = StatusFrame(50, 2, 1, 3, 0xFFFF, 9)
    data = frame.encode()
    assert data[:7] == h("32 02 01 03 FF FF 09")
    assert frame.link_age is None
    assert StatusFrame(0, 0, 0, 0, 42, 0).link_age == 42
    with pytest.raises(can.CounterError):
        StatusFrame(0, 0, 0, 0, 0, 15).encode()
    with pytest.raises(can.ContentError):
        StatusFrame(256, 0, 0, 0, 0, 0).encode()
    with pytest.raises(can.ContentError):
        StatusFrame(0, 0, 0, 0, 0x10000, 0).encode()
    bad = data[:7] + bytes((data[7] ^ 1,))
    assert [p.kind for p in StatusFrame.check(bad)] == ["bad_crc"]


def test_counter_checker_sequence() -> None:
    chk = CounterChecker()
    seq = [0, 1, 2, 2, 5, 6, 14, 0, 15, 1, 0]
    got = [chk.check(c) for c in seq]
    assert [g.result for g in got] == [
        CounterResult.FIRST, CounterResult.OK, CounterResult.OK, CounterResult.REPEAT,
        CounterResult.JUMP, CounterResult.OK, CounterResult.JUMP, CounterResult.OK,
        CounterResult.INVALID, CounterResult.OK, CounterResult.JUMP]
    assert got[4].lost == 2 and got[4].expected == 3
    assert got[6].lost == 7
    assert got[10].lost == 13  # 1 -> 0 skips 2..14
    assert got[8].expected == 1 and chk.last == 0
    chk.reset()
    assert chk.check(7).result is CounterResult.FIRST


@given(st.integers(0, 14), st.integers(1, 400))
def test_counter_checker_accepts_a_clean_run(start: int, n: int) -> None:
    chk = CounterChecker()
    assert chk.check(start).ok
    for i in range(1, n):
        status = chk.check((start + i) % 15)
        assert status.result is CounterResult.OK


@given(st.integers(0, 14), st.integers(1, 14))
def test_counter_checker_counts_lost_frames(start: int, lost: int) -> None:
    chk = CounterChecker()
    chk.check(start)
    status = chk.check((start + 1 + lost) % 15)
    if lost == 14:
        assert status.result is CounterResult.REPEAT
    else:
        assert status.result is CounterResult.JUMP and status.lost == lost


# ------------------------------------------------------------------------------------ can log

def test_canlog_formats() -> None:
    rec = canlog.parse_line("(1.5) vcan0 12345678#")
    assert rec.extended and rec.can_id == 0x12345678 and rec.data == b""
    assert rec.timestamp_us == 1_500_000
    assert canlog.format_line(rec) == "(1.500000) vcan0 12345678#"
    rec = canlog.parse_line("  (0.000001) can0 7FF#0011223344556677  \n")
    assert rec.can_id == 0x7FF and len(rec.data) == 8
    assert canlog.parse_line("(2.1234567) x 050#").timestamp_us == 2_123_456


@pytest.mark.parametrize("line", [
    "", "hello", "(1.0) vcan0 050#0", "(1.0) vcan0 50#00", "(1.0) vcan0 800#00",
    "(1.0) vcan0 050#001122334455667788", "(1.0) vcan0 050##100", "(1.0) vcan0 050#R",
    "1.0 vcan0 050#00", "(1.0) vcan0 050#zz",
])
def test_canlog_rejects(line: str) -> None:
    with pytest.raises(canlog.CanLogError):
        canlog.parse_line(line)


def test_canlog_read_write_stream() -> None:
    recs = [canlog.CanLogRecord.at(1700000000.0 + i * 0.01, "estop", 0x50,
                                   BrakeFrame.for_state(0, 1, 0, i).encode()) for i in range(5)]
    buf = io.StringIO()
    for rec in recs:
        canlog.write_record(buf, rec)
    text = buf.getvalue()
    assert text.splitlines()[0] == SPEC_LOG_LINE.replace(".123456", ".000000")
    assert list(canlog.read_log(io.StringIO(text + "\n\n"))) == recs
    with pytest.raises(canlog.CanLogError, match="line 2"):
        list(canlog.read_log(["(1.0) a 050#", "junk"]))
    assert len(list(canlog.read_log(["(1.0) a 050#", "junk"], skip_bad=True))) == 1
    with pytest.raises(ValueError):
        canlog.format_line(canlog.CanLogRecord(0, "has space", 0x50, b""))
    with pytest.raises(ValueError):
        canlog.format_line(canlog.CanLogRecord(0, "a", 0x800, b""))
    with pytest.raises(ValueError):
        canlog.format_line(canlog.CanLogRecord(0, "a", 0x50, bytes(9)))


@given(st.integers(0, 2**41), st.from_regex(r"[a-z][a-z0-9_]{0,14}", fullmatch=True),
       st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))
def test_canlog_roundtrip(ts: int, iface: str, ext: bool, ident: int, data: bytes) -> None:
    rec = canlog.CanLogRecord(ts, iface, ident if ext else ident & 0x7FF, data, ext)
    assert canlog.parse_line(canlog.format_line(rec)) == rec


@pytest.mark.parametrize(("request_value", "level", "share", "emergency"), [
    (0, 0, 0.0, False), (1, 100, 1.0, True), (2, 30, 0.3, False), (2, 1, 0.01, False),
    (3, 0, 1.0, True), (255, 0, 1.0, True)])
def test_brake_request_grading(request_value: int, level: int, share: float,
                               emergency: bool) -> None:
    """Section 7: 2 decelerates at brake_level percent of the emergency deceleration; a value a
    receiver does not know means an emergency brake."""
    frame = BrakeFrame(request_value, level, 0, 1, 0, 0)
    assert frame.deceleration_share == pytest.approx(share)
    assert frame.emergency is emergency and frame.brakes is (request_value != 0)


@pytest.mark.parametrize("field", ["stops", "slowdowns"])
def test_can_status_nibbles_are_checked(field: str) -> None:
    frame = dataclasses.replace(StatusFrame(0, 0, 0, 0, 0, 0), **{field: 16})
    with pytest.raises(can.ContentError, match=f"{field} must be 0..15"):
        frame.encode()
