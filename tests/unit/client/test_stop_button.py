"""The stop button (``estop stop``, the remote's ``stop`` command and key, Remote.stop()): it
does not give up after one failed try, and it sends a stop datagram (spec section 1) at once.
``estop lift``, the other stop request: three lift datagrams 10 ms apart, then LIFT over TCP.

Real sockets on 127.0.0.1: a UDP socket receives the datagrams and checks their bytes; small
TCP servers on threads close the first connection, never answer, or NAK.
"""

from __future__ import annotations

import json
import re
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest

from cli_util import run_cli
from estop import cli
from estop.client.channel import StopChannelError
from estop.client.sender import Remote
from estop.protocol import auth, tcp
from estop.remote.keys import handle_key
from net_util import LOCAL, ScriptedStopPort, UdpSink, unused_tcp_port

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]


@pytest.fixture
def restarting() -> Iterator[ScriptedStopPort]:
    """The first connection is closed without a reply (as by a daemon restarting), the second
    and later are answered."""
    port = ScriptedStopPort("close", "ack")
    yield port
    port.close()


def check_stop_datagrams(datagrams: list[bytes], *, seqs: list[int] | None = None,
                         stop_id: int = tcp.DEFAULT_STOP_ID) -> None:
    """Each is a keyless stop datagram: a 48-byte request frame, msg_id the stop ID, session
    0, remote id 1 (the default), tag 16 zero bytes; counters rise."""
    counters = []
    for i, data in enumerate(datagrams):
        assert len(data) == 48 and data[:4] == b"ESQ2"
        msg_id, seq, remote_id, session, counter = struct.unpack("<IIIQQ", data[4:32])
        assert msg_id == stop_id and session == 0 and remote_id == 1
        assert data[32:] == bytes(16)
        if seqs is not None:
            assert seq == seqs[i]
        req = auth.AuthRequest.decode(data, None)
        assert req.kind(stop_id) == "stop"
        counters.append(counter)
    assert counters == sorted(counters) and len(set(counters)) == len(counters)


# --------------------------------------------------------------------------- estop stop

def test_stop_retries_on_a_fresh_connection(sink: UdpSink, restarting: ScriptedStopPort,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(restarting.port),
                             "--udp-port", str(sink.port))
    assert (code, err) == (0, "")
    assert out == "ACK seq=1 state=STOPPED reason=tcp_stop flags=0x00 (after 2 attempts)\n"
    assert restarting.connections == 2
    stop_frame = tcp.Request(tcp.DEFAULT_STOP_ID, 1).encode()
    assert restarting.requests == [stop_frame, stop_frame]
    assert sink.wait_for(2)
    check_stop_datagrams(sink.datagrams, seqs=[1, 1])


def test_stop_datagram_goes_out_before_the_handshake(sink: UdpSink,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    # A listener whose accept queue is full drops SYNs: no TCP connection can be made until
    # the test drains the queue. The stop datagram must arrive before that.
    lsn = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    lsn.bind((LOCAL, 0))
    lsn.listen(0)
    filler = socket.create_connection(lsn.getsockname(), timeout=5)
    result: list[int] = []
    cmd = threading.Thread(target=lambda: result.append(cli.main([
        "stop", "--host", LOCAL, "--port", str(lsn.getsockname()[1]), "--udp-port",
        str(sink.port), "--seq", "7", "--timeout", "20", "--stop-deadline", "20", "--json"])))
    try:
        cmd.start()
        assert sink.wait_for(1, timeout=10)
        assert cmd.is_alive() and result == []  # no handshake has been possible yet
        check_stop_datagrams(sink.datagrams, seqs=[7])
        lsn.settimeout(10)
        lsn.accept()[0].close()  # the filler: now the stop's SYN (retransmitted) gets through
        conn, _ = lsn.accept()
        with conn:
            conn.settimeout(10)
            frame = conn.recv(16)
            assert frame == tcp.Request(tcp.DEFAULT_STOP_ID, 7).encode()
            conn.sendall(tcp.Reply(True, 7, 0, 2).encode())
            cmd.join(10)
    finally:
        filler.close()
        lsn.close()
        cmd.join(30)
    assert result == [0]
    out = capsys.readouterr().out
    assert '"attempts": 1' in out and '"stop_datagrams": 1' in out
    assert len(sink.datagrams) == 1


def test_stop_without_any_answer_reaches_its_deadline(sink: UdpSink,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    port = ScriptedStopPort("silent")
    try:
        t0 = time.monotonic()
        code, out, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(port.port),
                                 "--udp-port", str(sink.port), "--timeout", "0.4",
                                 "--stop-deadline", "1")
        took = time.monotonic() - t0
    finally:
        port.close()
    assert code == 3 and out == ""
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    m = re.fullmatch(r"estop: error: no ACK within 1 s: (\d+) attempts failed \(last: no reply "
                     rf"from {LOCAL}:\d+ within [0-9.]+ s\)", lines[0])
    assert m is not None, lines[0]
    tries = int(m.group(1))
    assert tries >= 2 and 1.0 <= took < 5.0
    assert 2 <= port.connections <= tries
    assert sink.settle(tries) == tries  # one with the first press and one with each retry
    check_stop_datagrams(sink.datagrams)


def test_stop_refused_tries_until_the_deadline(sink: UdpSink,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    t0 = time.monotonic()
    code, _, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unused_tcp_port()),
                           "--udp-port", str(sink.port), "--stop-deadline", "0.6")
    assert code == 3 and time.monotonic() - t0 >= 0.6
    line = err.strip()
    assert "\n" not in line and "no ACK within 0.6 s: " in line and "cannot connect" in line
    assert sink.wait_for(2)  # refusals are quick: several tries, a datagram with each
    check_stop_datagrams(sink.datagrams)


def test_stop_nak_is_an_answer_not_retried(sink: UdpSink,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    port = ScriptedStopPort("nak")
    try:
        code, out, _ = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(port.port),
                               "--udp-port", str(sink.port))
        assert port.connections == 1
    finally:
        port.close()
    assert code == 1
    assert out.strip() == ("NAK seq=1 state=STOPPED reason=boot flags=0x00 nak=unknown_msg_id "
                           "(after 1 attempt)")


def test_stop_deadline_option_is_checked(capsys: pytest.CaptureFixture[str]) -> None:
    for bad in ("0", "-1", "nan", "x"):
        code, out, err = run_cli(capsys, "stop", "--host", LOCAL, "--stop-deadline", bad)
        assert code == 2 and out == "" and err.count("\n") == 1
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--stop-deadline", "0",
                           "--script", "stop")
    assert code == 2 and err.count("\n") == 1


# -------------------------------------------------------------------------- the remote

def test_remote_stop_after_a_daemon_restart(sink: UdpSink) -> None:
    port = ScriptedStopPort("ack")
    try:
        with Remote(LOCAL, sink.port, port.port) as r:
            assert r.status().ack  # the remote keeps this connection open, as the tablet does
            port.drop_all()  # the daemon restarts: that connection is dead
            time.sleep(0.05)
            outcome = r.press_stop()
            assert outcome.acked and outcome.attempts == 2
            assert outcome.summary() == "ACK after 2 attempts"
            assert "closed the connection" in outcome.errors[0] or "failed" in outcome.errors[0]
            again = r.press_stop()  # and the fresh connection stays in use
            assert again.acked and (again.attempts, again.datagrams) == (1, 1)
            assert r.stats.stop_datagrams == 3
        assert port.connections == 2
    finally:
        port.close()
    assert sink.wait_for(3)
    check_stop_datagrams(sink.datagrams)


def test_remote_stop_raises_with_the_summary_at_the_deadline(sink: UdpSink) -> None:
    with Remote(LOCAL, sink.port, unused_tcp_port(), stop_deadline=0.4) as r:
        with pytest.raises(StopChannelError, match=r"no ACK within 0\.4 s: \d+ attempts "
                                                   r"failed \(last: cannot connect"):
            r.stop()
        assert r.stats.stop_datagrams >= 2 and r.stats.sent == 0
    assert sink.wait_for(2)


def test_remote_script_stop_retries(sink: UdpSink, restarting: ScriptedStopPort,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(sink.port),
                           "--tcp-port", str(restarting.port), "--script",
                           "stop; expect ack stopped tcp_stop")
    assert code == 0, out
    assert "stop -> ACK seq=2 state=STOPPED reason=tcp_stop flags=0x00 (after 2 attempts)" in out
    assert "expect ack stopped tcp_stop: ok" in out
    assert sink.wait_for(2)
    check_stop_datagrams(sink.datagrams, seqs=[1, 2])


def test_remote_stop_key_retries(sink: UdpSink, restarting: ScriptedStopPort) -> None:
    r = Remote(LOCAL, sink.port, restarting.port)
    try:
        line = handle_key(r, "s")
    finally:
        r.close()
    assert line == "stop -> ACK seq=2 state=STOPPED reason=tcp_stop flags=0x00 (after 2 attempts)"
    assert sink.wait_for(2)


# --------------------------------------------------------------------------- estop lift

def check_lift_datagrams(sink: UdpSink, seq: int) -> None:
    """Three keyless lift datagrams with ``seq`` (msg_id 3, session 0, remote id 1, zero tag,
    rising counters), >= 10 ms apart by the kernel's receive stamps (a little less allowed for
    the wall clock's slew)."""
    received = sink.received()
    assert len(received) == 3
    fields = [struct.unpack("<IIIQQ", d[4:32]) for _, d in received]
    assert all(len(d) == 48 and d[:4] == b"ESQ2" and d[32:] == bytes(16) for _, d in received)
    assert {f[:4] for f in fields} == {(tcp.LIFT, seq, 1, 0)}
    counters = [f[4] for f in fields]
    assert counters == sorted(counters) and len(set(counters)) == 3
    gaps = [b[0] - a[0] for a, b in zip(received, received[1:], strict=False)]
    assert all(0.0095 <= g <= 0.1 for g in gaps), gaps


def test_lift_one_shot_sends_the_lift_datagrams_then_lift(sink: UdpSink,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    port = ScriptedStopPort("ack")
    try:
        code, out, err = run_cli(capsys, "lift", "--host", LOCAL, "--tcp-port", str(port.port),
                                 "--udp-port", str(sink.port), "--seq", "9")
        assert port.requests == [tcp.Request(tcp.LIFT, 9).encode()]
    finally:
        port.close()
    assert (code, err) == (0, "")
    assert out == "ACK seq=9 state=STOPPED reason=tcp_stop flags=0x00 (lift sent x3)\n"
    assert sink.settle(3, 0.1) == 3
    check_lift_datagrams(sink, 9)


def test_lift_one_shot_json_and_the_old_port_name(sink: UdpSink,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    port = ScriptedStopPort("nak")
    try:
        code, out, _ = run_cli(capsys, "lift", "--host", LOCAL, "--port", str(port.port),
                               "--udp-port", str(sink.port), "--json")
    finally:
        port.close()
    assert code == 1
    got = json.loads(out)
    assert (got["request"], got["reply"], got["nak"], got["lift_datagrams"]) == (
        "lift", "NAK", "unknown_msg_id", 3)


def test_lift_one_shot_without_tcp_still_sends_the_datagrams(sink: UdpSink,
                                                            capsys: pytest.CaptureFixture[str]
                                                            ) -> None:
    code, out, err = run_cli(capsys, "lift", "--host", LOCAL, "--tcp-port",
                             str(unused_tcp_port()), "--udp-port", str(sink.port))
    assert code == 3 and out == ""
    assert re.fullmatch(r"estop: error: lift sent x3, but no reply: cannot connect to "
                        rf"{LOCAL}:\d+: .*\n", err), err
    assert sink.settle(3, 0.1) == 3
    check_lift_datagrams(sink, 1)


@pytest.mark.parametrize(("argv", "deadline"), [
    (["--timeout-ms", "400", "--stop-deadline-ms", "1000"], 1.0),  # the unit in the name
    (["--timeout", "0.4", "--stop-deadline", "1"], 1.0),  # the older spelling, in seconds
])
def test_stop_times_in_milliseconds(sink: UdpSink, capsys: pytest.CaptureFixture[str],
                                    argv: list[str], deadline: float) -> None:
    """The project's vocabulary gives times with their unit (--timeout-ms, --stop-deadline-ms);
    the older names in seconds still mean the same."""
    port = ScriptedStopPort("silent")
    try:
        t0 = time.monotonic()
        code, _out, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(port.port),
                                  "--udp-port", str(sink.port), *argv)
        took = time.monotonic() - t0
    finally:
        port.close()
    assert code == 3 and f"no ACK within {deadline:g} s" in err
    assert deadline <= took < deadline + 1.5


def test_times_in_milliseconds_are_checked(capsys: pytest.CaptureFixture[str]) -> None:
    for cmd, opt in (("stop", "--stop-deadline-ms"), ("lift", "--reply-timeout-ms"),
                     ("status", "--reply-timeout-ms"), ("release", "--timeout-ms")):
        for bad in ("0", "-5", "nan", "x"):
            code, out, err = run_cli(capsys, cmd, "--host", LOCAL, opt, bad)
            assert code == 2 and out == "" and err.count("\n") == 1, (cmd, opt, bad, err)
    assert "--reply-timeout-ms MS" in cli_help(capsys, "lift")
    # the older names (--timeout-ms here, --timeout in seconds) work but are not listed
    assert "--timeout " not in cli_help(capsys, "lift")
    assert "--timeout-ms" not in cli_help(capsys, "lift").replace("--reply-timeout-ms", "")


def cli_help(capsys: pytest.CaptureFixture[str], cmd: str) -> str:
    code, out, _err = run_cli(capsys, cmd, "--help")
    assert code == 0
    return out
