"""Memory soak: estopd's resident set over a long run of mixed traffic must stay flat.

The daemon allocates nothing after start-up, so once its pages are touched its RSS should not
move. This drives it for --seconds through repeated cycles of everything it handles: control
packets at 50 Hz, RELEASE, timeout stops, TCP stops, a burst of invalid UDP, short-lived TCP
clients (STATUS then close), a client with a bad CRC, and one that connects and says nothing.
Every second it samples VmRSS, VmSize and the open file descriptors from /proc.

Output: a table (printed, and bench/out/rss_soak.md), JSON and a PNG of RSS over time.
Goal: RSS after the warm-up grows by at most one page, and no descriptor leaks.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from estop.protocol import tcp
from estop.unit.canlog import DaemonError
from estop.unit.daemon import Daemon, find_estopd
from estop.unit.looplink import Link

OUT = Path(__file__).resolve().parent / "out"
PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024


def proc_sample(pid: int) -> dict[str, int]:
    fields: dict[str, int] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmSize", "VmHWM"):
            fields[key] = int(value.split()[0])
    fields["fds"] = len(os.listdir(f"/proc/{pid}/fd"))
    return fields


def drive(link: Link, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        link.send_control(0.0, 0.1)
        time.sleep(0.02)


def side_clients(tcp_port: int) -> None:
    """A polite client, a client with a bad CRC, and a silent one: all closed again."""
    with socket.create_connection(("127.0.0.1", tcp_port), timeout=2) as polite:
        polite.sendall(tcp.status_request(1).encode())
        polite.recv(16)
    with socket.create_connection(("127.0.0.1", tcp_port), timeout=2) as broken:
        broken.sendall(b"\x00" * 16)
        broken.recv(16)  # the daemon closes it
    with socket.create_connection(("127.0.0.1", tcp_port), timeout=2):
        pass


def one_cycle(link: Link, daemon: Daemon, junk: socket.socket) -> None:
    drive(link, 0.15)
    link.request(tcp.RELEASE)
    drive(link, 0.3)
    time.sleep(0.3)  # finger lifted: timeout stop
    drive(link, 0.15)
    link.request(tcp.RELEASE)
    for _ in range(1000):  # invalid packets, as fast as they go
        junk.sendto(b"\xff" * 7, ("127.0.0.1", daemon.udp_port))
    drive(link, 0.1)
    link.request(tcp.DEFAULT_STOP_ID)
    side_clients(daemon.tcp_port)


def drain(frames: queue.Queue[object]) -> None:
    while True:
        try:
            frames.get_nowait()
        except queue.Empty:
            return


def plot(samples: list[dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot([s["t"] for s in samples], [s["VmRSS"] for s in samples], marker=".")
    ax.set_xlabel("s since start")
    ax.set_ylabel("VmRSS, KiB")
    ax.set_title("estopd resident set under mixed traffic")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


@dataclass
class Soak:
    """What one soak measured: a sample a second, and the growth after the warm-up."""

    samples: list[dict[str, float]]
    cycles: int
    state_changes: int
    warmup: float

    @property
    def settled(self) -> list[dict[str, float]]:
        return [s for s in self.samples if s["t"] >= self.warmup]

    @property
    def rss_growth_kib(self) -> float:
        return self.settled[-1]["VmRSS"] - self.settled[0]["VmRSS"]

    @property
    def fd_growth(self) -> float:
        return self.settled[-1]["fds"] - self.settled[0]["fds"]


def soak(exe: str, seconds: float, warmup: float) -> Soak:
    """Runs estopd for `seconds` of mixed traffic, sampling once a second. Raises DaemonError
    or OSError, or ValueError when the run is too short for the warm-up."""
    samples: list[dict[str, float]] = []
    cycles = 0
    with Daemon([exe]) as daemon:
        assert daemon.pid is not None
        link = Link(daemon.udp_port, daemon.tcp_port)
        junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        start = time.monotonic()
        next_sample = start
        while time.monotonic() - start < seconds:
            one_cycle(link, daemon, junk)
            cycles += 1
            drain(daemon.frames)  # type: ignore[arg-type]
            now = time.monotonic()
            if now >= next_sample:
                samples.append({"t": round(now - start, 2), **proc_sample(daemon.pid)})
                next_sample = now + 1.0
        link.close()
        junk.close()
        # The last sample once the traffic has stopped: a client closed at the end of the
        # last cycle may still hold its descriptor until the daemon reads its end of file.
        time.sleep(0.5)
        samples.append({"t": round(time.monotonic() - start, 2), **proc_sample(daemon.pid)})
        state_changes = sum(" state " in line for line in daemon.log_lines)
    result = Soak(samples, cycles, state_changes, warmup)
    if len(result.settled) < 2:
        raise ValueError("run too short for the warm-up; raise --seconds")
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description="estopd memory soak")
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    args = parser.parse_args()
    exe = find_estopd()
    if exe is None:
        print("rss_soak: error: estopd not found (run make setup)", file=sys.stderr)
        return 1
    OUT.mkdir(exist_ok=True)
    try:
        run = soak(exe, args.seconds, args.warmup)
    except (DaemonError, OSError, ValueError) as exc:
        print(f"rss_soak: error: {exc}", file=sys.stderr)
        return 1
    samples, settled = run.samples, run.settled
    growth, fd_growth = run.rss_growth_kib, run.fd_growth
    ok = growth <= PAGE_KIB and fd_growth <= 0
    lines = [
        "# estopd memory soak",
        "",
        f"{time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}; {args.seconds:.0f} s, "
        f"{run.cycles} traffic cycles ({run.state_changes} state changes logged), "
        f"{len(samples)} samples",
        "",
        "| sample | t (s) | VmRSS KiB | VmHWM KiB | VmSize KiB | fds |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, s in (("first", samples[0]), ("after warm-up", settled[0]), ("last", settled[-1])):
        lines.append(f"| {name} | {s['t']} | {s['VmRSS']} | {s['VmHWM']} | {s['VmSize']} | "
                     f"{s['fds']} |")
    lines += ["", f"RSS growth after warm-up: {growth:+.0f} KiB (goal <= {PAGE_KIB} KiB, one "
              f"page); descriptor growth {fd_growth:+.0f}: {'PASS' if ok else 'FAIL'}"]
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "rss_soak.md").write_text(text)
    (OUT / "rss_soak.json").write_text(json.dumps({"samples": samples, "cycles": run.cycles,
                                                   "state_changes": run.state_changes,
                                                   "rss_growth_kib": growth, "ok": ok}))
    plot(samples, OUT / "rss_soak.png")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
