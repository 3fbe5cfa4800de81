"""estopd's UDP receive buffer (firmware/estopd/README.md, receive buffer): big enough that a
flood of 80,000 forged 60-byte packets a second loses nothing while the daemon cannot run for
50 ms; shown in the start line, a warning when the kernel gives less, and datagrams the kernel
drops all the same are counted (SO_RXQ_OVFL) and logged as `udp_drops`.

The hiccup is made with SIGSTOP; a smaller buffer (a car without CAP_NET_ADMIN and with the
default net.core.rmem_max) is made with an LD_PRELOAD shim, as net.core.rmem_max is the
machine's, not the test's, to change.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from daemon_util import ACK, MSG_STATUS, Daemon
from estop.protocol import auth
from estop.protocol.udp import ControlPacket
from estop.unit.udpsocket import udp_socket

pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]

KEY = bytes(range(32))
WANTED = 8 * 1024 * 1024  # 4 MiB asked for, doubled by the kernel
HICCUP = 4000  # 50 ms of an 80,000/s flood (and one more after it)
SMALL = 2 * 212992  # what SO_RCVBUF gives under the default net.core.rmem_max

CAP_SHIM_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <stddef.h>
#include <sys/socket.h>

typedef int (*setsockopt_fn)(int, int, int, const void *, socklen_t);

/* As without CAP_NET_ADMIN under the default net.core.rmem_max of 212992 bytes. */
int setsockopt(int fd, int level, int name, const void *v, socklen_t len)
{
    static setsockopt_fn real;
    static const int cap = 212992;
    if (real == NULL) {
        real = (setsockopt_fn)dlsym(RTLD_NEXT, "setsockopt");
    }
    if (level == SOL_SOCKET && name == SO_RCVBUFFORCE) {
        errno = EPERM;
        return -1;
    }
    if (level == SOL_SOCKET && name == SO_RCVBUF && *(const int *)v > cap) {
        v = &cap;
    }
    return real(fd, level, name, v, len);
}
"""


@pytest.fixture(scope="module")
def cap_shim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "no C compiler for the shim"
    d = tmp_path_factory.mktemp("capshim")
    (d / "cap.c").write_text(CAP_SHIM_C)
    so = d / "cap.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(so), str(d / "cap.c"), "-ldl"],
                   check=True, timeout=60)
    return so


def keyed(tmp_path: Path) -> Daemon:
    path = tmp_path / "key"
    path.write_text(KEY.hex() + "\n")
    path.chmod(0o600)
    return Daemon(tmp_path, "--key-file", str(path))


def rcvbuf(d: Daemon) -> int:
    m = re.search(r"\budp_rcvbuf=(\d+)\b", d.start_line)
    assert m, d.start_line
    return int(m.group(1))


def counts(line: str) -> dict[str, int]:
    return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", line)}


def hiccup(d: Daemon, n: int) -> None:
    """n forged authenticated packets (each read and refused) while it cannot run, then
    one more after it: the kernel's drop count comes with the datagrams queued after a drop."""
    assert d.proc is not None
    forged = auth.AuthControlPacket(7, 1, 1, ControlPacket()).encode(bytes(32))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("127.0.0.1", d.udp_port))
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            for _ in range(n):
                s.send(forged)
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        time.sleep(0.1)
        s.send(forged)


def tag_failures_and_drops(d: Daemon) -> tuple[int, int | None]:
    """After the run, from the read-outs written at exit: authentication failures by tag, and
    the total of udp_drops (None: no udp_drops event, nothing was dropped)."""
    deadline = time.monotonic() + 10
    while rx_queued(d.udp_port) and time.monotonic() < deadline:
        time.sleep(0.02)  # everything sent has been read once the socket's queue is empty
    assert d.request(MSG_STATUS, 1).msg == ACK  # the loop runs
    assert d.signal() == 0
    log = d.log()
    fails = [counts(line) for line in log if " auth_failures " in line]
    drops = [counts(line) for line in log if " udp_drops " in line]
    # Every forged datagram read is refused once: by a check, or unchecked over the budget.
    return (sum(fails[-1].values()) if fails else 0), (drops[-1]["total"] if drops else None)


def rx_queued(port: int) -> int:
    """Bytes waiting in the receive queue of the UDP socket bound to port (/proc/net/udp)."""
    sock = udp_socket(port)
    return 0 if sock is None else sock.rx_queue


def test_the_buffer_absorbs_50_ms_of_an_80000_per_second_flood(tmp_path: Path) -> None:
    with keyed(tmp_path) as d:
        if rcvbuf(d) < WANTED:
            assert any(" udp_rcvbuf_small " in line for line in d.log())
            pytest.skip(f"the kernel gave {rcvbuf(d)} bytes here (no CAP_NET_ADMIN, low "
                        "net.core.rmem_max): the case of test_a_small_buffer_warns")
        assert rcvbuf(d) == WANTED
        hiccup(d, HICCUP)
        tags, drops = tag_failures_and_drops(d)
    assert (tags, drops) == (HICCUP + 1, None)  # every one read and checked, none dropped


def test_a_small_buffer_warns_and_drops_are_counted(tmp_path: Path, cap_shim: Path) -> None:
    d = keyed(tmp_path)
    d.env = {"LD_PRELOAD": str(cap_shim)}
    with d:
        assert rcvbuf(d) == SMALL
        warn = d.wait_log(lambda line: " udp_rcvbuf_small " in line)
        assert warn.split()[2:] == ["udp_rcvbuf_small", f"bytes={SMALL}", f"wanted={WANTED}",
                                    "hint=net.core.rmem_max"]
        hiccup(d, HICCUP)
        tags, drops = tag_failures_and_drops(d)
    # 832 bytes a datagram in the queue on loopback: about 512 fit, the rest are dropped
    assert drops is not None and tags + drops == HICCUP + 1 and tags < HICCUP // 2, (tags, drops)
