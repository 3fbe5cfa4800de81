"""estopd's memory: flat from the start (issue 25 item 7), and with --mlock locked before the key
is read (item 5).

RSS is not a timing: the short soak judges the growth of the resident set over 20 s of the
mixed traffic of bench/rss_soak.py (which runs the same for 120 s: `make bench`).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from daemon_util import find_estopd
from tool_util import load_bench_script

pytestmark = pytest.mark.timeout(120)

KEY_HEX = "9f3c1a7e5b2d48c6e0a1f7b3d9c5e2a46b8d0f1e3c5a7b9d2f4e6a8c0b1d3e5f"


def test_the_resident_set_is_flat_after_the_warm_up() -> None:
    """Growth after a 3 s warm-up at most 4 KiB over 20 s of mixed traffic. Before, the pages
    of the two 64 KiB output rings and of the UDP batch were touched as the lines first wrapped
    round them: +88 KiB over the soak's 120 s, +60 KiB over these 20 s. Now they are touched at
    start."""
    rss_soak = load_bench_script("rss_soak")
    run = rss_soak.soak(find_estopd(), seconds=23.0, warmup=3.0)
    settled = run.settled
    trace = [(s["t"], s["VmRSS"]) for s in settled]
    assert run.rss_growth_kib <= 4, f"VmRSS (KiB) after the warm-up: {trace}"
    assert run.fd_growth <= 0, [(s["t"], s["fds"]) for s in settled]


def test_memory_is_locked_before_the_key_is_read(tmp_path: Path) -> None:
    """With --mlock, mlockall comes before the key file is opened: the key's bytes on the
    stack and the MAC state are never in pages that could have been swapped out. Before, the
    key was loaded first. Traced with strace (system calls in order)."""
    strace = shutil.which("strace")
    if strace is None:
        pytest.fail("strace not found (it is on every new machine: "
                    "../shared/tools/new-machine-debs.txt)")
    key = tmp_path / "key"
    key.write_text(KEY_HEX + "\n")
    key.chmod(0o600)
    trace = tmp_path / "trace"
    proc = subprocess.Popen([strace, "-f", "-qq", "-e", "trace=mlockall,openat", "-o",
                             str(trace), find_estopd(), "--key-file", str(key), "--mlock",
                             "--udp-port", "0", "--tcp-port", "0", "--bind", "127.0.0.1",
                             "--can-log", str(tmp_path / "can.log")],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        deadline = time.monotonic() + 30
        line = ""
        while " start " not in line and time.monotonic() < deadline:
            line = proc.stderr.readline()
            assert line or proc.poll() is None, "estopd exited before its start line"
        assert " start " in line, "no start line"
        # the daemon itself (strace passes no SIGTERM on and would leave it running)
        os.kill(int(line.split(" pid=")[1].split()[0]), signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    calls = [ln for ln in trace.read_text().splitlines()
             if "mlockall(" in ln or str(key) in ln]
    assert len(calls) == 2, calls
    assert "mlockall(" in calls[0] and "= 0" in calls[0], calls
    assert str(key) in calls[1], calls
