"""End to end for `estop link` (issue 12): estopd on loopback, fed for 30 s by the remote's link
model (9 % loss in bursts of mean 3), writes its gap histogram to its JSON log; the tool reads
that log and must agree with the sender's own record of what it lost."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daemon_util import Daemon
from estop.linkmodel import LinkConfig
from estop.remote import Remote

pytestmark = pytest.mark.timeout(120)

SECONDS = 30.0
RATE_HZ = 50.0


def runs_of_losses(delivered: list[bool]) -> list[int]:
    runs, n = [], 0
    for ok in delivered:
        if ok:
            if n:
                runs.append(n)
            n = 0
        else:
            n += 1
    return runs


def test_link_report_from_the_daemons_own_log_agrees_with_the_sender(tmp_path: Path) -> None:
    delivered: list[bool] = []

    def record(_t: float, _data: bytes, t_deliver: float | None) -> None:
        delivered.append(t_deliver is not None)

    with Daemon(tmp_path, "--log-json") as d:
        link = LinkConfig(loss=0.09, burst=3.0, delay=0.0, jitter=0.0)
        with Remote("127.0.0.1", d.udp_port, d.tcp_port, rate_hz=RATE_HZ, link=link, seed=7,
                    on_packet=record) as remote:
            remote.hold()
            time.sleep(SECONDS)
            remote.lift()
        assert d.signal() == 0  # the last link_histogram is written at exit
    log = tmp_path / "daemon.json.log"
    log.write_text("\n".join(d.log()) + "\n")
    events = [json.loads(line) for line in d.log() if '"link_histogram"' in line]
    assert events, "no link_histogram event in the daemon's log"
    # The daemon counted exactly the packets the sender delivered.
    assert events[-1]["valid"] == sum(delivered)
    assert sum(events[-1]["counts"]) == sum(delivered) - 1

    res = subprocess.run([sys.executable, "-m", "estop", "link", str(log), "--json",
                          "--rate-hz", str(RATE_HZ)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    # Ground truth: what the sender lost, counted from its first delivered packet on (the
    # daemon cannot see losses before its first packet or after its last).
    first = delivered.index(True)
    last = len(delivered) - 1 - delivered[::-1].index(True)
    seen = delivered[first:last + 1]
    runs = runs_of_losses(seen)
    true_loss = seen.count(False) / len(seen)
    true_burst = sum(runs) / len(runs)
    assert report["loss"] == pytest.approx(true_loss, rel=0.15), (report["loss"], true_loss)
    assert report["mean_burst"] == pytest.approx(true_burst, rel=0.25), (
        report["mean_burst"], true_burst)
    assert report["hours"] == pytest.approx((last - first) / RATE_HZ / 3600, rel=0.05)
    rows = {row["timeout_ms"]: row for row in report["rows"]}
    assert 200 in rows and rows[200]["false_stops_per_hour"] > 0
