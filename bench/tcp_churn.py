"""Stop-port churn: a well-behaved client's round trips while connections preloaded with
32 KiB of STATUS requests keep evicting clients (issue 25 item 4).

Two loads, each on a fresh daemon, and with --estopd-before on a daemon of that binary right
after (compare them in one run, under the same load of the machine):

- steady: a churner process opens connection after connection, each preloaded with 32 KiB of
  STATUS requests whose replies it never reads, keeping the newest 32 open;
- bursts: the daemon is stopped (SIGSTOP) while 24 such connections queue in the listen
  backlog and the client's next request waits in its socket, then resumed (a busy daemon
  finds them so); the round trips count from the resume.

The client sends one STATUS at a time on one connection and reads each reply. Reported: its
round trips on an established connection (p50, p99, max; goal p99 <= 20 ms, max <= 50 ms),
how often it was evicted (PROTOCOL.md 2: no rule for whom to close helps; it then connects
anew) and what the first round trip on the new connection took (it waits in the backlog behind
the churn's), beside this machine's timer floor measured in the same run.

Output: a table (printed, and bench/out/tcp_churn.md) and JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from estop.protocol import tcp
from estop.unit.canlog import DaemonError
from estop.unit.daemon import Daemon, find_estopd
from latency_machine import timer_floor
from latency_stats import summarize

OUT = Path(__file__).resolve().parent / "out"
BURST = 24
PRELOAD = tcp.status_request(7).encode() * (32 * 1024 // 16)

# The churner: runs until its stdin closes, then prints how many connections it opened.
_CHURN = """
import collections, socket, sys, threading
port, preload = int(sys.argv[1]), bytes.fromhex(sys.argv[2])
done = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
held, opened = collections.deque(), 0
print("ready", flush=True)
while not done.is_set():
    try:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        s.settimeout(0.5)
        s.connect(("127.0.0.1", port))
        s.setblocking(False)
        try:
            s.send(preload)
        except OSError:
            pass
        held.append(s)
        opened += 1
        while len(held) > 32:
            held.popleft().close()
    except OSError:
        pass
print(opened, flush=True)
"""


class Client:
    """The well-behaved client: one STATUS at a time; connects anew when evicted."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.trips: list[float] = []    # s, on an established connection
        self.fresh: list[float] = []    # s, the first on a new connection
        self.evicted = 0
        self.seq = 0
        self.sock = self._connect()
        self.is_fresh = True

    def _connect(self) -> socket.socket:
        s = socket.create_connection(("127.0.0.1", self.port), timeout=5)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s

    def send(self) -> None:
        self.seq += 1
        try:
            self.sock.sendall(tcp.status_request(self.seq).encode())
        except OSError:
            self._evicted()
            self.sock.sendall(tcp.status_request(self.seq).encode())

    def wait(self, since: float) -> None:
        """Reads the reply to the latest request; its round trip counts from `since`."""
        buf = b""
        try:
            while len(buf) < 16:
                chunk = self.sock.recv(16 - len(buf))
                if not chunk:
                    raise ConnectionError("closed")
                buf += chunk
        except OSError:
            self._evicted()
            return
        (self.fresh if self.is_fresh else self.trips).append(time.perf_counter() - since)
        self.is_fresh = False

    def _evicted(self) -> None:
        self.evicted += 1
        self.sock.close()
        self.sock = self._connect()
        self.is_fresh = True

    def close(self) -> None:
        self.sock.close()


def steady(exe: str, seconds: float) -> Client:
    with Daemon([exe]) as d:
        churn = subprocess.Popen([sys.executable, "-c", _CHURN, str(d.tcp_port), PRELOAD.hex()],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert churn.stdout is not None and churn.stdout.readline() == "ready\n"
            time.sleep(0.3)
            c = Client(d.tcp_port)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                t = time.perf_counter()
                c.send()
                c.wait(t)
            c.close()
            churn.communicate("", timeout=30)
        finally:
            if churn.poll() is None:
                churn.kill()
                churn.wait(timeout=10)
    return c


def bursts(exe: str, n: int) -> Client:
    with Daemon([exe]) as d:
        assert d.pid is not None
        c = Client(d.tcp_port)
        held: list[socket.socket] = []
        try:
            for _ in range(n):
                os.kill(d.pid, signal.SIGSTOP)
                time.sleep(0.01)
                for _ in range(BURST):
                    s = socket.socket()
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
                    s.connect(("127.0.0.1", d.tcp_port))
                    s.setblocking(False)
                    s.send(PRELOAD)
                    held.append(s)
                c.send()
                t = time.perf_counter()
                os.kill(d.pid, signal.SIGCONT)
                c.wait(t)
                end = time.monotonic() + 0.15
                while time.monotonic() < end:
                    t = time.perf_counter()
                    c.send()
                    c.wait(t)
                for s in held[:-2 * BURST]:
                    s.close()
                del held[:-2 * BURST]
        finally:
            os.kill(d.pid, signal.SIGCONT)
            for s in held:
                s.close()
            c.close()
    return c


def row(name: str, label: str, c: Client) -> str:
    t = summarize([x * 1e3 for x in c.trips])
    f = summarize([x * 1e3 for x in c.fresh])
    ok = t["p99"] <= 20.0 and t["max"] <= 50.0
    return (f"| {name} | {label} | {t['n']:.0f} | {t['p50']:.2f} | {t['p99']:.2f} | "
            f"{t['max']:.1f} | {c.evicted} | {f['p50']:.1f} | {f['max']:.1f} | "
            f"{'PASS' if ok else 'FAIL'} |")


def main() -> int:
    parser = argparse.ArgumentParser(description="estopd stop-port churn")
    parser.add_argument("--seconds", type=float, default=5.0, help="steady churn per daemon")
    parser.add_argument("--bursts", type=int, default=20)
    parser.add_argument("--estopd-before", help="a previous estopd binary, run beside")
    args = parser.parse_args()
    exe = find_estopd()
    if exe is None:
        print("tcp_churn: error: estopd not found (run make setup)", file=sys.stderr)
        return 1
    daemons = [("after", exe)] + ([("before", args.estopd_before)] if args.estopd_before else [])
    floor = summarize(timer_floor(200, 0.001))
    lines = ["# estopd stop-port churn", "",
             f"{time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}; load "
             f"{os.getloadavg()[0]:.1f}; timer floor (1 ms sleeps) p50 {floor['p50']:.3f} ms, "
             f"p99 {floor['p99']:.3f} ms, max {floor['max']:.3f} ms", "",
             "| load | daemon | round trips | p50 ms | p99 ms | max ms | evicted | first on a "
             "new connection p50 ms | max ms | goal |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    result: dict[str, dict[str, object]] = {}
    try:
        for load, run, arg in (("steady", steady, args.seconds), ("bursts", bursts, args.bursts)):
            for label, path in daemons:
                c = run(path, arg)  # type: ignore[operator]
                lines.append(row(load, label, c))
                result[f"{load}/{label}"] = {"trips_ms": [x * 1e3 for x in c.trips],
                                             "fresh_ms": [x * 1e3 for x in c.fresh],
                                             "evicted": c.evicted}
    except (DaemonError, OSError) as exc:
        print(f"tcp_churn: error: {exc}", file=sys.stderr)
        return 1
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(exist_ok=True)
    (OUT / "tcp_churn.md").write_text(text)
    (OUT / "tcp_churn.json").write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
