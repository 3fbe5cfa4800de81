"""Shared pytest set-up: tests import the helpers of this folder (reference_model, ...); each
test is marked with the kind of its folder; one session fixture finds the estopd binary.

The kinds (their markers are registered in pyproject.toml, and --strict-markers refuses any
other): ``unit`` (the Python package, mirroring src/estop), ``core`` (the C core through
cffi), ``daemon`` (estopd itself), ``browser`` (Debian's chromium), ``vm`` (kernel parts this
host lacks: tools/vm-pytest), ``mcu`` (the Cortex-M toolchain), ``harness`` (hil/ and bench/
code), ``docs``. A test anywhere that asks for the ``estopd`` fixture is a ``daemon`` test too.
``make test-fast`` runs what is neither daemon, browser, vm nor mcu. A module that measures time
with tests/stall_probe must be marked ``timing`` as well (refused otherwise): make test runs the
timing tests alone, the others beside the provers."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from daemon_util import locate_estopd  # noqa: E402 - needs the path above
from net_util import UdpSink  # noqa: E402
from tool_util import load_bench_script  # noqa: E402

HERE = Path(__file__).resolve().parent
KINDS = ("unit", "core", "daemon", "browser", "vm", "mcu", "harness", "docs")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The marker of each test's kind, from its folder; ``daemon`` also for a test that asks
    for the estopd fixture. A test file outside the kinds' folders is refused: its kind would
    decide what ``make test-fast`` and tools/vm-pytest run."""
    astray: set[str] = set()
    for item in items:
        try:
            kind = item.path.relative_to(HERE).parts[0]
        except ValueError:
            continue  # a test file named on the command line from elsewhere
        if kind not in KINDS:
            astray.add(str(item.path.relative_to(HERE.parent)))
            continue
        item.add_marker(kind)
        if "estopd" in getattr(item, "fixturenames", ()) and kind != "daemon":
            item.add_marker("daemon")
    untimed = sorted({str(item.path.relative_to(HERE.parent)) for item in items
                      if _uses_stall_probe(item) and item.get_closest_marker("timing") is None})
    if untimed:
        raise pytest.UsageError(
            f"test modules that measure time with tests/stall_probe but are not marked timing: "
            f"{', '.join(untimed)}; add pytest.mark.timing to their pytestmark (make test runs "
            f"timing tests alone, not beside the provers)")
    if astray:
        raise pytest.UsageError(
            f"test files outside the folders of the test kinds: {', '.join(sorted(astray))}; "
            f"move each into tests/<kind>/ ({', '.join(KINDS)}; unit tests mirror "
            f"src/estop: tests/unit/<subpackage>/)")


def _uses_stall_probe(item: pytest.Item) -> bool:
    """Whether the test's module took anything from tests/stall_probe (a timing test's aid)."""
    module = getattr(item, "module", None)
    probe = sys.modules.get("stall_probe")
    return module is not None and any(
        (probe is not None and value is probe)
        or getattr(value, "__module__", None) == "stall_probe"
        for value in vars(module).values())


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """``-m KIND`` for a kind that its folder alone holds (every kind but daemon): the other
    kinds' folders are not collected at all (in a TCG VM, importing every test module would
    take minutes)."""
    kind = config.getoption("markexpr", "") or ""
    if kind not in KINDS or kind == "daemon" or not collection_path.is_dir():
        return None
    try:
        rel = collection_path.relative_to(HERE)
    except ValueError:
        return None
    if len(rel.parts) == 1 and rel.parts[0] in KINDS and rel.parts[0] != kind:
        return True
    return None


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="session")
def estopd() -> str:
    """The estopd binary (tests/daemon_util.locate_estopd). Where it is not built, the test is
    skipped on a developer's machine and fails in CI ($CI set, as .ci/run does), which builds
    it (make setup)."""
    exe = locate_estopd()
    if exe is None:
        where = f"$ESTOPD={os.environ['ESTOPD']}" if os.environ.get("ESTOPD") else \
            "firmware/build/estopd or estopd on PATH"
        if _in_ci():
            pytest.fail(f"estopd not found in CI ({where}); make setup builds it")
        pytest.skip(f"estopd not built ({where}): make setup, or make -C firmware")
    return exe

_SETTINGS_ENV = ("ESTOP_HOST", "ESTOP_UDP_PORT", "ESTOP_TCP_PORT", "ESTOP_KEY_FILE",
                 "ESTOP_REMOTE_ID", "ESTOP_STOP_ID", "ESTOP_RATE_HZ", "ESTOP_CONFIG",
                 # python-can's own configuration (the bus of estop monitor and dashboard)
                 "CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG")


@pytest.fixture(autouse=True)
def _no_settings_from_the_developer(monkeypatch: pytest.MonkeyPatch,
                                    tmp_path_factory: pytest.TempPathFactory) -> None:
    """A developer's $ESTOP_* and configuration file must not change what the tools send in
    the tests, and the tests must not write the developer's configuration (the remote id an
    installation makes on first use with a key): every test gets its own config home, whose
    config.toml holds only ``remote_id = 1`` (the id the tests' frames carry; the first use
    itself is tested in tests/unit/commands/test_cli_settings.py)."""
    for name in _SETTINGS_ENV:
        monkeypatch.delenv(name, raising=False)
    home = tmp_path_factory.mktemp("config-home")
    (home / "estop").mkdir()
    (home / "estop" / "config.toml").write_text("remote_id = 1\n")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))


@pytest.fixture
def sink() -> Iterator[UdpSink]:
    """A UDP socket on loopback that records what arrives (the unit's control port)."""
    s = UdpSink()
    yield s
    s.close()


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    """bench/stop_latency.py as a module, for the tests of the bench and its helpers."""
    return load_bench_script("stop_latency")
