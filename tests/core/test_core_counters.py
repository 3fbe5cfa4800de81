"""The core's diagnostic and link counters saturate at 2^32 - 1 (issue 16, defect 9): a unit
that has run long enough to fill one must not report a small number again. Every counter is
set to its top through the core's state, then every path that counts runs once."""

from __future__ import annotations

from core_util import MS, STOP_ID, Unit, request
from estop.core import Config, Watchdog
from estop.protocol import auth
from estop.protocol.udp import ControlPacket, Gear

TOP = 0xFFFFFFFF
K = bytes(range(32))
N = 0x0123456789ABCDEF
RELEASE, STATUS, LIFT = 2, 1, 3
COUNTERS = ("udp_valid", "udp_invalid", "udp_stops", "tcp_frames", "tcp_bad_crc",
            "tcp_unknown_id", "releases_accepted", "releases_refused", "slowdowns", "rearms",
            "faults", "auth_bad_tag", "auth_bad_session", "auth_old_counter", "auth_table_full",
            "auth_unchecked")


def fill(wd: Watchdog) -> None:
    """Every counter of the core at its top: the diagnostic ones and the link's."""
    c = wd._core.counters
    for name in COUNTERS:
        setattr(c, name, TOP)
    for i in range(len(c.stops)):
        c.stops[i] = TOP
    wd._core.silences = TOP
    for i in range(len(wd._core.gaps)):
        wd._core.gaps[i] = TOP


def assert_all_top(wd: Watchdog) -> None:
    st = wd.status()
    low = {n: getattr(st.counters, n) for n in COUNTERS if getattr(st.counters, n) != TOP}
    low.update({f"stops[{i}]": v for i, v in enumerate(st.counters.stops) if v != TOP})
    ls = wd.link_stats()
    low.update({f"gaps[{i}]": v for i, v in enumerate(ls.gaps) if v != TOP})
    if ls.silences != TOP:
        low["silences"] = ls.silences
    assert not low, f"counters that wrapped: {low}"


def test_every_counter_of_a_plain_unit_saturates() -> None:
    u = Unit(Config(slow_us=100 * MS, timeout_us=300 * MS, warn_us=50 * MS))
    fill(u.wd)
    u.drive(5)  # valid packets, gaps
    u.udp(b"junk")  # invalid
    assert u.ask(RELEASE)[5] == 0  # accepted
    u.ask(RELEASE)  # acknowledged while ARMED
    u.ask(STATUS)
    u.ask(0x77)  # unknown id
    u.wait(150 * MS)  # slows down (a silence)
    u.drive(3)  # back to ARMED: a rearm
    u.wait(400 * MS)  # the timeout stops it
    u.ask(RELEASE)  # refused: no live link
    u.drive(5)
    u.ask(RELEASE)
    u.ask(STOP_ID)  # a TCP stop
    u.drive(5)
    u.ask(RELEASE)
    u.ask(LIFT)  # a lift
    u.udp(auth.AuthRequest(STOP_ID, 1, 7, 0, 1).encode(None))  # a stop datagram
    u.drive(5)
    u.ask(RELEASE)
    u.wd.fault(u.t)  # a fault stops it
    u.send(request(STATUS, good_crc=False))  # bad crc
    u.wd.tcp_open(0, u.t)
    u.wait(3000 * MS)
    u.drive(1)  # a long gap
    assert_all_top(u.wd)


def test_every_authentication_counter_saturates() -> None:
    u = Unit(Config(key=K, session=N))
    fill(u.wd)
    body = ControlPacket(gear=Gear.NEUTRAL)
    for rid in range(8):
        u.udp(auth.AuthControlPacket(rid, N, 5, body).encode(K))
    u.udp(auth.AuthControlPacket(8, N, 1, body).encode(K))  # a ninth remote id
    u.udp(auth.AuthControlPacket(0, N, 5, body).encode(K))  # an old counter
    u.udp(auth.AuthControlPacket(0, N + 1, 9, body).encode(K))  # another session
    u.udp(auth.AuthControlPacket(0, N, 9, body).encode(bytes(32)))  # a forged tag
    for i in range(12):  # over the tag-check budget of remote 0 in this window
        u.udp(auth.AuthControlPacket(0, N, 10 + i, body).encode(bytes(32)))
    assert u.wd._core.remotes[0].checks == 10  # the budget was reached: unchecked counted
    assert_all_top(u.wd)
