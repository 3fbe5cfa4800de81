"""The minimal Debian systems `make systemd-vm` boots (issue 26): a root file system built with
mmdebstrap, packed into an ext4 image with `mkfs.ext4 -d`, and the kernel and initrd to boot it.

- debian12 (bookworm, systemd 252) boots this machine's Debian kernel from /boot, with an
  initrd that mkinitramfs builds for it holding only what mounts the root (the one in /boot
  holds most modules: 31 MB to unpack at every boot); the modules the test needs that the
  initrd lacks (CAN, vcan, 9p) are copied in.
- debian13 (trixie, systemd 257) boots its own kernel (linux-image-amd64 in the image) with an
  initrd that initramfs-tools builds inside it, holding only what mounts the root.

An image is built once and kept in the cache directory under a key made of everything that
goes into it (this file's text, the suite, the packages, the host kernel for debian12), so a
change to the test itself never rebuilds it. Only the newest image of each system is kept.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

MIRROR = "http://deb.debian.org/debian"
# What a team's board has for estopd (issue 26), plus what the checks run: make for `make
# install`, python3 (and numpy for `estop link`) for the estop tools, acl for getfacl.
PACKAGES = ["systemd-sysv", "udev", "dbus", "iproute2", "can-utils", "kmod", "acl", "procps",
            "make", "python3", "python3-numpy", "python3-dpkt"]
# debian12: the modules to copy from this machine (with their dependencies).
HOST_MODULES = ["vcan", "can-raw", "can-dev", "9p", "9pnet_virtio", "virtio-rng"]
# What each initrd must hold to mount the root (MODULES=list).
INITRD_MODULES = ["virtio_pci", "virtio_blk", "ext4"]
# Files no check reads: not unpacked (less to write, to byte-compile, to pack).
DPKG_EXCLUDES = ["/usr/share/doc/*", "/usr/share/man/*", "/usr/share/locale/*",
                 "/usr/share/info/*"]
# debian13's kernel: only the module trees a VM with virtio disks, 9p and vcan can use.
KERNEL_KEEP = ["kernel/fs/*", "kernel/net/9p/*", "kernel/net/can/*", "kernel/lib/*",
               "kernel/crypto/*", "kernel/arch/*", "kernel/drivers/block/*",
               "kernel/drivers/virtio/*", "kernel/drivers/net/can/*", "kernel/drivers/char/*"]
KERNEL_DROP = ["kernel/drivers/*", "kernel/sound/*", "kernel/net/*"]
# Units a test VM does without: no first-boot questions, no logins, no maintenance timers
# (each costs seconds of emulated CPU at every boot).
BOOT_MASKED = ["systemd-firstboot.service", "getty@tty1.service", "serial-getty@ttyS0.service",
               "systemd-binfmt.service", "proc-sys-fs-binfmt_misc.automount",
               "dpkg-db-backup.timer", "fstrim.timer", "e2scrub_all.timer",
               "e2scrub_reap.service", "systemd-tmpfiles-clean.timer",
               "systemd-update-utmp.service", "systemd-update-utmp-runlevel.service",
               "systemd-pstore.service",
               # logins (a unit on the car needs none; multi-user.target waited 4 s for it)
               "systemd-logind.service",
               # an image is never updated in place, but every boot starts from it as built,
               # so each found /etc "older than /usr" and rebuilt these caches (3 s, Debian 13)
               "ldconfig.service", "systemd-journal-catalog-update.service",
               "systemd-update-done.service"]
# Generators with nothing to generate here, run at every boot and every daemon-reload. Kept:
# systemd-debug-generator (systemd.wants= on the kernel command line) and the fstab one.
GENERATORS_MASKED = ["systemd-cryptsetup-generator", "systemd-getty-generator",
                     "systemd-gpt-auto-generator", "systemd-hibernate-resume-generator",
                     "systemd-integritysetup-generator", "systemd-rc-local-generator",
                     "systemd-run-generator", "systemd-ssh-generator",
                     "systemd-system-update-generator", "systemd-sysv-generator",
                     "systemd-tpm2-generator", "systemd-veritysetup-generator"]
# The unit the kernel command line asks for (systemd.wants=); it runs the test from the share.
TEST_UNIT = "estop-vmtest.service"
TEST_UNIT_TEXT = """[Unit]
Description=estop systemd-vm test (tools/systemd_vm/inner.py from the project's share)
# Outside the boot's targets (no default dependencies): the boot finishes without waiting for
# the test, which watches it (a unit holding multi-user.target back shows).
DefaultDependencies=no
After=basic.target
Conflicts=shutdown.target
Before=shutdown.target

[Service]
# Not a oneshot: its start job would keep the boot "starting" for the whole test.
Type=exec
ExecStart=/usr/local/sbin/estop-vmtest
StandardOutput=journal+console
StandardError=journal+console
"""
# Mounts the shares named on the kernel command line and runs the test; powers off whatever
# happens, so the host never waits for its timeout on a broken test.
TEST_SCRIPT = """#!/bin/sh
project=$(sed -n 's/.*estop_vm.project=\\([^ ]*\\).*/\\1/p' /proc/cmdline)
mkdir -p "$project" /run/estop-vm-out
# A share's virtio device may still be probing when this runs (Debian 13's kernel once said
# "9pnet_virtio: no channels available for device project" at 20 s): tried for 30 s.
mount9p() {
  i=0
  while ! mount -t 9p -o trans=virtio,version=9p2000.L,$3,msize=262144 "$1" "$2" 2>/dev/null
  do
    i=$((i + 1))
    if [ "$i" -ge 60 ]; then
      mount -t 9p -o trans=virtio,version=9p2000.L,$3,msize=262144 "$1" "$2"
      return
    fi
    sleep 0.5
  done
  if [ "$i" -gt 0 ]; then echo "estop-vmtest: share $1 mounted after $i retries" >/dev/console; fi
  return 0
}
mount9p project "$project" ro && mount9p out /run/estop-vm-out rw &&
  python3 -B "$project/tools/systemd_vm/inner.py" --project "$project" \\
    --out /run/estop-vm-out
echo "estop-vmtest: exit $?" >/dev/console
sync
systemctl poweroff --no-block
"""


@dataclasses.dataclass(frozen=True)
class System:
    name: str
    suite: str
    systemd: str
    own_kernel: bool  # boots the kernel of the image (else this machine's)


SYSTEMS = {
    "debian12": System("debian12", "bookworm", "252", own_kernel=False),
    "debian13": System("debian13", "trixie", "257", own_kernel=True),
}


@dataclasses.dataclass(frozen=True)
class Image:
    system: System
    root: Path  # the ext4 image (booted through an overlay: never written)
    kernel: Path
    initrd: Path
    built_s: float  # seconds this run spent building it (0 when cached)
    built_cpu_s: float  # the CPU seconds of that build (its cost on an idle machine)


class ImageUnavailable(Exception):
    """The image cannot be had here (no mmdebstrap, no mirror, no host kernel): a skip."""


def host_kernel() -> tuple[str, Path, Path]:
    """This machine's newest Debian kernel in /boot: version, vmlinuz, initrd."""
    found = sorted(Path("/boot").glob("vmlinuz-*"))
    for vmlinuz in reversed(found):
        version = vmlinuz.name[len("vmlinuz-"):]
        initrd = Path("/boot") / f"initrd.img-{version}"
        if initrd.exists() and (Path("/lib/modules") / version / "modules.dep").exists():
            return version, vmlinuz, initrd
    raise ImageUnavailable("no Debian kernel with its initrd and modules in /boot "
                           "(scripts/ensure-debs systemd-vm installs linux-image-amd64)")


def cache_dir() -> Path:
    base = os.environ.get("ESTOP_VM_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "estop",
        "systemd-vm")
    return Path(base)


def image_key(system: System) -> str:
    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update(repr(dataclasses.astuple(system)).encode())
    if not system.own_kernel:
        version, vmlinuz, initrd = host_kernel()
        h.update(f"{version} {vmlinuz.stat().st_size} {initrd.stat().st_size}".encode())
    return h.hexdigest()[:16]


CPU = threading.local()  # the CPU seconds of the commands a build ran (per building thread)


def run(argv: list[str], log: Path, timeout: float) -> None:
    with log.open("a") as out:
        out.write(f"$ {' '.join(argv)}\n")
        out.flush()
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
        t0 = time.monotonic()
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() - t0 > timeout:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.2)
        proc.returncode = os.waitstatus_to_exitcode(status)
    CPU.seconds = getattr(CPU, "seconds", 0.0) + usage.ru_utime + usage.ru_stime
    if proc.returncode != 0:
        tail = log.read_text(errors="replace").splitlines()[-5:]
        raise subprocess.CalledProcessError(proc.returncode, argv, output="\n".join(tail))


def mmdebstrap_argv(system: System, root: Path) -> list[str]:
    packages = list(PACKAGES)
    opts = ["force-unsafe-io", *(f"path-exclude={p}" for p in DPKG_EXCLUDES)]
    hooks: list[str] = []
    if system.own_kernel:
        packages += ["linux-image-amd64", "initramfs-tools"]
        for base in ("/lib/modules/*/", "/usr/lib/modules/*/"):
            opts += [f"path-exclude={base}{p}" for p in KERNEL_DROP]
            opts += [f"path-include={base}{p}" for p in KERNEL_KEEP]
        # Before the kernel's postinst builds the initrd: only the modules that mount the root.
        hooks.append('mkdir -p "$1/etc/initramfs-tools/conf.d" '
                     '"$1/usr/share/initramfs-tools/modules.d" && '
                     'echo MODULES=list > "$1/etc/initramfs-tools/conf.d/estop-vm" && '
                     f'printf "%s\\n" {" ".join(INITRD_MODULES)} '
                     '> "$1/usr/share/initramfs-tools/modules.d/estop-vm"')
    return ["mmdebstrap", "--variant=essential", "--mode=root",
            f"--include={','.join(packages)}",
            *(f"--dpkgopt={o}" for o in opts),
            "--aptopt=Acquire::Retries \"3\"",
            *(f"--essential-hook={h}" for h in hooks),
            system.suite, str(root), MIRROR]


def copy_host_modules(root: Path, version: str, log: Path) -> None:
    """The host kernel's modules the test loads, with what they depend on, then depmod."""
    lines = []
    for module in HOST_MODULES:  # --show-depends takes one module (the rest are parameters)
        lines += subprocess.run(["modprobe", "-S", version, "--show-depends", module],
                                capture_output=True, text=True, timeout=60,
                                check=True).stdout.splitlines()
    src = Path("/lib/modules") / version
    dst = root / "usr/lib/modules" / version
    for line in lines:
        words = line.split()
        if words and words[0] == "insmod":
            ko = Path(words[1]).resolve()
            target = dst / ko.relative_to(src.resolve())
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ko, target)
    for f in src.glob("modules.*"):
        if f.name in ("modules.order", "modules.builtin", "modules.builtin.modinfo"):
            shutil.copy2(f, dst / f.name)
    run(["depmod", "-b", str(root), version], log, 120)


def customize(system: System, root: Path) -> None:
    """What every boot needs: a machine id (the journal's), no first-boot questions, the test
    unit and its script, a root that fsck leaves alone."""
    (root / "etc/machine-id").write_text("e5709e5709e5709e5709e5709e570900\n")
    (root / "etc/hostname").write_text(f"estop-{system.name}\n")
    (root / "etc/fstab").write_text("/dev/vda / ext4 rw,relatime 0 0\n")
    for masked in BOOT_MASKED:
        link = root / "etc/systemd/system" / masked
        link.unlink(missing_ok=True)
        link.symlink_to("/dev/null")
    generators = root / "etc/systemd/system-generators"
    generators.mkdir(parents=True, exist_ok=True)
    for masked in GENERATORS_MASKED:
        (generators / masked).symlink_to("/dev/null")
    unit = root / "etc/systemd/system" / TEST_UNIT
    unit.write_text(TEST_UNIT_TEXT)
    script = root / "usr/local/sbin/estop-vmtest"
    script.parent.mkdir(parents=True, exist_ok=True)
    script.write_text(TEST_SCRIPT)
    script.chmod(0o755)
    # The journal in memory (each boot's test copies its own out): no flush to disk at boot.
    conf = root / "etc/systemd/journald.conf.d/estop-vm.conf"
    conf.parent.mkdir(parents=True, exist_ok=True)
    conf.write_text("[Journal]\nStorage=volatile\n")


def host_initrd(version: str, dest: Path, log: Path) -> None:
    """An initrd for this machine's kernel that holds only what mounts the root."""
    conf = dest.parent / f"{dest.name}.conf"
    shutil.rmtree(conf, ignore_errors=True)
    (conf / "scripts").mkdir(parents=True)
    (conf / "initramfs.conf").write_text("MODULES=list\nBUSYBOX=auto\nCOMPRESS=zstd\n")
    (conf / "modules").write_text("".join(f"{m}\n" for m in INITRD_MODULES))
    try:
        run(["mkinitramfs", "-d", str(conf), "-o", str(dest), version], log, 300)
    finally:
        shutil.rmtree(conf, ignore_errors=True)


def pack(root: Path, image: Path, log: Path) -> None:
    used = int(subprocess.run(["du", "-sxk", str(root)], capture_output=True, text=True,
                              check=True, timeout=120).stdout.split()[0])
    size_mb = used // 1024 + 512  # room for the install, the journal, the logs
    image.unlink(missing_ok=True)
    run(["mkfs.ext4", "-q", "-F", "-L", "estop-root", "-E", "lazy_itable_init=1",
         "-d", str(root), str(image), f"{size_mb}M"], log, 600)


def build(system: System, dest: Path, log: Path) -> None:
    """Builds the system into dest (root.img, vmlinuz, initrd.img)."""
    root = dest / "rootfs"
    if shutil.which("mmdebstrap") is None:
        raise ImageUnavailable("mmdebstrap is not installed (scripts/ensure-debs systemd-vm)")
    try:
        run(mmdebstrap_argv(system, root), log, 1200)
    except subprocess.CalledProcessError as e:
        raise ImageUnavailable(f"mmdebstrap {system.suite} failed (no mirror here?): "
                               f"{e.output}") from e
    if system.own_kernel:
        kernels = sorted((root / "boot").glob("vmlinuz-*"))
        initrds = sorted((root / "boot").glob("initrd.img-*"))
        if not kernels or not initrds:
            raise RuntimeError(f"{system.name}: no kernel or initrd in the image's /boot")
        shutil.copy2(kernels[-1], dest / "vmlinuz")
        shutil.copy2(initrds[-1], dest / "initrd.img")
    else:
        version, vmlinuz, _ = host_kernel()  # /boot's initrd only keys the image
        copy_host_modules(root, version, log)
        shutil.copy2(vmlinuz, dest / "vmlinuz")
        host_initrd(version, dest / "initrd.img", log)
    customize(system, root)
    pack(root, dest / "root.img", log)
    shutil.rmtree(root)


def ensure(system: System, log_dir: Path) -> Image:
    """The cached image of system, built first where there is none."""
    if os.geteuid() != 0:
        raise ImageUnavailable("building the image needs root (mmdebstrap --mode=root)")
    key = image_key(system)
    base = cache_dir()
    base.mkdir(parents=True, exist_ok=True)
    final = base / f"{system.name}-{key}"
    log = log_dir / f"image-{system.name}.log"
    with (base / f"{system.name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another run building the same image: wait for it
        built_s = 0.0
        CPU.seconds = 0.0
        if not (final / "root.img").exists():
            t0 = time.monotonic()
            tmp = base / f".{system.name}-{key}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir()
            try:
                build(system, tmp, log)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
            tmp.rename(final)
            built_s = time.monotonic() - t0
            for old in base.glob(f"{system.name}-*"):
                if old != final:
                    shutil.rmtree(old, ignore_errors=True)
    return Image(system, final / "root.img", final / "vmlinuz", final / "initrd.img", built_s,
                 CPU.seconds)
