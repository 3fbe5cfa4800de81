"""`estop remote` against a small fake unit on 127.0.0.1: scripts, the send rate and content,
expect, the link model from the options, the terminal keys; the Remote library under it.
Loopback-only, bounded in time, and closes what it opens.
"""

from __future__ import annotations

import io
import statistics
import sys
import time
from pathlib import Path

import pytest
from fake_unit import FakeUnit, free_port

from cli_util import one_error_line, run_cli
from estop.client.sender import Remote
from estop.model.wifi import LinkConfig
from estop.protocol import tcp, udp
from estop.protocol.tcp import Request
from estop.protocol.udp import ControlPacket, Gear
from estop.remote import keys as remoteterm
from estop.remote.script import ScriptError, parse_script
from net_util import LOCAL, wait_until

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]



# -------------------------------------------------------------------------------- remote

def intervals(times: list[float]) -> list[float]:
    return [b - a for a, b in zip(times, times[1:], strict=False)]


def test_remote_script_sends_at_rate_with_exact_content(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script", "hold 1.0; lift 0.1")
    assert code == 0
    wait_until(lambda: len(unit.packets) >= 35)
    datas = [d for _, d in unit.packets]
    assert 35 <= len(datas) <= 60  # 50 Hz for 1 s, roughly
    assert set(datas) == {bytes.fromhex("00000000 00000000 04000000 00000000 00000000")}
    gaps = intervals([t for t, _ in unit.packets])
    assert 0.016 <= statistics.median(gaps) <= 0.024
    assert f"summary: {len(datas)} packets sent, {len(datas)} delivered, 0 lost" in out


def test_remote_full_script_against_fake_unit(unit: FakeUnit, capsys) -> None:
    script = ("hold 0.3; release; expect ack armed; drive 0.3 0.2; steer -0.25; signal left; "
              "horn on; wait 0.1; lift; wait 0.1; status; expect stopped lift; "
              "stop; expect ack stopped lift")
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--rate", "100", "--script", script)
    assert code == 0, out
    assert "release -> ACK seq=1 state=ARMED reason=none flags=0x00" in out
    # v3: the lift datagrams stop the unit at once, with reason lift
    assert "lift: lift sent x3" in out
    assert "status -> ACK seq=2 state=STOPPED reason=lift" in out
    assert "stop -> ACK seq=3 state=STOPPED reason=lift" in out
    assert [r.msg_id for r in unit.requests] == [tcp.RELEASE, tcp.STATUS, tcp.DEFAULT_STOP_ID]
    pkts = [udp.decode(d) for _, d in unit.packets]
    # neutral, then drive at 0.3, back to gas 0 in drive, then steering/signal/horn
    distinct = list(dict.fromkeys(pkts))
    f32 = udp.decode(ControlPacket(0.3).encode()).gas_brake
    expected = [ControlPacket(), ControlPacket(f32, 0.0, Gear.DRIVE),
                ControlPacket(0.0, 0.0, Gear.DRIVE), ControlPacket(0.0, -0.25, Gear.DRIVE),
                ControlPacket(0.0, -0.25, Gear.DRIVE, 1),
                ControlPacket(0.0, -0.25, Gear.DRIVE, 1, 1)]
    # the quick steer/signal/horn changes may fall between two packets: a subsequence
    assert distinct[:2] == expected[:2] and distinct[-1] == expected[-1]
    assert [p for p in expected if p in distinct] == distinct
    assert unit.packets[-1][1] == bytes.fromhex("00000000 000080BE 08000000 01000000 01000000")


def test_remote_expect_failure_exit_1(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script",
                           "release; expect ack; status")
    assert code == 1
    assert "expect failed: expect ack: got NAK seq=1" in out
    assert len(unit.requests) == 1  # the script stopped at the failed expect


def test_remote_script_file_and_legacy(unit: FakeUnit, tmp_path: Path, capsys) -> None:
    script = tmp_path / "drive.txt"
    script.write_text("# a comment line\nhold 0.2   # finger down\n\nlift\n")
    code, _, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                         "--tcp-port", str(unit.tcp_port), "--legacy", "-q",
                         "--script-file", str(script))
    assert code == 0
    wait_until(lambda: bool(unit.packets))
    assert unit.packets and all(len(d) == 16 and udp.is_valid(d) for _, d in unit.packets)


def test_remote_bad_script_sends_nothing(unit: FakeUnit, capsys) -> None:
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script", "hold 0.2; gear sport")
    assert code == 2 and "'gear sport'" in one_error_line(err)
    time.sleep(0.1)
    assert unit.packets == [] and unit.requests == []


def test_remote_tcp_refused_exit_3(unit: FakeUnit, capsys) -> None:
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(free_port()), "--stop-deadline", "0.5",
                           "--script", "hold 0.1; stop")
    line = one_error_line(err)
    assert code == 3 and "cannot connect" in line and "no ACK within 0.5 s" in line
    wait_until(lambda: bool(unit.stop_datagrams))
    assert unit.stop_datagrams  # the stop datagram went out all the same


def test_remote_interactive_needs_a_terminal(monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL)
    assert code == 2 and "terminal" in one_error_line(err)


def test_remote_loss_via_cli(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--rate", "200", "--loss", "30",
                           "--burst", "2", "--seed", "7", "--script", "hold 1.0; lift 0.05")
    assert code == 0
    summary = out.splitlines()[-1]
    sent = int(summary.split()[1])
    delivered = int(summary.split()[4])
    wait_until(lambda: len(unit.packets) >= delivered)
    assert delivered == len(unit.packets)
    assert 0.15 <= 1 - delivered / sent <= 0.45


def test_remote_api_delay_and_hook(unit: FakeUnit) -> None:
    log: list[tuple[float, bytes, float | None]] = []
    cfg = LinkConfig(delay=0.1, jitter=0.02)
    with Remote(LOCAL, unit.udp_port, unit.tcp_port, rate_hz=50, link=cfg, seed=1,
                on_packet=lambda t, d, td: log.append((t, d, td))) as r:
        t_hold = time.monotonic()
        r.hold()
        time.sleep(0.3)
        r.lift()
        assert r.held is False
    # close() flushed the packets in flight
    wait_until(lambda: len(unit.packets) >= r.stats.delivered)
    assert len(unit.packets) == len(log) == r.stats.delivered
    first_arrival = unit.packets[0][0]
    assert first_arrival - t_hold >= 0.1
    for t, _, td in log:
        assert td is not None and 0.1 <= td - t <= 0.12 + 1e-9


def test_remote_api_control_and_requests(unit: FakeUnit) -> None:
    with Remote(LOCAL, unit.udp_port, unit.tcp_port, rate_hz=100) as r:
        assert r.status().state == 0
        r.hold()
        time.sleep(0.15)
        reply = r.release()
        assert reply.ack and reply.state == 1
        r.set_control(gas_brake=0.5, gear=Gear.DRIVE)
        time.sleep(0.05)
        again = r.release()  # RELEASE while ARMED: acknowledged, changes nothing
        assert again.ack and again.state == 1
        with pytest.raises(udp.InvalidPacket):
            r.set_control(steering=3.0)
        with pytest.raises(udp.InvalidPacket):
            r.set_control(gear=3)
        assert r.control == ControlPacket(0.5, 0.0, Gear.DRIVE)
        r.rate_hz = 20
        assert r.rate_hz == 20
        stop = r.stop()
        assert stop.ack and (stop.state, stop.reason) == (0, 2)
        assert r.stats.requests == 4
    assert unit.requests[-1] == Request(tcp.DEFAULT_STOP_ID, 4)


def test_remote_handle_key(unit: FakeUnit) -> None:
    r = Remote(LOCAL, unit.udp_port, unit.tcp_port)
    try:
        assert remoteterm.handle_key(r, " ") is None and r.held
        remoteterm.handle_key(r, " ")
        assert not r.held
        remoteterm.handle_key(r, "\x1b[A")
        remoteterm.handle_key(r, "\x1b[A")
        remoteterm.handle_key(r, "\x1b[D")
        assert (r.control.gas_brake, r.control.steering) == (0.2, -0.1)
        for _ in range(30):
            remoteterm.handle_key(r, "\x1b[B")
        assert r.control.gas_brake == -1.0
        remoteterm.handle_key(r, "g")
        assert r.control.gear == Gear.DRIVE
        remoteterm.handle_key(r, "g")
        assert r.control.gear == Gear.PARK
        remoteterm.handle_key(r, "h")
        remoteterm.handle_key(r, "2")
        assert (r.control.horn, r.control.turn_signal) == (1, 2)
        remoteterm.handle_key(r, "n")
        assert (r.control.gas_brake, r.control.gear) == (0.0, Gear.NEUTRAL)
        line = remoteterm.handle_key(r, "t")
        assert line == "status -> ACK seq=1 state=STOPPED reason=boot flags=0x00"
        assert remoteterm.handle_key(r, "q") == "quit"
        assert list(remoteterm._split_keys("a\x1b[Ab")) == ["a", "\x1b[A", "b"]
    finally:
        r.close()


def test_parse_script() -> None:
    steps = parse_script("hold 1.0; release\n drive 0.3 2.0 # go\nlift; wait 0.5; stop; "
                         "gear P; signal both; horn off; rate 20; expect NAK no_live_link")
    assert [s.op for s in steps] == ["hold", "release", "drive", "lift", "wait", "stop", "gear",
                                     "signal", "horn", "rate", "expect"]
    assert steps[0].args == (1.0,) and steps[2].args == (0.3, 2.0) and steps[3].args == ()
    assert steps[6].args == (1,) and steps[7].args == (3,) and steps[8].args == (0,)
    assert steps[10].words == ("nak", "no_live_link")
    for bad, msg in [("", "empty"), ("hold -1", "out of range"), ("wait", "takes 1"),
                     ("gas nan", "out of range"), ("steer x", "not a number"),
                     ("expect maybe", "unknown word"), ("stop now", "takes 0"),
                     ("drive 0.1 1 2", "takes 1 or 2"), ("launch", "unknown command"),
                     ("signal up", "unknown"), ("rate 0", "out of range")]:
        with pytest.raises(ScriptError, match=msg):
            parse_script(bad)
