"""estopd shutdown: SIGTERM/SIGINT send one last braking ESTOP_BRAKE frame, exit 0."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from daemon_util import (
    ARMED,
    BRAKE_ID,
    R_BOOT,
    R_FAULT,
    R_TCP_STOP,
    STOP_ID,
    STOPPED,
    Daemon,
    check_frames,
)

pytestmark = pytest.mark.timeout(60)


def _last_frame_brakes(d: Daemon, reason: int) -> None:
    frames = d.frames()
    check_frames(frames)  # the last frame continues the counter sequence, good CRC
    last = frames[-1]
    assert last.can_id == BRAKE_ID
    assert last.data[0] == 1 and last.data[1] == 100 and last.state == STOPPED
    assert last.reason == reason
    lines = d.log()
    assert "exit" in lines[-1] and "code=0" in lines[-1]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_while_stopped(tmp_path: Path, sig: int) -> None:
    with Daemon(tmp_path) as d:
        time.sleep(0.05)
        assert d.signal(sig) == 0
        _last_frame_brakes(d, R_BOOT)
        assert signal.Signals(sig).name in d.log()[-1]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_while_armed_ends_braking(tmp_path: Path, sig: int) -> None:
    with Daemon(tmp_path) as d:
        d.arm()
        d.make_live()
        assert any(f.is_brake() and f.state == ARMED for f in d.frames()) or d.wait_frame(
            lambda f: f.is_brake() and f.state == ARMED)
        assert d.signal(sig) == 0
        _last_frame_brakes(d, R_FAULT)
        assert any("state ARMED->STOPPED reason=fault" in line for line in d.log())


def test_signal_after_tcp_stop_keeps_reason(tmp_path: Path) -> None:
    with Daemon(tmp_path) as d:
        d.arm()
        d.request(STOP_ID, 1)
        assert d.signal() == 0
        _last_frame_brakes(d, R_TCP_STOP)


def test_signal_right_after_start(tmp_path: Path) -> None:
    with Daemon(tmp_path) as d:
        assert d.signal() == 0
        _last_frame_brakes(d, R_BOOT)
