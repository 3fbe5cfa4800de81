"""estopd as a service on the car (issue 7, section 3): the systemd notify protocol against a
fake $NOTIFY_SOCKET, the unit file checked by systemd-analyze, and `make install`.

A stalled loop is made with an LD_PRELOAD shim: a datagram "ESTOP-TEST-STALL" on the control
port makes the daemon's recvmmsg sleep 1.5 s in the loop's own thread, as a stuck call would.
The output threads keep running meanwhile; no WATCHDOG=1 may come from them.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon_util import ROOT, Daemon, find_estopd, run_estopd

pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]

STALL_SHIM_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

typedef int (*recvmmsg_fn)(int, struct mmsghdr *, unsigned int, int, struct timespec *);

int recvmmsg(int fd, struct mmsghdr *msgs, unsigned int vlen, int flags,
             struct timespec *timeout)
{
    static recvmmsg_fn real;
    int n;
    int i;
    if (real == NULL) {
        real = (recvmmsg_fn)dlsym(RTLD_NEXT, "recvmmsg");
    }
    n = real(fd, msgs, vlen, flags, timeout);
    for (i = 0; i < n; i++) {
        if (msgs[i].msg_len == 16 &&
            memcmp(msgs[i].msg_hdr.msg_iov[0].iov_base, "ESTOP-TEST-STALL", 16) == 0) {
            usleep(1500000); /* the loop is stuck in a call, as a wedged driver would leave it */
        }
    }
    return n;
}
"""


@pytest.fixture(scope="module")
def stall_shim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "no C compiler for the stall shim"
    d = tmp_path_factory.mktemp("stall")
    (d / "stall.c").write_text(STALL_SHIM_C)
    so = d / "stall.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(so), str(d / "stall.c"), "-ldl"],
                   check=True, timeout=60)
    return so


class Supervisor:
    """The systemd side of sd_notify: a datagram socket that collects (time, message)."""

    def __init__(self, tmp_path: Path, abstract: bool = False) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if abstract:
            name = f"estop-notify-{os.getpid()}-{time.monotonic_ns()}"
            self.sock.bind("\0" + name)
            self.env_value = "@" + name
        else:
            path = tmp_path / "notify.sock"
            self.sock.bind(str(path))
            self.env_value = str(path)
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, str]] = []

    def collect(self, seconds: float) -> list[tuple[float, str]]:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append((time.monotonic(), data.decode()))
        return self.messages

    def wait_for(self, text: str, timeout: float = 5.0) -> float:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for t, msg in self.messages:
                if text in msg.split("\n"):
                    return t
            self.collect(0.05)
        raise AssertionError(f"no {text!r} within {timeout} s: {self.messages}")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Supervisor]:
    s = Supervisor(tmp_path)
    yield s
    s.close()


def pings(messages: list[tuple[float, str]], after: float = 0.0,
          before: float = float("inf")) -> list[float]:
    return [t for t, m in messages if "WATCHDOG=1" in m.split("\n") and after <= t < before]


def test_ready_then_watchdog_pings_then_stopping(tmp_path: Path,
                                                 supervisor: Supervisor) -> None:
    d = Daemon(tmp_path)
    d.env = {"NOTIFY_SOCKET": supervisor.env_value, "WATCHDOG_USEC": "400000"}
    with d:
        t_ready = supervisor.wait_for("READY=1")
        supervisor.collect(1.0)
        assert d.signal(signal.SIGTERM) == 0
        supervisor.collect(0.3)
    first = supervisor.messages[0][1].split("\n")
    assert first[0] == "READY=1"  # nothing before READY
    got = pings(supervisor.messages, after=t_ready)
    assert len(got) >= 5, supervisor.messages  # every 100 ms (a quarter of 400 ms)
    assert max(b - a for a, b in zip(got, got[1:], strict=False)) < 0.4
    assert supervisor.messages[-1][1] == "STOPPING=1"


def test_status_names_every_state_change(tmp_path: Path, supervisor: Supervisor) -> None:
    """STATUS= (systemctl status) follows the state, SLOWING included, with the reason while
    STOPPED."""
    d = Daemon(tmp_path, "--slow-ms", "50", "--timeout-ms", "300")
    d.env = {"NOTIFY_SOCKET": supervisor.env_value}
    with d:
        supervisor.wait_for("READY=1")
        d.arm()
        supervisor.wait_for("STATUS=watching: STOPPED (udp_timeout)")
    status = [m for _, msg in supervisor.messages for m in msg.split("\n")
              if m.startswith("STATUS=")]
    assert status == ["STATUS=watching: STOPPED (boot)", "STATUS=watching: ARMED",
                      "STATUS=watching: SLOWING", "STATUS=watching: STOPPED (udp_timeout)"]


def test_abstract_notify_socket(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path, abstract=True)
    try:
        d = Daemon(tmp_path)
        d.env = {"NOTIFY_SOCKET": sup.env_value}
        with d:
            sup.wait_for("READY=1")
            sup.collect(0.3)
        assert pings(sup.messages) == []  # no WATCHDOG_USEC: no pings
    finally:
        sup.close()


def test_no_ping_while_the_loop_is_stalled(tmp_path: Path, supervisor: Supervisor,
                                           stall_shim: Path) -> None:
    d = Daemon(tmp_path)
    d.env = {"NOTIFY_SOCKET": supervisor.env_value, "WATCHDOG_USEC": "200000",
             "LD_PRELOAD": str(stall_shim)}
    with d:
        supervisor.wait_for("READY=1")
        supervisor.collect(0.5)
        assert len(pings(supervisor.messages)) >= 5
        t_stall = time.monotonic()
        d.send_udp(b"ESTOP-TEST-STALL")
        supervisor.collect(2.5)
    stalled = pings(supervisor.messages, after=t_stall + 0.1, before=t_stall + 1.4)
    assert stalled == [], stalled  # the loop is stuck: systemd must see silence
    assert pings(supervisor.messages, after=t_stall + 1.5)  # and pings once it runs again


def test_watchdog_for_another_pid_is_not_ours(tmp_path: Path, supervisor: Supervisor) -> None:
    d = Daemon(tmp_path)
    d.env = {"NOTIFY_SOCKET": supervisor.env_value, "WATCHDOG_USEC": "200000",
             "WATCHDOG_PID": "1"}
    with d:
        supervisor.wait_for("READY=1")
        supervisor.collect(0.5)
    assert pings(supervisor.messages) == []


# -- the unit file and make install --------------------------------------------------------------
@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("install")
    subprocess.run(["make", "-s", "install", f"PREFIX={root}/usr", f"SYSCONFDIR={root}/etc"],
                   cwd=ROOT, check=True, timeout=300, capture_output=True)
    return root


def test_make_install_puts_everything_in_place(installed: Path) -> None:
    exe = installed / "usr/bin/estopd"
    assert os.access(exe, os.X_OK)
    key = installed / "etc/estop/key"
    assert key.stat().st_mode & 0o777 == 0o600
    text = key.read_text()
    assert len(text) == 65 and text.endswith("\n") and int(text, 16) >= 0
    assert (installed / "etc/estop/estopd.conf").exists()
    sysctl = (installed / "etc/sysctl.d/90-estopd.conf").read_text()
    assert "net.core.rmem_max = 4194304" in sysctl.splitlines()  # estopd's UDP buffer
    unit = (installed / "usr/lib/systemd/system/estopd.service").read_text()
    assert f"ExecStart={installed}/usr/bin/estopd --key-file" in unit
    assert "@" not in unit.replace("@system-service", "").replace("@memlock", "")
    res = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=10,
                         check=False)
    assert res.returncode == 0 and res.stdout == "estopd 3.0\n"


def test_installed_key_is_accepted_and_never_overwritten(installed: Path,
                                                         tmp_path: Path) -> None:
    key = installed / "etc/estop/key"
    before = key.read_text()
    with Daemon(tmp_path, "--key-file", str(key)) as d:
        assert "auth=key" in d.start_line
    subprocess.run(["make", "-s", "install", f"PREFIX={installed}/usr",
                    f"SYSCONFDIR={installed}/etc"], cwd=ROOT, check=True, timeout=300,
                   capture_output=True)
    assert key.read_text() == before
    res = subprocess.run([str(ROOT / "scripts/new-key"), str(key)], capture_output=True,
                         text=True, timeout=10, check=False)
    assert res.returncode == 1 and "not overwritten" in res.stderr


def test_systemd_analyze_verifies_the_unit(installed: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing (Debian package systemd, group check)"
    unit = installed / "usr/lib/systemd/system/estopd.service"
    res = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip() == "", res.stderr  # unknown keys are only warnings: none allowed
    # The check can fail: a misspelt key is reported.
    bad = installed / "bad.service"
    bad.write_text(unit.read_text().replace("WatchdogSec=", "WatchdogSecs="))
    res = subprocess.run([analyze, "verify", str(bad)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert "WatchdogSecs" in res.stderr


def test_unit_asks_for_what_the_issue_names(installed: Path) -> None:
    unit = (installed / "usr/lib/systemd/system/estopd.service").read_text()
    for line in ("Type=notify", "Restart=always", "CPUSchedulingPolicy=fifo", "WatchdogSec=1s",
                 "NoNewPrivileges=yes", "ProtectSystem=strict", "CapabilityBoundingSet=\n"):
        assert line in unit, line
    assert find_estopd()


# -- --rt-prio and --mlock, for hosts without systemd ----------------------------------------------
def _policy(pid: int, tid: int) -> tuple[int, int]:
    """(scheduling policy, rt priority) of one thread, from /proc (fields 41 and 40)."""
    fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[38]), int(fields[37])


def test_rt_prio_is_for_the_loop_only_and_mlock_locks(tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO and mlockall need root here")
    with Daemon(tmp_path, "--rt-prio", "7", "--mlock") as d:
        assert d.proc is not None
        pid = d.proc.pid
        tids = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
        policies = {tid: _policy(pid, tid) for tid in tids}
        assert policies[pid] == (1, 7)  # SCHED_FIFO, priority 7: the loop
        others = [p for tid, p in policies.items() if tid != pid]
        assert others and all(p == (0, 0) for p in others)  # the output threads: normal
        locked = [line for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                  if line.startswith("VmLck:")]
        assert locked and int(locked[0].split()[1]) > 0
        assert "rt_prio=7" in d.start_line and "mlock=1" in d.start_line


@pytest.mark.parametrize("value", ["0", "100", "-1", "x"])
def test_rt_prio_out_of_range_is_a_usage_error(value: str) -> None:
    res = run_estopd(["--rt-prio", value])
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 1, res


# -- --check: the service's ExecCondition= (issue 26) ------------------------------------------
def test_check_says_what_a_start_would_refuse_in_one_line(tmp_path: Path) -> None:
    """Under systemd a refused start was restarted every second for ever, the reason lost in the
    storm (a missing key file: only systemd's 'Failed to set up credentials: Protocol error').
    `estopd --check` runs first, as ExecCondition=: one line and exit 1 (2 for a bad option)
    for what no restart mends, exit 0 and nothing said otherwise."""
    key = tmp_path / "key"
    key.write_text("00" * 32 + "\n")
    key.chmod(0o600)
    cases = [
        ([], 0, ""),
        (["--key-file", str(key), "--channel", "lo"], 0, ""),
        (["--key-file", str(tmp_path / "nope")], 1, "No such file or directory"),
        (["--channel", "nosuch0"], 1, "no CAN interface 'nosuch0'"),
        (["--timeout-ms", "0"], 2, "--timeout-ms"),
        (["--no-auth", "--key-file", str(key)], 2, "exclude each other"),
    ]
    key.with_name("open").write_text("00" * 32 + "\n")
    key.with_name("open").chmod(0o644)
    cases.append((["--key-file", str(key.with_name("open"))], 1, "group or others have access"))
    for args, code, why in cases:
        res = run_estopd(["--check", *args], auth=False)
        assert res.returncode == code, (args, res)
        assert res.stdout == "", (args, res)
        if code:
            lines = res.stderr.splitlines()
            assert len(lines) == 1 and why in lines[0], (args, res.stderr)
        else:
            assert res.stderr == "", (args, res)


def test_check_opens_no_socket() -> None:
    """--check is not a start: with the ports taken it still says all is well (a port in use
    is a start-up failure that a restart may mend, for systemd's Restart= to handle)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u, \
            socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
        u.bind(("127.0.0.1", 0))
        t.bind(("127.0.0.1", 0))
        t.listen()
        res = run_estopd(["--check", "--no-auth", "--bind", "127.0.0.1", "--udp-port",
                          str(u.getsockname()[1]), "--tcp-port", str(t.getsockname()[1])])
        assert res.returncode == 0 and res.stderr == "", res
        res = run_estopd(["--no-auth", "--bind", "127.0.0.1", "--udp-port",
                          str(u.getsockname()[1]), "--tcp-port", "0"])
        assert res.returncode == 1, res  # the same options, started: the port is taken
