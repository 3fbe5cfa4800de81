"""`estopd --rt-prio` under the shipped service (issue 16, defect 2; deploy/estopd.service.in):
systemd starts it under SCHED_FIFO with CPUSchedulingResetOnFork, as a user without any
capability. Here that is `chrt -f -R` and `setpriv` to uid 65534 with every capability gone:
a process already at that policy and priority or higher keeps it, one below asks with
SCHED_RESET_ON_FORK, and a refusal names the real cause in one line (exit 1).

Needs root (to switch user) and a kernel that grants SCHED_FIFO here; skipped with the reason
otherwise.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from daemon_util import MSG_STATUS, STOPPED, Daemon, find_estopd

pytestmark = pytest.mark.timeout(120)

NOBODY = 65534
SCHED_RESET_ON_FORK = 0x40000000


def as_service(prio: int, argv: list[str], rtprio_limit: int | None = None) -> list[str]:
    """argv as the service runs it: SCHED_FIFO at prio with reset-on-fork, uid 65534, no
    capability (and RLIMIT_RTPRIO lowered to rtprio_limit, if given)."""
    limit = ["prlimit", f"--rtprio={rtprio_limit}"] if rtprio_limit is not None else []
    sched = ["chrt", "-f", "-R", str(prio)] if prio > 0 else []
    return [*limit, *sched, "setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}",
            "--clear-groups", "--inh-caps=-all", "--bounding-set=-all", *argv]


@pytest.fixture(autouse=True)
def fifo_allowed() -> None:
    if os.geteuid() != 0:
        pytest.skip("switching to an unprivileged user needs root")
    for tool in ("chrt", "setpriv", "prlimit"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} (util-linux) is not installed")
    res = subprocess.run(["chrt", "-f", "-R", "10", "true"], capture_output=True, text=True,
                         timeout=10, check=False)
    if res.returncode != 0:
        pytest.skip(f"this container grants no SCHED_FIFO: {res.stderr.strip()}")


def policy(pid: int) -> tuple[int, int, bool]:
    raw = os.sched_getscheduler(pid)
    return (raw & ~SCHED_RESET_ON_FORK, os.sched_getparam(pid).sched_priority,
            bool(raw & SCHED_RESET_ON_FORK))


@pytest.mark.parametrize(("started", "asked"), [(10, 10), (50, 10)])
def test_a_service_already_at_the_priority_or_higher_keeps_it(tmp_path: Path, started: int,
                                                              asked: int) -> None:
    """Started under SCHED_FIFO at `started`, --rt-prio `asked` (not above it): it runs and
    keeps what it was given. Before, it asked for SCHED_FIFO without SCHED_RESET_ON_FORK, got
    EPERM and exited 1 (and systemd restarted it forever with the car braked)."""
    d = Daemon(tmp_path, "--rt-prio", str(asked))
    d.argv = as_service(started, d.argv)
    with d:
        assert d.proc is not None
        assert policy(d.proc.pid) == (os.SCHED_FIFO, started, True)
        assert d.request(MSG_STATUS, 1).state == STOPPED
        assert f"rt_prio={started} " in d.start_line, d.start_line


@pytest.mark.parametrize("started", [0, 50])
def test_the_start_line_says_what_the_loop_runs_at(tmp_path: Path, started: int) -> None:
    """As the service starts it (SCHED_FIFO 50 from systemd, no --rt-prio; issue 26): the
    start line says rt_prio=50, the priority the loop runs at; before, it said what
    --rt-prio asked for (0). At a normal policy it says 0."""
    d = Daemon(tmp_path)
    d.argv = as_service(started, d.argv)
    with d:
        assert d.proc is not None
        assert policy(d.proc.pid)[:2] == ((os.SCHED_FIFO, started) if started
                                          else (os.SCHED_OTHER, 0))
        assert f"rt_prio={started} " in d.start_line, d.start_line


def test_a_process_below_the_priority_asks_with_reset_on_fork(tmp_path: Path) -> None:
    """Started at normal priority with the right to raise itself (root's CAP_SYS_NICE here:
    this container lets no one raise RLIMIT_RTPRIO), --rt-prio 20: SCHED_FIFO 20 with
    SCHED_RESET_ON_FORK, so nothing it starts inherits real time. Before, without it."""
    with Daemon(tmp_path, "--rt-prio", "20") as d:
        assert d.proc is not None
        assert policy(d.proc.pid) == (os.SCHED_FIFO, 20, True)
        assert "rt_prio=20 " in d.start_line, d.start_line


def test_a_priority_it_may_not_have_is_refused_naming_the_cause() -> None:
    """Started under SCHED_FIFO 10, no capability, RLIMIT_RTPRIO 0, --rt-prio 60: one line
    that says what would allow it (CAP_SYS_NICE, RLIMIT_RTPRIO, the service's priority), exit
    1."""
    res = subprocess.run(as_service(10, [find_estopd(), "--no-auth", "--udp-port", "0",
                                         "--tcp-port", "0", "--bind", "127.0.0.1",
                                         "--rt-prio", "60"], rtprio_limit=0),
                         capture_output=True, text=True, timeout=30, check=False,
                         stdin=subprocess.DEVNULL)
    assert res.returncode == 1, res
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    for what in ("--rt-prio 60", "CAP_SYS_NICE", "RLIMIT_RTPRIO >= 60 (it is 0)",
                 "CPUSchedulingPriority"):
        assert what in lines[0], lines[0]


def test_check_as_the_service_refuses_a_priority_above_its_own() -> None:
    """The service's second ExecCondition= runs `estopd --check --mlock $ESTOPD_ARGS` as the
    service (SCHED_FIFO 50, no capability): --rt-prio 60 in the options is one line naming the
    cause and exit 1 there, so the start is skipped instead of failing every second; --rt-prio
    50 passes."""
    base = [find_estopd(), "--check", "--channel", "lo"]
    for prio, code in ((60, 1), (50, 0)):
        res = subprocess.run(as_service(50, [*base, "--rt-prio", str(prio)], rtprio_limit=0),
                             capture_output=True, text=True, timeout=30, check=False,
                             stdin=subprocess.DEVNULL)
        assert res.returncode == code, res
        if code:
            assert "CPUSchedulingPriority=60" in res.stderr and len(
                res.stderr.splitlines()) == 1, res.stderr
