"""scripts/kvm-works, the bounded KVM probe of the VMs of make test (tools/vm-pytest, hil/run):
a fake vng stands for the boot. Its verdict is kept for the host's boot, so that a machine
where KVM hangs pays the probe's 30 s once, not again in make test's last minutes."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

PROBE = ROOT / "scripts" / "kvm-works"


def probe(tmp_path: Path, answer: str) -> int:
    vng = tmp_path / "vng"
    # the fake boot: prints what the probe looks for, or nothing, and counts its boots
    vng.write_text(f"#!/bin/sh\necho boot >>{tmp_path}/boots\n{answer}\n")
    vng.chmod(0o755)
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    return subprocess.run([str(PROBE), str(vng), "--run", "k"], env=env, timeout=60,
                          capture_output=True, text=True).returncode


def boots(tmp_path: Path) -> int:
    f = tmp_path / "boots"
    return len(f.read_text().splitlines()) if f.exists() else 0


@pytest.fixture
def kvm_device() -> None:
    if not (os.access("/dev/kvm", os.R_OK) and os.access("/dev/kvm", os.W_OK)):
        pytest.skip("no usable /dev/kvm: the probe answers no without booting")


def test_a_failed_boot_says_no_once_per_host_boot(tmp_path: Path, kvm_device: None) -> None:
    assert probe(tmp_path, "true") == 1
    assert probe(tmp_path, "echo ESTOP-KVM-OK") == 1  # the verdict kept, no second boot
    assert boots(tmp_path) == 1


def test_a_boot_that_answers_says_yes_and_is_kept(tmp_path: Path, kvm_device: None) -> None:
    assert probe(tmp_path, "echo ESTOP-KVM-OK") == 0
    assert probe(tmp_path, "true") == 0
    assert boots(tmp_path) == 1
    boot_id = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    assert (tmp_path / f"estop-kvm-{os.getuid()}-{boot_id}").read_text() == "yes\n"


def test_without_arguments_it_says_how_to_call_it() -> None:
    r = subprocess.run([str(PROBE)], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2 and "usage" in r.stderr
