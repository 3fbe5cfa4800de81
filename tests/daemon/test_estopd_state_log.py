"""Every state change is logged with its cause (issue 25, item 5): when one core call carries
two changes, the clock's and the input's, estopd logs two lines."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from daemon_util import Daemon, state_lines
from estop.protocol import auth


def test_a_clock_slowing_and_a_stop_in_one_call_are_logged_as_two_changes(
        tmp_path: Path) -> None:
    """The daemon is held (SIGSTOP) past the slow time S, then a stop datagram arrives: on
    waking, estopd reads it before its due tick, so one core call moves the unit ARMED ->
    SLOWING (the clock) and SLOWING -> STOPPED (the datagram). It was logged as one line,
    `ARMED->STOPPED reason=tcp_stop src=- cause=stop_datagram`: neither the slow-down nor the
    datagram's sender. Now two lines, each with its cause and source."""
    with Daemon(tmp_path, "--slow-ms", "500", "--timeout-ms", "3000") as d:
        assert d.proc is not None
        d.arm()
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            time.sleep(0.8)  # past S = 500 ms after the latest packet
            d.send_udp(auth.stop_datagram(1, 0, key=None))
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        d.wait_log(lambda s: "reason=tcp_stop" in s)
        lines = state_lines(d.log())
        slow = [i for i, s in enumerate(lines) if "ARMED->SLOWING" in s]
        assert slow, lines
        first, second = lines[slow[-1]], lines[slow[-1] + 1]
        assert "src=-" in first and "cause=udp_silence" in first, first
        assert "SLOWING->STOPPED reason=tcp_stop src=127.0.0.1:" in second, second
        assert "cause=stop_datagram" in second, second
