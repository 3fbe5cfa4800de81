"""The link's record in the core (issue 12): a histogram of the gaps between consecutive valid
control packets, and the silences of at least the warn time. The bin rule is written here
again, independently, from docs/LINK.md."""

from __future__ import annotations

import math

import hypothesis.strategies as st
from hypothesis import given

from core_util import MS, Unit, packet
from estop.core import Config, Watchdog, ffi, lib


def bin_of(gap_us: int) -> int:
    """Bin 0 below 1024 us; then half-octaves: 1 + 2 (e - 10) + the bit below the top one."""
    if gap_us < 1024:
        return 0
    e = int(math.log2(gap_us))
    while 2 ** e > gap_us:  # float log2 near powers of two
        e -= 1
    while 2 ** (e + 1) <= gap_us:
        e += 1
    return min(31, 1 + 2 * (e - 10) + ((gap_us >> (e - 1)) & 1))


def test_bin_edges() -> None:
    for e in range(10, 26):
        lo = 2 ** e
        assert lib.estop_gap_bin(lo - 1) == bin_of(lo - 1)
        assert lib.estop_gap_bin(lo) == 1 + 2 * (e - 10)
        assert lib.estop_gap_bin(lo + 2 ** (e - 1)) == min(31, 2 + 2 * (e - 10))
    assert [lib.estop_gap_bin(g) for g in (0, 1023, 1024, 1535, 1536, 2047)] == [0, 0, 1, 1, 2, 2]
    assert lib.estop_gap_bin(20_000) == 9  # 50 Hz
    assert lib.estop_gap_bin(2**32 - 1) == 31


@given(st.integers(0, 2**32 - 1))
def test_bin_matches_the_rule(gap: int) -> None:
    assert lib.estop_gap_bin(gap) == bin_of(gap)


def test_gaps_and_silences_are_recorded_between_valid_packets_only() -> None:
    u = Unit()
    u.drive(1)
    for gap in (20 * MS, 20 * MS, 40 * MS, 150 * MS, 3000 * MS):
        u.wait(gap)
        u.udp(b"junk")  # invalid packets do not end a gap
        u.udp(packet())
    stats = u.wd.link_stats()
    assert stats.valid == 6
    expected = [0] * 32
    for gap in (20 * MS, 20 * MS, 40 * MS, 150 * MS, 3000 * MS):
        expected[bin_of(gap)] += 1
    assert list(stats.gaps) == expected
    assert stats.silences == 2  # 150 ms and 3 s: at least the 100 ms warn time


def test_a_gap_too_long_for_the_tick_lands_in_the_top_bin() -> None:
    wd = Watchdog(Config())
    wd.udp(packet(), 0)
    wd.udp(packet(), 2 * 3600 * 10**6)  # two hours: the wrapper feeds it in steps
    stats = wd.link_stats()
    assert stats.gaps[31] == 1 and sum(stats.gaps) == 1 and stats.silences == 1


def test_a_gap_across_a_tick_going_backwards_is_not_recorded() -> None:
    core = ffi.new("estop_core_t *")
    out = ffi.new("estop_out_t *")
    cfg = Config().to_c()
    assert lib.estop_init(core, cfg, 1_000_000) == lib.ESTOP_OK
    data = ffi.from_buffer("uint8_t[]", packet())
    assert lib.estop_udp_rx(core, data, 20, 1_000_000, out) == lib.ESTOP_OK
    assert lib.estop_tick(core, 500_000, out) == lib.ESTOP_OK  # backwards: a fault
    assert lib.estop_udp_rx(core, data, 20, 520_000, out) == lib.ESTOP_OK
    assert lib.estop_udp_rx(core, data, 20, 540_000, out) == lib.ESTOP_OK
    ls = ffi.new("estop_link_stats_t *")
    assert lib.estop_get_link_stats(core, ls) == lib.ESTOP_OK
    assert ls.valid == 3 and sum(ls.gaps) == 1 and ls.gaps[bin_of(20_000)] == 1


def test_link_stats_read_out_refuses_null_and_uninitialised() -> None:
    ls = ffi.new("estop_link_stats_t *")
    assert lib.estop_get_link_stats(ffi.NULL, ls) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_get_link_stats(ffi.new("estop_core_t *"), ffi.NULL) == lib.ESTOP_ERR_NULL_ARG
    assert lib.estop_get_link_stats(ffi.new("estop_core_t *"), ls) == lib.ESTOP_ERR_NOT_INIT


def test_a_long_stall_fed_in_steps_is_recorded_once_as_very_long() -> None:
    """Issue 16, defect 9: the host feeds a stall of more than 2^32 us in steps of at most
    ESTOP_MAX_STEP_US. The step that ages the link past the timeout is already past the top
    bin's limit; the next one wraps the 32-bit age back to a short one. The outage must still
    be one gap in the top bin and one silence, never a short gap."""
    core = ffi.new("estop_core_t *")
    out = ffi.new("estop_out_t *")
    assert lib.estop_init(core, Config().to_c(), 0) == lib.ESTOP_OK
    data = ffi.from_buffer("uint8_t[]", packet())
    t = 20_000
    assert lib.estop_udp_rx(core, data, 20, t, out) == lib.ESTOP_OK  # the first valid packet
    t += 60_000
    assert lib.estop_tick(core, t, out) == lib.ESTOP_OK  # still fresh (T = 200 ms)
    for _ in range(2):  # two steps of 2^31 - 1 us: 2^32 - 2 in all
        t += lib.ESTOP_MAX_STEP_US
        assert lib.estop_tick(core, t & 0xFFFFFFFF, out) == lib.ESTOP_OK
    t += 1000
    assert lib.estop_udp_rx(core, data, 20, t & 0xFFFFFFFF, out) == lib.ESTOP_OK
    ls = ffi.new("estop_link_stats_t *")
    assert lib.estop_get_link_stats(core, ls) == lib.ESTOP_OK
    gaps = {i: ls.gaps[i] for i in range(32) if ls.gaps[i]}
    assert (gaps, ls.silences) == ({31: 1}, 1)
