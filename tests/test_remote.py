"""``estop remote`` / :class:`estop.remote.Remote`: the dead-man heartbeat ends at lift(), and
the send rate is bounded. Real UDP sockets on 127.0.0.1; every thread and socket is closed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from estop import cli
from estop.remote import MAX_RATE_HZ, MIN_RATE_HZ, Remote, ScriptError, parse_script
from net_util import LOCAL, UdpSink, unused_tcp_port

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def sink() -> Iterator[UdpSink]:
    s = UdpSink()
    yield s
    s.close()



def lift_within(remote: Remote, seconds: float) -> bool:
    """Call lift() on another thread; True if it returned within ``seconds``. If it did not
    (the sender thread never lets go of its lock), end the sender so the test can go on."""
    lifter = threading.Thread(target=remote.lift, daemon=True)
    lifter.start()
    lifter.join(seconds)
    if lifter.is_alive():
        remote._held = False  # unlocked on purpose: the lock is what is stuck
        remote._closing = True
        lifter.join(5)
        return False
    return True


# ------------------------------------------------------------------------------ lift()

def test_lift_stops_heartbeats_at_once_when_the_sender_falls_behind(sink: UdpSink) -> None:
    # a packet hook slower than the period keeps the sender behind its schedule all the time:
    # it must still let go of its lock, so lift() returns and nothing is sent after it
    r = Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=MAX_RATE_HZ,
               on_packet=lambda *_: time.sleep(0.003))
    with r:
        r.hold()
        assert sink.wait_for(20)
        assert lift_within(r, 3.0), "lift() did not return: the sender thread kept its lock"
        at_lift = r.stats.delivered
        time.sleep(0.3)
        assert r.stats.delivered == at_lift
        assert sink.settle(at_lift) == at_lift


def test_lift_at_the_highest_rate_many_times(sink: UdpSink) -> None:
    with Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=MAX_RATE_HZ) as r:
        for _ in range(10):
            before = r.stats.delivered
            r.hold()
            assert sink.wait_for(before + 5)
            assert lift_within(r, 3.0)
            at_lift = r.stats.delivered
            assert sink.settle(at_lift, 0.1) == at_lift  # not one datagram after lift() returned
            assert r.stats.sent == r.stats.delivered == at_lift


def test_packets_in_flight_may_still_arrive_after_lift(sink: UdpSink) -> None:
    # the link model's delay is the network's: what was sent before lift() still arrives
    from estop.linkmodel import LinkConfig

    with Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=200,
                link=LinkConfig(delay=0.2)) as r:
        r.hold()
        time.sleep(0.1)
        assert lift_within(r, 3.0)
        sent = r.stats.sent
        assert sent > 0
    assert sink.settle(sent) == sent  # close() flushed the packets in flight, no new ones


# ------------------------------------------------------------------------------- rates

def test_rate_bounds() -> None:
    assert (MIN_RATE_HZ, MAX_RATE_HZ) == (0.1, 1000.0)
    for bad in (2e5, 1000.5, 0.05, 0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"0\.1\.\.1000 Hz"):
            Remote(LOCAL, 9, 9, rate_hz=bad)
    r = Remote(LOCAL, 9, 9, rate_hz=0.1)
    try:
        r.rate_hz = 1000
        assert r.rate_hz == 1000
        with pytest.raises(ValueError, match=r"0\.1\.\.1000 Hz"):
            r.rate_hz = 2e5
        assert r.rate_hz == 1000
    finally:
        r.close()


@pytest.mark.parametrize("rate", ["2e5", "1001", "0.01", "0", "nan"])
def test_cli_rate_out_of_range_is_one_usage_line(rate: str, sink: UdpSink,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["remote", "--host", LOCAL, "--udp-port", str(sink.port), "--rate", rate,
                     "--script", "hold 0.2; lift"])
    cap = capsys.readouterr()
    assert code == 2 and cap.out == ""
    lines = cap.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("estop: error: ") and "--rate" in lines[0]
    assert "0.1..1000" in lines[0]
    time.sleep(0.1)
    assert sink.count == 0


def test_script_rate_bounds() -> None:
    assert parse_script("rate 1000; rate 0.1")[0].args == (1000.0,)
    for bad in ("rate 1001", "rate 2e5", "rate 0.09"):
        with pytest.raises(ScriptError, match=r"0\.1\.\.1000"):
            parse_script(bad)


def test_cli_max_rate_script_ends_cleanly(sink: UdpSink,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    t0 = time.monotonic()
    code = cli.main(["remote", "--host", LOCAL, "--udp-port", str(sink.port), "--rate", "1000",
                     "--tcp-port", str(unused_tcp_port()), "-q", "--script",
                     "hold 0.3; lift; wait 0.3"])
    out = capsys.readouterr().out
    assert code == 0
    assert time.monotonic() - t0 < 10
    sent = int(out.splitlines()[-1].split()[1])
    assert sink.settle(sent) == sent
