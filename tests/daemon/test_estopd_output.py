"""estopd's standard descriptors and shared outputs (issue 16, defect 8; firmware/estopd/
README.md, choices): started with 0-2 closed it holds them with /dev/null before it opens
anything, so no log line or frame can go into its own signalfd, eventfd or sockets; and when the
event log and the can-log share one pipe (`estopd 2>&1 | ...`) their lines never interleave
inside a line (each write is whole lines, at most PIPE_BUF bytes: atomic on a pipe).
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import socket
import subprocess
import threading
import time

import pytest

from daemon_util import (
    MSG_RELEASE,
    MSG_STATUS,
    START_RE,
    STOP_ID,
    STOPPED,
    find_estopd,
    parse_reply,
    recv_exact,
    tcp_frame,
    udp_packet,
)
from net_util import unused_tcp_port

pytestmark = pytest.mark.timeout(120)

F_SETPIPE_SZ = 1031
CANLOG_LINE = re.compile(r"^\(\d+\.\d{6}\) \S+ [0-9A-F]{3}#[0-9A-F]*$")
LOG_LINE = re.compile(r"^estopd \d+\.\d{6} [a-z_]+( \S+)*$")


def unused_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def close_std_fds() -> None:
    for fd in (0, 1, 2):
        os.close(fd)


def test_started_with_0_to_2_closed_it_holds_them_with_dev_null() -> None:
    """Before, the signalfd took fd 0, an output thread's eventfd fd 1 and epoll fd 2: the
    log went into epoll and the can-log into the eventfd."""
    tcp = unused_tcp_port()
    proc = subprocess.Popen([find_estopd(), "--no-auth", "--bind", "127.0.0.1", "--udp-port",
                             str(unused_udp_port()), "--tcp-port", str(tcp), "--can-log", "-"],
                            preexec_fn=close_std_fds)  # noqa: PLW1509 - closing is the point
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                s = socket.create_connection(("127.0.0.1", tcp), timeout=5)
                break
            except ConnectionRefusedError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.returncode
                time.sleep(0.02)
        with s:
            s.sendall(tcp_frame(MSG_STATUS, 5))
            assert parse_reply(recv_exact(s, 16)).state == STOPPED
        links = [os.readlink(f"/proc/{proc.pid}/fd/{fd}") for fd in (0, 1, 2)]
        assert links == ["/dev/null"] * 3, links
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_log_and_can_log_on_one_pipe_never_interleave_inside_a_line() -> None:
    """Both outputs on one small pipe that is read late (its writers block, their rings fill,
    then they write at once): every line that comes out is a whole log line or a whole
    can-log line. Before, a writer wrote up to its whole ring at a time (pieces far over
    PIPE_BUF, cut at the ring's end), and a can-log line had a log line in its middle."""
    r, w = os.pipe()
    fcntl.fcntl(w, F_SETPIPE_SZ, 4096)
    proc = subprocess.Popen([find_estopd(), "--no-auth", "--udp-port", "0", "--tcp-port", "0",
                             "--bind", "127.0.0.1", "--can-log", "-"],
                            stdin=subprocess.DEVNULL, stdout=w, stderr=w)
    os.close(w)
    stop = threading.Event()
    try:
        out = b""
        m = None
        while m is None:
            chunk = os.read(r, 65536)
            assert chunk, out
            out += chunk
            m = START_RE.search(out.decode(errors="replace"))
        udp, tcp = int(m["uport"]), int(m["tport"])

        def heartbeat() -> None:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
                while not stop.wait(0.01):
                    u.sendto(udp_packet(), ("127.0.0.1", udp))

        beat = threading.Thread(target=heartbeat, daemon=True)
        beat.start()
        time.sleep(0.2)
        with socket.create_connection(("127.0.0.1", tcp), timeout=5) as s:
            for _ in range(40):  # releases and stops: state lines and frames, nobody reading
                s.sendall(b"".join(tcp_frame(MSG_RELEASE, 2 * k) + tcp_frame(STOP_ID, 2 * k + 1)
                                   for k in range(100)))
                time.sleep(0.03)
            time.sleep(0.3)
        stop.set()
        beat.join(timeout=5)
        proc.send_signal(signal.SIGTERM)
        while chunk := os.read(r, 65536):
            out += chunk
        assert proc.wait(timeout=10) == 0
    finally:
        stop.set()
        os.close(r)
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    lines = out.decode(errors="replace").split("\n")
    assert lines[-1] == "", lines[-1]
    bad = [line for line in lines[:-1] if not (CANLOG_LINE.match(line) or LOG_LINE.match(line))]
    assert not bad, bad[:5]
    assert sum(bool(LOG_LINE.match(line)) for line in lines) >= 3 and sum(
        bool(CANLOG_LINE.match(line)) for line in lines) >= 20, lines[:20]
