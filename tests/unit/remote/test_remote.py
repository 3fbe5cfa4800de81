"""``estop remote`` / :class:`estop.client.sender.Remote`: the dead-man heartbeat ends at
lift(), the end of a hold is told with three lift datagrams 10 ms apart (spec section 8), and
the send rate is bounded. Real UDP sockets on 127.0.0.1; every thread and socket is closed.
"""

from __future__ import annotations

import signal
import struct
import threading
import time

import pytest

from estop import cli
from estop.client.sender import MAX_RATE_HZ, MIN_RATE_HZ, Remote
from estop.remote import keys as remoteterm
from estop.remote.script import ScriptError, parse_script
from net_util import LOCAL, UdpSink, unused_tcp_port
from stall_probe import StallProbe

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]


def is_lift(data: bytes) -> bool:
    """A lift datagram (spec sections 1 and 5.2): a 48-byte request frame with msg_id 3."""
    return len(data) == 48 and data[:4] == b"ESQ2" and struct.unpack_from("<I", data, 4)[0] == 3


def controls(sink: UdpSink) -> int:
    """Control packets received (the 20-byte plain body: these remotes have no key)."""
    return sum(len(d) == 20 for d in list(sink.datagrams))


def lifts(sink: UdpSink) -> int:
    return sum(is_lift(d) for d in list(sink.datagrams))


def wait_controls(sink: UdpSink, n: int, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while controls(sink) < n and time.monotonic() < deadline:
        time.sleep(0.005)
    return controls(sink) >= n



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
        assert sink.settle(at_lift + 3) == at_lift + 3  # and the three lift datagrams
        assert controls(sink) == at_lift and lifts(sink) == 3


def test_lift_at_the_highest_rate_many_times(sink: UdpSink) -> None:
    with Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=MAX_RATE_HZ) as r:
        for i in range(1, 11):
            before = r.stats.delivered
            r.hold()
            assert wait_controls(sink, before + 5)
            assert lift_within(r, 3.0)
            at_lift = r.stats.delivered
            assert r.wait_lift_sent(timeout=10.0)
            # not one control packet after lift() returned; its three lift datagrams
            assert sink.settle(at_lift + 3 * i, 0.1) == at_lift + 3 * i
            assert controls(sink) == at_lift and lifts(sink) == 3 * i
            assert r.stats.sent == r.stats.delivered == at_lift


def test_packets_in_flight_may_still_arrive_after_lift(sink: UdpSink) -> None:
    # the link model's delay is the network's: what was sent before lift() still arrives
    from estop.model.wifi import LinkConfig

    with Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=200,
                link=LinkConfig(delay=0.2)) as r:
        r.hold()
        time.sleep(0.1)
        assert lift_within(r, 3.0)
        sent = r.stats.sent
        assert sent > 0
    # close() flushed the packets in flight and the lift datagrams behind them, no new ones
    assert sink.settle(sent + 3) == sent + 3
    assert controls(sink) == sent and [is_lift(d) for d in sink.datagrams[-3:]] == [True] * 3


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
    code = cli.main(["remote", "--host", LOCAL, "--udp-port", str(sink.port), "--rate-hz", "1000",
                     "--tcp-port", str(unused_tcp_port()), "-q", "--script",
                     "hold 0.3; lift; wait 0.3"])
    out = capsys.readouterr().out
    assert code == 0
    assert time.monotonic() - t0 < 10
    summary = out.splitlines()[-1]
    sent = int(summary.split()[1])
    assert summary.endswith(", 3 lift datagrams")
    assert sink.settle(sent + 3) == sent + 3
    assert controls(sink) == sent and lifts(sink) == 3


# ---------------------------------------------------------------- lift datagrams (spec 8)

def check_lift_datagrams(received: list[tuple[float, bytes]], probe: StallProbe) -> None:
    """Exactly three lift datagrams, last of all: keyless form (zero tag, session 0, remote id
    1), one seq, rising counters, each >= 10 ms after the previous by the kernel's receive
    stamps (a little less allowed for the wall clock's slew) and well within the unit's
    timeout (100 ms, plus the machine's stall that the probe saw in the same run: the sender
    is a thread that sleeps between them, as the probe does); no control packet after the
    first of them."""
    first = next(i for i, (_, d) in enumerate(received) if is_lift(d))
    after = received[first:]
    assert len(after) == 3 and all(is_lift(d) for _, d in after), [len(d) for _, d in after]
    fields = [struct.unpack("<IIIQQ", d[4:32]) for _, d in after]
    assert {(msg_id, rid, session) for msg_id, _, rid, session, _ in fields} == {(3, 1, 0)}
    assert len({seq for _, seq, _, _, _ in fields}) == 1
    counters = [c for *_, c in fields]
    assert counters == sorted(counters) and len(set(counters)) == 3
    assert all(d[32:] == bytes(16) for _, d in after)
    stamps = [t for t, _ in after]
    for a, b in zip(stamps, stamps[1:], strict=False):
        assert 0.0095 <= b - a <= 0.1 + probe.slept_over_s(a, b), \
            (b - a, f"worst oversleep of a 1 ms sleeper in that gap: "
                    f"{probe.slept_over_s(a, b) * 1e3:.1f} ms")


def test_lift_sends_three_lift_datagrams_10_ms_apart_and_then_nothing(sink: UdpSink) -> None:
    with StallProbe() as probe, Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=200) as r:
        r.hold()
        assert wait_controls(sink, 10)
        t_before = time.time()
        assert r.lift() == 3
        t_after = time.time()
        at_lift = r.stats.delivered
        assert r.wait_lift_sent(timeout=10.0) and r.lift_sent == 3
        assert sink.settle(at_lift + 3, 0.3) == at_lift + 3
        assert r.stats.lift_datagrams == 3 and r.stats.sent == at_lift
    received = sink.received()
    check_lift_datagrams(received, probe)
    first_lift = next(t for t, d in received if is_lift(d))
    assert t_before <= first_lift <= t_after  # the first one went out before lift() returned


def test_lift_when_not_held_sends_nothing(sink: UdpSink) -> None:
    with Remote(LOCAL, sink.port, unused_tcp_port()) as r:
        assert r.lift() == 0
        r.hold()
        assert wait_controls(sink, 1)
        assert r.lift() == 3
        assert r.lift() == 0  # the hold ended once
    assert sink.settle(controls(sink) + 3) == controls(sink) + 3 and lifts(sink) == 3


def test_closing_a_held_remote_ends_the_hold_with_the_lift_datagrams(sink: UdpSink) -> None:
    with StallProbe() as probe:
        with Remote(LOCAL, sink.port, unused_tcp_port(), rate_hz=100) as r:
            r.hold()
            assert wait_controls(sink, 3)
    # close() waited for the repeats: all three are out
    assert r.stats.lift_datagrams == 3
    assert sink.settle(r.stats.sent + 3) == r.stats.sent + 3
    check_lift_datagrams(sink.received(), probe)


def test_space_key_lift_shows_in_the_status_line(sink: UdpSink) -> None:
    with StallProbe() as probe, Remote(LOCAL, sink.port, unused_tcp_port()) as r:
        assert "[lifted]" in remoteterm._status_line(r)
        assert remoteterm.handle_key(r, " ") is None and r.held
        assert "[HELD (toggle: space to lift)]" in remoteterm._status_line(r)
        assert wait_controls(sink, 1)
        assert remoteterm.handle_key(r, " ") is None and not r.held
        assert r.wait_lift_sent(timeout=10.0)
        assert "[lifted, lift sent x3]" in remoteterm._status_line(r)
    assert sink.settle(r.stats.sent + 3) == r.stats.sent + 3
    check_lift_datagrams(sink.received(), probe)


def test_script_lift_and_the_end_of_a_script_say_the_lift_was_sent(
        sink: UdpSink, capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["remote", "--host", LOCAL, "--udp-port", str(sink.port), "--tcp-port",
                     str(unused_tcp_port()), "--script", "lift; hold 0.1; lift; hold 0.1"])
    out = capsys.readouterr().out
    assert code == 0, out
    lines = out.splitlines()
    assert lines[0].endswith(" lift: not held: nothing to send")
    assert lines[2].endswith(" lift: lift sent x3")
    assert lines[4] == "end of run: lift sent x3"  # the script ended while held
    assert lines[5].endswith(", 6 lift datagrams")
    sent = int(lines[5].split()[1])
    assert sink.settle(sent + 6) == sent + 6 and lifts(sink) == 6
    assert all(is_lift(d) for d in sink.datagrams[-3:])


def test_ctrl_c_while_held_ends_the_hold_with_the_lift_datagrams(
        sink: UdpSink, capsys: pytest.CaptureFixture[str]) -> None:
    main = threading.main_thread().ident
    assert main is not None and threading.get_ident() == main
    # Python's own Ctrl-C, whatever an earlier test in this process left installed
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with StallProbe() as probe:  # started first: the SIGINT must find cli.main running
        # Ctrl-C (a real SIGINT to this thread), 0.3 s into a hold of 20 s
        timer = threading.Timer(0.3, signal.pthread_kill, (main, signal.SIGINT))
        timer.start()
        t0 = time.monotonic()
        try:
            code = cli.main(["remote", "--host", LOCAL, "--udp-port", str(sink.port),
                             "--tcp-port", str(unused_tcp_port()), "--script", "hold 20"])
        finally:
            timer.cancel()
    cap = capsys.readouterr()
    assert code == 130 and time.monotonic() - t0 < 10
    assert "end of run: lift sent x3" in cap.out and cap.err == "estop: interrupted\n"
    assert sink.wait_for(controls(sink) + 3)
    time.sleep(0.1)
    check_lift_datagrams(sink.received(), probe)


def test_the_keyboard_says_it_is_a_toggle_not_a_dead_man(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """A terminal never sees a key released: --help and the screen say the space bar is a
    toggle, and point at the gamepad, the real dead-man."""
    assert cli.main(["remote", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "TOGGLE, NOT a dead-man" in text and "--gamepad" in text
    warning = " ".join(remoteterm.WARNING.split())
    assert "TOGGLE, NOT a dead-man" in warning and "--gamepad" in warning
