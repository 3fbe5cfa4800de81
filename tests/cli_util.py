"""Running the ``estop`` command line inside a test: its code, output and errors."""

from __future__ import annotations

import pytest

from estop import cli


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``estop ARGV...`` in this process: (exit code, stdout, stderr)."""
    code = cli.main(list(argv))
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def one_error_line(err: str) -> str:
    """The one line ``estop: error: ...`` that ``err`` must be (never a traceback)."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("estop: error: ")
    assert "Traceback" not in err
    return lines[0]
