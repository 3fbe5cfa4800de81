"""Shared pytest set-up: tests import helpers that live beside them (reference_model, ...)."""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tool_util import load_bench_script  # noqa: E402 - needs the path above


@pytest.fixture(autouse=True)
def _no_key_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """A developer's $ESTOP_KEY_FILE must not change what the tools send in the tests."""
    monkeypatch.delenv("ESTOP_KEY_FILE", raising=False)


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    """bench/stop_latency.py as a module, for the tests of the bench and its helpers."""
    return load_bench_script("stop_latency")
