"""One exit-code table for every ``estop`` command: the same failure gives the same code
whichever command meets it, and the table in ``estop --help`` is the README's."""

from __future__ import annotations

import re
import socket
import sys
from pathlib import Path

import pytest

from cli_util import one_error_line, run_cli
from estop import errors
from estop.commands import output
from repo import ROOT

pytestmark = pytest.mark.timeout(120)
LOCAL = "127.0.0.1"
README = ROOT / "README.md"


def closed_port() -> int:
    with socket.socket() as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


# the commands that talk to a unit, each with what it needs to run briefly
UNIT_COMMANDS = {
    "stop": ["stop", "--stop-deadline-ms", "300"],
    "lift": ["lift"],
    "status": ["status"],
    "release": ["release"],
    "remote": ["remote", "--script", "status"],
}


@pytest.mark.parametrize("name", list(UNIT_COMMANDS))
def test_no_unit_listening_is_3(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [*UNIT_COMMANDS[name], "--host", LOCAL, "--tcp-port", str(closed_port()),
            "--reply-timeout-ms", "300"]
    code, _, err = run_cli(capsys, *argv)
    assert code == errors.EXIT_UNREACHABLE == 3, err
    assert "estop: error: " in err and "Traceback" not in err


@pytest.mark.parametrize("name", list(UNIT_COMMANDS))
def test_a_missing_key_file_is_4(name: str, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_cli(capsys, *UNIT_COMMANDS[name], "--host", LOCAL, "--key-file",
                             str(tmp_path / "missing.key"))
    assert code == errors.EXIT_FILE == 4 and out == ""
    assert "--key-file: key file" in one_error_line(err)


@pytest.mark.parametrize("name", list(UNIT_COMMANDS))
def test_a_bad_option_or_setting_is_2(name: str, monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_cli(capsys, *UNIT_COMMANDS[name], "--host", LOCAL, "--tcp-port", "x")
    assert code == errors.EXIT_USAGE == 2 and out == ""
    one_error_line(err)
    monkeypatch.setenv("ESTOP_TCP_PORT", "0")
    code, out, err = run_cli(capsys, *UNIT_COMMANDS[name], "--host", LOCAL)
    assert code == 2 and "ESTOP_TCP_PORT=0" in one_error_line(err)


@pytest.mark.parametrize("argv", [
    ["monitor", "--log", "{missing}"],
    ["monitor", "--log", "{missing}.asc"],
    ["link", "{missing}"],
    ["remote", "--host", LOCAL, "--script-file", "{missing}"],
    ["keygen", "{existing}"],
])
def test_a_file_that_cannot_be_read_or_written_is_4(argv: list[str], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "there"
    existing.write_text("")
    argv = [a.format(missing=tmp_path / "missing", existing=existing) for a in argv]
    code, out, err = run_cli(capsys, *argv)
    assert code == errors.EXIT_FILE == 4 and out == "", err
    one_error_line(err)


@pytest.mark.parametrize("argv, extra", [
    (["link", "{times}"], "link"),
    (["monitor", "--interface", "virtual"], "bus"),
    (["monitor", "--log", "{times}", "--dbc"], "bus"),
])
def test_a_missing_extra_is_5_and_named(argv: list[str], extra: str, tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    times = tmp_path / "t.txt"
    times.write_text("0\n0.02\n")
    for name in ("numpy", "dpkt", "matplotlib", "can", "cantools"):
        monkeypatch.setitem(sys.modules, name, None)  # import fails as if not installed
    code, out, err = run_cli(capsys, *[a.format(times=times) for a in argv])
    assert code == errors.EXIT_NOT_INSTALLED == 5 and out == ""
    assert f"pip install 'estop[{extra}]'" in one_error_line(err)


def test_an_internal_error_is_6_in_one_error_line(monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    from estop.commands import status

    def broken(args: object) -> int:
        raise ZeroDivisionError("x")

    monkeypatch.setattr(status, "run_request", broken)
    code, _, err = run_cli(capsys, "status", "--host", LOCAL)
    assert code == errors.EXIT_INTERNAL == 6
    assert "internal error" in one_error_line(err) and "ZeroDivisionError" in err


def test_help_and_readme_show_the_same_table(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(capsys, "--help")
    assert code == 0
    assert output.exit_code_table() in out
    readme = README.read_text()
    for number, text in errors.EXIT_CODES:
        row = re.search(rf"^\|\s*{number}\s*\|\s*(.+?)\s*\|\s*$", readme, re.MULTILINE)
        assert row is not None, f"README has no row for exit code {number}"
        assert row.group(1) == text, (number, row.group(1), text)
    # every sub-command points at the one table
    for name in ("stop", "lift", "status", "release", "monitor", "link", "keygen"):
        code, out, _ = run_cli(capsys, name, "--help")
        assert code == 0 and "estop --help" in out, name
