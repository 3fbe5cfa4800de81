"""A bounded cost per window against a flood of forged authenticated packets (issue 16,
defect 10; docs/PROTOCOL.md 5, "a bounded cost"): each 60-byte packet that reaches the tag
check costs a BLAKE2s block (about 8,100 instructions on a Cortex-M0+), so the core checks at
most cfg.tag_checks per cfg.tag_window_us for each remote id with a place (its next counters),
and as many for everything else together; the rest are dropped unchecked and counted. The
remote's own packets still get through at its rate, and no stop ever waits for the budget."""

from __future__ import annotations

from core_util import ARMED, LIFT, MS, STOP_ID, STOPPED, TCP_STOP, UDP_TIMEOUT, Unit
from estop.core import Config
from estop.protocol import auth
from estop.protocol.udp import ControlPacket, Gear

K = bytes(range(32))
N = 0x0123456789ABCDEF
RID = 7
RELEASE = 2
CHECKS, WINDOW_MS = 10, 100  # the defaults: 10 tag checks per 100 ms
BODY = ControlPacket(gear=Gear.NEUTRAL)


class Keyed(Unit):
    def __init__(self) -> None:
        super().__init__(Config(key=K, session=N))
        self.counter = 0

    def genuine(self) -> bytes:
        self.counter += 1
        return auth.AuthControlPacket(RID, N, self.counter, BODY).encode(K)

    def arm(self) -> None:
        for _ in range(5):
            self.wait(20 * MS)
            self.udp(self.genuine())
        self.counter += 1  # one counter for all the remote's messages
        steps = self.send(auth.AuthRequest(RELEASE, 1, RID, N, self.counter).encode(K))
        assert steps[-1].state == ARMED


def forged(i: int, rid: int | None = None, counter: int | None = None) -> bytes:
    """A packet an attacker without the key makes: right session (it travels in clear),
    a fresh counter, a remote id of its choice, a tag under the wrong key."""
    return auth.AuthControlPacket(1000 + i if rid is None else rid, N,
                                  10**6 + i if counter is None else counter,
                                  BODY).encode(bytes(32))


def flood(u: Keyed, seconds: float, per_window: int, rid: int | None = None) -> int:
    """The remote at 50 Hz, the attacker's packets spread between: returns how many."""
    sent = 0
    for _ in range(int(seconds * 1000 / 20)):
        for _ in range(per_window):
            u.wait(20 * MS // (per_window + 1))
            u.udp(forged(sent, rid))
            sent += 1
        u.wait(20 * MS - (20 * MS // (per_window + 1)) * per_window)
        u.udp(u.genuine())
    return sent


def test_a_flood_of_forged_packets_gets_a_bounded_number_of_tag_checks() -> None:
    """10,000 forgeries from new remote ids in 2 s (5,000 a second): at most 10 tag checks per
    100 ms window for all of them together; the remote, which has a place, keeps the unit
    ARMED with every one of its 100 packets. Without the budget every forgery was checked."""
    u = Keyed()
    u.arm()
    before = u.wd.status().counters
    sent = flood(u, 2.0, 100)
    c = u.wd.status().counters
    windows = 2000 // WINDOW_MS + 1
    checked = c.auth_bad_tag - before.auth_bad_tag
    assert checked <= CHECKS * windows, f"{checked} tag checks for {sent} forgeries"
    assert c.auth_unchecked - before.auth_unchecked == sent - checked
    assert c.udp_valid - before.udp_valid == 100  # every genuine packet, at the remote's rate
    assert u.state == ARMED


def test_forgeries_under_the_remotes_own_id_with_counters_far_ahead_can_only_stop_it() -> None:
    """The remote id travels in clear: a flood that copies it, with counters of its own far
    ahead of the remote's, draws on the shared allowance, not on the remote's. A forgery left
    unchecked uses up its counter under the remote's id (issue 25: it might have been
    genuine), so the remote's packets below it are refused and the unit stops at the timeout,
    as a stop datagram would stop it. After the flood the remote's next RELEASE brings its
    counter back to its own, and the remote arms the unit again."""
    u = Keyed()
    u.arm()
    before = u.wd.status().counters
    sent = flood(u, 1.0, 100, rid=RID)
    c = u.wd.status().counters
    assert (u.state, u.reason) == (STOPPED, UDP_TIMEOUT)
    assert c.auth_bad_tag - before.auth_bad_tag <= CHECKS * (1000 // WINDOW_MS + 1) < sent
    assert c.auth_old_counter - before.auth_old_counter >= 45  # the remote's own, refused
    u.counter += 1
    steps = u.send(auth.AuthRequest(RELEASE, 2, RID, N, u.counter).encode(K))
    assert steps[-1].reply is not None and steps[-1].reply[15] == 2  # no live link yet
    u.arm()


def test_two_remotes_each_keep_their_own_allowance() -> None:
    """A second remote (its own id, its own place) is not slowed by the first's traffic nor by
    a flood from new ids."""
    u = Keyed()
    u.arm()
    other = 0
    before = u.wd.status().counters
    for i in range(50):
        u.wait(10 * MS)
        u.udp(u.genuine())
        other += 1
        u.udp(auth.AuthControlPacket(8, N, other, BODY).encode(K))
        for j in range(20):
            u.udp(forged(20 * i + j))
    c = u.wd.status().counters
    assert c.udp_valid - before.udp_valid == 100
    assert u.state == ARMED


def test_a_replay_flood_costs_no_tag_check_and_leaves_the_budget_alone() -> None:
    """Recorded genuine packets (a right tag, an old counter) are refused by their counter
    before any MAC: they spend none of the remote's tag checks."""
    u = Keyed()
    recording = [u.genuine() for _ in range(5)]
    for p in recording:
        u.wait(20 * MS)
        u.udp(p)
    before = u.wd.status().counters
    for _ in range(50):
        u.wait(20 * MS)
        for p in recording * 10:
            u.udp(p)
        u.udp(u.genuine())
    c = u.wd.status().counters
    assert c.auth_old_counter - before.auth_old_counter == 50 * 50
    assert (c.auth_bad_tag, c.auth_unchecked) == (before.auth_bad_tag, before.auth_unchecked)
    assert c.udp_valid - before.udp_valid == 50


def test_stops_never_wait_for_the_budget() -> None:
    """With the remote's tag checks spent by forgeries under its own id, a stop datagram, a
    lift datagram and a STOP frame with a garbage tag still stop the unit at once."""
    for how in ("stop datagram", "lift datagram", "stop frame"):
        u = Keyed()
        u.arm()
        for i in range(30):  # the remote's next counters: its own allowance, spent
            u.udp(forged(i, rid=RID, counter=u.counter + 1 + i))
        assert u.wd.status().counters.auth_unchecked >= 20
        if how == "stop frame":
            steps = u.send(auth.AuthRequest(STOP_ID, 2, RID, N, 99).encode(bytes(32)))
            assert steps[-1].reply is not None
            reason = TCP_STOP
        else:
            msg_id, reason = (STOP_ID, TCP_STOP) if how == "stop datagram" else (3, LIFT)
            u.udp(auth.AuthRequest(msg_id, 1, RID, N, 1).encode(bytes(32)))
        st = u.wd.status()
        assert (st.state, st.reason) == (STOPPED, reason), how


def test_forging_the_remotes_own_id_can_only_stop_the_car() -> None:
    """The limit of the budget: an attacker who watches the link live and forges the remote's
    id with its next counters spends that remote's checks every window and starves it. It also
    records every genuine packet the unit left unchecked and feeds one back at the start of
    every window, also once the remote has fallen silent (issue 25: on the core as it was,
    that kept the unit ARMED for seconds). The unit stops at the timeout after the remote's
    last packet, as if the packets were lost (section 5: not promised), no forgery and no
    recorded packet is ever valid, and the tag checks stay bounded."""
    u = Keyed()
    u.arm()
    valid_before = u.wd.status().counters.udp_valid
    recorded: list[bytes] = []
    n = 0
    t_silent = u.t + 800 * MS
    for _ in range(80):  # 1.6 s: a forgery every 0.2 ms, the remote every 20 ms for 0.8 s
        if recorded:
            u.udp(recorded.pop(0))
        for k in range(100):
            u.wait(MS // 5)
            u.udp(forged(n, rid=RID, counter=u.counter + 1 + k % 12))
            n += 1
            if k == 49 and u.t < t_silent:
                before = u.wd.status().counters.udp_valid
                packet = u.genuine()
                u.udp(packet)
                if u.wd.status().counters.udp_valid == before:
                    recorded.append(packet)
                last_genuine = u.t
                valid_at_silence = u.wd.status().counters.udp_valid
    st = u.wd.status()
    assert st.counters.udp_valid == valid_at_silence, "recorded packets taken after the silence"
    assert (st.state, st.reason) == (STOPPED, UDP_TIMEOUT)
    stops = [t for t, d in u.brake_frames() if d[2] == STOPPED and t > t_silent - 800 * MS]
    assert stops and stops[0] <= last_genuine + 200 * MS
    assert st.counters.udp_valid - valid_before <= 40
    assert st.counters.auth_bad_tag <= CHECKS * (1600 // WINDOW_MS + 1)  # still bounded


# -- the edges of the budget (mutation tests) -------------------------------------------------
def spend_shared(u: Keyed, n: int = CHECKS) -> None:
    """Spends the shared allowance of the current window with forgeries from new ids."""
    for i in range(n):
        u.udp(forged(5000 + i + u.t))


def test_the_remotes_own_allowance_serves_counters_up_to_65536_ahead() -> None:
    for ahead, valid in ((65536, True), (65537, False)):
        u = Keyed()
        u.arm()
        u.wait(WINDOW_MS * MS)
        spend_shared(u)
        u.counter += ahead - 2  # the remote lost ahead - 1 messages (one was its RELEASE):
        # its next packet is `ahead` above its latest control packet
        before = u.wd.status().counters
        u.udp(u.genuine())
        c = u.wd.status().counters
        assert (c.udp_valid - before.udp_valid == 1) == valid, ahead
        assert (c.auth_unchecked - before.auth_unchecked == 1) == (not valid), ahead


def test_a_window_ends_exactly_tag_window_us_after_it_began() -> None:
    """The remote's allowance, spent at the window's start, is whole again exactly one window
    later, and not a microsecond before; the shared one likewise."""
    for delay, valid in ((WINDOW_MS * MS - 1, False), (WINDOW_MS * MS, True)):
        u = Keyed()
        u.arm()
        u.wait(WINDOW_MS * MS)  # a new window starts with the next check
        start = u.t
        for i in range(CHECKS):
            u.udp(forged(i, rid=RID, counter=u.counter + 1 + i))
        spend_shared(u)
        u.at(start + delay)
        before = u.wd.status().counters
        u.udp(u.genuine())
        u.udp(forged(99, rid=RID + 100))  # a new id: from the shared allowance
        c = u.wd.status().counters
        assert (c.udp_valid - before.udp_valid == 1) == valid, delay
        assert (c.auth_bad_tag - before.auth_bad_tag == 1) == valid, delay


def test_every_remotes_allowance_is_whole_again_in_a_new_window() -> None:
    """Two remotes, each spending its allowance in one window, are checked again in the
    next; dropped packets count as invalid, never as authentication failures (byte 2)."""
    u = Keyed()
    u.arm()
    ctr = {RID: u.counter, 8: 0}
    valid_before = u.wd.status().counters.udp_valid
    for _ in range(2):
        u.wait(WINDOW_MS * MS)
        for rid in (RID, 8):
            for _ in range(CHECKS + 2):
                ctr[rid] += 1
                u.udp(auth.AuthControlPacket(rid, N, ctr[rid], BODY).encode(K))
    c = u.wd.status().counters
    assert c.udp_valid - valid_before == 4 * CHECKS + 1  # remote 8: its first from the shared
    u.wait(WINDOW_MS * MS)
    status = [d for (_t, can_id, d) in u.frames if can_id == 0x051]
    assert all(d[2] == 0 for d in status), "unchecked packets counted as failures"


def test_a_remote_that_began_on_tcp_takes_any_first_udp_counter() -> None:
    """A new remote id authenticated first by a RELEASE (TCP) keeps no UDP counter yet: its
    first control packet may carry counter 0."""
    u = Keyed()
    for _ in range(5):
        u.wait(20 * MS)
        u.udp(u.genuine())
    new = 9
    steps = u.send(auth.AuthRequest(RELEASE, 1, new, N, 5).encode(K))
    assert steps[-1].state == ARMED  # the request gave remote 9 its place
    before = u.wd.status().counters.udp_valid
    u.udp(auth.AuthControlPacket(new, N, 0, BODY).encode(K))
    assert u.wd.status().counters.udp_valid == before + 1


def test_a_remote_without_a_udp_counter_draws_on_the_shared_allowance() -> None:
    """Its own allowance is for its next counters, which a remote that has only spoken TCP
    does not have yet: its first control packet waits, like a new id's, for the shared one."""
    u = Keyed()
    u.arm()
    steps = u.send(auth.AuthRequest(1, 2, 9, N, 1).encode(K))  # STATUS: no place
    steps = u.send(auth.AuthRequest(RELEASE, 3, 9, N, 1).encode(K))  # remote 9: a place
    assert steps[-1].reply is not None
    u.wait(WINDOW_MS * MS)
    spend_shared(u)
    before = u.wd.status().counters
    u.udp(auth.AuthControlPacket(9, N, 1, BODY).encode(K))
    c = u.wd.status().counters
    assert (c.udp_valid, c.auth_unchecked) == (before.udp_valid, before.auth_unchecked + 1)


def test_a_window_ends_after_an_idle_gap_of_2_to_the_32_us() -> None:
    """Issue 25, item 5: the window's age was looked at only at a check, on the wrapping tick,
    so an idle gap of a multiple of 2^32 us (71.6 minutes) brought a spent window back: the
    remote's allowance stayed spent and its packet went unchecked. Now every call looks at the
    age, and the window ends once it has lasted its length."""
    u = Keyed()
    u.arm()
    u.wait(WINDOW_MS * MS)
    for i in range(CHECKS):  # the remote's allowance, spent at the window's start
        u.udp(forged(i, rid=RID, counter=u.counter + 1 + i))
    start = u.t
    u.counter += CHECKS
    before = u.wd.status().counters
    u.wd.udp(u.genuine(), start + 2**32 + 5 * MS)  # the host feeds the gap in steps
    c = u.wd.status().counters
    assert (c.udp_valid, c.auth_unchecked) == (before.udp_valid + 1, before.auth_unchecked)


def test_an_allowance_of_one_check_serves_the_first_packet_of_every_window() -> None:
    """tag_checks 1 (issue 24: the budget is looked at before the tag and spent after it): a
    window that has ended opens with the allowance whole, so the remote's first packet of
    each window is checked and its second is not."""
    u = Unit(Config(key=K, session=N, tag_checks=1))
    counter = 0

    def genuine() -> bytes:
        nonlocal counter
        counter += 1
        return auth.AuthControlPacket(RID, N, counter, BODY).encode(K)

    u.udp(genuine())  # the id's first packet: from the shared allowance; it gets a place
    for _ in range(3):
        u.wait(WINDOW_MS * MS)
        before = u.wd.status().counters
        u.udp(genuine())
        u.udp(genuine())
        c = u.wd.status().counters
        assert (c.udp_valid - before.udp_valid, c.auth_unchecked - before.auth_unchecked) == (1, 1)
