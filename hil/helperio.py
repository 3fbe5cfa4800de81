"""The command loop of the harness's helper scripts (flood.py, storm.py), each run in a
process of its own by ``hilload.Helper``: commands one per line on standard input, every
answer one JSON line on standard output. Run as scripts from this folder, they import it as
a plain module."""

from __future__ import annotations

import json
import os
import select
import sys
import time
from collections.abc import Callable

__all__ = ["Lines", "answer", "serve"]


class Lines:
    """Command lines from a file descriptor, unbuffered beyond what was read (so that
    :meth:`waiting` can ask the kernel whether another line has come)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buf = b""
        self.eof = False

    def waiting(self) -> bool:
        return b"\n" in self.buf or self.eof or bool(select.select([self.fd], [], [], 0)[0])

    def readline(self) -> str | None:
        while b"\n" not in self.buf:
            chunk = os.read(self.fd, 4096)
            if not chunk:
                self.eof = True
                rest, self.buf = self.buf, b""
                return rest.decode(errors="replace") if rest else None
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode(errors="replace")


def answer(obj: dict[str, object]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# A command: its words after the name, and the command lines (to watch for the next one).
Command = Callable[[list[str], Lines], None]


def serve(commands: dict[str, Command]) -> int:
    """Say ``{"ready": true, ...}``, then run commands until ``quit`` or the end of the input.
    ``ready?`` asks again; a command that is not known, or whose words are wrong (ValueError),
    gets ``{"error": ...}``."""
    def ready() -> None:
        answer({"ready": True, "pid": os.getpid(), "t": time.time()})

    ready()
    lines = Lines(sys.stdin.fileno())
    while (line := lines.readline()) is not None:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "quit":
            break
        if cmd[0] == "ready?":
            ready()
            continue
        run = commands.get(cmd[0])
        try:
            if run is None:
                raise ValueError("unknown command")
            run(cmd[1:], lines)
        except ValueError as exc:
            answer({"error": f"{line.strip()!r}: {exc}"})
    return 0
