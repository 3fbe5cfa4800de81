"""The C entry points called directly through cffi: configuration checks, argument errors,
the raw 32-bit tick (wrap, steps that look backwards) and the error names."""

from __future__ import annotations

import dataclasses

import pytest

from core_util import MS, STOP_ID, packet, reply_fields, request
from estop.core import TEST_SESSION, Config, CoreError, Watchdog, check_config, ffi, lib
from estop.protocol import auth
from estop.protocol.udp import ControlPacket

U32 = 0xFFFFFFFF


class Raw:
    """The core driven with raw uint32 ticks, as a microcontroller host would."""

    def __init__(self, now: int = 0) -> None:
        self.core = ffi.new("estop_core_t *")
        self.out = ffi.new("estop_out_t *")
        self.consumed = ffi.new("size_t *")
        cfg = ffi.new("estop_config_t *")
        lib.estop_config_default(cfg)
        cfg.session = 1  # the host's to draw; the defaults leave it 0, which init refuses
        assert lib.estop_init(self.core, cfg, now & U32) == lib.ESTOP_OK

    def tick(self, t: int) -> int:
        assert lib.estop_tick(self.core, t & U32, self.out) == lib.ESTOP_OK
        return self.out.state

    def udp(self, data: bytes, t: int) -> None:
        buf = ffi.from_buffer("uint8_t[]", data)
        assert lib.estop_udp_rx(self.core, buf, len(data), t & U32, self.out) == lib.ESTOP_OK

    def tcp(self, slot: int, data: bytes, t: int) -> int:
        buf = ffi.from_buffer("uint8_t[]", data)
        return lib.estop_tcp_rx(self.core, slot, buf, len(data), self.consumed, t & U32,
                                self.out)

    def release(self, t: int) -> tuple[int, int, int, int, int, int]:
        assert lib.estop_tcp_open(self.core, 0, t & U32, self.out) == lib.ESTOP_OK
        assert self.tcp(0, request(2), t) == lib.ESTOP_OK
        return reply_fields(bytes(ffi.buffer(self.out.reply, 16)))

    def state(self) -> tuple[int, int]:
        st = ffi.new("estop_status_t *")
        assert lib.estop_get_status(self.core, st) == lib.ESTOP_OK
        return st.state, st.reason


# -- configuration ----------------------------------------------------------------------------
BAD_CONFIGS = [
    ({"timeout_us": 999}, "bad_timeout"),
    ({"timeout_us": 60_000_001}, "bad_timeout"),
    ({"warn_us": 0}, "bad_warn_time"),
    ({"warn_us": 200_001}, "bad_warn_time"),  # above the slow time (= the timeout)
    ({"slow_us": 100_000, "warn_us": 100_001}, "bad_warn_time"),
    ({"slow_us": 0, "warn_us": 1}, "bad_slow_time"),
    ({"slow_us": 200_001}, "bad_slow_time"),  # above the timeout
    ({"slow_level": 0}, "bad_slow_level"),
    ({"slow_level": 100}, "bad_slow_level"),
    ({"slow_level": 255}, "bad_slow_level"),
    ({"tag_checks": 101}, "bad_tag_budget"),
    ({"tag_window_us": 999}, "bad_tag_budget"),
    ({"tag_window_us": 1_000_001}, "bad_tag_budget"),
    ({"stop_id": 0}, "bad_stop_id"),
    ({"stop_id": 1}, "bad_stop_id"),
    ({"stop_id": 2}, "bad_stop_id"),
    ({"stop_id": 3}, "bad_stop_id"),  # LIFT
    ({"stop_id": 0x32515345}, "bad_stop_id"),  # "ESQ2": a plain STOP would read as a magic
    ({"brake_can_id": 0x800}, "bad_can_id"),
    ({"status_can_id": 0x800}, "bad_can_id"),
    ({"status_can_id": 0x050}, "bad_can_id"),
    ({"status_data_id": 0x0E57}, "bad_data_id"),
    ({"release_packets": 0}, "bad_release_count"),
    ({"brake_period_us": 999}, "bad_brake_period"),
    ({"brake_period_us": 25_001}, "bad_brake_period"),
    ({"status_period_us": 9_999}, "bad_status_period"),
    ({"status_period_us": 1_000_001}, "bad_status_period"),
    ({"brake_period_us": 20_000, "status_period_us": 15_000}, "bad_status_period"),
    ({"key": bytes(31)}, "bad_key"),
    ({"key": bytes(33)}, "bad_key"),
    ({"session": 0}, "bad_session"),
    ({"session": 0, "key": bytes(32)}, "bad_session"),
]


@pytest.mark.parametrize(("change", "name"), BAD_CONFIGS)
def test_bad_configuration_is_refused_with_a_named_error(change: dict[str, int], name: str) -> None:
    cfg = dataclasses.replace(Config(), **change)
    with pytest.raises(CoreError) as err:
        check_config(cfg)
    assert err.value.name == name
    with pytest.raises(CoreError):
        Watchdog(cfg)


def test_failed_init_leaves_an_unusable_core() -> None:
    core = ffi.new("estop_core_t *")
    out = ffi.new("estop_out_t *")
    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)
    assert lib.estop_init(core, cfg, 0) == lib.ESTOP_ERR_SESSION  # the host must draw one
    cfg.session = 7
    assert lib.estop_init(core, cfg, 0) == lib.ESTOP_OK
    cfg.stop_id = 0
    assert lib.estop_init(core, cfg, 0) == lib.ESTOP_ERR_STOP_ID
    for rc in (lib.estop_tick(core, 0, out), lib.estop_fault(core, 0, out),
               lib.estop_udp_rx(core, ffi.NULL, 0, 0, out),
               lib.estop_tcp_open(core, 0, 0, out),
               lib.estop_get_status(core, ffi.new("estop_status_t *"))):
        assert rc == lib.ESTOP_ERR_NOT_INIT


def test_boundary_configurations_are_accepted() -> None:
    for cfg in (Config(timeout_us=1000, warn_us=999), Config(timeout_us=60_000_000),
                Config(timeout_us=1000, slow_us=1000, warn_us=1000),  # W = S = T
                Config(timeout_us=1000, slow_us=1, warn_us=1),  # the smallest times
                Config(timeout_us=60_000_000, slow_us=60_000_000, warn_us=60_000_000),
                Config(slow_level=1), Config(slow_level=99),
                Config(tag_checks=0),  # ESTOP_TAG_CHECKS_ALL: every tag checked
                Config(tag_checks=1, tag_window_us=1000),
                Config(tag_checks=100, tag_window_us=1_000_000),
                Config(brake_period_us=1000, status_period_us=10_000),
                Config(brake_period_us=25_000, status_period_us=1_000_000),
                Config(release_packets=1, brake_can_id=0x7FF, status_can_id=0)):
        check_config(cfg)


def test_null_arguments_are_refused() -> None:
    raw = Raw()
    out = ffi.new("estop_out_t *")
    assert lib.estop_init(ffi.NULL, ffi.NULL, 0) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_init(ffi.new("estop_core_t *"), ffi.NULL, 0) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_config_check(ffi.NULL) == lib.ESTOP_ERR_NULL_ARG
    lib.estop_config_default(ffi.NULL)  # must not crash
    assert lib.estop_tick(ffi.NULL, 0, out) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_tick(raw.core, 0, ffi.NULL) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_get_status(raw.core, ffi.NULL) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_tcp_open(ffi.NULL, 0, 0, out) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_tcp_rx(raw.core, 0, ffi.NULL, 1, raw.consumed, 0, out) == \
        lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_tcp_rx(raw.core, 0, ffi.NULL, 0, ffi.NULL, 0, out) == \
        lib.ESTOP_ERR_NULL_ARG
    raw.udp(b"", 0)  # a zero-length datagram is just invalid
    assert lib.estop_udp_rx(raw.core, ffi.NULL, 0, 0, raw.out) == lib.ESTOP_OK


def test_slot_errors() -> None:
    raw = Raw()
    out = raw.out
    assert lib.estop_tcp_open(raw.core, 8, 0, out) == lib.ESTOP_ERR_SLOT
    assert lib.estop_tcp_close(raw.core, 8, 0, out) == lib.ESTOP_ERR_SLOT
    assert raw.tcp(8, request(1), 0) == lib.ESTOP_ERR_SLOT
    assert raw.tcp(3, request(1), 0) == lib.ESTOP_ERR_SLOT_CLOSED
    assert raw.consumed[0] == 0 and not out.has_reply
    assert lib.estop_tcp_open(raw.core, 3, 0, out) == lib.ESTOP_OK
    assert raw.tcp(3, request(1), 0) == lib.ESTOP_OK and out.has_reply
    assert lib.estop_tcp_close(raw.core, 3, 0, out) == lib.ESTOP_OK
    assert raw.tcp(3, request(1), 0) == lib.ESTOP_ERR_SLOT_CLOSED


def test_reopened_slot_drops_a_half_frame() -> None:
    raw = Raw()
    lib.estop_tcp_open(raw.core, 0, 0, raw.out)
    raw.tcp(0, request(1)[:7], 0)
    lib.estop_tcp_open(raw.core, 0, 0, raw.out)
    assert raw.tcp(0, request(1), 0) == lib.ESTOP_OK and raw.out.has_reply


def test_names() -> None:
    assert ffi.string(lib.estop_err_name(0)) == b"ok"
    assert ffi.string(lib.estop_err_name(lib.ESTOP_ERR_SLOT_CLOSED)) == b"slot_closed"
    assert ffi.string(lib.estop_err_name(-99)) == b"unknown_error"
    assert ffi.string(lib.estop_err_name(5)) == b"unknown_error"
    assert [ffi.string(lib.estop_state_name(i)) for i in range(4)] == [
        b"STOPPED", b"ARMED", b"SLOWING", b"?"]
    assert [ffi.string(lib.estop_reason_name(i)) for i in range(7)] == [
        b"none", b"boot", b"tcp_stop", b"udp_timeout", b"fault", b"lift", b"?"]
    assert ffi.string(lib.estop_err_name(lib.ESTOP_ERR_SLOW)) == b"bad_slow_time"
    assert ffi.string(lib.estop_err_name(lib.ESTOP_ERR_SLOW_LEVEL)) == b"bad_slow_level"
    assert ffi.string(lib.estop_err_name(lib.ESTOP_ERR_TAG_BUDGET)) == b"bad_tag_budget"
    assert ffi.string(lib.estop_err_name(lib.ESTOP_ERR_TAG_BUDGET - 1)) == b"unknown_error"


# -- the raw tick ---------------------------------------------------------------------------
def feed_raw(raw: Raw, start: int, n: int = 5) -> int:
    """n valid packets 20 ms apart after start, each after a tick; returns the last time."""
    t = start
    for _ in range(n):
        t += 20 * MS
        raw.tick(t)
        raw.udp(packet(), t)
    return t


def arm_raw(raw: Raw, start: int) -> int:
    t = feed_raw(raw, start)
    assert raw.release(t)[2] == 1
    return t


@pytest.mark.parametrize("start", [0, 0x7FFFFFFF, 0xFFFFFFFF - 50 * MS, 0xFFFFFFFF])
def test_timeout_is_exact_across_the_tick_wrap(start: int) -> None:
    raw = Raw(start)
    last = arm_raw(raw, start)
    assert raw.tick(last + 200 * MS - 1) == 1
    assert raw.out.next_call_us == (last + 200 * MS) & U32 or \
        ((raw.out.next_call_us - (last & U32)) & U32) < 200 * MS
    assert raw.tick(last + 200 * MS) == 0
    assert raw.state() == (0, 3)


def test_silent_link_past_the_tick_wrap_period_never_looks_alive_again() -> None:
    """71.6 minutes of silence bring the 32-bit age back to 0; the link must stay dead."""
    raw = Raw(0)
    t = 0
    for _ in range(5):
        t += 20 * MS
        raw.tick(t)
        raw.udp(packet(), t)
    last = t
    # The host calls at least every half range: the core sees the link age out on the way.
    for t in (last + 150 * MS, last + 250 * MS, last + 0x7FFFFFFF, last + 2**32 - 1,
              last + 2**32, last + 2**32 + 10 * MS):
        raw.tick(t)
    st = ffi.new("estop_status_t *")
    lib.estop_get_status(raw.core, st)
    assert not st.link_live and st.link_age_us == U32
    assert raw.release(last + 2**32 + 10 * MS)[5] == 2


def test_wrapper_splits_long_gaps_so_the_link_stays_dead() -> None:
    wd = Watchdog()
    for k in range(1, 6):
        wd.udp(packet(), k * 20 * MS)
    wd.tcp_open(0, 100 * MS)
    assert reply_fields(wd.tcp_data(0, request(2), 100 * MS)[0].reply)[2] == 1
    later = 100 * MS + 2**32  # exactly one wrap later: the same 32-bit tick
    step = wd.tick(later)
    assert (step.state, step.reason) == (0, 3) and step.changed_by_clock
    assert reply_fields(wd.tcp_data(0, request(2), later)[0].reply)[5] == 2


def test_tick_that_goes_backwards_is_a_fault_stop() -> None:
    raw = Raw(1_000_000)
    last = arm_raw(raw, 1_000_000)
    assert raw.tick(last - 1) == 0
    assert raw.state() == (0, 4)
    assert raw.out.state_changed and raw.out.changed_by_clock
    st = ffi.new("estop_status_t *")
    lib.estop_get_status(raw.core, st)
    assert st.counters.faults == 1 and not st.link_live


def test_tick_going_backwards_restarts_a_stopped_units_release_count() -> None:
    """A STOPPED unit with 5 valid packets counted, then a tick backwards: the link is stale
    and the count starts over from 0, so four packets after it cannot make a RELEASE succeed.
    advance_clock resets valid_run itself, since it stops a moving unit only; the mutants that
    dropped the reset, or reset to 1, survived every test."""
    raw = Raw(1_000_000)
    t = feed_raw(raw, 1_000_000)
    assert raw.state() == (0, 1)  # still STOPPED, reason boot: no RELEASE sent yet
    back = t - 1
    assert raw.tick(back) == 0
    for k in range(4):
        raw.udp(packet(), back + k * MS)
    assert raw.release(back + 3 * MS)[5] == 2  # NAK no live link: 4 packets since the step
    raw.udp(packet(), back + 4 * MS)
    assert raw.release(back + 4 * MS)[5] == 0


def _frame_times(raw: Raw, start: int, end: int, step: int, can_id: int) -> list[int]:
    """Ticks the raw core every `step` us from start to end; the times frames of can_id left."""
    times = []
    for t in range(start, end, step):
        raw.tick(t)
        times += [t for i in range(raw.out.n_can) if raw.out.can[i].id == can_id]
    return times


@pytest.mark.parametrize("back_us", [1, 1_000_000, 2**31 - 1])
def test_brake_period_holds_when_the_tick_goes_back_while_stopped(back_us: int) -> None:
    """A 1 s step back used to silence ESTOP_BRAKE for 1 s, until the tick caught up."""
    raw = Raw(5_000_000)
    _frame_times(raw, 5_000_000, 5_100_001, 1_000, 0x050)  # last tick at 5.1 s, a frame then
    back = 5_100_000 - back_us
    times = _frame_times(raw, back, back + 100_000, 1_000, 0x050)
    assert times[0] - back <= 10_000  # no later than one period after the step back
    assert all(b - a <= 10_000 for a, b in zip(times, times[1:], strict=False))
    assert len(times) >= 10
    assert raw.state() == (0, 1)  # still STOPPED, still the first reason


def test_status_period_holds_when_the_tick_goes_back_while_armed() -> None:
    raw = Raw(1_000_000)
    last = arm_raw(raw, 1_000_000)
    back = last - 500_000
    status = _frame_times(raw, back, back + 150_000, 1_000, 0x051)
    assert status[0] == back and status[1] - status[0] == 100_000
    assert raw.state() == (0, 4)


def test_err_name_of_any_int_is_safe() -> None:
    """-INT_MIN overflowed (UBSan reported it under the instrumented build)."""
    for code in (-(2**31), 2**31 - 1, 1, -18, -10**6):
        assert ffi.string(lib.estop_err_name(code)) == b"unknown_error"
    assert ffi.string(lib.estop_err_name(-12)) == b"slot_closed"
    assert ffi.string(lib.estop_err_name(-14)) == b"bad_session"


def test_wrapper_refuses_time_going_backwards() -> None:
    wd = Watchdog(now_us=500)
    with pytest.raises(ValueError, match="backwards"):
        wd.tick(499)


def test_reply_while_stopped_reports_state_reason_flags() -> None:
    raw = Raw()
    lib.estop_tcp_open(raw.core, 1, 0, raw.out)
    raw.tcp(1, request(STOP_ID, 42), 0)
    assert reply_fields(bytes(ffi.buffer(raw.out.reply, 16))) == (0x80, 42, 0, 1, 0, 0)


def test_status_frame_counts_saturate_at_255() -> None:
    key = bytes(32)
    wd = Watchdog(dataclasses.replace(Config(), key=key))
    wd.tick(0)
    good = auth.AuthControlPacket(1, TEST_SESSION, 1, ControlPacket()).encode(key)
    wd.udp(good, 500)
    for _ in range(300):
        wd.udp(good, 1000)  # a replay: invalid and an authentication failure
        wd.udp(b"x", 1000)
    for _ in range(300):
        wd.tcp_open(0, 2000)
        assert wd.tcp_data(0, b"\x00" * 16, 2000)[-1].close
    status = [f.data for f in wd.tick(100 * MS).frames if f.can_id == 0x051]
    assert status[0][:3] == bytes([1, 255, 255])
    counters = wd.status().counters
    assert (counters.tcp_bad_crc, counters.auth_old_counter) == (300, 300)
    status = [f.data for f in wd.tick(200 * MS).frames if f.can_id == 0x051]
    assert status[0][:3] == bytes([0, 0, 0])  # window counts restart with every frame


def test_null_status_read_out_and_empty_tcp_read() -> None:
    raw = Raw()
    assert lib.estop_get_status(ffi.NULL, ffi.new("estop_status_t *")) == lib.ESTOP_ERR_NULL_ARG
    lib.estop_tcp_open(raw.core, 0, 0, raw.out)
    assert lib.estop_tcp_rx(raw.core, 0, ffi.NULL, 0, raw.consumed, 0, raw.out) == lib.ESTOP_OK
    assert raw.consumed[0] == 0 and not raw.out.has_reply


# -- the core's own byte loops (zero_bytes, copy_bytes) ------------------------------------------
GUARD = 16  # bytes of 0xA5 on each side of a structure, checked after every call


def guarded(ctype: str) -> tuple[object, object]:
    """A `ctype` inside a buffer with guard bytes before and after it: (pointer, buffer)."""
    size = ffi.sizeof(ctype)
    buf = ffi.new("uint8_t[]", size + 2 * GUARD)
    ffi.memmove(buf, b"\xa5" * (size + 2 * GUARD), size + 2 * GUARD)
    return ffi.cast(ctype + " *", buf + GUARD), buf


def guards_intact(buf: object, size: int) -> bool:
    raw = bytes(ffi.buffer(buf, size + 2 * GUARD))
    return raw[:GUARD] == b"\xa5" * GUARD and raw[GUARD + size:] == b"\xa5" * GUARD


def test_init_over_a_used_core_starts_afresh_and_writes_only_the_core() -> None:
    """A host may re-initialise the core in place (a reset without a reboot): every byte of the
    old state must go, and not one byte around the structure may change."""
    size = ffi.sizeof("estop_core_t")
    core, buf = guarded("estop_core_t")
    out = ffi.new("estop_out_t *")
    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)
    cfg.session = 1
    fresh = ffi.new("estop_core_t *")
    assert lib.estop_init(fresh, cfg, 0) == lib.ESTOP_OK
    # Use the guarded core, then fill it with junk, as memory never cleared would be.
    assert lib.estop_init(core, cfg, 0) == lib.ESTOP_OK
    for t in range(0, 200 * MS, 20 * MS):
        data = ffi.from_buffer("uint8_t[]", packet())
        lib.estop_udp_rx(core, data, 20, t, out)
    ffi.memmove(core, b"\x5a" * size, size)
    assert lib.estop_init(core, cfg, 0) == lib.ESTOP_OK
    assert bytes(ffi.buffer(core, size)) == bytes(ffi.buffer(fresh, size))
    assert guards_intact(buf, size)


def test_refused_init_wipes_every_byte_of_the_core() -> None:
    """prove/assumed.txt's core_wiped: estop_init first zeroes the whole core (magic 0, no slot
    fill, no MAC state), so that a refused configuration leaves nothing of an old core behind
    and every entry point refuses it (ESTOP_ERR_NOT_INIT)."""
    size = ffi.sizeof("estop_core_t")
    core, buf = guarded("estop_core_t")
    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)  # session 0: refused
    for junk in (b"\x5a", b"\xff"):
        ffi.memmove(core, junk * size, size)
        assert lib.estop_init(core, cfg, 0) == lib.ESTOP_ERR_SESSION
        assert bytes(ffi.buffer(core, size)) == bytes(size)
        assert guards_intact(buf, size)
    assert lib.estop_tick(core, 0, ffi.new("estop_out_t *")) == lib.ESTOP_ERR_NOT_INIT


def test_status_read_out_writes_only_the_status() -> None:
    size = ffi.sizeof("estop_status_t")
    status, buf = guarded("estop_status_t")
    raw = Raw()
    assert lib.estop_get_status(raw.core, status) == lib.ESTOP_OK
    assert status.counters.stops[lib.ESTOP_REASON_BOOT] == 1
    assert guards_intact(buf, size)

