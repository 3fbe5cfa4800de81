"""The core on a (emulated) board: a bare-metal image for QEMU's mps2-an385 (Cortex-M3) with a
vector table, a reset handler and SysTick as the core's only clock, linked from the very M0+
-Os objects of the core. It runs the examples of PROTOCOL.md (sections 1, 2, 4, and 5.4 with
tags computed on the device) and reports over semihosting; QEMU's exit status is the verdict."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from mcu_util import ensure_built, mcubuild

CHECKS = [
    "init without a key",
    "boot brake frame 01 64 00 01 00 00 00 9C",
    "UDP example is a valid packet",
    "RELEASE example refused: not neutral",
    "RELEASE example accepted: ARMED",
    "STOP example: STOPPED, tcp stop",
    "re-armed",
    "silence: STOPPED, udp timeout",
    "timeout stop at the deadline, by SysTick",
    "brake frame 01 64 00 03 00 00 0E 1D",
    "init a two-stage unit",
    "silence: SLOWING, controlled stop at the slow level",
    "slow-down at its deadline, by SysTick",
    "3 valid packets: ARMED again",
    "LIFT example: STOPPED, lift",
    "init with the key of 5.4",
    "5.4 STATUS reply, byte for byte",
    "5.4 control packet authenticated",
    "heartbeats tagged on the device authenticated",
    "5.4 RELEASE: ACK, ARMED",
    "5.4 LIFT as a lift datagram: STOPPED, lift",
    "5.4 STOP: acknowledged, the first reason kept",
]


def test_the_core_boots_on_mps2_an385_and_passes_the_spec_examples() -> None:
    ensure_built()
    try:
        mcubuild.make("baremetal")
    except mcubuild.McuError as exc:
        pytest.fail(str(exc), pytrace=False)
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        pytest.fail("qemu-system-arm not found (scripts/ensure-debs mcu installs it; make test "
                    "runs that)", pytrace=False)
    image = mcubuild.OUT_DIR / "baremetal" / "estop-an385.elf"
    proc = subprocess.run(
        [qemu, "-M", "mps2-an385", "-display", "none", "-monitor", "none", "-serial", "none",
         "-semihosting-config", "enable=on,target=native", "-kernel", str(image)],
        capture_output=True, text=True, timeout=60, check=False)
    report = proc.stdout + proc.stderr
    assert proc.returncode == 0, report
    assert [line[5:] for line in report.splitlines() if line.startswith("ok   ")] == CHECKS
    assert f"{len(CHECKS)} passed, 0 failed" in report
    # SysTick really ran the clock: the silence of 300 ms and the run to counter 14 alone
    # take that long, and the brake frames kept coming every 10 ms.
    m = re.search(r"systick: (\d+) ms, brake frames: (\d+)", report)
    assert m is not None, report
    ms, frames = int(m.group(1)), int(m.group(2))
    assert ms >= 500 and frames >= ms // 10 - 20, report
