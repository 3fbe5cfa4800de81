"""Connect storm of the HIL harness: an attacker who holds every place of the stop channel,
from a process of its own (the harness's threads keep the GIL).

    python storm.py PORT [--busy 8] [--busy-ms 4] [--connect-ms 4] [--keep 2] [--nice 10]

The unit keeps 8 connections and, when a new one comes, closes the one quiet longest (no
complete frame for the longest time; docs/PROTOCOL.md section 2). So an attacker

- keeps ``--busy`` connections busy: each sends a STATUS request every ``--busy-ms`` and reads
  its replies;
- and opens a new connection every ``--connect-ms``: a busy one the unit closed, else a fresh
  one (holding the newest ``--keep``, closing the older ones). Each makes the unit close the
  quietest connection: a genuine client that is idle for a few ms is that one, every time.

Once up it writes ``{"ready": true, "t": ...}``; then commands, one per line on standard input,
every answer one JSON line on standard output:

- ``storm``: start; answer ``{"busy": true, "t": ...}`` once every busy connection has had
  a reply (the attacker holds its places), then go on until the next command line;
- ``stop`` (after ``storm``): close everything; answer the counts (connects made and refused,
  STATUS requests sent, replies read, busy connections the unit closed, the span);
- ``quit``: exit.

Times are wall-clock seconds (CLOCK_REALTIME), as the harness's and SocketCAN's.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import socket
import sys
import time
from collections import deque

from estop.protocol import tcp
from helperio import Lines, answer, serve  # this folder (run as a script)

READY_TIMEOUT_S = 5.0  # every busy connection has a reply within this, or the answer says not


class Busy:
    """One busy connection: STATUS every period, replies read and counted."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=1.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.setblocking(False)
        self.seq = 0
        self.replies = 0
        self.due = 0.0
        self._rest = 0  # bytes of a reply read so far (replies are 16 bytes)

    def send(self) -> bool:
        """One STATUS request; False when the unit closed the connection."""
        self.seq += 1
        try:
            self.sock.send(tcp.Request(tcp.STATUS, self.seq).encode())
        except BlockingIOError:
            pass  # the unit reads slower than we send: this one is not sent
        except OSError:
            return False
        return True

    def read(self) -> bool:
        """Read what came; False when the unit closed the connection."""
        try:
            data = self.sock.recv(65536)
        except BlockingIOError:
            return True
        except OSError:
            return False
        if not data:
            return False
        self._rest += len(data)
        self.replies += self._rest // tcp.FRAME_SIZE
        self._rest %= tcp.FRAME_SIZE
        return True

    def close(self) -> None:
        self.sock.close()


def new_connection(port: int) -> socket.socket | None:
    """A connection opened without waiting (on loopback it is up at once or refused)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setblocking(False)
    err = s.connect_ex(("127.0.0.1", port))
    if err not in (0, errno.EINPROGRESS):
        s.close()
        return None
    return s


def storm(args: argparse.Namespace, lines: Lines) -> dict[str, object]:
    """Run until a command line comes. One new connection every ``connect_ms``: a busy one the
    unit closed is opened again first, else a fresh one (so the connects, each of which makes
    the unit close its quietest, come at that rate, not faster: a busy one opened again at
    once would close another busy one, and so on as fast as the CPU goes)."""
    t0 = time.time()
    busy: list[Busy | None] = [Busy(args.port) for _ in range(args.busy)]
    fresh: deque[socket.socket] = deque()
    connects = refused = sent = closed_by_unit = replies_lost = 0
    announced = False
    next_connect = time.monotonic()
    period = args.busy_ms / 1000.0
    for i, b in enumerate(busy):  # spread the busy requests over the period
        assert b is not None
        b.due = time.monotonic() + period * i / len(busy)
    readable: set[socket.socket] = set()
    while True:
        now = time.monotonic()
        for i, b in enumerate(busy):
            if b is None:
                continue
            ok = b.read() if b.sock in readable else True  # no recv() that finds nothing
            if ok and now >= b.due:
                ok = b.send()
                sent += 1
                b.due = max(b.due + period, now)
            if not ok:  # the unit closed it (made room): opened again at the next connect
                closed_by_unit += 1
                replies_lost += b.replies
                b.close()
                busy[i] = None
        if now >= next_connect:
            next_connect = max(next_connect + args.connect_ms / 1000.0, now)
            gone = [i for i, b in enumerate(busy) if b is None]
            if gone:
                try:
                    busy[gone[0]] = Busy(args.port)
                    connects += 1
                except OSError:
                    refused += 1
            else:
                s = new_connection(args.port)
                if s is None:
                    refused += 1
                else:
                    connects += 1
                    fresh.append(s)
                    while len(fresh) > args.keep:
                        fresh.popleft().close()
        held = [b for b in busy if b is not None]
        if not announced and ((len(held) == len(busy) and all(b.replies for b in held))
                              or time.time() - t0 > READY_TIMEOUT_S):
            announced = True
            answer({"busy": len(held) == len(busy) and all(b.replies for b in held),
                    "t": time.time(), "connections": len(held) + len(fresh)})
        if announced and lines.waiting():
            break
        wake = min([b.due for b in held] + [next_connect]) - time.monotonic()
        readable = set(select.select([b.sock for b in held], [], [], max(0.0, wake))[0])
    t1 = time.time()
    replies = replies_lost + sum(b.replies for b in busy if b is not None)
    for b in busy:
        if b is not None:
            b.close()
    for s in fresh:
        s.close()
    return {"t0": t0, "t1": t1, "busy": args.busy, "busy_ms": args.busy_ms,
            "connect_ms": args.connect_ms, "connects": connects, "refused": refused,
            "status_sent": sent, "replies": replies, "busy_closed_by_unit": closed_by_unit}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("port", type=int)
    p.add_argument("--busy", type=int, default=8, help="busy connections (the unit keeps 8)")
    p.add_argument("--busy-ms", type=float, default=4.0, help="STATUS period of each, ms")
    p.add_argument("--connect-ms", type=float, default=4.0, help="a new connection every ... ms")
    p.add_argument("--keep", type=int, default=2, help="new connections held open")
    p.add_argument("--nice", type=int, default=10,
                   help="niceness: on the rig the attacker shares the CPUs with the harness "
                        "and the command under test; a real one would run on its own machine")
    args = p.parse_args(argv)
    os.nice(args.nice)

    def do_storm(_words: list[str], lines: Lines) -> None:
        try:
            res = storm(args, lines)
        except OSError as exc:
            answer({"error": f"storm: {exc}"})
            return
        lines.readline()  # the line that ended the storm ("stop")
        answer(res)

    return serve({"storm": do_storm})


if __name__ == "__main__":
    sys.exit(main())
