"""What estopd reads before it lets a stop-port connection go (firmware/estopd/README.md,
choices): every byte the unit's kernel has taken is handled, whether the connection is evicted
(issue 16, defect 3), never read its replies (defect 4) or is still open at SIGTERM (defect 5).

Real loopback sockets; the daemon is held with SIGSTOP where a test needs connections to queue
in the listen backlog.
"""

from __future__ import annotations

import contextlib
import fcntl
import gc
import os
import signal
import socket
import struct
import termios
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_estopd_attacks import Heartbeat, status
from test_estopd_rxtime import pause, resume

from daemon_util import (
    ACK,
    MSG_STATUS,
    R_TCP_STOP,
    STOP_ID,
    STOPPED,
    Daemon,
    parse_reply,
    recv_exact,
    tcp_frame,
)
from stall_probe import StallProbe

pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]

SLOTS = 8


def unacked(s: socket.socket) -> int:
    """Bytes of s's send queue the peer's kernel has not acknowledged yet (SIOCOUTQ)."""
    return int(struct.unpack("i", fcntl.ioctl(s, termios.TIOCOUTQ, b"\0" * 4))[0])


def test_a_stop_a_backlogged_connection_queued_counts_when_it_is_evicted(
        tmp_path: Path) -> None:
    """A client connects while the daemon cannot run, so its connection waits in the listen
    backlog, and sends 96 KiB of STATUS requests and a STOP; eight more connect behind it, and
    the ninth evicts it before it was ever read. Whatever the unit's kernel acknowledged must be
    handled: if it took the STOP, the unit stops; if it did not, the client sees its connection
    reset, never a STOP taken and dropped.

    Before, the backlogged connection had the listener's default buffer (128 KiB here), so the
    kernel took all of it, and the drain before the close read 64 KiB: the STOP was lost."""
    with Daemon(tmp_path) as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        os.kill(d.proc.pid, signal.SIGSTOP)
        others: list[socket.socket] = []
        try:
            v = socket.socket()
            v.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            v.connect(("127.0.0.1", d.tcp_port))
            v.setblocking(False)
            data = tcp_frame(MSG_STATUS, 1) * (96 * 1024 // 16) + tcp_frame(STOP_ID, 99)
            sent = v.send(data)
            assert sent == len(data), sent  # all in the client's own send buffer
            time.sleep(0.3)
            taken = sent - unacked(v)  # what the unit's kernel holds for the daemon
            for _ in range(SLOTS):
                others.append(socket.create_connection(("127.0.0.1", d.tcp_port), timeout=5))
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        d.wait_log(lambda s: " client_evict " in s, timeout=5)
        time.sleep(0.3)
        if taken == len(data):
            assert status(d) == (STOPPED, R_TCP_STOP), (taken, d.log())
        else:
            # What the kernel holds for a backlogged connection is within the drain's bound
            # (twice the 16 KiB SO_RCVBUF reads back as): what it took, it was read whole.
            assert taken <= 2 * 16384, taken
            v.settimeout(3)
            with pytest.raises(ConnectionResetError):  # noqa: PT012 - drain the replies first
                while v.recv(65536):
                    pass
            assert unacked(v) > 0  # the STOP never reached the unit: the client knows
        v.close()
        for s in others:
            s.close()


def test_a_stop_behind_3000_unread_replies_stops_every_time(tmp_path: Path) -> None:
    """Issue 16's case of defect 4, as it was reported: 3,000 STATUS requests and then a STOP
    on one connection, no reply ever read, ten tries: every one stops the unit (it lost 7 of
    10 when the unit closed a client whose replies blocked; version 3 drops and counts the
    replies instead, reply.c). The client's receive buffer is the kernel's minimum, so the
    replies do block."""
    with Daemon(tmp_path) as d, Heartbeat(d.udp_port):
        for attempt in range(10):
            d.arm()
            with socket.socket() as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)
                s.settimeout(10)
                s.connect(("127.0.0.1", d.tcp_port))
                s.sendall(b"".join(tcp_frame(MSG_STATUS, i) for i in range(3000)) +
                          tcp_frame(STOP_ID, 3001))
                deadline = time.monotonic() + 5
                while status(d) != (STOPPED, R_TCP_STOP):
                    assert time.monotonic() < deadline, (attempt, d.log()[-20:])
                    time.sleep(0.02)
        lines = d.log()
        assert sum("reason=tcp_stop" in s for s in lines) == 10, lines
        assert not any("why=reply_blocked" in s for s in lines), lines


def test_a_stop_already_in_a_socket_at_sigterm_is_handled_and_answered(tmp_path: Path) -> None:
    """SIGTERM arrives while a client's 20 STATUS requests (more than one 256-byte read) and
    its STOP wait in its socket (the daemon held with SIGSTOP meanwhile): the exit handles them
    all before the last frame, answers the STOP, and the last frame says why the unit stopped.
    Before, the loop read one 256-byte piece of the client's input, left for the exit and
    closed the rest unread (a reset): the STOP was neither handled nor answered."""
    with Daemon(tmp_path) as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        s = d.connect()
        s.settimeout(5)
        d.wait_log(lambda line: " client_open " in line)
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            d.proc.send_signal(signal.SIGTERM)
            s.sendall(b"".join(tcp_frame(MSG_STATUS, i) for i in range(20)) +
                      tcp_frame(STOP_ID, 777))
            time.sleep(0.1)
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        assert d.proc.wait(timeout=10) == 0
        replies = b""
        while chunk := s.recv(65536):
            replies += chunk
        s.close()
        parsed = [parse_reply(replies[i:i + 16]) for i in range(0, len(replies), 16)]
        stop = [r for r in parsed if r.seq == 777]
        assert stop and stop[0].msg == ACK and stop[0].state == STOPPED, parsed[-3:]
        lines = d.log()
        at_stop = next(i for i, line in enumerate(lines) if "reason=tcp_stop" in line)
        at_exit = next(i for i, line in enumerate(lines) if " exit " in line)
        assert at_stop < at_exit, lines
        last = [f for f in d.frames() if f.is_brake()][-1]
        assert last.state == STOPPED and last.reason == R_TCP_STOP, last


def test_a_stop_on_a_connection_still_in_the_backlog_at_sigterm_counts(tmp_path: Path) -> None:
    """SIGTERM, then a client connects and sends a STOP while the daemon cannot run: its
    connection is still in the listen backlog when the exit begins. The exit accepts it and
    handles the STOP before the last frame."""
    with Daemon(tmp_path) as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            d.proc.send_signal(signal.SIGTERM)
            s = socket.create_connection(("127.0.0.1", d.tcp_port), timeout=5)
            s.sendall(tcp_frame(STOP_ID, 778))
            time.sleep(0.1)
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        assert d.proc.wait(timeout=10) == 0
        with s:
            reply = parse_reply(recv_exact(s, 16))
        assert reply.seq == 778 and reply.msg == ACK and reply.state == STOPPED, reply
        last = [f for f in d.frames() if f.is_brake()][-1]
        assert last.state == STOPPED and last.reason == R_TCP_STOP, last


def test_at_sigterm_busy_clients_in_early_slots_cannot_starve_a_stop_in_a_later_one(
        tmp_path: Path) -> None:
    """Issue 25 item 5. Seven clients in the first places send STATUS requests as fast as
    they can and never read a reply; the eighth has a STOP in its socket when SIGTERM comes.
    Before, the exit drain read the places one after another, each up to its bound (32 KiB),
    so the STOP waited behind 7 x 32 KiB of requests, and behind the 100 ms exit deadline on a
    slower host. Now the clients are read in turns: the STOP is handled in the first turns.
    The eighth client's STOP comes behind 32 requests, more than the round that sees the
    signal reads of it, so the rest is the exit drain's. Replies may be dropped (the clients
    read none while the daemon was stopped): the brake frame tells when the STOP was handled.
    T is 2 s: the heartbeat thread shares this process with the seven pumps."""
    with Daemon(tmp_path, "--timeout-ms", "2000") as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        busy = [d.connect() for _ in range(SLOTS - 1)]
        stopper = d.connect()
        pumping = threading.Event()
        pumping.set()

        def pump(s: socket.socket) -> None:
            chunk = tcp_frame(MSG_STATUS, 1) * 4096
            s.settimeout(0.1)
            while pumping.is_set():
                try:
                    s.sendall(chunk)
                except TimeoutError:
                    continue
                except OSError:
                    return

        pumps = [threading.Thread(target=pump, args=(s,), daemon=True) for s in busy]
        try:
            d.wait_log(lambda line: " client_open slot=7 " in line)
            for th in pumps:
                th.start()
            time.sleep(0.2)
            with StallProbe(d.proc.pid) as probe:
                pause(d)
                d.proc.send_signal(signal.SIGTERM)
                # More than one read (256 bytes) before the STOP: the round that sees the
                # signal reads a piece, the exit drain the rest.
                stopper.sendall(b"".join(tcp_frame(MSG_STATUS, 100 + i) for i in range(32)) +
                                tcp_frame(STOP_ID, 5))
                t_resume = resume(d)
                assert d.proc.wait(timeout=10) == 0
        finally:
            pumping.clear()
            for th in pumps:
                th.join(timeout=5)
            for s in [*busy, stopper]:
                s.close()
        frames = d.frames()
        lines = d.log()
    stops = [f for f in frames if f.is_brake() and f.reason == R_TCP_STOP and f.t >= t_resume]
    assert stops, f"the STOP was never handled: the exit drain ran out of time: {lines[-12:]}"
    stop = stops[0]  # emitted when the STOP was handled
    last = [f for f in frames if f.is_brake()][-1]
    assert last.state == STOPPED and last.reason == R_TCP_STOP, last
    # The daemon's own work before the STOP: a turn or two of each client (about 1 ms here),
    # not seven clients' 32 KiB each (20 ms here). Its time is judged beside the stall.
    ran = probe.ran_s(t_resume, stop.t)
    assert ran <= 0.010, \
        f"{ran * 1e3:.1f} ms of work before the STOP: {probe.explain(t_resume, stop.t)}"
    assert stop.t - t_resume <= 0.020 + probe.stall_s(t_resume, stop.t), \
        probe.explain(t_resume, stop.t)


BURST = 24  # connections a burst of the churn opens (more than one listener event accepted)


def preloaded_burst(port: int) -> list[socket.socket]:
    """BURST connections, each with 32 KiB of STATUS requests whose replies are never read."""
    preload = tcp_frame(MSG_STATUS, 7) * (32 * 1024 // 16)
    burst = []
    for _ in range(BURST):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        s.connect(("127.0.0.1", port))  # the kernel completes it while the daemon is stopped
        s.setblocking(False)
        assert s.send(preload) == len(preload)
        burst.append(s)
    return burst


def test_a_stop_waits_behind_one_eviction_at_most(tmp_path: Path) -> None:
    """Issue 25 item 4: TCP stops waited behind eviction work. Seven clients hold places
    without a complete frame since they connected (the quietest); an eighth sent a STATUS. The
    daemon is stopped for a moment while the seven each send 32 KiB of STATUS requests, a
    burst of 24 connections preloaded the same way queues in the listen backlog, and the
    eighth sends a STOP. Before, the listener's event came first and accepted 16 of them,
    evicting and draining the seven whole (32 KiB each, one core call per frame) before the
    STOP, which the eighth connection's own eviction then handled: seven evictions before it.
    Now one eviction begins per loop round and gets 2 ms of it; the STOP, readable in the same
    round, is handled in it. (T is 2 s: the test's heartbeat thread may starve a while on a
    busy machine, and a timeout stop would hide the STOP.)"""
    with Daemon(tmp_path, "--timeout-ms", "2000") as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        quiet = [d.connect() for _ in range(SLOTS - 1)]
        stopper = d.connect()
        burst: list[socket.socket] = []
        try:
            time.sleep(0.1)  # all eight hold places
            assert d.request(MSG_STATUS, 1, stopper).seq == 1
            preload = tcp_frame(MSG_STATUS, 7) * (32 * 1024 // 16)
            with StallProbe(d.proc.pid) as probe:
                pause(d)
                burst = preloaded_burst(d.tcp_port)  # the listener is readable first
                for s in quiet:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
                    s.setblocking(False)
                    s.send(preload)
                stopper.sendall(tcp_frame(STOP_ID, 2))
                t_resume = resume(d)
                reply = parse_reply(recv_exact(stopper, 16))
                t_reply = time.time()
            lines = d.log()
        finally:
            for s in [*quiet, stopper, *burst]:
                s.close()
    assert reply.seq == 2 and reply.msg == ACK and reply.state == STOPPED, reply
    at_stop = next(i for i, line in enumerate(lines) if "reason=tcp_stop" in line)
    evicted = [line for line in lines[:at_stop] if "why=evicted" in line]
    assert len(evicted) <= 1, (f"{len(evicted)} evictions done before the STOP, "
                               f"{(t_reply - t_resume) * 1e3:.1f} ms after the resume")
    # Beyond the machine's stall in the same interval: one round's work.
    assert t_reply - t_resume <= 0.020 + probe.stall_s(t_resume, t_reply), \
        probe.explain(t_resume, t_reply)


ROUND_S = 0.15  # a round of the eviction test lasts at least this long after the resume
ROUND_JUDGED = 12  # and until this many round trips were judged in it
ROUND_CAP_S = 3.0  # but no longer than this


def round_over(since_resume_s: float, judged: int) -> bool:
    """Whether a round of the eviction test is over. CI's run of e42a4c6 judged 88 round trips
    in ten rounds of 0.15 s (p99 and max within their bounds): the measuring client was evicted
    in each round, and its new connection's first reply, which waits in the listen backlog behind
    the churn's and is not judged, took most of the round on that loaded machine. A round now
    lasts until it judged enough round trips, within a cap, so that the count measures the
    daemon rather than the backlog."""
    if since_resume_s >= ROUND_CAP_S:
        return True
    return since_resume_s >= ROUND_S and judged >= ROUND_JUDGED


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off for a timed part: the test judges the daemon's
    round trips, and a full collection in this (pytest's) process lands inside one. A
    fresh-clone run of b034d06 failed a round trip of 120 ms while the daemon ran 1.1 ms and
    waited 0.5 ms for a CPU and no sleeper overslept more than 3.3 ms: the time was not the
    daemon's nor the machine's, so most likely this process's own (not shown: its logs were
    gone)."""
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def test_eviction_work_cannot_hold_up_a_well_behaved_client(tmp_path: Path) -> None:
    """Issue 25 item 4: a client keeps opening connections preloaded with 32 KiB of STATUS
    requests (in bursts of 24, queued while the daemon is stopped for a moment, as a busy
    daemon would find them), and every accept beyond the 8 places evicts a client and drains
    what it sent. A client that sends one STATUS at a time and reads each reply must get its
    replies within 20 ms at the 99th percentile and 50 ms at most. Before, one listener event
    accepted up to 16 connections and drained an evicted client for each, whole, while the
    requests already readable on other connections waited. Now at most one eviction begins per
    loop round, its drain gets 2 ms a round and the other clients are served between.

    Each round trip is judged with the machine's stall over it allowed on top (the daemon's
    run-queue wait and a sleeper's worst oversleep, tests/stall_probe.py), and none overlaps a
    stop. The measuring client is the quietest now and then (PROTOCOL.md 2: no rule for whom to
    close helps); its connection is then evicted and it connects anew: those round trips, and
    the first on the new connection (which waits in the listen backlog behind the churn's), are
    counted, not judged."""
    with Daemon(tmp_path) as d, Heartbeat(d.udp_port):
        d.arm()
        assert d.proc is not None
        trips: list[tuple[float, float]] = []
        evicted = 0
        held: list[socket.socket] = []
        s, fresh, seq = d.connect(), True, 0
        try:
            with StallProbe(d.proc.pid) as probe, collector_paused():
                for _ in range(10):
                    pause(d)
                    held += preloaded_burst(d.tcp_port)
                    # A request waits in the socket when the daemon runs again, behind the
                    # burst; its round trip counts from the resume.
                    seq += 1
                    s.sendall(tcp_frame(MSG_STATUS, seq))
                    resumed = resume(d)
                    judged_before = len(trips)
                    a = time.time()
                    while True:
                        try:
                            reply = parse_reply(recv_exact(s, 16))
                        except OSError:
                            evicted += 1
                            s.close()
                            s, fresh = d.connect(), True
                        else:
                            assert reply.seq == seq, reply
                            if not fresh:
                                trips.append((a, time.time()))
                            fresh = False
                        if round_over(time.time() - resumed, len(trips) - judged_before):
                            break
                        seq += 1
                        a = time.time()
                        try:
                            s.sendall(tcp_frame(MSG_STATUS, seq))
                        except OSError:
                            evicted += 1
                            s.close()
                            s, fresh = d.connect(), True
                            s.sendall(tcp_frame(MSG_STATUS, seq))
                    for old in held[:-2 * BURST]:
                        old.close()
                    del held[:-2 * BURST]
        finally:
            s.close()
            for old in held:
                old.close()
        evictions = sum(" client_evict " in line for line in d.log())
    assert len(trips) > 100, \
        f"{len(trips)} round trips judged, the measuring client evicted {evicted} times"
    # What each round trip took beyond the machine's stall over it.
    over = sorted(b - a - probe.stall_s(a, b) for a, b in trips)
    p99 = over[int(0.99 * (len(over) - 1))]
    worst = max(trips, key=lambda t: t[1] - t[0] - probe.stall_s(*t))
    summary = (f"{len(trips)} round trips, {evictions} evictions logged, {evicted} of the "
               f"measuring client; beyond the stall: p50 {over[len(over) // 2] * 1e3:.2f} ms, "
               f"p99 {p99 * 1e3:.2f} ms, max {over[-1] * 1e3:.2f} ms; raw max "
               f"{max(b - a for a, b in trips) * 1e3:.2f} ms")
    assert p99 <= 0.020, summary
    assert over[-1] <= 0.050, f"{summary}; the worst: {probe.explain(*worst)}"
