"""Boots one image under qemu (TCG: /dev/kvm hangs on these machines) with the project's
checkout shared read-only and an output directory shared writable (9p), and waits until the
guest powers itself off. The guest's test (inner.py) writes its results there.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import time
from pathlib import Path

from image import TEST_UNIT, Image

QEMU = "qemu-system-x86_64"
# The emulated CPU ("max"; the baseline qemu64 cost more CPU time per boot here).
CPU_MODEL = "max"
# Modules no test uses, which udev would load at every boot (the list's header says why).
UNUSED_MODULES = Path(__file__).resolve().parent.parent / "vm_unused_modules.txt"


def unused_modules(path: Path = UNUSED_MODULES) -> list[str]:
    return [w for w in path.read_text().splitlines() if w and not w.startswith("#")]


@dataclasses.dataclass(frozen=True)
class Boot:
    returncode: int | None  # None: killed at the timeout
    seconds: float
    cpu_s: float  # qemu's CPU time (user + system): the boot's cost on an idle machine
    console: Path


def overlay(image: Image, path: Path) -> Path:
    """A copy-on-write disk over the cached image: the boots of one run share it (the second
    boot finds what the first installed), the image itself is never written."""
    path.unlink(missing_ok=True)
    subprocess.run(["qemu-img", "create", "-q", "-f", "qcow2", "-b", str(image.root), "-F", "raw",
                    str(path)], check=True, timeout=60, capture_output=True)
    return path


def qemu_argv(image: Image, disk: Path, project: Path, out: Path, memory_mb: int, cpus: int,
              extra_cmdline: str = "") -> list[str]:
    cmdline = " ".join([
        # no_timer_check: the kernel's IO-APIC timer test fails when a busy host runs the
        # emulation slowly ("IO-APIC + timer doesn't work!", a panic seen here under load)
        "console=ttyS0", "root=/dev/vda", "rw", "loglevel=4", "panic=-1", "no_timer_check",
        f"systemd.wants={TEST_UNIT}", f"estop_vm.project={project}",
        "systemd.show_status=auto", "net.ifnames=0",
        f"modprobe.blacklist={','.join(unused_modules())}", extra_cmdline,
    ]).strip()
    return [
        QEMU, "-accel", "tcg", "-cpu", os.environ.get("SYSTEMD_VM_CPU", CPU_MODEL), "-m",
        str(memory_mb), "-smp", str(cpus),
        "-nodefaults", "-no-user-config", "-display", "none", "-serial", "stdio",
        "-kernel", str(image.kernel), "-initrd", str(image.initrd), "-append", cmdline,
        "-drive", f"file={disk},if=virtio,format=qcow2,cache=unsafe",
        "-virtfs", f"local,path={project},mount_tag=project,security_model=none,readonly=on,"
                   "multidevs=remap",
        "-virtfs", f"local,path={out},mount_tag=out,security_model=none,multidevs=remap",
        "-device", "virtio-rng-pci",
        # A kernel panic reboots (panic=-1), and any reboot ends qemu: the host starts each boot.
        "-no-reboot",
    ]


def boot(image: Image, disk: Path, project: Path, out: Path, console: Path, timeout_s: float,
         memory_mb: int = 1024, cpus: int = 1, extra_cmdline: str = "") -> Boot:
    """Runs one qemu until it exits (the guest powered off or rebooted) or timeout_s passes."""
    if shutil.which(QEMU) is None:
        raise FileNotFoundError(f"{QEMU} is not installed (scripts/ensure-debs systemd-vm)")
    argv = qemu_argv(image, disk, project, out, memory_mb, cpus, extra_cmdline)
    t0 = time.monotonic()
    rc: int | None = None
    with console.open("ab") as log:
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
        while time.monotonic() - t0 < timeout_s:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                rc = os.waitstatus_to_exitcode(status)
                proc.returncode = rc
                break
            time.sleep(0.2)
        else:
            proc.kill()
            pid, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
    return Boot(rc, time.monotonic() - t0, usage.ru_utime + usage.ru_stime, console)
