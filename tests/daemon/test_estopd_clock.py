"""estopd's clock (firmware/estopd/clock.h): the unit's time is CLOCK_BOOTTIME, so a suspend of
the host is a silence of that length, and a clock that cannot be read is a fault, not a frozen
time.

A suspend cannot be made here (no root over the host's power), so an LD_PRELOAD shim
(tests/c/clock_shim.c) moves CLOCK_BOOTTIME forward on demand, as a resume does, and leaves
CLOCK_MONOTONIC alone, as a resume does; it can also make CLOCK_BOOTTIME fail. Real loopback
sockets, the real daemon.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest
from test_estopd_attacks import Heartbeat, status

from daemon_util import (
    ACK,
    ARMED,
    MSG_RELEASE,
    MSG_STATUS,
    NAK,
    R_FAULT,
    STOPPED,
    Daemon,
    build_preload_shim,
)
from repo import ROOT

pytestmark = pytest.mark.timeout(120)

SUSPEND_US = 120 * 1_000_000  # two minutes asleep


@pytest.fixture(scope="module")
def clock_shim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_preload_shim(ROOT / "tests" / "c" / "clock_shim.c",
                              tmp_path_factory.mktemp("clockshim"))


class Clock:
    """The shim's control file: a suspend of the host so far, and whether the clock fails."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.set(0, fail=False)

    def set(self, offset_us: int, fail: bool) -> None:
        with self.path.open("r+b" if self.path.exists() else "wb") as fh:
            fh.write(struct.pack("<qQ", offset_us, 1 if fail else 0))

    def suspend(self, us: int) -> None:
        self.set(us, fail=False)


def shimmed(tmp_path: Path, shim: Path) -> tuple[Daemon, Clock]:
    clock = Clock(tmp_path / "clock.ctl")
    d = Daemon(tmp_path)
    d.env = {"LD_PRELOAD": str(shim), "ESTOP_CLOCK_SHIM": str(clock.path)}
    return d, clock


def test_an_armed_unit_stops_at_the_resume_after_a_suspend(tmp_path: Path,
                                                           clock_shim: Path) -> None:
    """ARMED with packets flowing, the host sleeps two minutes and wakes with the tablet
    still sending: the link was silent all that time, so the unit stops for the timeout at
    the resume (with CLOCK_MONOTONIC the suspend did not exist and it stayed ARMED)."""
    d, clock = shimmed(tmp_path, clock_shim)
    with d, Heartbeat(d.udp_port):
        d.arm()
        time.sleep(0.1)
        clock.suspend(SUSPEND_US)
        line = d.wait_log(lambda s: " state " in s and "ARMED->STOPPED" in s, timeout=3)
        assert "reason=udp_timeout" in line and "cause=udp_timeout" in line, line
        time.sleep(0.2)  # the packets after the resume do not re-arm it: the stop is latched
        assert status(d) == (STOPPED, 3)


def test_a_release_right_after_a_resume_is_refused(tmp_path: Path, clock_shim: Path) -> None:
    """STOPPED with a fresh run of valid packets, then a suspend: the run is as old as the
    suspend, so a RELEASE sent at the resume is refused (it passed with CLOCK_MONOTONIC)."""
    d, clock = shimmed(tmp_path, clock_shim)
    with d:
        d.make_live()
        time.sleep(0.02)
        # A request drains the control port first: the run is in before the host sleeps (the
        # shim leaves the wall clock alone, so a packet read after the jump would look new).
        assert d.request(MSG_STATUS, 6).state == STOPPED
        clock.suspend(SUSPEND_US)
        reply = d.request(MSG_RELEASE, 7)
        assert reply.msg == NAK and reply.state == STOPPED, reply
        assert not any("->ARMED" in s for s in d.log()), d.log()


def test_a_suspend_changes_nothing_for_a_fresh_run_after_it(tmp_path: Path,
                                                            clock_shim: Path) -> None:
    """After the resume the unit works as before: a new run of packets, a RELEASE, ARMED."""
    d, clock = shimmed(tmp_path, clock_shim)
    with d:
        clock.suspend(SUSPEND_US)
        time.sleep(0.1)
        reply = d.arm()
        assert reply.msg == ACK and reply.state == ARMED, reply


def test_a_clock_that_fails_is_a_fault(tmp_path: Path, clock_shim: Path) -> None:
    """CLOCK_BOOTTIME failing while ARMED: the daemon reports a fault to the core (STOPPED,
    reason fault, cause clock), and frames keep going out on the stand-in clock. Before, the
    clock read as 0 and was clamped: time stood still, no deadline passed and frames stopped."""
    d, clock = shimmed(tmp_path, clock_shim)
    with d, Heartbeat(d.udp_port):
        d.arm()
        clock.set(0, fail=True)
        fault = d.wait_log(lambda s: " fault " in s, timeout=3)
        assert "cause=clock" in fault, fault
        state = d.wait_log(lambda s: " state " in s and "ARMED->STOPPED" in s, timeout=3)
        assert "reason=fault" in state and "cause=fault" in state, state
        n = len(d.frames())
        time.sleep(0.3)
        later = d.frames()[n:]
        assert len(later) >= 5, later  # brake frames every brake period, the clock or not
        assert all(f.state == STOPPED for f in later if f.is_brake()), later
        clock.set(0, fail=False)
        time.sleep(0.1)
        assert status(d) == (STOPPED, R_FAULT)  # latched: a clock back is no release
        assert sum(" fault " in s for s in d.log()) == 1, d.log()  # once per episode
