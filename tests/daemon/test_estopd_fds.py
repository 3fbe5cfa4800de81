"""The stop port at the descriptor limit (firmware/estopd/tcp.c): a spare descriptor is freed
for the accept and the quietest client gives one back, as when the places run out; where not
even that is possible, accept() backs off instead of spinning (issue 7, defect 4).

The daemon runs with a low RLIMIT_NOFILE: stdio, epoll, timer, signals, UDP, TCP and the two
output queues take 10 descriptors, the spare an 11th.
"""

from __future__ import annotations

import resource
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from test_estopd_attacks import Heartbeat, cpu_seconds

from daemon_util import (
    ACK,
    ARMED,
    MSG_RELEASE,
    MSG_STATUS,
    R_TCP_STOP,
    R_UDP_TIMEOUT,
    START_RE,
    STOP_ID,
    STOPPED,
    Daemon,
    parse_reply,
    recv_exact,
    tcp_frame,
)

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]


@contextmanager
def limited(tmp_path: Path, limit: int) -> Iterator[Daemon]:
    """A daemon started with RLIMIT_NOFILE at limit."""
    d = Daemon(tmp_path)

    def low_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))

    with d.out_path.open("wb") as out, d.err_path.open("wb") as err:
        d.proc = subprocess.Popen(d.argv, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                  preexec_fn=low_limit)
    try:
        line = d.wait_log(lambda line: " start " in line)
        m = START_RE.search(line)
        assert m
        d.udp_port, d.tcp_port = int(m["uport"]), int(m["tport"])
        yield d
    finally:
        d.kill()


def status_on(s: socket.socket) -> tuple[int, int]:
    s.sendall(tcp_frame(MSG_STATUS, 777))
    r = parse_reply(recv_exact(s, 16))
    return r.state, r.reason


def test_at_the_descriptor_limit_the_quietest_makes_room(tmp_path: Path) -> None:
    """Issue 25 item 5. Room for one client and the spare: six idle clients connect. Before,
    accept() failed with EMFILE and nothing was evicted: new clients waited in the backlog
    while the idle ones held the descriptors, and a RELEASE or a STOP on a new connection was
    never read. Now the spare is closed for each accept, the quietest client is closed to give
    a descriptor back, and every new client is served at once, without spinning."""
    with limited(tmp_path, 12) as d, Heartbeat(d.udp_port):
        assert d.proc is not None
        held = [d.connect() for _ in range(6)]
        try:
            time.sleep(0.3)
            cpu0 = cpu_seconds(d.proc.pid)
            d.make_live()
            time.sleep(0.02)
            assert d.request(MSG_RELEASE, 1).state == ARMED  # a new connection, served
            time.sleep(1.0)
            assert cpu_seconds(d.proc.pid) - cpu0 < 0.3  # no spinning
            reply = d.request(STOP_ID, 2)
            assert reply.msg == ACK and reply.state == STOPPED and reply.reason == R_TCP_STOP
            lines = d.log()
            assert any(" client_evict " in line and "why=fd_limit" in line for line in lines)
            assert not any(" accept_error " in line for line in lines), lines
            # the held ones were closed one after another to make room: the latest still holds
            for s in held[:-1]:
                s.settimeout(2)
                with pytest.raises(OSError):  # noqa: PT012 - EOF or a reset, either way closed
                    s.sendall(tcp_frame(MSG_STATUS, 3))
                    if not s.recv(16):
                        raise ConnectionResetError("closed")
        finally:
            for s in held:
                s.close()


def test_out_of_descriptors_backs_off_logs_once_and_keeps_watching(tmp_path: Path) -> None:
    """Room for the spare only: the first client takes its place, and no other client can
    give a descriptor back. With accept() failing the listener stayed readable: 100 % CPU and
    1.8 million accept_error lines in 2 s (issue 7). Now: pause, keep serving, log once per
    episode; when the client goes, the next is accepted."""
    with limited(tmp_path, 11) as d:
        assert d.proc is not None
        held = [d.connect() for _ in range(4)]  # the first gets the place, the rest wait
        try:
            time.sleep(0.3)
            cpu0 = cpu_seconds(d.proc.pid)
            d.make_live()
            time.sleep(0.02)
            held[0].sendall(tcp_frame(MSG_RELEASE, 1))
            assert parse_reply(recv_exact(held[0], 16)).state == ARMED
            time.sleep(2.0)
            assert cpu_seconds(d.proc.pid) - cpu0 < 0.5  # no spinning
            errors = [line for line in d.log() if " accept_error " in line]
            assert len(errors) == 1 and "err=EMFILE" in errors[0], errors
            assert status_on(held[0]) == (STOPPED, R_UDP_TIMEOUT)  # the watchdog kept watching
            held[0].close()
            # Its descriptor came back: the next waiting client is accepted and served.
            held[1].settimeout(5)
            held[1].sendall(tcp_frame(MSG_STATUS, 50))
            assert parse_reply(recv_exact(held[1], 16)).seq == 50
            d.wait_log(lambda line: " accept_ok " in line)
        finally:
            for s in held:
                s.close()
