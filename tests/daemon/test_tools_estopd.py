"""The ``estop`` tools against the real estopd (protocol version 3) on loopback, with a key and
without: what the unit does is read from its can-log (the brake frames), not from the tools.
"""

from __future__ import annotations

import queue
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cli_util import run_cli
from estop import cli
from estop.client.keyfile import load_key_file
from estop.client.sender import Remote
from estop.protocol import can, canlog
from estop.unit.canlog import stamp as canlog_stamp
from estop.unit.daemon import Daemon
from net_util import LOCAL, unused_tcp_port

pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]


@pytest.fixture
def key_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    path = tmp_path / "estop.key"
    assert cli.main(["keygen", str(path)]) == 0
    capsys.readouterr()
    return str(path)


@pytest.fixture
def keyed(key_path: str, estopd: str) -> Iterator[Daemon]:
    with Daemon([estopd], key_file=key_path) as d:
        yield d


@pytest.fixture
def keyless(estopd: str) -> Iterator[Daemon]:
    with Daemon([estopd]) as d:
        yield d


def brake_states(d: Daemon, until: tuple[int, int] | None = None,
                 timeout: float = 5.0) -> list[tuple[int, int]]:
    """(state, reason) of the ESTOP_BRAKE frames logged so far, repeats collapsed; with
    ``until``, read on (at most ``timeout`` s: the log reader may lag) until that is the
    latest."""
    out: list[tuple[int, int]] = []
    deadline = time.monotonic() + timeout
    while True:
        rec: canlog.CanLogRecord | None
        try:
            rec = d.frames.get(timeout=0.05)
        except queue.Empty:
            rec = None
        if rec is not None and rec.can_id == can.BRAKE_ID:
            f = can.BrakeFrame.decode(rec.data)
            if not out or out[-1] != (f.state, f.reason):
                out.append((f.state, f.reason))
        caught_up = rec is None or d.frames.empty()
        if caught_up and (until is None or (out and out[-1] == until)):
            return out
        if time.monotonic() > deadline:
            return out


def key_path_of(d: Daemon) -> str:
    return d.argv[d.argv.index("--key-file") + 1]


def arm(r: Remote) -> None:
    """Hold, and RELEASE once the unit has enough packets (at most 5 s: a busy machine)."""
    r.hold()
    deadline = time.monotonic() + 5.0
    while not r.release().ack:
        assert time.monotonic() < deadline, "the unit would not release"
        time.sleep(0.1)


def test_keyed_remote_drives_and_stops(keyed: Daemon, key_path: str, capsys) -> None:
    code, out, err = run_cli(
        capsys, "remote", "--host", LOCAL, "--udp-port", str(keyed.udp_port), "--tcp-port",
        str(keyed.tcp_port), "--key-file", key_path, "--remote-id", "3", "--script",
        "hold 0.5; release; expect ack armed; drive 0.2 0.3; lift; wait 0.1; status; "
        "expect stopped lift; hold 0.5; release; expect ack armed; stop; "
        "expect ack stopped tcp_stop; lift")
    assert code == 0, out + err
    # v3: the lift stops the unit at once with reason lift (not udp_timeout at the timeout);
    # the last lift, while stopped, keeps the first reason
    assert out.count("lift: lift sent x3") == 2
    assert brake_states(keyed, (0, 2)) == [(0, 1), (1, 0), (0, 5), (1, 0), (0, 2)]


def test_keyed_unit_refuses_the_plain_forms(keyed: Daemon, capsys) -> None:
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(keyed.tcp_port))
    assert code == 1 and out.strip().endswith("nak=not_authenticated")
    # plain packets keep nothing alive: a keyless remote cannot release it
    with Remote(LOCAL, keyed.udp_port, keyed.tcp_port) as r:
        r.hold()
        time.sleep(0.3)
        assert r.release().nak_code == 4
        r.lift()
    assert brake_states(keyed) == [(0, 1)]


def test_tools_with_another_key_are_refused_loudly(keyed: Daemon, tmp_path: Path,
                                                   capsys) -> None:
    other = tmp_path / "other.key"
    assert cli.main(["keygen", str(other)]) == 0
    capsys.readouterr()
    code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", str(keyed.tcp_port),
                             "--key-file", str(other))
    assert code == 3 and out == "" and "does NOT verify under the key" in err
    # ... but its stop button still stops (anyone may stop): the datagram and the STOP are
    # honoured even though the ACKs cannot be believed
    key = load_key_file(key_path_of(keyed))
    with Remote(LOCAL, keyed.udp_port, keyed.tcp_port, key=key) as r:
        arm(r)
        code, _, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(keyed.tcp_port),
                               "--udp-port", str(keyed.udp_port), "--key-file", str(other),
                               "--stop-deadline", "0.3")
        r.lift()
    assert code == 3 and "does NOT verify" in err
    assert brake_states(keyed, (0, 2))[-1] == (0, 2)


def test_stop_datagram_alone_stops_the_unit(keyed: Daemon, capsys) -> None:
    with Remote(LOCAL, keyed.udp_port, keyed.tcp_port,
                key=load_key_file(key_path_of(keyed))) as r:
        arm(r)
        # a keyless stop button whose TCP port is wrong: only its datagram reaches the unit
        code, _, err = run_cli(capsys, "stop", "--host", LOCAL, "--port",
                               str(unused_tcp_port()), "--udp-port", str(keyed.udp_port),
                               "--stop-deadline", "0.3")
        assert code == 3 and "cannot connect" in err
        status = r.status()
        r.lift()
    assert (status.state, status.reason) == (0, 2)
    assert brake_states(keyed, (0, 2)) == [(0, 1), (1, 0), (0, 2)]


def test_lift_one_shot_stops_the_unit_with_reason_lift(keyed: Daemon, capsys) -> None:
    with Remote(LOCAL, keyed.udp_port, keyed.tcp_port,
                key=load_key_file(key_path_of(keyed))) as r:
        arm(r)
        # anyone may send a LIFT: a keyless one-shot stops the keyed unit
        code, out, err = run_cli(capsys, "lift", "--host", LOCAL, "--tcp-port",
                                 str(keyed.tcp_port), "--udp-port", str(keyed.udp_port))
        assert (code, err) == (0, "")
        assert out == "ACK seq=1 state=STOPPED reason=lift flags=0x00 (lift sent x3)\n"
    assert brake_states(keyed, (0, 5)) == [(0, 1), (1, 0), (0, 5)]


def test_keyless_unit_with_the_plain_tools(keyless: Daemon, capsys) -> None:
    code, out, _ = run_cli(
        capsys, "remote", "--host", LOCAL, "--udp-port", str(keyless.udp_port), "--tcp-port",
        str(keyless.tcp_port), "--script",
        "hold 0.5; release; expect ack armed; stop; expect ack stopped tcp_stop; lift")
    assert code == 0, out
    assert "(after 1 attempt)" in out
    assert brake_states(keyless, (0, 2)) == [(0, 1), (1, 0), (0, 2)]


def test_stop_button_survives_a_daemon_restart(key_path: str, tmp_path: Path, estopd: str) -> None:
    exe = estopd
    first = Daemon([exe], key_file=key_path)
    first.start()
    udp_port, tcp_port = first.udp_port, first.tcp_port
    try:
        with Remote(LOCAL, udp_port, tcp_port, key=load_key_file(key_path)) as r:
            assert r.status().ack  # the connection the remote keeps open
            old_session = r.channel.session
            first.stop()
            proc = subprocess.Popen(
                [exe, "--key-file", key_path, "--bind", LOCAL, "--udp-port", str(udp_port),
                 "--tcp-port", str(tcp_port), "--can-log", str(tmp_path / "second.log")],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE, text=True)
            try:
                assert proc.stderr is not None
                assert " start " in f" {proc.stderr.readline()}"
                outcome = r.press_stop()
                assert outcome.acked and outcome.attempts == 2, outcome
                assert r.channel.session not in (0, old_session)  # learned again
                arm(r)  # the new session works for the key holder
                r.lift()
            finally:
                proc.terminate()
                proc.wait(10)
                if proc.stderr is not None:
                    proc.stderr.close()
    finally:
        first.stop()


@pytest.mark.parametrize("keyed_unit", [True, False], ids=["key", "no-key"])
def test_a_remotes_lift_stops_the_unit_at_once_with_reason_lift(keyed_unit: bool,
                                                                key_path: str, estopd: str) -> None:
    # a timeout of 1 s: a stop within the bound below can only be the lift's. The warn time
    # is given, as it must lie below the slow time, which the daemon may leave at its 200 ms
    # default until it has --slow-ms
    key = load_key_file(key_path) if keyed_unit else None
    with Daemon([estopd], timeout_ms=1000, extra_args=["--warn-ms", "100"],
                key_file=key_path if keyed_unit else None) as d:
        with Remote(LOCAL, d.udp_port, d.tcp_port, key=key) as r:
            arm(r)
            assert brake_states(d, (1, 0))[-1] == (1, 0)
            t_lift = time.time()
            assert r.lift() == 3
            stopped_at = None
            deadline = time.monotonic() + 5.0
            while stopped_at is None and time.monotonic() < deadline:
                try:
                    rec = d.frames.get(timeout=0.05)
                except queue.Empty:
                    continue
                if rec.can_id == can.BRAKE_ID:
                    f = can.BrakeFrame.decode(rec.data)
                    if (f.state, f.reason) == (can.State.STOPPED, can.Reason.LIFT):
                        stopped_at = canlog_stamp(rec)
            status = r.status()
    assert stopped_at is not None, "the unit did not stop with reason lift"
    # at once (the daemon sends the frame on the change of state), not at the 1 s timeout;
    # 150 ms leaves room for a loaded machine
    assert stopped_at - t_lift < 0.150, stopped_at - t_lift
    assert (status.state, status.reason) == (can.State.STOPPED, can.Reason.LIFT)
