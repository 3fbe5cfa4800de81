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

import hashlib
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
    LIFT,
    LIFT_ID,
    MS,
    SLOWING,
    STOP_ID,
    STOPPED,
    TCP_STOP,
    UDP_TIMEOUT,
    packet,
    reply_fields,
    request,
)
from estop.core import TEST_SESSION, ffi, lib
from estop.protocol import auth
from estop.protocol.udp import ControlPacket
from mcu_util import U32, Mismatch, Twin, TwinUnit, config_bytes, mcubuild
from vectors import AUTH_CONTROL_EXAMPLE as V_CONTROL
from vectors import AUTH_RELEASE_EXAMPLE as V_RELEASE
from vectors import AUTH_STATUS_EXAMPLE as V_STATUS
from vectors import AUTH_STATUS_REPLY_EXAMPLE as V_STATUS_REPLY
from vectors import AUTH_STOP_EXAMPLE as V_STOP
from vectors import (
    BRAKE_ARMED_7,
    BRAKE_BOOT_0,
    BRAKE_TIMEOUT_14,
    RELEASE_EXAMPLE,
    STOP_EXAMPLE,
    UDP_EXAMPLE,
)

STATUS, RELEASE = 0x00000001, 0x00000002
NEUTRAL = packet()
K = bytes(range(32))        # the key of PROTOCOL.md 5.4
N = TEST_SESSION            # ... and its session
RID = 7


def beat(counter: int, gas: float = 0.0, *, rid: int = RID, key: bytes | None = K,
         session: int = N, gear: int = 4) -> bytes:
    """An authenticated control packet (PROTOCOL.md 5.1)."""
    body = ControlPacket(gas_brake=gas, gear=gear)
    return auth.AuthControlPacket(rid, session, counter, body).encode(key, validate=False)


def frame(msg_id: int, seq: int, counter: int, *, rid: int = RID, key: bytes | None = K,
          session: int = N) -> bytes:
    """A request frame (PROTOCOL.md 5.2)."""
    return auth.AuthRequest(msg_id, seq, rid, session, counter).encode(key)
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


def test_spec_vectors_of_section_5_on_the_mcu_builds() -> None:
    """The 5.4 vectors on a unit with the key K and session N: the STATUS reply byte for byte,
    the control packet, RELEASE and STOP."""
    twin = Twin()
    u = TwinUnit(twin, cfg=config_bytes(auth_key=K))
    u.open(0)
    assert u.tcp(0, V_STATUS) == [V_STATUS_REPLY]
    u.wait(20 * MS)
    u.udp(V_CONTROL)
    twin.call("estop_get_status")
    assert twin.host.objects["estop_status_t"].counters.udp_valid == 1
    for counter in range(1, 6):  # the link from remote 8: the vectors are remote 7's messages
        u.wait(20 * MS)       # in order, and a RELEASE must be above its newest control packet
        u.udp(beat(counter, rid=RID + 1))
    (rep,) = u.tcp(0, V_RELEASE)
    r = auth.AuthReply.decode(rep, K, auth.request_tag(V_RELEASE))
    assert (r.ack, r.state, r.session, r.counter) == (True, ARMED, N, 2)
    (rep,) = u.tcp(0, V_STOP)
    r = auth.AuthReply.decode(rep, K, auth.request_tag(V_STOP))
    assert (r.ack, r.state, r.reason, r.counter) == (True, STOPPED, TCP_STOP, 3)


# -- an hour of driving, compressed --------------------------------------------------------------
def drive_body(i: int) -> tuple[float, float, int, int, int]:
    gas = 0.6 * math.sin(i / 7.0)
    steer = max(-1.0, min(1.0, math.cos(i / 5.0)))
    return gas, steer, 8 if gas > 0 else 4, i % 4, i % 2


class Remote:
    """The tablet: plain packets and frames, or (keyed) authenticated ones with its counters."""

    def __init__(self, keyed: bool) -> None:
        self.keyed = keyed
        self.counter = 0  # one for all its messages (PROTOCOL.md 5)

    def packet(self, gas: float = 0.0, steer: float = 0.0, gear: int = 4, turn: int = 0,
               horn: int = 0) -> bytes:
        if not self.keyed:
            return packet(gas=gas, steer=steer, gear=gear, turn=turn, horn=horn)
        self.counter += 1
        body = ControlPacket(gas, steer, gear, turn, horn)
        return auth.AuthControlPacket(RID, N, self.counter, body).encode(K)

    def request(self, msg_id: int, seq: int) -> bytes:
        if not self.keyed:
            return request(msg_id, seq)
        self.counter += 1
        return frame(msg_id, seq, self.counter)


def fields(rep: bytes, req: bytes) -> tuple[int, int, int, int]:
    """(ACK/NAK, seq, state, reason) of a plain reply, or of a 48-byte one that verifies under
    the key as the answer to req."""
    if len(rep) == 48:
        r = auth.AuthReply.decode(rep, K, auth.request_tag(req))
        return r.msg_id, r.seq, r.state, r.reason
    return reply_fields(rep)[:4]


@pytest.mark.parametrize("keyed", [False, True], ids=["plain", "keyed"])
def test_an_hour_of_driving_compressed(keyed: bool) -> None:
    """Each minute: the gap since the last one (one tick), heartbeats at 50 Hz, a RELEASE, a
    second of driving with STATUS requests split across reads (and a burst of lost packets
    that slows the unit down until three packets bring it back), then one of eight endings.
    The unit stops in two stages (S 100 ms, T 200 ms). The clock starts half an hour before
    its 32-bit wrap. Keyed: every packet and request is authenticated, and the endings include
    a replay and forged tags. The stack every entry point used is measured and must stay
    within the static bound of test_mcu_footprint.py."""
    twin = Twin(measure_stack=True)
    start = (1 << 32) - 1_800_000_000
    u = TwinUnit(twin, start, cfg=config_bytes(auth_key=K if keyed else None,
                                               timeout_us=200 * MS, slow_us=100 * MS,
                                               warn_us=50 * MS, slow_level=40))
    remote = Remote(keyed)
    u.open(0)
    u.open(1)
    seq = 0
    endings: Counter[str] = Counter()
    for minute in range(MINUTES):
        u.jump(start + minute * 60_000_000 + 1)
        for _ in range(6):
            u.wait(20 * MS)
            u.udp(remote.packet())
        seq += 1
        req = remote.request(RELEASE, seq)
        (rep,) = u.tcp(0, req)
        assert fields(rep, req)[:3] == (ACK, seq, ARMED), f"minute {minute}"
        last = b""
        for i in range(50):
            u.wait((130 if i == 25 else 20) * MS)  # the 25th: after a burst of lost packets
            last = remote.packet(*drive_body(minute * 50 + i))
            u.udp(last)
            assert u.state == (SLOWING if i in (25, 26) else ARMED), f"minute {minute}, {i}"
            if i % 10 == 5:
                seq += 1
                req = remote.request(STATUS, seq)
                assert u.tcp(1, req[:5]) == []
                u.wait(1 * MS)
                (rep,) = u.tcp(1, req[5:])
                assert fields(rep, req)[:3] == (ACK, seq, u.state)
        ending = ("tcp_stop", "silence", "fault", "bad_crc", "stale", "invalid", "lift",
                  "lift_datagram")[minute % 8]
        endings[ending] += 1
        if ending == "tcp_stop":
            seq += 1
            req = remote.request(STOP_ID, seq)
            (rep,) = u.tcp(0, req)
            assert fields(rep, req)[2:4] == (STOPPED, TCP_STOP)
        elif ending == "silence":
            u.wait(150 * MS)
            assert u.state == SLOWING
            u.wait(100 * MS)
            assert u.reason == UDP_TIMEOUT
        elif ending == "lift":
            seq += 1
            req = remote.request(LIFT_ID, seq)
            (rep,) = u.tcp(0, req)
            assert fields(rep, req)[2:4] == (STOPPED, LIFT)
        elif ending == "lift_datagram":
            u.wait(120 * MS)  # from SLOWING: a lift datagram, whatever its tag
            assert u.state == SLOWING
            u.udp(b"ESQ2" + struct.pack("<I", LIFT_ID) + bytes(40))
            assert u.reason == LIFT
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
        elif ending == "stale":
            # Keyed: the last packet replayed; plain: the older 16-byte form (valid).
            for _ in range(25):
                u.wait(20 * MS)
                u.udp(last if keyed else packet(legacy=True))
            u.wait(300 * MS)
            assert u.reason == UDP_TIMEOUT
        else:
            for _ in range(15):
                u.wait(20 * MS)
                u.udp(last[:44] + bytes(16) if keyed
                      else struct.pack("<ffiii", math.nan, 0.0, 4, 0, 0))
            assert u.reason == UDP_TIMEOUT
        u.wait(300 * MS)
        assert u.state == STOPPED
    assert u.t > 1 << 32 and set(endings) == {"tcp_stop", "silence", "fault", "bad_crc",
                                               "stale", "invalid", "lift", "lift_datagram"}
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
        lambda d: {**d, "slow_us": d["timeout_us"], "warn_us": d["timeout_us"] // 2}),
    # a two-stage stop (protocol version 3): SLOWING from a quarter of the timeout
    st.fixed_dictionaries({"timeout_us": st.integers(4000, 1_000_000),
                           "slow_level": st.integers(1, 99)}).map(
        lambda d: {**d, "slow_us": d["timeout_us"] // 4, "warn_us": d["timeout_us"] // 8}),
    st.lists(st.sampled_from(CONFIG_FIELDS).flatmap(field_values), max_size=2).map(dict),
)

# Time steps: mostly a host's pace, sometimes long silences, rarely a huge jump or the clock
# going backwards (which the core treats as a fault).
dt = st.one_of(st.integers(0, 25_000), st.integers(0, 25_000), st.integers(0, 400_000),
               st.integers(0, 0x7FFFFFFF), st.sampled_from([0x7FFFFFFF, 0x80000000, U32]),
               st.integers(-50_000, -1))
short = st.integers(0, 25_000)

# Authenticated messages are made at run time from these choices, with the remote's counters.
rid = st.one_of(st.just(RID), st.just(RID), st.integers(0, 10))
counter_mode = st.sampled_from(["next", "next", "next", "same", "jump", "zero", "max"])
session_mode = st.sampled_from(["N", "N", "N", "N", "zero", "other"])
msg_id = st.one_of(st.sampled_from([RELEASE, STOP_ID, STATUS, LIFT_ID]), st.integers(0, U32))

step = st.one_of(
    st.tuples(st.just("tick"), dt),
    st.tuples(st.just("udp"), dt, udp_data),
    st.tuples(st.just("udp"), dt, udp_data),
    st.tuples(st.just("beats"), dt, st.integers(1, 8)),
    st.tuples(st.just("beats"), short, st.integers(5, 8)),
    st.tuples(st.just("tcp"), short, st.just(0), release_now),
    st.tuples(st.just("arm"), short, st.integers(0, U32)),
    st.tuples(st.just("arm"), short, st.integers(0, U32)),
    st.tuples(st.just("tcp"), dt, st.integers(0, 3), tcp_bytes),
    st.tuples(st.just("tcp"), dt, st.integers(0, 3), tcp_bytes),
    st.tuples(st.just("auth_udp"), short, rid, counter_mode, st.sampled_from([0.0, -0.5, 0.5]),
              st.booleans() | st.just(True), session_mode),
    st.tuples(st.just("auth_udp"), dt, rid, counter_mode, st.sampled_from([0.0, 2.0]),
              st.booleans(), session_mode),
    st.tuples(st.just("auth_tcp"), short, st.integers(0, 3), msg_id, st.integers(0, U32), rid,
              counter_mode, st.booleans() | st.just(True), session_mode, st.integers(0, 47)),
    st.tuples(st.just("stop_dgram"), dt, st.booleans(), st.integers(0, U32)),
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
U64 = (1 << 64) - 1
SESSIONS = {"N": N, "zero": 0, "other": N ^ 0x10}


class Driver:
    def __init__(self, twin: Twin, t: int, keyed: bool) -> None:
        self.twin, self.t, self.keyed = twin, t, keyed
        self.wrapped = self.armed = False
        self.counters: dict[tuple[int, str], int] = {}

    def call(self, fn: str, **values: Any) -> Any:
        return self.twin.call(fn, **values)

    def counter(self, remote: int, channel: str, mode: str) -> int:
        """A remote's counter: one for both channels (PROTOCOL.md 5; `channel` is for whom)."""
        del channel
        last = self.counters.get((remote, "any"), 0)
        value = {"next": last + 1, "same": last, "jump": last + 1000, "zero": 0,
                 "max": U64}[mode] & U64
        self.counters[(remote, "any")] = value
        return value

    def beat(self) -> bytes:
        return beat(self.counter(RID, "udp", "next")) if self.keyed else NEUTRAL

    def run(self, s: tuple[Any, ...]) -> None:
        kind = s[0]
        if isinstance(s[1], int) and kind not in ("status", "null", "config", "name"):
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
                self.call("estop_udp_rx", data=self.beat(), now_us=self.t)
        elif kind == "arm":
            self.run(("beats", 0, 6))
            release = (frame(RELEASE, s[2], self.counter(RID, "tcp", "next")) if self.keyed
                       else request(RELEASE, s[2]))
            self.run(("tcp", 1000, 0, release))
        elif kind == "auth_udp":
            _, _, remote, mode, gas, tag_ok, session = s
            pkt = beat(self.counter(remote, "udp", mode), gas, rid=remote,
                       session=SESSIONS[session])
            self.call("estop_udp_rx", data=pkt if tag_ok else pkt[:-1] + b"\x00", now_us=now)
        elif kind == "auth_tcp":
            _, _, slot, msg, seq, remote, mode, tag_ok, session, cut = s
            req = frame(msg, seq, self.counter(remote, "tcp", mode), rid=remote,
                        session=SESSIONS[session], key=K if tag_ok else bytes(32))
            self.run(("tcp", 0, slot, req[:cut] if cut else req))
        elif kind == "stop_dgram":
            dgram = auth.stop_datagram(s[3], self.counter(RID, "udp", "next"),
                                       key=K if s[2] else None, session=N, remote_id=RID)
            self.call("estop_udp_rx", data=dgram, now_us=now)
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
            self.call("estop_init", cfg=config_bytes(auth_key=K if self.keyed else None, **s[2]),
                      now_us=now)
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
@given(keyed=st.booleans(), t0=start_time,
       steps=st.integers(1, 50).flatmap(lambda n: st.lists(step, min_size=n, max_size=n)))
def test_random_traces_match_the_host_build(keyed: bool, t0: int,
                                            steps: list[tuple[Any, ...]]) -> None:
    """Plain and keyed units (key K): every call on both builds, compared after each."""
    twin = shared_twin()
    d = Driver(twin, t0, keyed)
    d.call("estop_init", cfg=config_bytes(auth_key=K if keyed else None), now_us=t0)
    d.call("estop_tick", now_us=t0)
    d.call("estop_tcp_open", slot=0, now_us=t0)
    for s in steps:
        d.run(s)
    SEEN["traces"] += 1
    SEEN["calls"] += len(twin.history)
    SEEN["steps"] += len(steps)
    SEEN["wrapped"] += d.wrapped
    SEEN["armed"] += d.armed
    SEEN["keyed"] += keyed
    SEEN["keyed_armed"] += keyed and d.armed


def test_random_traces_reached_the_interesting_states() -> None:
    """The trace test above is not vacuous: it armed the unit and wrapped the clock often.
    (Runs after it in file order; on its own it runs a short batch first.)"""
    if SEEN["traces"] < 100:
        test_random_traces_match_the_host_build()
    assert SEEN["armed"] > 0.2 * SEEN["traces"], SEEN
    assert SEEN["keyed_armed"] > 0.1 * SEEN["keyed"] > 0.03 * SEEN["traces"], SEEN
    assert SEEN["wrapped"] > 0.05 * SEEN["traces"], SEEN


def test_the_comparison_catches_a_build_that_differs(tmp_path: Path) -> None:
    """A copy of the core whose CAN alive counter wraps one step early, built for M0+: the
    twin must tell it from the host build at the first frame where the counters part."""
    core = tmp_path / "core"
    shutil.copytree(mcubuild.CORE_DIR, core)
    src = core / "estop_clock.c"
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


# -- BLAKE2s: the MCU build against the host build and against hashlib --------------------------
@settings(max_examples=150, deadline=None)
@given(key=st.binary(max_size=33), msg=st.binary(max_size=200), outlen=st.integers(0, 33),
       flip=st.integers(0, 15))
def test_blake2s_on_the_mcu_matches_hashlib(key: bytes, msg: bytes, outlen: int,
                                            flip: int) -> None:
    """estop_blake2s, the precomputed-key MAC and the constant-time compare, called on both
    builds (compared by the twin), and the digests checked against hashlib."""
    twin = shared_twin()
    res = twin.call("estop_blake2s", outlen=outlen, key=key, msg=msg)
    ok = 1 <= outlen <= 32 and len(key) <= 32
    assert (res.ret == 0) == ok
    if ok:
        want = hashlib.blake2s(msg, key=key, digest_size=outlen).digest()
        assert bytes(twin.host.objects["buf:out"])[:outlen] == want
    res = twin.call("estop_b2s_key_init", key=key, outlen=outlen)
    if res.ret == 0:
        res = twin.call("estop_b2s_mac", msg=msg)
        assert (res.ret == 0) == (len(msg) > 0)
        if msg:
            tag = bytes(twin.host.objects["buf:out"])[:outlen]
            assert tag == hashlib.blake2s(msg, key=key, digest_size=outlen).digest()
            other = bytearray(tag)
            other[flip % len(tag)] ^= 1 << (flip % 8)
            assert twin.call("estop_ct_equal", a=tag, b=tag).ret == 1
            assert twin.call("estop_ct_equal", a=tag, b=bytes(other)).ret == 0
