"""tools/systemd-vm builds the systems' images at once and boots their VMs one at a time.

Beside make prove two TCG guests at once cost the host 255 to 292 CPU-s, one after the other
217 to 262 (issue 24's fortieth round); the images' downloads still overlap. Here the image
build and the boot are stand-ins that sleep (a real boot takes minutes of TCG): what is
checked is the script's own scheduling, with its real run_systems and run_system."""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import sys
import threading
import time
import types
from collections.abc import Iterator
from pathlib import Path

import pytest

from repo import ROOT

STEP_S = 0.3


@pytest.fixture()
def script() -> Iterator[types.ModuleType]:
    path = ROOT / "tools" / "systemd-vm"
    loader = importlib.machinery.SourceFileLoader("systemd_vm_script", str(path))
    spec = importlib.util.spec_from_loader(loader.name, loader)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    saved = list(sys.path)
    try:
        loader.exec_module(module)
        yield module
    finally:
        sys.path[:] = saved
        # its helpers (boot, image, report...) were imported by their bare names: not left
        # behind for another test's import of the same name
        helpers = str(ROOT / "tools" / "systemd_vm")
        for name, mod in list(sys.modules.items()):
            if str(getattr(mod, "__file__", "") or "").startswith(helpers):
                del sys.modules[name]


def intervals(script: types.ModuleType, monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
              *argv: str) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """The image builds' and the boots' (start, end) with stand-ins that sleep STEP_S."""
    lock = threading.Lock()
    builds: list[tuple[float, float]] = []
    boots: list[tuple[float, float]] = []

    def ensure(system: object, out: Path) -> object:
        t0 = time.monotonic()
        time.sleep(STEP_S)
        with lock:
            builds.append((t0, time.monotonic()))
        return types.SimpleNamespace(built_s=STEP_S, built_cpu_s=0.0)

    def boot(*_a: object, **_k: object) -> object:
        t0 = time.monotonic()
        time.sleep(STEP_S)
        with lock:
            boots.append((t0, time.monotonic()))
        return types.SimpleNamespace(seconds=STEP_S, cpu_s=0.0, returncode=0)

    monkeypatch.setattr(script.image, "ensure", ensure)
    monkeypatch.setattr(script.boot, "overlay", lambda img, path: path)
    monkeypatch.setattr(script.boot, "boot", boot)
    monkeypatch.setattr(script.report, "prepared", lambda share: True)
    args = argparse.Namespace(script=None, plant="", cpus=1, serial=False,
                              boots_at_once=script.BOOTS_AT_ONCE)
    for a in argv:
        key, value = a.split("=")
        setattr(args, key, int(value))
    script.run_systems(["debian12", "debian13"], tmp_path, args)
    return builds, boots


def overlap(a: list[tuple[float, float]]) -> bool:
    first, second = sorted(a)[:2]
    return second[0] < first[1]  # the second began before the first ended


def test_the_images_are_built_at_once_and_the_vms_boot_one_at_a_time(
        script: types.ModuleType, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    builds, boots = intervals(script, monkeypatch, tmp_path)
    assert len(builds) == 2 and len(boots) == 4  # each system: its main boot and nocan
    assert overlap(builds), builds
    ordered = sorted(boots)
    assert all(b[0] >= a[1] for a, b in zip(ordered, ordered[1:], strict=False)), ordered


def test_two_boots_at_once_overlap_so_the_check_can_fail(
        script: types.ModuleType, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    _, boots = intervals(script, monkeypatch, tmp_path, "boots_at_once=2")
    assert overlap(boots), boots
