"""`estop monitor` from the command line: can-utils logs (files and standard input), bad
inputs, a python-can virtual bus.
"""

from __future__ import annotations

import io
import os
import sys
import threading
import time
from pathlib import Path

import pytest

from cli_util import one_error_line, run_cli
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.canlog import CanLogRecord, format_line
from stall_probe import StallProbe

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]



# ------------------------------------------------------------------------------- monitor

T0 = 1_700_000_000.0


def brake(t: float, counter: int, state: int = 1, reason: int = 0) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x050,
                           BrakeFrame.for_state(state, reason, 0, counter % 15).encode())


def status(t: float, counter: int) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x051,
                           StatusFrame(5, 0, 0, 1, 12, counter % 15).encode())


def clean_log(n: int = 40) -> list[CanLogRecord]:
    recs = []
    for i in range(n):
        recs.append(brake(T0 + i * 0.010, i))
        if i % 10 == 0:
            recs.append(status(T0 + i * 0.010 + 0.001, i // 10))
    return recs


def write_log(path: Path, recs: list[CanLogRecord]) -> str:
    path.write_text("".join(format_line(r) + "\n" for r in recs))
    return str(path)


def test_monitor_clean_log(tmp_path: Path, capsys) -> None:
    code, out, err = run_cli(capsys, "monitor", "--log", write_log(tmp_path / "a.log",
                                                                   clean_log()))
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert lines[-1] == "summary: 44 frames, 44 accepted; problems: none"
    assert lines[-2] == "brake commands: release 40, controlled 0, emergency 0"
    # v3: each ESTOP_BRAKE line ends with what the brake controller does on it
    assert lines[0] == ("(1700000000.000000) 050 ESTOP_BRAKE ARMED reason=none brake=0 "
                        "level=0 flags=0x00 ctr=0 => release")
    assert lines[1] == ("(1700000000.001000) 051 ESTOP_STATUS valid=5 invalid=0 auth_failures=0 "
                        "stops=1 link_age=12ms ctr=0")
    assert "!" not in out


def test_monitor_flags_crc_jump_gap(tmp_path: Path, capsys) -> None:
    recs = [brake(T0 + i * 0.010, i) for i in range(10)]            # counters 0..9, fine
    bad = bytearray(brake(T0 + 0.095, 10).data)
    bad[7] ^= 0x5A
    recs.append(CanLogRecord.at(T0 + 0.095, "vcan0", 0x050, bytes(bad)))  # extra, bad CRC
    recs += [brake(T0 + 0.100, 10), brake(T0 + 0.110, 13)]           # jump: 11, 12 lost
    recs += [brake(T0 + 0.120, 14), brake(T0 + 0.180, 0)]            # 60 ms gap
    recs += [brake(T0 + 0.190, 1, 0, 2)]                             # state change
    recs += [CanLogRecord.at(T0 + 0.2, "vcan0", 0x123, b"\x00")]     # other ID: ignored
    code, out, _ = run_cli(capsys, "monitor", "--log", write_log(tmp_path / "b.log", recs))
    assert code == 1
    assert "(1700000000.095000) 050 ! bad_crc: CRC " in out
    assert "(1700000000.110000) 050 ! counter_jump: counter 11 expected, got 13 (2 lost)" in out
    assert "(1700000000.180000) 050 ! gap: 60.0 ms without a good frame (limit 50 ms)" in out
    assert ("STOPPED reason=tcp_stop brake=1 level=100 flags=0x00 ctr=1 => EMERGENCY  "
            "<- state change") in out
    # the frame with the bad CRC did not come whole from the unit: it commands nothing
    assert "flags=0x00 ctr=10  [rejected]" in out
    assert out.splitlines()[-1] == ("summary: 16 frames, 15 accepted; problems: bad_crc 1, "
                                    "counter_jump 1, gap 1")


def test_monitor_bad_crc_in_place_also_costs_a_counter(tmp_path: Path, capsys) -> None:
    recs = clean_log(10)
    bad = bytearray(recs[5].data)
    bad[7] ^= 1
    recs[5] = CanLogRecord(recs[5].timestamp_us, "vcan0", 0x050, bytes(bad))
    code, out, _ = run_cli(capsys, "monitor", "-q", "--log", write_log(tmp_path / "c.log", recs))
    assert code == 1
    assert out.splitlines()[-1].endswith("problems: bad_crc 1, counter_jump 1")
    assert "ESTOP_BRAKE" not in out  # quiet: only problems and the summary


def test_monitor_stdin_and_timeout_option(monkeypatch, capsys) -> None:
    recs = [brake(T0, 0), brake(T0 + 0.030, 1)]
    monkeypatch.setattr(sys, "stdin", io.StringIO("".join(format_line(r) + "\n" for r in recs)))
    code, out, _ = run_cli(capsys, "monitor", "--log", "-", "--timeout-ms", "25")
    assert code == 1 and "! gap: 30.0 ms" in out


def test_monitor_bad_inputs(tmp_path: Path, capsys) -> None:
    path = tmp_path / "junk.log"
    path.write_text(format_line(brake(T0, 0)) + "\nthis is not a log line\n")
    code, _, err = run_cli(capsys, "monitor", "--log", str(path))
    assert code == 4 and "line 2" in one_error_line(err)
    code, _, err = run_cli(capsys, "monitor", "--log", str(tmp_path / "missing.log"))
    assert code == 4 and "No such file" in one_error_line(err)
    code, _, err = run_cli(capsys, "monitor", "--interface", "no_such_interface_xyz")
    assert code == 2 and one_error_line(err)  # python-can knows no such interface


def test_monitor_virtual_bus(capsys) -> None:
    can = pytest.importorskip("can")
    channel = f"estop_test_{os.getpid()}_{time.monotonic_ns()}"
    sent_at: list[float] = []  # the frames' own stamps, as the monitor reads them

    def monitor_listening() -> bool:
        # python-can's virtual bus keeps one queue per open end, by channel
        from can.interfaces import virtual
        return len(getattr(virtual, "channels", {}).get(channel, ())) >= 2

    def send() -> None:
        with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
            deadline = time.monotonic() + 5
            while not monitor_listening() and time.monotonic() < deadline:
                time.sleep(0.01)
            for i in range(5):
                sent_at.append(time.time())
                bus.send(can.Message(arbitration_id=0x050, is_extended_id=False,
                                     timestamp=sent_at[-1],
                                     data=BrakeFrame.for_state(1, 0, 0, i).encode()))
                time.sleep(0.01)
            # then silence: the monitor reports a timeout while it lasts

    sender = threading.Thread(target=send)
    with StallProbe() as probe:
        sender.start()
        try:
            code, out, _ = run_cli(capsys, "monitor", "--interface", "virtual", "--channel",
                                   channel, "--duration", "0.8")
        finally:
            sender.join(timeout=5)
    assert code == 1
    assert out.count("ESTOP_BRAKE ARMED") == 5
    assert "! timeout: no good ESTOP_BRAKE for" in out
    summary = out.splitlines()[-1]
    # The sender sleeps 10 ms between frames; a gap of 50 ms between their own stamps is a
    # gap the monitor must count, whoever caused it (on a loaded machine, the sender stalls).
    gaps = sum(b - a >= 0.05 for a, b in zip(sent_at, sent_at[1:], strict=False))
    if gaps == 0 and probe.worst_s < 0.03:
        assert summary == "summary: 5 frames, 5 accepted; problems: timeout 1"
    else:
        # A stalled machine: the gaps exactly, and the timeouts that silences of the sender
        # (before its first frame, in a gap) or a late monitor add to the final one.
        assert summary.startswith("summary: 5 frames, 5 accepted; problems: "), summary
        found = dict(p.split(" ") for p in summary.split("problems: ")[1].split(", "))
        assert set(found) <= {"gap", "timeout"}, (summary, str(probe))
        assert int(found.get("gap", 0)) == gaps, (summary, sent_at, str(probe))
        assert int(found["timeout"]) >= 1, (summary, str(probe))
