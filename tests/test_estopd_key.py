"""Key hygiene in estopd (issue 16, defect 7; firmware/estopd/README.md, the key): the key
file must belong to the daemon's user or root, no copy of the key (its hex text or its bytes)
stays in the daemon's memory once the core holds its MAC state, and the process cannot be
dumped or traced by its own user (PR_SET_DUMPABLE 0).

The memory is read from /proc/PID/mem, which needs root (CAP_SYS_PTRACE): skipped otherwise.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from daemon_util import Daemon, find_estopd, run_estopd

pytestmark = pytest.mark.timeout(120)

# Not bytes(range(32)) as elsewhere: a key that cannot turn up in memory by chance.
KEY = bytes.fromhex("9f3c1a7e5b2d48c6e0a1f7b3d9c5e2a4" "6b8d0f1e3c5a7b9d2f4e6a8c0b1d3e5f")
NOBODY = 65534


def key_file(tmp_path: Path, uid: int | None = None) -> Path:
    path = tmp_path / "key"
    path.write_text(KEY.hex() + "\n")
    path.chmod(0o600)
    if uid is not None:
        os.chown(path, uid, uid)
    return path


def memory(pid: int) -> bytes:
    """Every readable private or anonymous mapping of pid (stack, heap, data, bss)."""
    out = []
    with open(f"/proc/{pid}/maps") as maps, open(f"/proc/{pid}/mem", "rb", 0) as mem:
        for line in maps:
            m = re.match(r"([0-9a-f]+)-([0-9a-f]+) (r...) \S+ \S+ \S+\s*(.*)$", line)
            if m is None or "[vvar" in m[4] or "[vsyscall" in m[4]:
                continue
            start, end = int(m[1], 16), int(m[2], 16)
            try:
                mem.seek(start)
                out.append(mem.read(end - start))
            except OSError:
                continue
    return b"".join(out)


def test_no_copy_of_the_key_stays_in_memory(tmp_path: Path) -> None:
    """Once running, neither the key file's text nor the key's bytes are anywhere in the
    daemon's memory: the buffers that held them were wiped with explicit_bzero (a plain memset
    of a buffer never read again is a dead store the compiler may drop: the hex text stayed on
    the stack)."""
    if os.geteuid() != 0:
        pytest.skip("reading another process's memory needs root")
    with Daemon(tmp_path, "--key-file", str(key_file(tmp_path))) as d:
        assert d.proc is not None
        mem = memory(d.proc.pid)
        assert len(mem) > 100_000 and str(d.argv[-1]).encode() in mem  # argv: the stack is read
        text = KEY.hex().encode()
        assert text not in mem and text.upper() not in mem, "the key file's text is in memory"
        assert KEY not in mem, "the key's bytes are in memory"


def test_a_key_file_of_another_user_is_refused(tmp_path: Path) -> None:
    """A key file owned by neither the daemon's user nor root is refused in one line (exit 1,
    as any key file that cannot be used): someone else could change the key."""
    if os.geteuid() != 0:
        pytest.skip("giving the key file to another user needs root")
    path = key_file(tmp_path, uid=NOBODY)
    res = run_estopd(["--key-file", str(path), "--udp-port", "0", "--tcp-port", "0",
                      "--bind", "127.0.0.1"])
    assert res.returncode == 1, res
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and f"uid {NOBODY}" in lines[0], res.stderr


def as_nobody(argv: list[str]) -> list[str]:
    return ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups",
            "--inh-caps=-all", "--bounding-set=-all", *argv]


def test_the_daemon_is_not_dumpable_and_takes_its_own_users_key(tmp_path: Path) -> None:
    """Run as an unprivileged user with a key file of its own: it starts, and its /proc files
    belong to root (the kernel's sign of PR_SET_DUMPABLE 0): no core dump, and no process of
    the same user can ptrace it or read its memory for the MAC state."""
    if os.geteuid() != 0:
        pytest.skip("switching to another user needs root")
    home = Path(tempfile.mkdtemp(prefix="estopd-key-"))  # /tmp/pytest-of-root is root's alone
    home.chmod(0o755)
    path = key_file(home, uid=NOBODY)
    d = Daemon(tmp_path, "--key-file", str(path))
    d.argv = as_nobody(d.argv)
    with d:
        assert d.proc is not None
        pid = d.proc.pid
        assert Path(f"/proc/{pid}/status").read_text().count(f"\t{NOBODY}\t") >= 1
        assert os.stat(f"/proc/{pid}/mem").st_uid == 0
        assert os.stat(f"/proc/{pid}/environ").st_uid == 0
    shutil.rmtree(home)


def test_help_says_what_mlock_protects() -> None:
    res = subprocess.run([find_estopd(), "--help"], capture_output=True, text=True, timeout=10,
                         check=False)
    assert res.returncode == 0 and "--mlock" in res.stdout and "swap" in res.stdout, res.stdout
