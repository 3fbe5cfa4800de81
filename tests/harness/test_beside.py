"""scripts/beside, which make test uses to run make prove beside the other steps: its exit
status is the first failure's, its background's output is printed after the foreground's, and
a failed foreground stops the whole background (every process it started) at once rather than
waiting for it (make prove takes a quarter of an hour)."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

from repo import ROOT

BESIDE = ROOT / "scripts" / "beside"


def beside(cwd: Path, bg: str, *fg: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BESIDE), bg, *fg], cwd=cwd, capture_output=True, text=True,
                          timeout=60)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie left for its parent counts as gone
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_both_pass_and_the_background_output_follows(tmp_path: Path) -> None:
    r = beside(tmp_path, "echo from-bg", "echo", "from-fg")
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.index("from-fg") < r.stdout.index("from-bg")
    assert "(exit 0," in r.stdout


def test_a_failed_background_fails_it(tmp_path: Path) -> None:
    r = beside(tmp_path, "echo bg-broke; exit 3", "true")
    assert r.returncode == 3
    assert "bg-broke" in r.stdout


def test_a_failed_foreground_stops_the_background_and_its_children(tmp_path: Path) -> None:
    # the background starts a child (as make prove starts frama-c and the solvers) and would
    # run for 50 s; the foreground fails at once
    bg = "sleep 50 & echo $! > child.pid; wait"
    t0 = time.monotonic()
    r = beside(tmp_path, bg, "bash", "-c", "while [ ! -s child.pid ]; do sleep 0.05; done; "
               "exit 4")
    took = time.monotonic() - t0
    assert r.returncode == 4, r.stdout + r.stderr
    assert "the foreground failed (exit 4)" in r.stdout
    assert took < 20, f"waited {took:.1f} s for a background that should have been stopped"
    child = int((tmp_path / "child.pid").read_text())
    deadline = time.monotonic() + 5
    while alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(child), "the background's child outlived it"


def test_usage_error(tmp_path: Path) -> None:
    r = beside(tmp_path, "true")
    assert r.returncode == 2
    assert "usage" in r.stderr


def test_keep_waits_for_the_background_when_the_foreground_fails(tmp_path: Path) -> None:
    # --keep (make test's apt-get run): the background is let finish, not stopped halfway
    r = subprocess.run([str(BESIDE), "--keep", "sleep 1; echo bg-finished > done", "false"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert (tmp_path / "done").read_text().strip() == "bg-finished"
    assert "stopping" not in r.stdout


def test_nested_runs_keep_both_outputs(tmp_path: Path) -> None:
    # make test nests them (the provers beside the fuzzers, which run beside apt-get): each
    # keeps its own log
    inner = f"{BESIDE} 'sleep 0.5; echo inner-bg' echo inner-fg"
    r = beside(tmp_path, "sleep 1; echo outer-bg", "bash", "-c", inner)
    assert r.returncode == 0, r.stdout + r.stderr
    for word in ("inner-fg", "inner-bg", "outer-bg"):
        assert r.stdout.splitlines().count(word) == 1, r.stdout
    assert not list((tmp_path / "build").glob("beside*.log"))
