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
        steps = self.send(auth.AuthRequest(RELEASE, 1, RID, N, 1).encode(K))
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


def test_forgeries_under_the_remotes_own_id_with_counters_far_ahead_do_not_starve_it() -> None:
    """The remote id travels in clear: a flood that copies it, with counters of its own far
    ahead of the remote's (it cannot follow the remote's counter without watching the link
    live), draws on the shared allowance, not on the remote's."""
    u = Keyed()
    u.arm()
    before = u.wd.status().counters
    sent = flood(u, 1.0, 100, rid=RID)
    c = u.wd.status().counters
    assert c.udp_valid - before.udp_valid == 50 and u.state == ARMED
    assert c.auth_bad_tag - before.auth_bad_tag <= CHECKS * (1000 // WINDOW_MS + 1) < sent


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
    id with its next counters spends that remote's checks every window and starves it. The
    unit then stops at the timeout, as if the packets were lost (section 5: not promised),
    and no forgery is ever valid."""
    u = Keyed()
    u.arm()
    valid_before = u.wd.status().counters.udp_valid
    t_last_valid = u.t
    n = 0
    for _ in range(40):  # 800 ms: a forgery every 0.2 ms, the remote every 20 ms
        for k in range(100):
            u.wait(MS // 5)
            u.udp(forged(n, rid=RID, counter=u.counter + 1 + k % 12))
            n += 1
            if k == 49:
                u.udp(u.genuine())
        if u.wd.status().counters.udp_valid > valid_before:
            valid_before = u.wd.status().counters.udp_valid
            t_last_valid = u.t
    st = u.wd.status()
    assert (st.state, st.reason) == (STOPPED, UDP_TIMEOUT)
    assert u.t - t_last_valid > 500 * MS  # starved: no valid packet since the flood began
    assert st.counters.auth_bad_tag <= CHECKS * (800 // WINDOW_MS + 1)  # still bounded
