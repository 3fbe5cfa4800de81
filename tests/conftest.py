"""Shared pytest set-up: tests import helpers that live beside them (reference_model, ...)."""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tool_util import load_bench_script  # noqa: E402 - needs the path above

_SETTINGS_ENV = ("ESTOP_HOST", "ESTOP_UDP_PORT", "ESTOP_TCP_PORT", "ESTOP_KEY_FILE",
                 "ESTOP_REMOTE_ID", "ESTOP_STOP_ID", "ESTOP_RATE_HZ", "ESTOP_CONFIG")


@pytest.fixture(autouse=True)
def _no_settings_from_the_developer(monkeypatch: pytest.MonkeyPatch,
                                    tmp_path_factory: pytest.TempPathFactory) -> None:
    """A developer's $ESTOP_* and configuration file must not change what the tools send in
    the tests, and the tests must not write the developer's configuration (the remote id an
    installation makes on first use with a key): every test gets its own config home, whose
    config.toml holds only ``remote_id = 1`` (the id the tests' frames carry; the first use
    itself is tested in tests/test_cli_settings.py)."""
    for name in _SETTINGS_ENV:
        monkeypatch.delenv(name, raising=False)
    home = tmp_path_factory.mktemp("config-home")
    (home / "estop").mkdir()
    (home / "estop" / "config.toml").write_text("remote_id = 1\n")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    """bench/stop_latency.py as a module, for the tests of the bench and its helpers."""
    return load_bench_script("stop_latency")
