"""estopd and protocol version 3 end to end (PROTOCOL.md 2, 3, 4, 6): the two-stage stop
(SLOWING at the slow time, back to ARMED after 3 packets, STOPPED at the timeout), LIFT by TCP
(plain and request frame) and by datagram, and the `cause` of every state line."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from daemon_util import (
    ACK,
    ARMED,
    MSG_LIFT,
    MSG_RELEASE,
    MSG_STATUS,
    R_FAULT,
    R_LIFT,
    R_NONE,
    R_TCP_STOP,
    R_UDP_TIMEOUT,
    SLOWING,
    STOP_ID,
    STOPPED,
    Daemon,
    check_frames,
    recv_exact,
    state_lines,
    udp_packet,
)
from estop.protocol import auth

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]

TWO_STAGE = ("--slow-ms", "100", "--timeout-ms", "1000")


def fields(line: str) -> dict[str, str]:
    """key=value pairs of a text log line."""
    return dict(kv.split("=", 1) for kv in line.split() if "=" in kv)


def state_changes(d: Daemon) -> list[tuple[str, str, str, str]]:
    """(FROM->TO, reason, src, cause) of every state line so far; src without the port."""
    out = []
    for line in state_lines(d.log()):
        kv = fields(line)
        out.append((line.split()[3], kv["reason"], kv["src"].split(":")[0], kv["cause"]))
    return out


def test_slowing_at_the_slow_time_armed_after_3_packets_stopped_at_the_timeout(
        tmp_path: Path) -> None:
    with Daemon(tmp_path, *TWO_STAGE) as d:
        d.arm()
        sent_from = time.time()  # the packet is sent between these two readings: the lower
        d.send_udp(udp_packet())  # bounds count from before it, the upper ones from after
        t_last = time.time()
        slow = d.wait_frame(lambda f: f.is_brake() and f.state == SLOWING)
        # brake_request 2 at the slow level, state SLOWING, reason none, link degraded (W 50 ms)
        assert slow.data[:6].hex() == "021e02000100", slow
        assert 0.1 - 0.002 <= slow.t - sent_from and slow.t - t_last <= 0.1 + 0.08, \
            (slow.t - sent_from, t_last - sent_from)
        d.send_udp(udp_packet())
        d.send_udp(udp_packet())
        time.sleep(0.02)
        reply = d.request(MSG_STATUS, 1)
        assert (reply.state, reply.reason) == (SLOWING, R_NONE)  # two packets are not enough
        n = len(d.frames())
        back_from = time.time()
        d.send_udp(udp_packet())
        t_back = time.time()
        armed = d.wait_frame(lambda f: f.is_brake() and f.state == ARMED, after=n)
        assert armed.data[:4].hex() == "00000100" and armed.t - t_back < 0.05
        # silent again: SLOWING at S, then STOPPED (udp timeout) at T after the last packet
        stop = d.wait_frame(lambda f: f.is_brake() and f.state == STOPPED, after=n, timeout=5)
        assert stop.data[:4].hex() == "01640003", stop
        assert 1.0 - 0.002 <= stop.t - back_from and stop.t - t_back <= 1.0 + 0.1, \
            (stop.t - back_from, t_back - back_from)
        d.wait_log(lambda s: "SLOWING->STOPPED" in s)
        frames = d.frames()
    check_frames(frames)
    assert state_changes(d) == [
        ("STOPPED->ARMED", "none", "127.0.0.1", "release"),
        ("ARMED->SLOWING", "none", "-", "udp_silence"),
        ("SLOWING->ARMED", "none", "127.0.0.1", "link_back"),
        ("ARMED->SLOWING", "none", "-", "udp_silence"),
        ("SLOWING->STOPPED", "udp_timeout", "-", "udp_timeout"),
    ]


def test_with_the_slow_time_equal_to_the_timeout_there_is_no_slowing(tmp_path: Path) -> None:
    with Daemon(tmp_path, "--timeout-ms", "150") as d:
        d.arm()
        d.wait_frame(lambda f: f.is_brake() and f.reason == R_UDP_TIMEOUT)
        # the event log has its own writer thread: its line can follow the frame (load 8)
        d.wait_log(lambda s: "ARMED->STOPPED" in s)
        frames = d.frames()
    check_frames(frames)
    assert not any(f.is_brake() and f.state == SLOWING for f in frames)
    assert state_changes(d)[-1] == ("ARMED->STOPPED", "udp_timeout", "-", "udp_timeout")


def lift_request(seq: int) -> bytes:
    """A LIFT request frame (PROTOCOL.md 5.2) with a tag no key made: anyone may stop."""
    return auth.AuthRequest(MSG_LIFT, seq, 7, 0, 1).encode(None)


def stop_request(seq: int) -> bytes:
    return auth.AuthRequest(STOP_ID, seq, 7, 0, 1).encode(None)


@pytest.mark.parametrize(("how", "reason", "cause"), [
    ("tcp_plain", R_LIFT, "lift"),
    ("tcp_request", R_LIFT, "lift"),
    ("lift_datagram", R_LIFT, "lift_datagram"),
    ("stop_datagram", R_TCP_STOP, "stop_datagram"),
])
def test_lift_and_stop_requests_stop_with_their_reason_and_cause(
        tmp_path: Path, how: str, reason: int, cause: str) -> None:
    with Daemon(tmp_path) as d:
        d.arm()
        n = d.count_once_armed()
        if how == "tcp_plain":
            reply = d.request(MSG_LIFT, 9)
            assert (reply.msg, reply.seq, reply.state, reply.reason) == (ACK, 9, STOPPED, R_LIFT)
        elif how == "tcp_request":
            with d.connect() as s:
                s.sendall(lift_request(9))
                r = auth.AuthReply.decode(recv_exact(s, 48), None)
            assert (r.ack, r.seq, r.state, r.reason) == (True, 9, STOPPED, R_LIFT)
        else:
            d.send_udp(lift_request(9) if how == "lift_datagram" else stop_request(9))
        stop = d.wait_frame(lambda f: f.is_brake() and f.state == STOPPED, after=n)
        assert stop.data[:6].hex() == f"016400{reason:02x}0000", stop
        d.wait_log(lambda s: "ARMED->STOPPED" in s)
        # latched: a later stop request keeps the first reason
        assert d.request(STOP_ID if reason == R_LIFT else MSG_LIFT, 10).reason == reason
        frames = d.frames()
    check_frames(frames)
    name = "lift" if reason == R_LIFT else "tcp_stop"
    assert state_changes(d)[-1] == ("ARMED->STOPPED", name, "127.0.0.1", cause)


def test_lift_while_slowing(tmp_path: Path) -> None:
    with Daemon(tmp_path, *TWO_STAGE, "--log-json") as d:
        d.arm()
        d.wait_frame(lambda f: f.is_brake() and f.state == SLOWING)
        reply = d.request(MSG_LIFT, 3)
        assert (reply.state, reply.reason) == (STOPPED, R_LIFT)
        line = d.wait_log(lambda s: '"to":"STOPPED"' in s)
    ev = json.loads(line)
    assert (ev["event"], ev["from"], ev["to"], ev["reason"], ev["cause"]) == \
        ("state", "SLOWING", "STOPPED", "lift", "lift")
    assert ev["src"].startswith("127.0.0.1:")


def test_release_of_a_link_silent_for_the_slow_time_goes_straight_to_slowing(
        tmp_path: Path) -> None:
    """PROTOCOL.md 3: a RELEASE is accepted for a link younger than T; one older than S never
    releases the brake: the unit goes from STOPPED to SLOWING."""
    with Daemon(tmp_path, *TWO_STAGE) as d:
        d.make_live()
        time.sleep(0.25)  # older than S (100 ms), well younger than T (1 s)
        reply = d.request(MSG_RELEASE, 1)
        assert (reply.msg, reply.state, reply.reason) == (ACK, SLOWING, R_NONE)
        for _ in range(3):
            d.send_udp(udp_packet())
        d.wait_log(lambda s: "SLOWING->ARMED" in s)
        frames = d.frames()
    check_frames(frames)
    first = next(f for f in frames if f.is_brake() and f.state != STOPPED)
    assert first.state == SLOWING  # no frame released the brake for the stale link
    assert state_changes(d) == [
        ("STOPPED->SLOWING", "none", "127.0.0.1", "release"),
        ("SLOWING->ARMED", "none", "127.0.0.1", "link_back"),
    ]


def test_shutdown_while_slowing_ends_with_a_stopped_frame_from_the_core(tmp_path: Path) -> None:
    """SLOWING is not latched: SIGTERM there is a fault (cause shutdown), as while ARMED, so
    the core itself sends the STOPPED frame and the change is logged."""
    with Daemon(tmp_path, "--slow-ms", "50", "--timeout-ms", "10000") as d:
        d.arm()
        d.wait_frame(lambda f: f.is_brake() and f.state == SLOWING)
        assert d.signal() == 0
        frames = d.frames()
        log = d.log()
    check_frames(frames)
    last = [f for f in frames if f.is_brake()][-1]
    assert (last.data[0], last.state, last.reason) == (1, STOPPED, R_FAULT)
    assert any(line.split()[2:] == ["fault", "cause=shutdown"] for line in log), log
    assert state_changes(d)[-1] == ("SLOWING->STOPPED", "fault", "-", "fault")


def test_link_histogram_counts_slowdowns_and_timeouts(tmp_path: Path) -> None:
    with Daemon(tmp_path, "--slow-ms", "60", "--timeout-ms", "300", "--log-json") as d:
        d.arm()
        d.wait_frame(lambda f: f.is_brake() and f.reason == R_UDP_TIMEOUT)
        assert d.signal() == 0
        hist = [json.loads(line) for line in d.log() if '"link_histogram"' in line]
    last = hist[-1]
    assert (last["slowdowns"], last["timeouts"]) == (1, 1)
    assert (last["warn_us"], last["slow_us"], last["timeout_us"]) == (30000, 60000, 300000)
    assert last["valid"] == 6 and len(last["counts"]) == len(last["edges_us"]) == 32
