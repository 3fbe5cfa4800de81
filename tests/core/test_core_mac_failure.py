"""The core checks what estop_b2s_mac returns (issue 16, defect 9): a MAC that fails means
"not authentic", and a reply whose tag could not be made carries a zero tag. The C program
tests/c/mac_failure.c breaks the core's MAC state and runs under valgrind's memcheck, so a tag
that was never written cannot pass by chance: comparing it is an error of its own
(MemorySanitizer would miss it: its shadow arithmetic loses the carry in estop_ct_equal's
constant-time fold)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from repo import ROOT

CORE = ROOT / "firmware" / "core"

pytestmark = pytest.mark.timeout(180)


def test_a_failing_mac_is_not_authentic_and_tags_no_reply(tmp_path: Path) -> None:
    cc = shutil.which("gcc")
    valgrind = shutil.which("valgrind")
    if cc is None or valgrind is None:
        pytest.fail("gcc or valgrind is missing: scripts/ensure-debs build check "
                    "(deps/debian-packages.txt)")
    exe = tmp_path / "mac_failure"
    subprocess.run([cc, "-std=c99", "-g", "-O2", "-Wall", "-Wextra", "-Werror", f"-I{CORE}",
                    str(ROOT / "tests" / "c" / "mac_failure.c"),
                    *map(str, sorted(CORE.glob("estop_*.c"))), "-o", str(exe)],
                   check=True, timeout=120)
    res = subprocess.run([valgrind, "-q", "--error-exitcode=99", str(exe)],
                         capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.strip() == "all mac failure checks passed"


def test_the_same_through_the_binding() -> None:
    """The same checks on the module the other tests use (and that make coverage measures):
    with the MAC state broken, a rightly tagged packet is not valid, and a reply's tag is
    zero (the previous reply's tag bytes are still in the output buffer)."""
    from estop.core import Config, Watchdog
    from estop.protocol import auth
    from estop.protocol.udp import ControlPacket

    key, session = bytes(range(32)), 0x0123456789ABCDEF
    wd = Watchdog(Config(key=key, session=session))
    wd.tcp_open(0, 1000)
    first = wd.tcp_data(0, auth.AuthRequest(1, 1, 7, session, 1).encode(key), 2000)
    assert first[-1].reply is not None and first[-1].reply[32:] != bytes(16)
    wd._core.mac.outlen = 0  # every MAC fails from here on
    wd.udp(auth.AuthControlPacket(7, session, 1, ControlPacket()).encode(key), 3000)
    c = wd.status().counters
    assert (c.udp_valid, c.auth_bad_tag) == (0, 1)
    steps = wd.tcp_data(0, auth.AuthRequest(1, 2, 7, session, 2).encode(key), 4000)
    assert steps[-1].reply is not None and steps[-1].reply[32:] == bytes(16)
