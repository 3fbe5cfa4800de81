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
from estop.client.sender import Remote
from estop.model.wifi import LinkConfig

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


def test_a_two_stage_unit_counts_its_slow_downs_and_the_report_checks_them(
        tmp_path: Path) -> None:
    """Protocol version 3 end to end: estopd with S = 100 ms and T = 1 s, released and driven
    for 20 s over the same bursty link, slows down on the long bursts and never stops; its
    link_histogram carries its own counts (slowdowns, timeouts, slow_us, timeout_us), which
    `estop link` compares with the model at the unit's S and T."""
    with Daemon(tmp_path, "--log-json", "--slow-ms", "100", "--timeout-ms", "1000") as d:
        link = LinkConfig(loss=0.09, burst=3.0, delay=0.0, jitter=0.0)
        with Remote("127.0.0.1", d.udp_port, d.tcp_port, rate_hz=RATE_HZ, link=link, seed=11
                    ) as remote:
            remote.hold()
            deadline = time.monotonic() + 5
            while remote.release().state != 1:  # ARMED (a burst may refuse it: NAK 2)
                assert time.monotonic() < deadline, "the unit could not be released"
                time.sleep(0.1)
            time.sleep(20.0)
            status = remote.status()
            remote.lift()
        assert d.signal() == 0
    assert status.state in (1, 2)  # still moving: the bursts never reached T
    events = [json.loads(line) for line in d.log() if '"link_histogram"' in line]
    last = events[-1]
    assert (last["slow_us"], last["timeout_us"]) == (100_000, 1_000_000)
    assert last["slowdowns"] > 5 and last["timeouts"] == 0  # about 26 per minute expected
    states = [json.loads(line) for line in d.log() if '"state"' in line]
    assert any(e["to"] == "SLOWING" and e["cause"] == "udp_silence" for e in states)
    assert any(e["from"] == "SLOWING" and e["cause"] == "link_back" for e in states)
    log = tmp_path / "daemon.json.log"
    log.write_text("\n".join(d.log()) + "\n")
    res = subprocess.run([sys.executable, "-m", "estop", "link", str(log), "--json",
                          "--rate-hz", str(RATE_HZ)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert res.returncode == 0, res.stderr
    unit = json.loads(res.stdout)["unit"]
    assert unit is not None and (unit["slow_ms"], unit["timeout_ms"]) == (100, 1000)
    assert unit["slowdowns"] == last["slowdowns"]
    assert unit["slowdowns_check"]["verdict"] == "agrees", unit
