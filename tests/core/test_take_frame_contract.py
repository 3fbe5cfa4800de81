"""take_frame's contract (docs/PROOF.md: the reassembly) checked on the C code for every fill,
call length and buffer form, by tests/c/take_frame_contract.c: the figure the docs quote
(13,968 cases, no violation), and the plain direction of take_whole that the contract leaves
out because Eva's over-approximation reports it false."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

CORE = ROOT / "firmware" / "core"

pytestmark = pytest.mark.timeout(180)


def test_take_frame_keeps_its_contract_in_every_case(tmp_path: Path) -> None:
    cc = shutil.which("gcc")
    if cc is None:
        pytest.fail("gcc is missing: scripts/ensure-debs build (deps/debian-packages.txt)")
    exe = tmp_path / "take_frame_contract"
    others = [str(p) for p in sorted(CORE.glob("estop_*.c")) if p.name != "estop_tcp.c"]
    subprocess.run([cc, "-std=c99", "-O1", "-Wall", "-Wextra", "-Werror", "-pedantic",
                    f"-I{CORE}", str(ROOT / "tests" / "c" / "take_frame_contract.c"), *others,
                    "-o", str(exe)], check=True, timeout=120)
    res = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.strip() == "take_frame: 13968 cases, 0 violations"
