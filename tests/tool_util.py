"""Helpers for the tests of the Python tools against the real estopd and of the bench scripts."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH_DIR = Path(__file__).resolve().parents[1] / "bench"


def estopd_or_skip() -> str:
    """The built estopd; skipped where it is not built, but a failure in CI, which builds it."""
    from estop.unit.daemon import find_estopd  # here: conftest imports this module for every test

    exe = find_estopd()
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("estopd not found in CI (make setup should have built it)")
        pytest.skip("estopd not built (make -C firmware)")
    return exe


def load_bench_script(name: str) -> ModuleType:
    """bench/<name>.py imported as the module <name> (the bench is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, BENCH_DIR / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
