"""The flood of the stop-latency bench: a child process sending invalid (or forged
authenticated) datagrams at a paced rate for a bounded time, loopback only, and the kernel's
receive drops of the flooded socket (/proc/net/udp).

Run as a script it is that child: ``latency_flood.py PORTS RATE MAX_S [SESSIONS]``."""

from __future__ import annotations

import json
import random
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from estop.protocol import auth, udp
from estop.unit import events
from estop.unit.udpsocket import udp_socket

FLOOD_PAYLOADS = (
    b"\x00" * 7,                                        # wrong length
    b"\x00\x00\xc0\x7f" + b"\x00" * 4 + b"\x08\x00\x00\x00" + b"\x00" * 8,  # gas NaN
    b"\x00" * 8 + b"\x03\x00\x00\x00" + b"\x00" * 8,    # gear 3 unknown
    b"\xff" * 24,                                       # wrong length
)


FORGED_REMOTE_ID = 1  # half the forgeries claim the bench's own remote id


def forged_packets(session: int, n: int = 64) -> list[bytes]:
    """Forged authenticated control packets (spec 5.1) for a unit with ``session``: valid
    bodies, the right session, high counters, but a tag not made with the key, so each one
    costs a keyed unit a BLAKE2s before it is refused. Half claim the bench's remote id."""
    rng = random.Random(session)
    out = []
    for i in range(n):
        body = udp.ControlPacket(round(rng.uniform(-1.0, 1.0), 3),
                                 round(rng.uniform(-1.0, 1.0), 3),
                                 rng.choice((udp.Gear.NEUTRAL, udp.Gear.DRIVE)))
        remote = FORGED_REMOTE_ID if i % 2 == 0 else rng.getrandbits(32)
        signed = auth.AuthControlPacket(remote, session, 2**40 + i, body).encode(None)[:44]
        out.append(signed + rng.randbytes(auth.TAG_SIZE))
    return out


def flood_child(ports: list[int], rate: float, max_s: float,
                sessions: list[int] | None = None) -> int:
    """Send invalid datagrams at ``rate``/s to 127.0.0.1:ports[i] until SIGTERM, end of
    stdin, or max_s: the plain invalid packets of FLOOD_PAYLOADS, or with ``sessions`` (one
    per port) forged authenticated packets for that port's unit. A line on stdin holding an
    index switches the target (the pacing goes on without a burst). At the end print one JSON
    line: per port, packets sent and seconds spent on it."""
    stop = False

    def on_term(_sig: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_term)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    sent = [0] * len(ports)
    busy_s = [0.0] * len(ports)
    errors = 0
    target = 0
    addr = ("127.0.0.1", ports[target])
    pools = ([forged_packets(sess) for sess in sessions] if sessions
             else [list(FLOOD_PAYLOADS)] * len(ports))
    payloads = pools[target]
    batch = 25
    total = 0
    start = time.monotonic()
    since = start
    end = start + max_s
    poller = select.poll()
    poller.register(sys.stdin.fileno(), select.POLLIN)
    while not stop:
        now = time.monotonic()
        if now >= end:
            break
        if poller.poll(0):
            line = sys.stdin.readline()
            if not line:
                break
            busy_s[target] += now - since
            since = now
            target = int(line) % len(ports)
            addr = ("127.0.0.1", ports[target])
            payloads = pools[target]
        due = start + total / rate
        if now < due:
            time.sleep(min(due - now, 0.001))
            continue
        n_pool = len(payloads)
        for i in range(batch):
            try:
                sock.sendto(payloads[(total + i) % n_pool], addr)
                sent[target] += 1
            except (BlockingIOError, ConnectionRefusedError):
                errors += 1
        total += batch
    busy_s[target] += time.monotonic() - since
    sys.stdout.write(json.dumps({"ports": ports, "sent": sent, "seconds": busy_s,
                                 "errors": errors}) + "\n")
    return 0


def udp_drops(port: int) -> int | None:
    """Kernel receive drops of the loopback UDP socket bound to ``port`` (/proc/net/udp)."""
    sock = udp_socket(port)
    return None if sock is None else sock.drops


def start_rcvbuf(log_lines: Sequence[str]) -> int | None:
    """The UDP receive buffer a daemon's start line reports (``udp_rcvbuf``, text or JSON;
    estopd since version 3); None when it reports none (the kernel's default then)."""
    for line in log_lines:
        ev = events.parse(line)
        if ev is not None and ev.kind == "start":
            return ev.integer("udp_rcvbuf")
    return None


def reported_udp_drops(log_lines: Sequence[str]) -> int | None:
    """The kernel drops a daemon reported itself (the ``total`` of its last ``udp_drops``
    event); 0 when it reports its buffer but no drop, None when it reports neither (a daemon
    that does not count them)."""
    total: int | None = 0 if start_rcvbuf(log_lines) is not None else None
    for line in log_lines:
        ev = events.parse(line)
        if ev is not None and ev.kind == "udp_drops" and ev.integer("total") is not None:
            total = ev.integer("total")
    return total


def reported_deadline_cuts(log_lines: Sequence[str]) -> int | None:
    """Drains a silence deadline cut short (``deadline_cuts`` of the daemon's last
    ``udp_reads`` event): each a deadline that came while the daemon read a backlog, acted on
    after one batch instead of the rest of the round. None from a daemon that does not count
    them (estopd before issue 25's follow-up, the baseline)."""
    cuts: int | None = None
    for line in log_lines:
        ev = events.parse(line)
        if ev is not None and ev.kind == "udp_reads" and ev.integer("deadline_cuts") is not None:
            cuts = ev.integer("deadline_cuts")
    return cuts


@dataclass
class FloodStats:
    target_rate: float
    sent: int = 0
    errors: int = 0
    elapsed_s: float = 0.0
    kernel_drops: int | None = None
    forged: bool = False  # forged authenticated packets (--auth), not plain invalid ones

    @property
    def rate(self) -> float:
        return self.sent / self.elapsed_s if self.elapsed_s > 0 else 0.0


class Flood:
    """One flooder child aimed at one of several daemons' UDP ports at a time."""

    def __init__(self, ports: list[int], rate: float, max_s: float,
                 sessions: list[int] | None = None) -> None:
        self.ports = ports
        self.rate = rate
        self.forged = sessions is not None
        self._drops0 = {p: udp_drops(p) for p in ports}
        extra = [",".join(f"{s:x}" for s in sessions)] if sessions is not None else []
        self._proc: subprocess.Popen[str] = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--flood-child",
             ",".join(map(str, ports)), str(rate), str(max_s), *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    @property
    def pid(self) -> int:
        return self._proc.pid

    def aim(self, index: int) -> None:
        """Send the flood to ports[index] from now on."""
        assert self._proc.stdin is not None
        self._proc.stdin.write(f"{index}\n")
        self._proc.stdin.flush()

    def stop(self) -> dict[int, FloodStats]:
        """End the child; per port: packets sent to it over the time it was the target."""
        if self._proc.poll() is None:
            self._proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self._proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            out, _ = self._proc.communicate()
        stats = {p: FloodStats(self.rate, forged=self.forged) for p in self.ports}
        for line in out.splitlines():
            if line.startswith("{"):
                d = json.loads(line)
                for i, p in enumerate(d["ports"]):
                    stats[p].sent, stats[p].elapsed_s = d["sent"][i], d["seconds"][i]
                    stats[p].errors = d["errors"]
        for p, st in stats.items():
            d0, d1 = self._drops0[p], udp_drops(p)
            if d0 is not None and d1 is not None:
                st.kernel_drops = d1 - d0
        return stats


def main(argv: list[str]) -> int:
    """The flood child's command line: ``--flood-child PORTS RATE MAX_S [SESSIONS]`` (ports
    comma-separated, sessions in hex)."""
    if argv[:1] != ["--flood-child"] or len(argv) < 4:
        sys.stderr.write("usage: latency_flood.py --flood-child PORTS RATE MAX_S [SESSIONS]\n")
        return 2
    sessions = [int(x, 16) for x in argv[4].split(",")] if len(argv) > 4 else None
    return flood_child([int(p) for p in argv[1].split(",")], float(argv[2]), float(argv[3]),
                       sessions)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
