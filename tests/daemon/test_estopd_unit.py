"""The unit of estopd (firmware/estopd/unit.c) on its own, built with the daemon's flags: the
core's clock as the unit keeps it (a failed core call moves it too) and the silence deadline
(tests/c/unit_check.c)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

SRC = ROOT / "firmware" / "estopd"
CORE = ROOT / "firmware" / "core"

pytestmark = pytest.mark.timeout(120)


def test_unit_checks(tmp_path: Path) -> None:
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.fail("no C compiler: run `make setup` (deps/debian-packages.txt, group build)")
    exe = tmp_path / "unit_check"
    sources = [ROOT / "tests" / "c" / "unit_check.c",
               *(SRC / name for name in ("unit.c", "rxtime.c", "frame.c", "opts.c")),
               *sorted(CORE.glob("*.c"))]
    subprocess.run([cc, "-std=c99", "-D_GNU_SOURCE", "-O2", "-Wall", "-Wextra", "-Werror",
                    "-pedantic", "-Wconversion", f"-I{SRC}", f"-I{CORE}",
                    *map(str, sources), "-o", str(exe)], check=True, timeout=120)
    res = subprocess.run([str(exe)], capture_output=True, text=True, timeout=30, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.strip() == "all unit checks passed"
