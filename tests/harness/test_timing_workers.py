"""How make test's timing tests share their two pytest-xdist workers (tests/conftest.py and the
Makefile's coverage-timed): a module on one worker at a time, and both browser modules on the
same one, one after the other. With a module a worker (--dist loadfile), the two chromium
modules ran at once whenever the order of the modules put them side by side
(--no-loadscope-reorder did), and that is how the pages' 300-ms bounds failed before."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from repo import ROOT

# Prints each collected test with its xdist_group, as tests/conftest.py marked it.
PLUGIN = """
def pytest_collection_finish(session):
    for item in session.items:
        mark = item.get_closest_marker("xdist_group")
        group = (mark.args[0] if mark.args else mark.kwargs.get("name")) if mark else "-"
        print("GROUP", item.nodeid, group)
"""


def groups(tmp_path: Path, *paths: str, **env_extra: str) -> dict[str, str]:
    """Test node id -> its xdist group, for the tests of paths (collected only)."""
    (tmp_path / "show_groups.py").write_text(PLUGIN)
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               **env_extra)
    p = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q",
                        "-p", "no:cacheprovider", "-p", "show_groups", *paths],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
                       check=False)
    # a node id may hold spaces (a parameter's), a group none
    found = dict(line.removeprefix("GROUP ").rsplit(" ", 1) for line in p.stdout.splitlines()
                 if line.startswith("GROUP "))
    assert p.returncode == 0 and found, p.stdout + p.stderr
    return found


def test_the_browser_modules_share_a_worker_and_every_other_module_has_its_own(
        tmp_path: Path) -> None:
    found = groups(tmp_path, "tests/browser", "tests/daemon/test_estopd_attacks.py",
                   "tests/daemon/test_estopd_basic.py")
    by_module: dict[str, set[str]] = {}
    for node, group in found.items():
        by_module.setdefault(node.split("::")[0], set()).add(group)
    assert all(len(g) == 1 for g in by_module.values()), by_module
    browser = {m: g for m, g in by_module.items() if m.startswith("tests/browser/")}
    assert len(browser) >= 2 and set.union(*browser.values()) == {"chromium"}, browser
    others = [next(iter(g)) for m, g in by_module.items() if m not in browser]
    assert len(set(others)) == len(others) and "chromium" not in others, by_module


def test_make_runs_the_timing_tests_by_those_groups() -> None:
    """The groups do nothing unless xdist is told to distribute by them."""
    recipe = (ROOT / "Makefile").read_text().split("\ncoverage-timed:", 1)[1].split("\n\n")[0]
    parallel = [line for line in recipe.splitlines() if re.search(r"\s-n\s+\d", line)]
    assert parallel and all("--dist loadgroup" in line for line in parallel), recipe


def test_without_xdist_the_tests_are_collected_with_no_group(tmp_path: Path) -> None:
    """tools/vm-pytest loads no plugin it does not name: there, under --strict-markers, an
    xdist_group marker stopped the collection (the first draft of the groups did)."""
    found = groups(tmp_path, "tests/harness/test_beside.py", PYTEST_DISABLE_PLUGIN_AUTOLOAD="1")
    assert set(found.values()) == {"-"}, found
