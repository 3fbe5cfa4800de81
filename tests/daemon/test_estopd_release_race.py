"""A keyed RELEASE from the real remote against the real estopd is not refused for the remote's
own control packets (issue 25, item 2's rule: a RELEASE must be above its remote's newest
counter on either channel; the remote raises one counter for both; estopd reads the control
port before each stop-channel frame). tests/core/test_core_release_race.py has the cause at
core level; docs/REMOTE.md section 4 the remote's side of the rule."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from daemon_util import Daemon
from estop.client.sender import Remote
from estop.protocol import tcp

KEY = bytes(range(32))
RID = 5

pytestmark = pytest.mark.timeout(120)


def _keyed(tmp_path: Path) -> Daemon:
    key = tmp_path / "key"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    return Daemon(tmp_path, "--key-file", str(key))


def _live(r: Remote) -> None:
    """Wait until the remote has sent 10 more control packets (the unit wants 5 since it
    stopped: a live link), at most 5 s (a loaded machine)."""
    target = r.stats.sent + 10
    deadline = time.monotonic() + 5.0
    while r.stats.sent < target:
        assert time.monotonic() < deadline, "the remote's sender did not run"
        time.sleep(0.002)


def test_a_keyed_release_is_not_refused_for_the_remotes_own_packets(
        tmp_path: Path, estopd: str) -> None:
    """40 RELEASEs (each after a STOP) from a remote sending 1,000 control packets a second,
    so that its sender ticks while most RELEASEs are in flight. Before: 9 of 60 refused NAK 4
    (`auth_failures counter=8`), each with a control packet sent while it waited; none with
    estopd built before item 2's rule (27f6ec2). Now none."""
    refused: list[str] = []
    with _keyed(tmp_path) as d, Remote("127.0.0.1", d.udp_port, d.tcp_port, key=KEY,
                                       remote_id=RID, rate_hz=1000.0) as r:
        r.hold()
        for i in range(40):
            _live(r)
            reply = r.release()
            if reply.nak_code == 4:
                refused.append(f"#{i}: {reply}")
            else:
                assert reply.ack, reply  # NAK 2 or 3 would be another fault
            assert r.stop().ack
        r.lift()
    assert refused == []


def test_a_release_waiting_in_a_held_daemon_is_not_overtaken(tmp_path: Path,
                                                             estopd: str) -> None:
    """The daemon held (SIGSTOP) for 100 ms while the RELEASE waits in its socket, the remote
    at 1,000 Hz: before, its sender went on, 100 control packets above the RELEASE were read
    first, NAK 4 every time. Now the sender makes none until the reply (the quiet's bound is
    raised to 1 s here; the shipped 50 ms is tests/core's and tests/unit's)."""
    with _keyed(tmp_path) as d, Remote("127.0.0.1", d.udp_port, d.tcp_port, key=KEY,
                                       remote_id=RID, rate_hz=1000.0,
                                       release_quiet_s=1.0) as r:
        assert d.proc is not None
        r.hold()
        _live(r)
        got: list[tcp.Reply] = []
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            th = threading.Thread(target=lambda: got.append(r.release()), daemon=True)
            th.start()
            time.sleep(0.1)
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        th.join(timeout=5)
        r.lift()
    assert got and got[0].ack and got[0].state == 1, got
