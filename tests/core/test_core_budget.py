"""The core's instruction budget (issue 15): a plain control packet costs at most 230
instructions, an authenticated one at most 2,000, counted by callgrind on the -O2 build
(bench/core_instructions.py). Instruction counts do not depend on the machine's load, so this
is a deterministic check, not a timing."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from repo import ROOT

SCRIPT = ROOT / "bench" / "core_instructions.py"


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed")
def test_plain_and_authenticated_packets_stay_within_budget() -> None:
    res = subprocess.run([sys.executable, str(SCRIPT), "--calls", "2000", "--strict",
                          "--only", "plain_udp,auth_udp"],
                         capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stdout + res.stderr
    rows = [line for line in res.stdout.splitlines() if line.startswith("| ") and "|" in line[2:]]
    plain = next(r for r in rows if r.startswith("| plain control packet"))
    per_call = float(plain.split("|")[2])
    assert 50 < per_call <= 230  # a count far below the real cost means the driver broke


def test_the_budget_check_fails_an_unknown_row() -> None:
    res = subprocess.run([sys.executable, str(SCRIPT), "--only", "no_such_fn"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "unknown --only no_such_fn" in res.stderr
