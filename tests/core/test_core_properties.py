"""Hypothesis properties of the C core on random input.

- Random bytes on either channel never crash it (and every call keeps its output sane).
- Random bytes never keep it alive unless they form a valid packet.
"""

from __future__ import annotations

import struct

import hypothesis.strategies as st
from hypothesis import given, settings

from core_util import ARMED, MS, STOPPED, UDP_TIMEOUT, Unit
from estop.core import MAX_SLOTS, Watchdog
from estop.protocol.crc import e2e_crc8
from reference_model import parse_control

chunks = st.lists(st.tuples(st.booleans(), st.binary(max_size=64), st.integers(0, 50_000)),
                  max_size=40)


def check_frames(frames: list[tuple[int, bytes]]) -> None:
    for can_id, data in frames:
        assert can_id in (0x050, 0x051) and len(data) == 8
        assert data[6] < 15
        assert e2e_crc8(0x0E57 if can_id == 0x050 else 0x0E58, data[:7]) == data[7]


@settings(max_examples=500, deadline=None)
@given(chunks=chunks, slot=st.integers(0, MAX_SLOTS - 1))
def test_random_bytes_on_either_channel_never_crash(chunks: list[tuple[bool, bytes, int]],
                                                   slot: int) -> None:
    wd = Watchdog()
    t = 0
    wd.tcp_open(slot, t)
    slot_open = True
    for on_tcp, data, dt in chunks:
        t += dt
        if on_tcp and slot_open:
            steps = wd.tcp_data(slot, data, t)
            slot_open = not steps[-1].close
        else:
            steps = [wd.udp(data, t)]
        for s in steps:
            check_frames([(f.can_id, f.data) for f in s.frames])
            assert s.state in (STOPPED, ARMED) and 0 <= s.reason <= 4
            # 16 bytes answer a plain frame, 48 a request frame (random bytes can start "ESQ2")
            assert s.reply is None or len(s.reply) in (16, 48)
    assert wd.status().state == STOPPED  # random bytes never release the unit


@settings(max_examples=300, deadline=None)
@given(junk=st.lists(st.binary(max_size=32), min_size=1, max_size=60))
def test_random_bytes_never_keep_it_alive_unless_valid(junk: list[bytes]) -> None:
    u = Unit()
    u.arm()
    last_valid = u.t
    step = 200 * MS // (len(junk) + 1)
    for data in junk:
        u.wait(step)
        u.udp(data)
        if parse_control(data)[0]:
            last_valid = u.t
    u.at(last_valid + 200 * MS - 1)
    assert u.state == ARMED
    u.at(last_valid + 200 * MS)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)


@settings(max_examples=300, deadline=None)
@given(fields=st.tuples(st.floats(width=32), st.floats(width=32), st.integers(-2**31, 2**31 - 1),
                        st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1)),
       length=st.one_of(st.sampled_from([16, 20]), st.integers(0, 24)))
def test_core_and_python_codec_agree_on_validity(fields: tuple[float, float, int, int, int],
                                                 length: int) -> None:
    data = (struct.pack("<ffiii", *fields) + bytes(4))[:length]
    wd = Watchdog()
    wd.udp(data, 0)
    counters = wd.status().counters
    assert (counters.udp_valid == 1) == parse_control(data)[0]
