"""Tests written for the mutants that survived the other core tests (tools/mutants.py, issue 9).

Each test pins down a behaviour that a planted change showed to be unchecked; the docstring
names the kind of mutant it kills. They drive the C entry points through cffi with raw 32-bit
ticks, as a microcontroller host would, so the wrapper's own care (splitting long gaps) cannot
hide the core's.
"""

from __future__ import annotations

from core_util import packet, request
from estop.core import Config, ffi, lib
from estop.protocol import auth
from estop.protocol.udp import ControlPacket, Gear

U32 = 0xFFFFFFFF
MAX_STEP = 0x7FFFFFFF
GAP_LONG = 1 << 30


class Raw:
    """A core driven with raw uint32 ticks."""

    def __init__(self, now: int = 0, config: Config | None = None) -> None:
        self.core = ffi.new("estop_core_t *")
        self.out = ffi.new("estop_out_t *")
        self.consumed = ffi.new("size_t *")
        cfg = (config or Config()).to_c()
        assert lib.estop_init(self.core, cfg, now & U32) == lib.ESTOP_OK

    def tick(self, t: int) -> None:
        assert lib.estop_tick(self.core, t & U32, self.out) == lib.ESTOP_OK

    def udp(self, data: bytes, t: int) -> None:
        buf = ffi.from_buffer("uint8_t[]", data)
        assert lib.estop_udp_rx(self.core, buf, len(data), t & U32, self.out) == lib.ESTOP_OK

    def tcp(self, slot: int, data: bytes, t: int) -> int:
        buf = ffi.from_buffer("uint8_t[]", data)
        return int(lib.estop_tcp_rx(self.core, slot, buf, len(data), self.consumed, t & U32,
                                    self.out))

    def status(self) -> object:
        st = ffi.new("estop_status_t *")
        assert lib.estop_get_status(self.core, st) == lib.ESTOP_OK
        return st

    def gaps(self) -> tuple[list[int], int]:
        ls = ffi.new("estop_link_stats_t *")
        assert lib.estop_get_link_stats(self.core, ls) == lib.ESTOP_OK
        return [ls.gaps[i] for i in range(32)], ls.silences

    def walk(self, start: int, end: int) -> None:
        """Ticks from start to end in the longest steps the contract allows."""
        t = start
        while end - t > MAX_STEP:
            t += MAX_STEP
            self.tick(t)
        self.tick(end)


# -- a tick that goes backwards ----------------------------------------------------------------
def test_a_tick_going_backwards_forgets_the_link_even_after_the_latest_packet() -> None:
    """Mutant: the backwards branch keeps link_fresh. The tick lands between the latest valid
    packet and the previous call, so the age alone would still look young."""
    r = Raw(1_000_000)
    r.udp(packet(), 1_000_000)
    r.tick(1_100_000)
    r.tick(1_050_000)  # backwards, yet after the packet at 1_000_000
    st = r.status()
    assert st.counters.faults == 1  # type: ignore[attr-defined]
    assert st.link_age_us == U32  # type: ignore[attr-defined]
    assert st.link_live == 0  # type: ignore[attr-defined]


# -- the gap histogram: gaps too long for the tick ---------------------------------------------
def test_a_long_silence_after_the_timeout_is_recorded_once_in_the_top_bin() -> None:
    """Mutants: the 'very long' record made only while the link is fresh; made one call late
    (>= to >); the top bin counted from a neighbouring bin or field. The link goes stale at the
    timeout first, then the silence grows past the tick's reach before the next packet."""
    r = Raw(0)
    r.udp(packet(), 0)
    r.udp(packet(), 33_000_000)  # a 33 s gap: bin 30 (the top bin's neighbour)
    r.udp(b"junk", 33_000_001)  # an invalid packet, so the counter after gaps[] is not 0
    r.tick(33_000_000 + 300_000)  # the link goes stale at the timeout
    r.tick(33_000_000 + GAP_LONG - 1)
    assert r.gaps()[0][31] == 0
    r.tick(33_000_000 + GAP_LONG)  # exactly the age past which a gap is "very long"
    gaps, silences = r.gaps()
    assert gaps[31] == 1 and gaps[30] == 1 and sum(gaps) == 2 and silences == 2
    r.walk(33_000_000 + GAP_LONG, 33_000_000 + (1 << 32) + 40_000)  # past the wrap
    r.udp(packet(), 33_000_000 + (1 << 32) + 40_000)  # would look like a 40 ms gap
    gaps, silences = r.gaps()
    assert gaps[31] == 1 and gaps[30] == 1 and sum(gaps) == 2 and silences == 2


# -- flags are 0 or 1 --------------------------------------------------------------------------
def test_the_output_flags_are_0_or_1() -> None:
    """Mutants: a flag set to another true value (2). The header calls them flags; hosts in C
    may compare them with 1."""
    r = Raw(0)
    r.tick(0)
    for _ in range(5):
        r.udp(packet(), 0)
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(2), 0) == lib.ESTOP_OK  # RELEASE: state change by the input
    assert (r.out.state_changed, r.out.changed_by_clock, r.out.has_reply) == (1, 0, 1)
    assert r.status().link_live == 1  # type: ignore[attr-defined]
    r.tick(200_000)  # the deadline: state change by the clock
    assert (r.out.state_changed, r.out.changed_by_clock, r.out.has_reply) == (1, 1, 0)
    bad = request(1, good_crc=False)
    assert r.tcp(0, bad, 200_001) == lib.ESTOP_OK
    assert r.out.close_slot == 1


# -- TCP framing -------------------------------------------------------------------------------
def test_a_frame_length_is_decided_on_its_own_four_bytes_never_on_stale_ones() -> None:
    """Mutants: fewer magic bytes than 4 decide a frame's length (MAGIC_LEN 0, 1, 3). After a
    request frame the slot's buffer still starts with "ESQ2"; a plain frame beginning "ESQ3"
    arrives as 3 bytes, then its rest together with a second plain frame."""
    r = Raw(0)
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    status = auth.AuthRequest(1, 7, 7, 0, 1).encode(None)  # STATUS as a request frame
    assert r.tcp(0, status, 0) == lib.ESTOP_OK and r.out.has_reply == 1
    assert r.consumed[0] == 48
    odd = request(0x33515345, seq=5)  # "ESQ3": a plain frame with an unknown msg_id
    assert r.tcp(0, odd[:3], 1) == lib.ESTOP_OK
    assert r.consumed[0] == 3 and r.out.has_reply == 0
    rest = odd[3:] + request(1, seq=6)
    assert r.tcp(0, rest, 2) == lib.ESTOP_OK
    assert r.consumed[0] == 13 and r.out.has_reply == 1 and r.out.reply_len == 16
    assert bytes(ffi.buffer(r.out.reply, 16))[4:8] == (5).to_bytes(4, "little")
    assert r.tcp(0, rest[13:], 3) == lib.ESTOP_OK
    assert r.consumed[0] == 16 and r.out.has_reply == 1
    assert bytes(ffi.buffer(r.out.reply, 16))[4:8] == (6).to_bytes(4, "little")


# -- saturating counters -----------------------------------------------------------------------
def test_32_bit_counters_saturate_at_the_top_and_not_before() -> None:
    """Mutants: sat32_inc wrapping to 0 (< to <=) or stopping one short (0xFFFFFFFE). Four
    billion packets are out of a test's reach, so the counters are set near the top in the
    caller-owned state (white box), then real packets and gaps move them."""
    r = Raw(0)
    r.udp(packet(), 0)
    r.core.valid_run = 0xFFFFFFFD
    r.core.gaps[lib.estop_gap_bin(20_000)] = 0xFFFFFFFD
    r.core.silences = 0xFFFFFFFD
    for t in (20_000, 40_000):
        r.udp(packet(), t)
    st = r.status()
    gaps, silences = r.gaps()
    assert st.valid_run == 0xFFFFFFFF  # type: ignore[attr-defined]
    assert gaps[lib.estop_gap_bin(20_000)] == 0xFFFFFFFF
    r.udp(packet(), 60_000)
    r.udp(packet(), 400_000)  # a silence (past the warn time)
    r.udp(packet(), 800_000)
    gaps, silences = r.gaps()
    assert r.status().valid_run == 1  # type: ignore[attr-defined]  # the silence restarted it
    assert gaps[lib.estop_gap_bin(20_000)] == 0xFFFFFFFF
    assert silences == 0xFFFFFFFF


# -- configuration -----------------------------------------------------------------------------
def test_config_default_sets_every_field_and_writes_nothing_else() -> None:
    """Mutants: a field of estop_config_default left as it was, the warn time at another
    fraction, the key wipe shortened or run one byte past the key. The struct starts as
    garbage (0xA5) and must come out as PROTOCOL.md's defaults, its padding untouched."""
    cfg = ffi.new("estop_config_t *")
    size = ffi.sizeof("estop_config_t")
    ffi.memmove(cfg, b"\xa5" * size, size)
    lib.estop_config_default(cfg)
    assert (cfg.timeout_us, cfg.warn_us, cfg.stop_id) == (200_000, 100_000, 0xE570E570)
    assert (cfg.brake_can_id, cfg.status_can_id) == (0x050, 0x051)
    assert (cfg.brake_data_id, cfg.status_data_id) == (0x0E57, 0x0E58)
    assert (cfg.release_packets, cfg.brake_period_us, cfg.status_period_us) == (5, 10_000,
                                                                                100_000)
    assert (cfg.session, cfg.key_len) == (0, 0)
    assert (cfg.tag_checks, cfg.tag_window_us) == (10, 100_000)
    assert bytes(ffi.buffer(cfg.key, 32)) == bytes(32)
    end_of_key = ffi.offsetof("estop_config_t", "key") + 32
    assert bytes(ffi.buffer(cfg, size))[end_of_key:] == b"\xa5" * (size - end_of_key)
    lib.estop_config_default(ffi.NULL)  # a NULL is ignored


def test_config_limits_are_inclusive_at_the_edges() -> None:
    """Mutants: > to >= on the status CAN id's limit, < to <= on 'status period below the brake
    period'. Both edges are valid configurations."""
    for cfg in (Config(status_can_id=0x7FF), Config(brake_can_id=0x7FF),
                Config(brake_period_us=20_000, status_period_us=20_000)):
        assert lib.estop_config_check(cfg.to_c()) == lib.ESTOP_OK
    assert lib.estop_config_check(Config(status_can_id=0x800).to_c()) == lib.ESTOP_ERR_CAN_ID
    assert lib.estop_config_check(Config(brake_period_us=20_000, status_period_us=19_999)
                                  .to_c()) == lib.ESTOP_ERR_STATUS_PERIOD


def test_init_keeps_no_key_byte() -> None:
    """Mutants: the key wipe in estop_init starting at byte 1 or writing another value. The
    key is absorbed into the MAC state; none of its bytes stays in the caller-owned state."""
    key = bytes(range(1, 33))
    r = Raw(0, Config(key=key))
    assert r.core.cfg.key_len == 32
    assert bytes(ffi.buffer(r.core.cfg.key, 32)) == bytes(32)
    assert key not in bytes(ffi.buffer(r.core, ffi.sizeof("estop_core_t")))


def test_init_starts_the_clock_at_its_own_tick() -> None:
    """Mutant: estop_init leaves the core's tick at 0. Booted at a tick more than half the
    range away from 0, the first call at the same tick must not look like a tick going
    backwards (a fault)."""
    for boot in (3_000_000_000, 0x80000000):
        r = Raw(boot)
        r.tick(boot)
        st = r.status()
        assert st.counters.faults == 0  # type: ignore[attr-defined]
        assert r.out.n_can == 2 and r.out.next_call_us == (boot + 10_000) & U32


# -- ESTOP_STATUS: the link age in milliseconds --------------------------------------------------
def status_age_ms(r: Raw) -> int:
    frames = [r.out.can[i] for i in range(r.out.n_can) if r.out.can[i].id == 0x051]
    assert len(frames) == 1
    return int(frames[0].data[4]) | (int(frames[0].data[5]) << 8)


def test_status_link_age_is_floored_to_whole_milliseconds() -> None:
    """Mutants: the age divided by 999 or 1001 instead of 1000. Status frames go out every
    100 ms from boot; a packet 1 ms and 199.8 ms before one of them."""
    r = Raw(0)
    r.tick(0)
    r.udp(packet(), 99_000)
    r.tick(100_000)
    assert status_age_ms(r) == 1  # 1000 us: 1 (not 0 with /1001)
    r = Raw(0)
    r.tick(0)
    r.udp(packet(), 200)
    r.tick(100_000)
    assert status_age_ms(r) == 99
    r.tick(200_000)
    assert status_age_ms(r) == 199  # 199800 us: 199 (not 200 with /999)
    r.tick(300_000)
    assert status_age_ms(r) == 0xFFFF  # the link went stale at the timeout: no age


def test_reply_len_is_0_on_every_call_without_a_reply() -> None:
    """Mutant: clear_out leaving reply_len as the previous call set it. reply_len says how
    much of the output is meaningful, so a host may send reply[0 .. reply_len-1] by it alone."""
    r = Raw(0)
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(1), 0) == lib.ESTOP_OK
    assert (r.out.has_reply, r.out.reply_len) == (1, 16)
    r.tick(1)
    assert (r.out.has_reply, r.out.reply_len) == (0, 0)


def test_change_flags_are_cleared_on_the_next_call() -> None:
    """Mutants: clear_out leaving state_changed or changed_by_clock set from the previous
    call. The deadline stops the unit (both set), the next tick changes nothing (both clear)."""
    r = Raw(0)
    for t in range(0, 100_000, 20_000):
        r.udp(packet(), t)
    assert lib.estop_tcp_open(r.core, 0, 80_000, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(2), 80_000) == lib.ESTOP_OK and r.out.state == 1
    r.tick(280_000)  # the deadline
    assert (r.out.state, r.out.state_changed, r.out.changed_by_clock) == (0, 1, 1)
    r.tick(280_001)
    assert (r.out.state_changed, r.out.changed_by_clock) == (0, 0)


# -- estop_ct_equal: every length, every position -------------------------------------------------
def ct_equal(a: bytes | None, b: bytes | None, n: int) -> int:
    pa = ffi.NULL if a is None else ffi.from_buffer("uint8_t[]", a)
    pb = ffi.NULL if b is None else ffi.from_buffer("uint8_t[]", b)
    return int(lib.estop_ct_equal(pa, pb, n))


def test_ct_equal_sees_a_difference_in_any_byte_of_any_length() -> None:
    """Mutants: the byte-wise tail after the 4-byte groups skipped, run backwards or masking
    instead of collecting; a NULL pointer with n 1 taken as equal. Lengths that are not a
    multiple of 4 put bytes in the tail."""
    for n in range(0, 21):
        a = bytes(range(1, n + 1))
        assert ct_equal(a, bytes(a), n) == 1
        for where in range(n):
            for flip in (0x01, 0x80):
                other = bytearray(a)
                other[where] ^= flip
                assert ct_equal(a, bytes(other), n) == 0, (n, where, flip)
    assert ct_equal(None, b"\x00", 1) == 0
    assert ct_equal(b"\x00", None, 1) == 0


# -- the deadline as a call time ---------------------------------------------------------------
def test_a_host_that_calls_only_when_asked_stops_at_the_deadline_off_the_frame_grid() -> None:
    """Mutants: finish() leaving the deadline out of next_call_us (or putting it a timeout
    before the packet). The latest packet arrives 3.333 ms off the 10 ms brake grid, so only
    the deadline itself can make the host call at latest + timeout."""
    r = Raw(0)
    r.tick(0)
    for t in range(0, 100_000, 20_000):
        r.udp(packet(), t)
    assert lib.estop_tcp_open(r.core, 0, 80_000, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(2), 80_000) == lib.ESTOP_OK and r.out.state == 1
    last = 93_333
    r.udp(packet(), last)
    t = last
    calls = 0
    while r.out.state == 1 and calls < 100:
        t = r.out.next_call_us
        r.tick(t)
        calls += 1
    assert r.out.state == 0 and r.out.reason == lib.ESTOP_REASON_UDP_TIMEOUT
    assert t == last + 200_000  # the stop at the deadline itself, not at the next frame time


# -- authentication (PROTOCOL.md 5) ------------------------------------------------------------
K = bytes(range(32))
N = 0x0123456789ABCDEF


def auth_packet(rid: int, counter: int, horn: int = 0) -> bytes:
    body = ControlPacket(gas_brake=0.0, gear=Gear.NEUTRAL, horn=horn)
    return auth.AuthControlPacket(rid, N, counter, body).encode(K, validate=False)


def valid_count(r: Raw) -> int:
    return int(r.status().counters.udp_valid)  # type: ignore[attr-defined]


def test_a_new_remote_id_may_start_at_counter_0_on_either_channel() -> None:
    """Mutants: a new remote's entry born with a counter 'seen' (seen = 1), and the seen test
    made always true (& to |): counter 0 would then count as a replay of nothing."""
    r = Raw(0, Config(key=K))
    r.udp(auth_packet(7, 0), 0)
    assert valid_count(r) == 1
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    status = auth.AuthRequest(1, 1, 7, N, 0).encode(K)  # TCP counter 0 of the same remote
    release = auth.AuthRequest(2, 2, 9, N, 0).encode(K)  # a new remote, counter 0, on TCP
    assert r.tcp(0, status, 1) == lib.ESTOP_OK
    assert r.tcp(0, release, 2) == lib.ESTOP_OK
    st = r.status()
    assert st.counters.auth_old_counter == 0  # type: ignore[attr-defined]
    reply = bytes(ffi.buffer(r.out.reply, 48))
    assert reply[4] == 0x81 and reply[15] == lib.ESTOP_NAK_NO_LIVE_LINK  # authenticated


def test_the_authenticated_body_is_checked_with_its_horn() -> None:
    """Mutant: the 60-byte packet's body checked as the 16-byte form (no horn)."""
    r = Raw(0, Config(key=K))
    r.udp(auth_packet(7, 1, horn=2), 0)
    assert valid_count(r) == 0
    r.udp(auth_packet(7, 2, horn=1), 1)
    assert valid_count(r) == 1


def test_remote_ids_differing_only_in_their_top_byte_are_kept_apart() -> None:
    """Mutants: the remote id read from offset 1 or 3 instead of 4. Two remotes whose ids
    differ only in the top byte must keep separate counters."""
    r = Raw(0, Config(key=K))
    r.udp(auth_packet(0x01000007, 10), 0)
    r.udp(auth_packet(0x02000007, 1), 1)
    assert valid_count(r) == 2


def test_the_counter_is_compared_as_the_whole_u64_at_its_offset() -> None:
    """Mutant: the counter read from offset 15 (one byte early). Above 2^56 the order of the
    shifted values differs from the real ones: 2 after 2^56 is stale."""
    r = Raw(0, Config(key=K))
    r.udp(auth_packet(7, 1 << 56), 0)
    r.udp(auth_packet(7, 2), 1)
    assert valid_count(r) == 1
    assert r.status().counters.auth_old_counter == 1  # type: ignore[attr-defined]


def ninth_of() -> int:
    return int(ffi.offsetof("estop_core_t", "remotes") + 8 * ffi.sizeof("estop_remote_t"))


def guarded_core(extra: bytes) -> tuple[object, object]:
    """A core in a buffer with a guard zone after it: `extra` where a 9th remote entry would
    be, zeros elsewhere."""
    size = ffi.sizeof("estop_core_t")
    ninth = ffi.offsetof("estop_core_t", "remotes") + 8 * ffi.sizeof("estop_remote_t")
    assert ninth >= size - 8
    buf = ffi.new("uint8_t[]", ninth + 256)
    ffi.memmove(buf + ninth, extra, len(extra))
    return buf, ffi.cast("estop_core_t *", buf)


def test_the_remote_table_never_reaches_past_its_8_entries() -> None:
    """Mutants: the table's loops running to index 8 (one past the end). The memory after the
    core is made to look like a free entry, then like a used entry for the 9th id: either way
    the 9th remote id must not be authenticated."""
    entry = ffi.new("estop_remote_t *")
    entry.used = 1
    entry.id = 99
    entry.checks = 7  # a 9th entry's allowance, which a new window must not clear
    used = bytes(ffi.buffer(entry))
    for extra in (b"", used):
        buf, core = guarded_core(extra)
        out = ffi.new("estop_out_t *")
        assert lib.estop_init(core, Config(key=K).to_c(), 0) == lib.ESTOP_OK
        for rid in range(8):  # 20 ms apart: each in a window of tag checks of its own
            data = auth_packet(rid, 1)
            assert lib.estop_udp_rx(core, ffi.from_buffer("uint8_t[]", data), 60,
                                    20_000 * (rid + 1), out) == lib.ESTOP_OK
        data = auth_packet(99, 5)
        assert lib.estop_udp_rx(core, ffi.from_buffer("uint8_t[]", data), 60, 9 * 20_000,
                                out) == lib.ESTOP_OK
        st = ffi.new("estop_status_t *")
        assert lib.estop_get_status(core, st) == lib.ESTOP_OK
        assert st.counters.udp_valid == 8 and st.counters.auth_table_full == 1
        assert core.tag_window_us > 0  # windows began anew (and cleared 8 allowances only)
        assert bytes(ffi.buffer(buf, len(buf)))[ninth_of():ninth_of() + len(extra)] == extra
        del buf


# -- counters of the TCP channel -----------------------------------------------------------------
def test_release_and_frame_counters() -> None:
    """Mutants: releases_accepted, releases_refused or tcp_frames not counted (or counted
    down, or in the wrong case)."""
    r = Raw(0)

    def counts() -> tuple[int, int, int]:
        c = r.status().counters  # type: ignore[attr-defined]
        return int(c.releases_refused), int(c.releases_accepted), int(c.tcp_frames)

    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(2), 0) == lib.ESTOP_OK  # NAK 2: refused
    assert counts() == (1, 0, 1)
    for t in range(1, 6):
        r.udp(packet(), t)
    assert r.tcp(0, request(2), 6) == lib.ESTOP_OK and r.out.state == 1  # accepted
    assert counts() == (1, 1, 2)
    assert r.tcp(0, request(2), 7) == lib.ESTOP_OK  # while ARMED: ACK, neither
    assert counts() == (1, 1, 3)
    assert r.tcp(0, request(1), 8) == lib.ESTOP_OK  # STATUS
    assert counts() == (1, 1, 4)


# -- outputs filled whatever the caller's buffer held ---------------------------------------------
def test_open_and_close_fill_the_read_out_of_out() -> None:
    """Mutant: estop_tcp_open / close not finishing (next_call_us, state, reason, flags left
    as the caller's buffer had them)."""
    r = Raw(0)
    r.tick(0)
    for fn in (lib.estop_tcp_open, lib.estop_tcp_close):
        out = ffi.new("estop_out_t *")
        ffi.memmove(out, b"\xa5" * ffi.sizeof("estop_out_t"), ffi.sizeof("estop_out_t"))
        assert fn(r.core, 0, 1_000, out) == lib.ESTOP_OK
        assert (out.state, out.reason, out.flags) == (0, lib.ESTOP_REASON_BOOT, 0)
        assert out.next_call_us == 10_000


def test_a_keyless_reply_frame_has_a_zero_tag_whatever_the_buffer_held() -> None:
    """Mutants: the zero tag of a keyless unit's reply frame written partly or not at all, or
    a MAC attempted without a key (which writes nothing)."""
    r = Raw(0)
    ffi.memmove(r.out, b"\xa5" * ffi.sizeof("estop_out_t"), ffi.sizeof("estop_out_t"))
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    ffi.memmove(r.out.reply, b"\xa5" * 48, 48)
    assert r.tcp(0, auth.AuthRequest(1, 1, 7, 0, 1).encode(None), 1) == lib.ESTOP_OK
    reply = bytes(ffi.buffer(r.out.reply, 48))
    assert r.out.reply_len == 48 and reply[32:] == bytes(16)


def test_a_reply_whose_tag_cannot_be_made_has_a_zero_tag_whatever_the_buffer_held() -> None:
    """Mutant: the zero tag dropped where the MAC of a keyed unit's reply fails (reply_tag):
    the reply would carry what the buffer held. tests/c/mac_failure.c shows it under valgrind;
    this is the same through cffi, which tools/mutants.py runs. The key state's digest length
    set to 0 (the invariant allows 0 to 16) makes estop_b2s_mac refuse."""
    r = Raw(0, Config(key=K))
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    r.core.mac.outlen = 0
    ffi.memmove(r.out.reply, b"\xa5" * 48, 48)
    status = auth.AuthRequest(1, 1, 7, N, 0).encode(K)
    assert r.tcp(0, status, 1) == lib.ESTOP_OK
    reply = bytes(ffi.buffer(r.out.reply, 48))
    assert r.out.reply_len == 48 and reply[4] == 0x80 and reply[32:] == bytes(16)


# -- silences --------------------------------------------------------------------------------------
def test_a_gap_of_exactly_the_warn_time_is_a_silence() -> None:
    """Mutant: >= to > on the warn time in record_gap."""
    r = Raw(0)
    r.udp(packet(), 0)
    r.udp(packet(), 100_000)  # the default warn time: half the 200 ms timeout
    r.udp(packet(), 199_999)
    assert r.gaps()[1] == 1


# -- TCP: after a bad frame, on a closed slot ----------------------------------------------------
def test_a_slot_with_a_bad_frame_takes_no_more_bytes_until_reopened() -> None:
    """Mutant: handle_plain not marking the slot closed. A host that calls again before it
    has closed the slot gets ESTOP_ERR_SLOT_CLOSED, consumed 0 (whatever it held) and a filled
    read-out."""
    r = Raw(0)
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(1, good_crc=False) + request(1), 1) == lib.ESTOP_OK
    assert r.out.close_slot == 1 and r.consumed[0] == 32
    r.consumed[0] = 12345
    ffi.memmove(r.out, b"\xa5" * ffi.sizeof("estop_out_t"), ffi.sizeof("estop_out_t"))
    assert r.tcp(0, request(1), 2) == lib.ESTOP_ERR_SLOT_CLOSED
    assert r.consumed[0] == 0
    assert (r.out.state, r.out.reason, r.out.n_can, r.out.has_reply) == (0, 1, 0, 0)
    assert r.out.next_call_us == 10_000


# -- TCP request frames: authentication only for RELEASE on a keyed unit ---------------------------
def test_only_a_release_on_a_keyed_unit_is_authenticated() -> None:
    """Mutants: handle_request authenticating on a keyless unit (key_len != 1), or every
    request frame on a keyed one (&& to ||). Neither may touch the authentication counters."""
    r = Raw(0)  # no key
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert r.tcp(0, auth.AuthRequest(2, 1, 7, N, 1).encode(K), 1) == lib.ESTOP_OK
    assert bytes(ffi.buffer(r.out.reply, 48))[15] == lib.ESTOP_NAK_NOT_AUTHENTICATED
    c = r.status().counters  # type: ignore[attr-defined]
    assert (c.auth_bad_tag, c.auth_bad_session, c.auth_old_counter) == (0, 0, 0)
    r = Raw(0, Config(key=K))
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    forged = bytearray(auth.AuthRequest(1, 1, 7, N, 1).encode(K))
    forged[40] ^= 1
    assert r.tcp(0, bytes(forged), 1) == lib.ESTOP_OK  # STATUS, wrong tag: answered
    assert r.tcp(0, auth.AuthRequest(1, 2, 7, 0, 0).encode(K), 2) == lib.ESTOP_OK
    c = r.status().counters  # type: ignore[attr-defined]
    assert (c.auth_bad_tag, c.auth_bad_session, c.auth_old_counter) == (0, 0, 0)


def release_nak(r: Raw, rid: int, counter: int, t: int) -> int:
    assert r.tcp(0, auth.AuthRequest(2, 1, rid, N, counter).encode(K), t) == lib.ESTOP_OK
    return int(bytes(ffi.buffer(r.out.reply, 48))[15])


def test_request_frames_read_remote_id_and_counter_at_their_offsets() -> None:
    """Mutants: the request frame's remote id read from offset 0, 1, 11 or 13, its counter
    from 23. Remote ids that differ only in one end byte must stay apart; a counter of 2 after
    2^56 is stale."""
    for a, b in ((0x01000007, 0x02000007), (0x07, 0x08)):
        r = Raw(0, Config(key=K))
        assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
        assert release_nak(r, a, 10, 1) == lib.ESTOP_NAK_NO_LIVE_LINK  # authenticated
        assert release_nak(r, b, 1, 2) == lib.ESTOP_NAK_NO_LIVE_LINK  # its own counter
    r = Raw(0, Config(key=K))
    assert lib.estop_tcp_open(r.core, 0, 0, r.out) == lib.ESTOP_OK
    assert release_nak(r, 7, 1 << 56, 1) == lib.ESTOP_NAK_NO_LIVE_LINK
    assert release_nak(r, 7, 2, 2) == lib.ESTOP_NAK_NOT_AUTHENTICATED


# -- read-outs filled whatever the caller's struct held --------------------------------------------
def test_read_outs_fill_every_field() -> None:
    """Mutants: estop_get_status leaving flags unset, estop_get_link_stats skipping bin 0.
    The read-out structs start as garbage; the unit is ARMED with a degraded link and has
    recorded a gap of bin 0 (under 1.024 ms)."""
    r = Raw(0)
    for t in (0, 500, 20_000, 40_000, 60_000):
        r.udp(packet(), t)
    assert lib.estop_tcp_open(r.core, 0, 60_000, r.out) == lib.ESTOP_OK
    assert r.tcp(0, request(2), 60_000) == lib.ESTOP_OK and r.out.state == 1
    r.tick(170_000)  # 110 ms of silence: past the 100 ms warn time
    st = ffi.new("estop_status_t *")
    ffi.memmove(st, b"\xa5" * ffi.sizeof("estop_status_t"), ffi.sizeof("estop_status_t"))
    assert lib.estop_get_status(r.core, st) == lib.ESTOP_OK
    assert (st.state, st.reason, st.flags, st.link_live) == (1, 0, 1, 1)
    ls = ffi.new("estop_link_stats_t *")
    ffi.memmove(ls, b"\xa5" * ffi.sizeof("estop_link_stats_t"),
                ffi.sizeof("estop_link_stats_t"))
    assert lib.estop_get_link_stats(r.core, ls) == lib.ESTOP_OK
    assert ls.gaps[0] == 1 and sum(ls.gaps[i] for i in range(32)) == 4 and ls.valid == 5
