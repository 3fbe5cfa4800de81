"""``estop demo`` end to end: a real keyed estopd on loopback, the scripted drive with an
attacker, every stop.

Checks what a person reads: exit code 0, the finger-lifted stop reported with reason
udp_timeout and the stop button with reason tcp_stop, both latencies measured, and the daemon
gone afterwards. No latency values are asserted (timing goals live in the bench).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from estop.demo import main
from tool_util import estopd_or_skip

ROOT = Path(__file__).resolve().parents[1]


def _pid_alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_demo_runs_both_stops_and_cleans_up() -> None:
    exe = estopd_or_skip()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "src"), *filter(None, [env.get("PYTHONPATH")])])
    proc = subprocess.run([sys.executable, "-m", "estop.demo", "--estopd", exe],
                          capture_output=True, text=True, timeout=60, env=env,
                          stdin=subprocess.DEVNULL)
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr
    assert "demo ok" in out and "PROBLEM" not in out
    assert re.search(r"finger lifted: stop reason udp_timeout +timeout overshoot +-?\d+\.\d+ ms",
                     out), out
    assert re.search(r"stop button: +stop reason tcp_stop +TCP stop latency +\d+\.\d+ ms", out), out
    assert "bus: STOPPED reason=udp_timeout" in out
    assert "bus: STOPPED reason=tcp_stop" in out
    assert "NAK 2" in out and "NAK 3" in out  # refused releases: no link, gas pressed
    # The keyed story: the attacker's heartbeats do not keep the unit alive, its forged
    # RELEASE is refused, its stop datagram stops the car.
    assert re.search(r"attacker: sent [1-9]\d* plain, [1-9]\d* wrong key, [1-9]\d* replayed", out)
    assert "attacker: RELEASE under a wrong key -> NAK 4 (not_authenticated)" in out
    assert re.search(r"stop datagram: stop reason tcp_stop +stop latency +\d+\.\d+ ms", out), out
    assert "\x1b[" not in out  # no TTY: plain lines
    m = re.search(r"estopd ended \(pid (\d+), exit code (-?\d+)\)", out)
    assert m is not None, out
    assert not _pid_alive(int(m.group(1)))


def test_demo_without_estopd_says_so_in_one_line(capsys: pytest.CaptureFixture[str],
                                                 tmp_path: Path) -> None:
    assert main(["--estopd", str(tmp_path / "no-such-estopd")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "estopd not found" in err


@pytest.mark.parametrize("value", ["0", "-5", "60001", "1e3", "abc", ""])
def test_demo_timeout_out_of_range_is_one_usage_line(value: str, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    # refused before anything starts: the daemon path does not even exist
    code = main(["--estopd", str(tmp_path / "no-such-estopd"), "--timeout-ms", value])
    cap = capsys.readouterr()
    assert code == 2 and cap.out == ""
    lines = cap.err.splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith("estop: error: argument --timeout-ms: ")
    assert "1..60000" in lines[0] and "Traceback" not in cap.err


def test_demo_timeout_range_ends_are_accepted(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    for value in ("1", "60000"):
        # accepted: the demo goes on and stops only at the missing daemon
        assert main(["--estopd", str(tmp_path / "no-such-estopd"), "--timeout-ms", value]) == 2
        assert "estopd not found" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--bogus"], ["--plain", "extra"], ["--timeout-ms"]])
def test_demo_usage_errors_are_one_line(argv: list[str],
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from estop import cli

    for run in (main, lambda a: cli.main(["demo", *a])):
        code = run(argv)
        cap = capsys.readouterr()
        assert code == 2 and cap.out == ""
        lines = cap.err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("estop: error: "), cap.err


def test_demo_help_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--timeout-ms" in out and "1..60000" in out
