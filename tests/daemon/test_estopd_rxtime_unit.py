"""The receive-time arithmetic of estopd (firmware/estopd/rxtime.c) on its own, built with the
daemon's flags: the kernel's CLOCK_REALTIME stamp becomes the earlier of the converted stamp and
the read time, a wall-clock step is no error and nothing overflows (tests/c/rxtime_check.c)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

SRC = ROOT / "firmware" / "estopd"

pytestmark = pytest.mark.timeout(120)


def test_rxtime_checks(tmp_path: Path) -> None:
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.fail("no C compiler: run `make setup` (deps/debian-packages.txt, group build)")
    exe = tmp_path / "rxtime_check"
    subprocess.run([cc, "-std=c99", "-D_GNU_SOURCE", "-O2", "-Wall", "-Wextra", "-Werror",
                    "-pedantic", "-Wconversion", f"-I{SRC}",
                    str(ROOT / "tests" / "c" / "rxtime_check.c"), str(SRC / "rxtime.c"),
                    "-o", str(exe)], check=True, timeout=120)
    res = subprocess.run([str(exe)], capture_output=True, text=True, timeout=30, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.strip() == "all rxtime checks passed"
