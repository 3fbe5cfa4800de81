"""Differential tests: the Cortex-M builds of the core (M0+ at -Os, M4 at -O2) run in the
unicorn emulator against the host build (the cffi module), call by call. After every call the
return value, the output structure, the consumed count and the core state must be equal byte
for byte (mcu_util.Twin checks it; the layouts are the same, see test_mcu_layout.py).

- the examples of PROTOCOL.md, driven as in test_spec_vectors.py, on the MCU builds;
- an hour of driving compressed (heartbeats at 50 Hz, releases, stops, timeouts, faults, a
  broken TCP stream, the 32-bit clock wrapping), with the stack each entry point used;
- random traces from hypothesis, with time wrapping past 2^32 us and going backwards.
"""

from __future__ import annotations

import math
import shutil
import struct
from collections import Counter
from pathlib import Path
from typing import Any

import hypothesis.strategies as st
import pytest
from hypothesis import given, settings

from core_util import (
    ARMED,
    BOOT,
    FAULT,
    MS,
    STOP_ID,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    packet,
    reply_fields,
    request,
)
from estop.core import ffi, lib
from mcu_util import U32, Mismatch, Twin, TwinUnit, config_bytes, mcubuild
from test_spec_vectors import (
    BRAKE_ARMED_7,
    BRAKE_BOOT_0,
    BRAKE_TIMEOUT_14,
    RELEASE_EXAMPLE,
    STOP_EXAMPLE,
    UDP_EXAMPLE,
)

STATUS, RELEASE = 0x00000001, 0x00000002
NEUTRAL = packet()
MINUTES = 60
ACK, NAK = 0x80, 0x81


def brake_data(u: TwinUnit) -> list[bytes]:
    return [d for _, can_id, d in u.frames if can_id == 0x050]


# -- the spec's examples ------------------------------------------------------------------------
def test_spec_vectors_on_the_mcu_builds() -> None:
    twin = Twin()
    u = TwinUnit(twin)
    assert brake_data(u)[0] == BRAKE_BOOT_0
    u.open(0)
    # Section 1: the example body is valid and not neutral.
    for _ in range(5):
        u.wait(20 * MS)
        u.udp(UDP_EXAMPLE)
    status = twin.call("estop_get_status")
    assert status.ret == lib.ESTOP_OK
    assert twin.host.objects["estop_status_t"].counters.udp_valid == 5
    (rep,) = u.tcp(0, RELEASE_EXAMPLE)
    assert reply_fields(rep) == (NAK, 2, STOPPED, BOOT, 0, 3)
    # Section 2: RELEASE with neutral packets, then the STOP example.
    for _ in range(5):
        u.wait(20 * MS)
        u.udp(NEUTRAL)
    (rep,) = u.tcp(0, RELEASE_EXAMPLE)
    assert reply_fields(rep) == (ACK, 2, ARMED, 0, 0, 0)
    # Section 4: an ARMED frame with counter 7 comes round while the packets flow.
    while BRAKE_ARMED_7 not in brake_data(u):
        u.wait(10 * MS)
        u.udp(NEUTRAL)
        assert len(u.frames) < 1000
    (rep,) = u.tcp(0, STOP_EXAMPLE)
    assert reply_fields(rep) == (ACK, 1, STOPPED, TCP_STOP, 0, 0)
    # Re-arm, then stop by silence and run until counter 14 shows the timeout.
    for _ in range(5):
        u.wait(20 * MS)
        u.udp(NEUTRAL)
    (rep,) = u.tcp(0, RELEASE_EXAMPLE)
    assert reply_fields(rep)[2] == ARMED
    u.wait(200 * MS)
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    while BRAKE_TIMEOUT_14 not in brake_data(u):
        u.wait(10 * MS)
        assert len(u.frames) < 2000
    assert twin.calls > 100


# -- an hour of driving, compressed --------------------------------------------------------------
def drive_packet(i: int) -> bytes:
    gas = 0.6 * math.sin(i / 7.0)
    steer = max(-1.0, min(1.0, math.cos(i / 5.0)))
    return packet(gas=gas, steer=steer, gear=8 if gas > 0 else 4, turn=i % 4, horn=i % 2)


def test_an_hour_of_driving_compressed() -> None:
    """Each minute: the gap since the last one (one tick), heartbeats at 50 Hz, a RELEASE, a
    second of driving with STATUS requests split across reads, then one of six endings. The
    clock starts half an hour before its 32-bit wrap. The stack every entry point used is
    measured and must stay within the static bound of test_mcu_footprint.py."""
    twin = Twin(measure_stack=True)
    start = (1 << 32) - 1_800_000_000
    u = TwinUnit(twin, start)
    u.open(0)
    u.open(1)
    seq = 0
    endings: Counter[str] = Counter()
    for minute in range(MINUTES):
        u.jump(start + minute * 60_000_000 + 1)
        for _ in range(6):
            u.wait(20 * MS)
            u.udp(NEUTRAL)
        seq += 1
        (rep,) = u.tcp(0, request(RELEASE, seq))
        assert reply_fields(rep)[:3] == (ACK, seq, ARMED), f"minute {minute}"
        for i in range(50):
            u.wait(20 * MS)
            u.udp(drive_packet(minute * 50 + i))
            if i % 10 == 5:
                seq += 1
                frame = request(STATUS, seq)
                assert u.tcp(1, frame[:5]) == []
                u.wait(1 * MS)
                (rep,) = u.tcp(1, frame[5:])
                assert reply_fields(rep)[:3] == (ACK, seq, ARMED)
        ending = ("tcp_stop", "silence", "fault", "bad_crc", "legacy", "invalid")[minute % 6]
        endings[ending] += 1
        if ending == "tcp_stop":
            seq += 1
            (rep,) = u.tcp(0, request(STOP_ID, seq))
            assert reply_fields(rep)[2:4] == (STOPPED, TCP_STOP)
        elif ending == "silence":
            u.wait(250 * MS)
            assert u.reason == UDP_TIMEOUT
        elif ending == "fault":
            u.fault()
            assert u.reason == FAULT
        elif ending == "bad_crc":
            assert u.tcp(1, request(STATUS, 1, good_crc=False) + bytes(7)) == []
            assert twin.out().close_slot == 1
            u.close(1)
            u.open(1)
            seq += 1
            u.tcp(1, request(STOP_ID, seq) + request(STATUS, seq + 1))
            seq += 1
            assert u.reason == TCP_STOP
        elif ending == "legacy":
            for _ in range(25):
                u.wait(20 * MS)
                u.udp(packet(legacy=True))
            assert u.state == ARMED
            u.wait(300 * MS)
            assert u.reason == UDP_TIMEOUT
        else:
            for _ in range(15):
                u.wait(20 * MS)
                u.udp(struct.pack("<ffiii", math.nan, 0.0, 4, 0, 0))
            assert u.reason == UDP_TIMEOUT
        u.wait(300 * MS)
        assert u.state == STOPPED
    assert u.t > 1 << 32 and set(endings) == {"tcp_stop", "silence", "fault", "bad_crc",
                                               "legacy", "invalid"}
    for v in twin.arms:
        bounds = mcubuild.stack_per_entry(v.variant)
        for (name, fn), used in twin.max_stack.items():
            if name == v.variant.name:
                assert 0 < used <= bounds[fn][0], f"{name} {fn}: used {used}, bound {bounds[fn]}"


# -- random traces --------------------------------------------------------------------------------
MAX_SLOTS = int(lib.ESTOP_MAX_SLOTS)
CONFIG_FIELDS = [name for name, _ in ffi.typeof("estop_config_t").fields]

valid_neutral = st.builds(lambda gas, steer, gear: packet(gas=gas, steer=steer, gear=gear),
                          st.sampled_from([0.0, -0.0, -0.25, -1.0]),
                          st.floats(-1.0, 1.0, width=32), st.sampled_from([1, 2, 4, 8]))
valid_moving = st.builds(lambda gas, legacy: packet(gas=gas, gear=8, legacy=legacy),
                         st.floats(0.125, 1.0, width=32), st.booleans())
odd_packets = st.one_of(
    st.binary(max_size=24),
    st.builds(lambda f: struct.pack("<ffiii", f, 0.0, 4, 0, 0),
              st.sampled_from([math.nan, math.inf, -math.inf, 1.0000001, -2.0])),
    st.builds(lambda g, t, h: struct.pack("<ffIII", 0.0, 0.0, g, t, h),
              st.integers(0, 16), st.integers(0, 5), st.integers(0, 2)),
    st.none(),
)
udp_data = st.one_of(valid_neutral, valid_neutral, valid_moving, odd_packets)

frames = st.one_of(
    st.builds(lambda seq: request(RELEASE, seq), st.integers(0, U32)),
    st.builds(lambda seq: request(STOP_ID, seq), st.integers(0, U32)),
    st.builds(lambda seq: request(STATUS, seq), st.integers(0, U32)),
    st.builds(lambda m, seq: request(m, seq), st.integers(0, U32), st.integers(0, U32)),
    st.builds(lambda seq: request(STATUS, seq, good_crc=False), st.integers(0, U32)),
    st.binary(min_size=16, max_size=16),
)
tcp_bytes = st.builds(lambda fs, cut: b"".join(fs)[cut:] if cut < 16 else b"".join(fs),
                      st.lists(frames, min_size=1, max_size=3),
                      st.one_of(st.just(0), st.integers(0, 40)))
release_now = st.builds(lambda seq: request(RELEASE, seq), st.integers(0, U32))



def field_values(name: str) -> st.SearchStrategy[tuple[str, Any]]:
    """Any value a configuration field can hold (its width read from the cffi type)."""
    ctype = dict(ffi.typeof("estop_config_t").fields)[name].type
    if ctype.kind == "array":
        return st.tuples(st.just(name), st.binary(min_size=ctype.length, max_size=ctype.length))
    top = (1 << (8 * ffi.sizeof(ctype))) - 1
    return st.tuples(st.just(name), st.one_of(st.integers(0, min(top, 0xFFFF)),
                                              st.integers(0, top)))


config_change = st.one_of(
    st.just({}),
    st.just({}),
    st.fixed_dictionaries({"timeout_us": st.integers(1000, 1_000_000)}).map(
        lambda d: {**d, "warn_us": d["timeout_us"] // 2}),
    st.lists(st.sampled_from(CONFIG_FIELDS).flatmap(field_values), max_size=2).map(dict),
)

# Time steps: mostly a host's pace, sometimes long silences, rarely a huge jump or the clock
# going backwards (which the core treats as a fault).
dt = st.one_of(st.integers(0, 25_000), st.integers(0, 25_000), st.integers(0, 400_000),
               st.integers(0, 0x7FFFFFFF), st.sampled_from([0x7FFFFFFF, 0x80000000, U32]),
               st.integers(-50_000, -1))

step = st.one_of(
    st.tuples(st.just("tick"), dt),
    st.tuples(st.just("udp"), dt, udp_data),
    st.tuples(st.just("udp"), dt, udp_data),
    st.tuples(st.just("beats"), dt, st.integers(1, 8)),
    st.tuples(st.just("beats"), st.integers(0, 25_000), st.integers(5, 8)),
    st.tuples(st.just("tcp"), st.integers(0, 25_000), st.just(0), release_now),
    st.tuples(st.just("arm"), st.integers(0, 25_000), st.integers(0, U32)),
    st.tuples(st.just("arm"), st.integers(0, 25_000), st.integers(0, U32)),
    st.tuples(st.just("tcp"), dt, st.integers(0, 3), tcp_bytes),
    st.tuples(st.just("tcp"), dt, st.integers(0, 3), tcp_bytes),
    st.tuples(st.just("open"), dt, st.integers(0, MAX_SLOTS + 1)),
    st.tuples(st.just("close"), dt, st.integers(0, MAX_SLOTS + 1)),
    st.tuples(st.just("fault"), dt),
    st.tuples(st.just("status"), st.booleans()),
    st.tuples(st.just("null"), st.sampled_from(["estop_tick", "estop_fault", "estop_udp_rx",
                                                "estop_tcp_open", "estop_tcp_rx"]),
              st.sampled_from(["core", "out", "consumed", "data"])),
    st.tuples(st.just("init"), dt, config_change),
    st.tuples(st.just("config"), config_change),
    st.tuples(st.just("name"), st.sampled_from(["estop_err_name", "estop_state_name",
                                                "estop_reason_name"]), st.integers(-20, 20)),
)

start_time = st.one_of(st.integers(0, U32), st.integers(U32 - 3_000_000, U32))
SEEN: Counter[str] = Counter()


class Driver:
    def __init__(self, twin: Twin, t: int) -> None:
        self.twin, self.t = twin, t
        self.wrapped = self.armed = False

    def call(self, fn: str, **values: Any) -> Any:
        return self.twin.call(fn, **values)

    def run(self, s: tuple[Any, ...]) -> None:
        kind = s[0]
        if kind in ("tick", "udp", "beats", "arm", "tcp", "open", "close", "fault", "init"):
            before, self.t = self.t, (self.t + s[1]) & U32
            if s[1] > 0 and self.t < before:
                self.wrapped = True
        now = self.t
        if kind == "tick":
            self.call("estop_tick", now_us=now)
        elif kind == "udp":
            self.call("estop_udp_rx", data=s[2], now_us=now)
        elif kind == "beats":
            for _ in range(s[2]):
                before, self.t = self.t, (self.t + 20_000) & U32
                self.wrapped |= self.t < before
                self.call("estop_tick", now_us=self.t)
                self.call("estop_udp_rx", data=NEUTRAL, now_us=self.t)
        elif kind == "arm":
            self.run(("beats", 0, 6))
            self.run(("tcp", 1000, 0, request(RELEASE, s[2])))
        elif kind == "tcp":
            data = s[3]
            for _ in range(len(data) + 1):
                res = self.call("estop_tcp_rx", slot=s[2], data=data, now_us=now)
                taken = int(res.objects["scalar:consumed"])
                if res.ret != lib.ESTOP_OK or taken >= len(data):
                    break
                data = data[taken:]
        elif kind in ("open", "close"):
            self.call(f"estop_tcp_{kind}", slot=s[2], now_us=now)
        elif kind == "fault":
            self.call("estop_fault", now_us=now)
        elif kind == "status":
            self.call("estop_get_status", status=... if s[1] else None)
        elif kind == "null":
            values: dict[str, Any] = {"now_us": now, "slot": 0, "data": NEUTRAL, s[2]: None}
            fn = s[1]
            names = {p.name for p in self.twin.host.proto(fn).params}
            self.call(fn, **{k: v for k, v in values.items() if k in names})
        elif kind == "init":
            self.call("estop_init", cfg=config_bytes(**s[2]), now_us=now)
        elif kind == "config":
            self.call("estop_config_check", cfg=config_bytes(**s[1]))
            self.call("estop_config_default", cfg=bytes(ffi.sizeof("estop_config_t")))
        elif kind == "name":
            param = self.twin.host.proto(s[1]).params[0].name
            self.call(s[1], **{param: s[2] if param == "err" else s[2] & U32})
        out = self.twin.host.objects.get("estop_out_t")
        if out is not None and out.state == ARMED:
            self.armed = True


TWIN: list[Twin] = []


def shared_twin() -> Twin:
    """One twin for all examples: the emulators keep their translated code between them."""
    if not TWIN:
        TWIN.append(Twin())
    TWIN[0].reset()
    return TWIN[0]


@settings(max_examples=500, deadline=None)
@given(t0=start_time,
       steps=st.integers(1, 50).flatmap(lambda n: st.lists(step, min_size=n, max_size=n)))
def test_random_traces_match_the_host_build(t0: int, steps: list[tuple[Any, ...]]) -> None:
    twin = shared_twin()
    d = Driver(twin, t0)
    d.call("estop_init", cfg=config_bytes(), now_us=t0)
    d.call("estop_tick", now_us=t0)
    d.call("estop_tcp_open", slot=0, now_us=t0)
    for s in steps:
        d.run(s)
    SEEN["traces"] += 1
    SEEN["calls"] += len(twin.history)
    SEEN["steps"] += len(steps)
    SEEN["wrapped"] += d.wrapped
    SEEN["armed"] += d.armed


def test_random_traces_reached_the_interesting_states() -> None:
    """The trace test above is not vacuous: it armed the unit and wrapped the clock often.
    (Runs after it in file order; on its own it runs a short batch first.)"""
    if SEEN["traces"] < 100:
        test_random_traces_match_the_host_build()
    assert SEEN["armed"] > 0.2 * SEEN["traces"], SEEN
    assert SEEN["wrapped"] > 0.05 * SEEN["traces"], SEEN


def test_the_comparison_catches_a_build_that_differs(tmp_path: Path) -> None:
    """A copy of the core whose CAN alive counter wraps one step early, built for M0+: the
    twin must tell it from the host build at the first frame where the counters part."""
    core = tmp_path / "core"
    shutil.copytree(mcubuild.CORE_DIR, core)
    src = core / "estop_core.c"
    text = src.read_text()
    assert "#define COUNTER_MODULO 15u" in text
    src.write_text(text.replace("#define COUNTER_MODULO 15u", "#define COUNTER_MODULO 14u"))
    try:
        (v,) = mcubuild.build(core, tmp_path / "out", ["m0plus-Os"])
    except mcubuild.McuError as exc:
        pytest.fail(str(exc), pytrace=False)
    u = TwinUnit(Twin((v,)))
    with pytest.raises(Mismatch, match=r"byte \d+ \((brake_counter|can\[\d\]\.data\[[67]\])\)"):
        for _ in range(20):
            u.wait(10 * MS)
