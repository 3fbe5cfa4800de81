"""estop.unit.daemon beyond starting a daemon: the daemon's ``output_dropped`` reports and the
windows they cover, the alive-counter follower, and the keyed Link against a real keyed
estopd (session learnt, arming with authenticated packets, replies verified), plus the bench's
forged flood packets reaching the keyed daemon's tag check.
"""

from __future__ import annotations

import math
import os
import queue
import socket
import time
from pathlib import Path
from types import ModuleType

import pytest

from estop.protocol import auth, can, canlog, tcp, udp
from estop.unit.canlog import DROP_REPORT_REACH_S, CanLogLoss, DaemonError, drop_windows
from estop.unit.daemon import Daemon
from estop.unit.events import OutputDropped
from estop.unit.looplink import Link


def test_drop_windows_reach_back_one_report_period_or_to_a_missing_report() -> None:
    reports = [OutputDropped(10.0, "can_log", 5, 5, "full"),
               OutputDropped(11.0, "can_log", 2, 7, "full"),
               OutputDropped(30.0, "can_log", 1, 20, "full"),  # 12 lines in a report we lost
               OutputDropped(40.0, "log", 2, 2, "full"),  # the event log lost lines too
               OutputDropped(50.0, "can_log", 0, 20, "full")]
    w = drop_windows(reports)
    assert w[0] == (10.0 - DROP_REPORT_REACH_S, 10.0, 5)
    assert w[1] == (10.0, 11.0, 2)  # no further back than the report before
    assert w[2] == (11.0, 30.0, 13)  # a report is missing: back to the one before
    assert w[3] == (40.0 - 2 * DROP_REPORT_REACH_S, 40.0, 2)
    assert len(w) == 4
    assert drop_windows(reports, "log") == [(40.0 - DROP_REPORT_REACH_S, 40.0, 2)]


def _rec(t: float, can_id: int, ctr: int) -> canlog.CanLogRecord:
    if can_id == can.BRAKE_ID:
        data = can.BrakeFrame.for_state(can.State.ARMED, 0, 0, ctr).encode()
    else:
        data = can.StatusFrame(0, 0, 0, 0, 0, ctr).encode()
    return canlog.CanLogRecord.at(t, "estop", can_id, data)


def test_counter_follower_finds_jumps_and_repeats_per_id() -> None:
    loss = CanLogLoss()
    for i in range(20):
        assert loss.take(_rec(100.0 + i * 0.01, can.BRAKE_ID, i % 15)) is None
    assert loss.take(_rec(100.0, can.STATUS_ID, 3)) is None  # first of its ID
    gap = loss.take(_rec(100.25, can.BRAKE_ID, (19 + 5) % 15))  # 4 frames missing
    assert gap is not None and gap.can_id == can.BRAKE_ID and gap.lost == 4
    assert gap.after == pytest.approx(100.19) and gap.before == pytest.approx(100.25)
    rep = loss.take(_rec(100.26, can.BRAKE_ID, (19 + 5) % 15))  # same counter: 14 missing
    assert rep is not None and rep.lost == 14
    assert loss.take(_rec(100.1, can.STATUS_ID, 5)) is not None  # STATUS: 1 missing
    assert loss.lines_lost == 4 + 14 + 1
    assert loss.lost_between(100.20, 100.21) == 4  # inside the first gap
    assert loss.lost_between(100.0, 100.18) == 1  # only the STATUS gap reaches back there
    assert loss.lost_between(101.0, 102.0) == 0
    assert loss.seen_after(100.05) and not loss.seen_after(100.2)
    not_ours = canlog.CanLogRecord.at(100.3, "estop", 0x123, bytes(8))
    assert loss.take(not_ours) is None and loss.frames == 24
    assert CanLogLoss().lost_between(-math.inf, math.inf) == 0


def test_reader_threads_run_at_the_asked_real_time_priority(estopd: str) -> None:
    d = Daemon([estopd], reader_rt_prio=1)
    try:
        d.start()
    except DaemonError as exc:
        if "real-time" in str(exc):
            pytest.skip(f"no real-time priority here: {exc}")
        raise
    try:
        for th in d._threads:
            assert th.native_id is not None
            policy = os.sched_getscheduler(th.native_id)
            assert policy & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
            assert os.sched_getparam(th.native_id).sched_priority == 1
        assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the caller is left alone
        assert d.pid is not None and os.sched_getscheduler(d.pid) == os.SCHED_OTHER
    finally:
        d.stop()


@pytest.fixture
def keyed(tmp_path: Path) -> tuple[bytes, str]:
    key = os.urandom(auth.KEY_SIZE)
    path = tmp_path / "k"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(auth.format_key(key))
    return key, str(path)


def test_keyed_link_learns_the_session_arms_and_verifies_replies(
        keyed: tuple[bytes, str], estopd: str) -> None:
    key, path = keyed
    with Daemon([estopd], key_file=path, timeout_ms=300) as d:
        link = Link(d.udp_port, d.tcp_port, key=key)
        try:
            assert link.session != 0 and link.session == d.session
            for _ in range(5):
                link.send_control(0.0, 0.0, udp.Gear.NEUTRAL)
            time.sleep(0.02)
            reply, _ = link.request(tcp.RELEASE)
            assert reply.ack and reply.state == can.State.ARMED, reply
            c = link.counter
            link.send_control(0.2, 0.0, udp.Gear.DRIVE)
            assert link.counter == c + 1  # the counter rises with every message
        finally:
            link.close()
        # a link with another key does not accept the unit's replies
        with pytest.raises(DaemonError, match="did not verify"):
            Link(d.udp_port, d.tcp_port, key=os.urandom(auth.KEY_SIZE))


def test_a_plain_link_gets_nak_4_for_release_from_a_keyed_unit(
        keyed: tuple[bytes, str], estopd: str) -> None:
    _key, path = keyed
    with Daemon([estopd], key_file=path) as d:
        link = Link(d.udp_port, d.tcp_port)
        try:
            for _ in range(5):
                link.send_control(0.0, 0.0, udp.Gear.NEUTRAL)
            reply, _ = link.request(tcp.RELEASE)
            assert not reply.ack and reply.nak_code == tcp.NakCode.NOT_AUTHENTICATED
        finally:
            link.close()


def test_forged_flood_packets_look_valid_but_fail_the_tag(bench: ModuleType) -> None:
    key = os.urandom(auth.KEY_SIZE)
    packets = bench.forged_packets(0x1122334455667788)
    assert len(set(packets)) == len(packets) >= 32
    for p in packets:
        assert len(p) == auth.CONTROL_SIZE and p[:4] == auth.CONTROL_MAGIC
        head = auth.AuthControlPacket.decode(p, None)  # no key: a well-formed packet
        assert head.session == 0x1122334455667788
        with pytest.raises(auth.TagMismatch):
            auth.AuthControlPacket.decode(p, key)
    assert any(auth.AuthControlPacket.decode(p, None).remote_id == bench.FORGED_REMOTE_ID
               for p in packets)


def test_forged_flood_packets_reach_the_keyed_daemons_tag_check(
        bench: ModuleType, keyed: tuple[bytes, str], estopd: str) -> None:
    key, path = keyed
    with Daemon([estopd], key_file=path) as d:
        link = Link(d.udp_port, d.tcp_port, key=key)
        link.close()
        forged = bench.forged_packets(link.session)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for p in forged * 4:
                s.sendto(p, ("127.0.0.1", d.udp_port))
        deadline = time.monotonic() + 3.0
        failures = 0
        while time.monotonic() < deadline and failures == 0:
            try:
                rec = d.frames.get(timeout=0.2)
            except queue.Empty:
                continue
            if rec.can_id == can.STATUS_ID:
                failures = can.StatusFrame.parse(rec.data).auth_failures
        assert failures > 0  # refused at the tag, and counted as authentication failures
