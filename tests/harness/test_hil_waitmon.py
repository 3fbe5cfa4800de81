"""hil/mon's waitmon on this kernel's real scheduler: it writes the time a thread waited on a
run queue (not its run time), and nothing for a thread that sleeps (a daemon that blocks is
still judged); the StallMonitor counts those waits with the CPU stalls; stallmon writes a stall
as short as the judges count. The monitors are built first, as hil/run does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import hilstalls
from hilrig import MON_BIN, StallMonitor
from hilstalls import overlap


@pytest.fixture(scope="module", autouse=True)
def monitors() -> None:
    subprocess.run(["make", "-s", "-C", str(MON_BIN.parent)], check=True, timeout=120)

# Spins, and ends by itself after 30 s should the test be killed before its clean-up.
SPIN = "import time\nend = time.monotonic() + 30\nwhile time.monotonic() < end: pass"
WATCH_S = 1.5


def _pinned(cpu: int, nice: int, code: str, stdout: int | None = None,
            ) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-c", code], stdout=stdout, preexec_fn=lambda: (
        os.sched_setaffinity(0, {cpu}), os.nice(nice)))


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for p in started:  # all killed first: each one's exit needs its turn on the CPU
        p.kill()
    for p in started:
        p.wait(timeout=5)


def _watch(tmp_path: Path, pid: int, first_pid: int | None = None) -> list[tuple[float, float]]:
    """The waits StallMonitor's waitmon wrote for ``pid`` over WATCH_S, every one of them
    among the monitor's intervals. ``first_pid``: the pidfile names it first (gone), then
    ``pid``, as at a daemon's restart."""
    pidfile = tmp_path / "daemon.pid"
    pidfile.write_text(f"{first_pid if first_pid is not None else pid}\n")
    mon = StallMonitor(tmp_path, pidfile, work=tmp_path / "work")
    try:
        if first_pid is not None:
            time.sleep(0.2)
            pidfile.write_text(f"{pid}\n")
        time.sleep(WATCH_S)
        waits = list(mon.waits())
        union = mon.intervals()
    finally:
        mon.stop()
    assert mon.wait_path is not None and mon.wait_path.read_text().startswith("# waits rt ")
    assert (tmp_path / "daemon-waits.txt").read_text() == mon.wait_path.read_text()  # copied
    for a, b in waits:
        assert overlap(union, a, b) == pytest.approx(b - a)
    return waits


def _total(waits: list[tuple[float, float]]) -> float:
    return sum(b - a for a, b in waits)


def test_a_thread_held_back_by_another_on_its_cpu_has_its_waits_written(
        tmp_path: Path, procs: list[subprocess.Popen[bytes]]) -> None:
    # At nice 5 beside a spinner at 0 on its CPU (one session: nice weighs between them) the
    # target runs a quarter of the time at most and waits the rest (the kernel adds each wait
    # when it ends, at the target's next turn): a monitor that wrote its run time instead
    # would write less than half.
    procs.append(_pinned(0, 0, SPIN))
    procs.append(target := _pinned(0, 5, SPIN))
    gone = subprocess.Popen(["true"])
    gone.wait()
    waits = _watch(tmp_path, target.pid, first_pid=gone.pid)
    assert _total(waits) > 0.5 * WATCH_S, waits


def test_a_sleeping_thread_writes_no_waits(tmp_path: Path,
                                           procs: list[subprocess.Popen[bytes]]) -> None:
    procs.append(_pinned(0, 0, SPIN))
    procs.append(target := _pinned(0, 0, "import time; print('up', flush=True); "
                                           "time.sleep(60)", stdout=subprocess.PIPE))
    assert target.stdout is not None and target.stdout.readline() == b"up\n"  # asleep now
    assert _total(_watch(tmp_path, target.pid)) < 0.05


def test_the_stall_monitor_records_a_stall_of_a_few_ms(tmp_path: Path) -> None:
    # Held 4 ms at a time (SIGSTOP, then SIGCONT): each hold is a stall of 2 ms or more beyond
    # its 2-ms period, which the judges count (STALL_EXCUSE_S), so each must be written. Until
    # 2026-12-03 it wrote only stalls of more than 4 ms beyond, and none of these.
    out = tmp_path / "stalls.txt"
    p = subprocess.Popen([str(MON_BIN / "stallmon"), "1", str(out)])
    try:
        end = time.monotonic() + 10
        while not out.exists() or not out.read_text().startswith("# cpu 1 "):
            assert time.monotonic() < end, "stallmon wrote no header"
            time.sleep(0.01)
        time.sleep(0.1)
        holds = []
        for _ in range(6):
            t0 = time.time()
            os.kill(p.pid, signal.SIGSTOP)
            time.sleep(0.004)
            os.kill(p.pid, signal.SIGCONT)
            holds.append((t0, time.time()))
            time.sleep(0.05)
    finally:
        p.terminate()
        p.wait(timeout=5)
    stalls = hilstalls.read_stalls(out.read_text().splitlines())
    seen = [h for h in holds if hilstalls.overlap(stalls, h[0], h[1] + 0.004) > 0]
    assert len(seen) >= 5, (holds, stalls)
