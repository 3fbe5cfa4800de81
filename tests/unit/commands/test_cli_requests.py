"""`estop stop|lift|release|status` against real sockets on 127.0.0.1 (a small fake unit): the
frames they send, the replies they print, their exit codes and one-line errors; the entry
points. Loopback-only, bounded in time, and closes what it opens.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest
from fake_unit import FakeUnit, free_port

from cli_util import one_error_line, run_cli
from estop import cli
from estop.protocol import tcp
from estop.protocol.tcp import Request
from net_util import LOCAL, wait_until
from repo import ROOT

pytestmark = pytest.mark.timeout(60)

SRC = ROOT / "src"


# ------------------------------------------------------------------------ one-shot commands

def test_stop_sends_the_spec_frame_and_prints_ack(unit: FakeUnit, capsys) -> None:
    code, out, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unit.tcp_port),
                             "--udp-port", str(unit.udp_port))
    assert code == 0 and err == ""
    assert unit.raw_requests == [bytes.fromhex("70E570E5010000000000000" "0DC09BF43")]
    assert out.strip() == "ACK seq=1 state=STOPPED reason=boot flags=0x00 (after 1 attempt)"
    wait_until(lambda: bool(unit.stop_datagrams))
    assert len(unit.stop_datagrams) == 1


def test_stop_seq_and_stop_id(unit: FakeUnit, capsys) -> None:
    unit.stop_id = 0x12345678
    code, out, _ = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--udp-port", str(unit.udp_port), "--seq", "0xFFFFFFFF",
                           "--stop-id", "0x12345678")
    assert code == 0
    assert unit.requests == [Request(0x12345678, 0xFFFFFFFF, 0)]
    assert "seq=4294967295" in out


def test_release_nak_exit_1(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--seq", "2")
    assert code == 1
    assert unit.raw_requests == [bytes.fromhex("02000000020000000000000" "08D5FCBD5")]
    assert out.strip() == "NAK seq=2 state=STOPPED reason=boot flags=0x00 nak=no_live_link"


def test_status_json(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "status", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["request"] == "status" and doc["reply"] == "ACK"
    assert doc["state"] == "STOPPED" and doc["reason"] == "boot" and doc["nak"] == "none"
    assert unit.requests == [Request(tcp.STATUS, 1)]


def test_reply_split_across_reads(capsys) -> None:
    u = FakeUnit(mode="split")
    try:
        code, out, _ = run_cli(capsys, "status", "--host", LOCAL, "--port", str(u.tcp_port))
    finally:
        u.close()
    assert code == 0 and out.startswith("ACK seq=1")


@pytest.mark.parametrize(("mode", "message"), [
    ("silent", "no reply"),
    ("close", "closed the connection"),
    ("badcrc", "CRC mismatch"),
    ("wrongseq", "does not match"),
])
@pytest.mark.parametrize("kind", ["status", "stop"])
def test_broken_replies_exit_3(mode: str, message: str, kind: str, capsys) -> None:
    u = FakeUnit(mode=mode)
    # Only the silent unit is waited out; the others answer (or close) at once, so a status
    # gives them 2 s, not 0.3: the fake unit is a thread of this process, and at load 10 it
    # was once later than 0.3 s ("no reply" instead of "closed the connection"). A tool that
    # missed the answer would wait the 2 s out and say "no reply", which fails the message.
    timeout = "0.3" if mode == "silent" or kind == "stop" else "2"
    argv = [kind, "--host", LOCAL, "--port", str(u.tcp_port), "--timeout", timeout]
    if kind == "stop":
        argv += ["--udp-port", str(u.udp_port), "--stop-deadline", "0.5"]
    try:
        t0 = time.monotonic()
        code, out, err = run_cli(capsys, *argv)
        assert time.monotonic() - t0 < 3
        if kind == "stop":
            wait_until(lambda: bool(u.stop_datagrams))
    finally:
        u.close()
    assert code == 3 and out == ""
    line = one_error_line(err)
    assert message in line
    if kind == "stop":  # the stop button tried again until its deadline
        assert "no ACK within 0.5 s: " in line and u.stop_datagrams
        assert len(u.requests) >= (1 if mode == "silent" else 2)


def test_connection_refused_exit_3(capsys) -> None:
    code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", str(free_port()))
    assert code == 3 and out == ""
    assert "cannot connect" in one_error_line(err)


@pytest.mark.parametrize("argv", [
    ["stop"],
    ["stop", "--host", LOCAL, "--port", "0"],
    ["stop", "--host", LOCAL, "--port", "70000"],
    ["stop", "--host", LOCAL, "--stop-id", "1"],
    ["stop", "--host", LOCAL, "--stop-id", "0x100000000"],
    ["release", "--host", LOCAL, "--seq", "-1"],
    ["status", "--host", LOCAL, "--timeout", "0"],
    ["status", "--host", LOCAL, "--timeout", "nan"],
    ["lift", "--host", LOCAL, "--udp-port", "0"],
    ["lift", "--host", LOCAL, "--tcp-port", "x"],
    ["lift", "--host", LOCAL, "--stop-deadline", "1"],  # no retries: a stop button's option
    ["frobnicate"],
    [],
    ["monitor"],
    ["monitor", "--log", "x", "--interface", "virtual"],
    ["remote", "--host", LOCAL, "--script", "hold 1; fly"],
    ["remote", "--host", LOCAL, "--script", "gas 2"],
    ["remote", "--host", LOCAL, "--loss", "60", "--burst", "1", "--script", "hold 1"],
    ["remote", "--host", LOCAL, "--rate", "-5", "--script", "hold 1"],
    ["remote", "--host", LOCAL, "--rate-hz", "0", "--script", "hold 1"],
    ["monitor", "-c", "vcan0", "--log", "x"],  # a channel needs an interface
])
def test_usage_errors_one_line_exit_2(argv: list[str], capsys) -> None:
    code = cli.main(argv)
    cap = capsys.readouterr()
    assert code == 2, cap
    one_error_line(cap.err)
    assert cap.out == ""


def test_subprocess_entry_point_no_traceback() -> None:
    env = {**os.environ, "PYTHONPATH": str(SRC) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for argv, want in ((["status", "--host", LOCAL, "--port", str(free_port())], 3),
                       (["stop", "--host", LOCAL, "--stop-id", "zz"], 2),
                       (["monitor", "--log", "/nonexistent/estop.log"], 4)):
        proc = subprocess.run([sys.executable, "-m", "estop", *argv], env=env, timeout=30,
                              capture_output=True, text=True, check=False)
        assert proc.returncode == want, proc
        one_error_line(proc.stderr)


def test_version(capsys) -> None:
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == "estop 1.0.0"
    assert cli.main(["monitor", "--help"]) == 0
    assert "-i IF, --interface IF" in capsys.readouterr().out
    assert cli.main(["lift", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--tcp-port PORT" in text and "--port" not in text  # the older name works, unlisted


# ------------------------------------------------------------------------------ demo slot

def test_demo_slot_dispatches_to_estop_demo(monkeypatch, capsys) -> None:
    from estop.commands import demo

    seen: list[list[str]] = []
    monkeypatch.setattr(demo, "main", lambda argv=None: seen.append(argv) or 5)
    assert cli.main(["demo", "--fast", "x"]) == 5
    assert seen == [["--fast", "x"]]
