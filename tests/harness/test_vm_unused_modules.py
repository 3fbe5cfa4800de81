"""tools/vm_unused_modules.txt: the modules every VM of make test boots without
(modprobe.blacklist=). The virtme-ng VMs get them through scripts/vng-opts, the systemd VMs
through tools/systemd_vm/boot.py's kernel command line: one list for both, and never a module
that a test loads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from repo import ROOT

# What the VMs' tests load or boot from: the HIL harness (vcan, CAN raw), the gamepad VM
# (uinput, evdev), the shares and disks (9p, virtio, ext4).
NEEDED = {"vcan", "can", "can_raw", "can_dev", "uinput", "evdev", "9p", "9pnet", "9pnet_virtio",
          "virtio", "virtio_pci", "virtio_blk", "virtio_rng", "virtio_console", "ext4", "overlay"}


def listed() -> list[str]:
    lines = (ROOT / "tools" / "vm_unused_modules.txt").read_text().splitlines()
    return [w for w in lines if w and not w.startswith("#")]


def test_no_module_a_test_needs_is_on_the_list() -> None:
    names = listed()
    assert names and len(names) == len(set(names))
    assert not {n.replace("-", "_") for n in names} & NEEDED


def test_both_kinds_of_vm_boot_without_the_same_modules() -> None:
    opts = subprocess.run([str(ROOT / "scripts" / "vng-opts")], capture_output=True, text=True,
                          timeout=30, check=True).stdout.splitlines()
    want = f"modprobe.blacklist={','.join(listed())}"
    assert opts == ["--force-9p", "--append", want]
    sys.path.insert(0, str(ROOT / "tools" / "systemd_vm"))
    try:
        import boot
        import image
        img = image.Image(image.SYSTEMS["debian12"], Path("root.img"), Path("vmlinuz"),
                          Path("initrd.img"), 0.0, 0.0)
        argv = boot.qemu_argv(img, Path("disk"), ROOT, Path("out"), 1024, 1)
    finally:
        sys.path.remove(str(ROOT / "tools" / "systemd_vm"))
        sys.modules.pop("boot", None)
        sys.modules.pop("image", None)
    assert want in argv[argv.index("-append") + 1].split()
