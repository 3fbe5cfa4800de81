"""The output ring of estopd (firmware/estopd/outq.c) under a stress no daemon test reaches
reliably: lines queued while the writer thread finishes a write. A lost wake-up there put the
writer to sleep with lines in the ring, and the daemon's log (or can-log) stopped for good: seen
in the HIL run as a missing 'state' line, and in CI as a log without its suppression report."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

SRC = ROOT / "firmware" / "estopd"


@pytest.fixture(scope="module")
def stress(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.fail("no C compiler: run `make setup` (deps/debian-packages.txt, group build)")
    exe = tmp_path_factory.mktemp("outq") / "outq_stress"
    subprocess.run([cc, "-std=c99", "-D_GNU_SOURCE", "-O2", "-Wall", "-Wextra", "-Werror",
                    "-pedantic", f"-I{SRC}", str(ROOT / "tests" / "c" / "outq_stress.c"),
                    str(SRC / "outq.c"), "-lpthread", "-o", str(exe)],
                   check=True, timeout=120)
    return exe


def test_writer_never_sleeps_with_lines_queued(stress: Path) -> None:
    # Before the fix this wedged within the first few hundred pairs on this machine.
    res = subprocess.run([str(stress), "200000"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr.strip()
    assert "every one drained" in res.stdout
