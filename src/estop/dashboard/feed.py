"""The inputs of ``estop dashboard``, each delivering to callbacks on the server's event loop:

- a file being written (a can-log of ``estopd --can-log FILE``, estopd's ``--log-json`` log
  redirected to a file), followed as ``tail -f`` does: what is there, then what comes, from
  the start again when the file is truncated or replaced (log rotation);
- a pipe or standard input (``-``): ``candump -L can0 |``, ``journalctl -u estopd -o cat -f |``,
  read on a thread;
- a python-can bus, read on a thread.

A line arrives with the wall-clock time it was read (``time.time()``); a frame from a bus with
its own timestamp. Problems (a file that vanishes, a bus error) go to ``on_note`` as one line;
a feed never raises into the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import stat
import sys
import threading
import time
from collections.abc import Callable
from typing import IO, Any

__all__ = ["BusFeed", "FileFollower", "LineFeed", "StreamFeed", "open_line_feed"]

LineSink = Callable[[str, float], None]
NoteSink = Callable[[str], None]
FOLLOW_POLL_S = 0.01  # a followed file is read this often: 10 ms of the 300 ms budget
CHUNK = 1 << 16


class LineFeed:
    """Common shape of the line inputs: ``start(loop)``, ``close()``."""

    name = ""

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class FileFollower(LineFeed):
    """``tail -f`` of a regular file, as an asyncio task polling every 10 ms."""

    def __init__(self, path: str, on_line: LineSink, on_note: NoteSink) -> None:
        self.name = path
        self.path = path
        self._on_line = on_line
        self._on_note = on_note
        self._task: asyncio.Task[None] | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._task = loop.create_task(self._run())

    def close(self) -> None:
        if self._task is not None:
            self._task.cancel()

    async def _run(self) -> None:
        fh: IO[bytes] | None = None
        buf = b""
        missing_said = False
        try:
            while True:
                if fh is None:
                    try:
                        fh = open(self.path, "rb")  # noqa: SIM115 - kept open while followed
                        buf = b""
                        missing_said = False
                    except OSError as exc:
                        if not missing_said:
                            self._on_note(f"{self.path}: {exc.strerror}; waiting for it")
                            missing_said = True
                        await asyncio.sleep(0.2)
                        continue
                chunk = fh.read(CHUNK)
                if chunk:
                    buf = self._lines(buf + chunk)
                    if len(chunk) == CHUNK:
                        await asyncio.sleep(0)  # a long file: let the page be served
                        continue
                elif self._replaced(fh):
                    fh.close()
                    fh = None
                    continue
                await asyncio.sleep(FOLLOW_POLL_S)
        finally:
            if fh is not None:
                fh.close()

    def _lines(self, data: bytes) -> bytes:
        *done, rest = data.split(b"\n")
        now = time.time()
        for raw in done:
            self._on_line(raw.decode("utf-8", errors="replace"), now)
        if len(rest) > CHUNK:  # a "line" without end: take it as a (bad) line
            self._on_line(rest.decode("utf-8", errors="replace"), now)
            rest = b""
        return rest

    def _replaced(self, fh: IO[bytes]) -> bool:
        """Truncated (shorter than what was read) or another file under the name."""
        try:
            now = os.stat(self.path)
        except OSError:
            return False  # gone for now: keep the old one until a new one appears
        old = os.fstat(fh.fileno())
        return (now.st_ino, now.st_dev) != (old.st_ino, old.st_dev) or now.st_size < fh.tell()


class StreamFeed(LineFeed):
    """Lines of a stream that blocks (standard input, a pipe), read on a thread: select with
    a short timeout, so that :meth:`close` ends the thread (closing a file another thread
    is reading would wait for that read)."""

    def __init__(self, name: str, fd: int, on_line: LineSink, on_note: NoteSink,
                 close_fd: bool) -> None:
        self.name = name
        self._fd = fd
        self._on_line = on_line
        self._on_note = on_note
        self._close_fd = close_fd
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        def deliver(call: Callable[..., None], *args: object) -> None:
            with contextlib.suppress(RuntimeError):  # the loop may be gone at exit
                loop.call_soon_threadsafe(call, *args)

        def read() -> None:
            buf = b""
            while not self._stop.is_set():
                try:
                    ready, _, _ = select.select([self._fd], [], [], 0.2)
                    chunk = os.read(self._fd, CHUNK) if ready else None
                except OSError as exc:
                    deliver(self._on_note, f"{self.name}: {exc.strerror or exc}")
                    return
                if chunk is None:
                    continue
                if not chunk:
                    deliver(self._on_note, f"{self.name}: ended")
                    return
                *done, buf = (buf + chunk).split(b"\n")
                if len(buf) > CHUNK:  # a "line" without end: taken as a (bad) line
                    done.append(buf)
                    buf = b""
                now = time.time()
                for raw in done:
                    deliver(self._on_line, raw.decode("utf-8", errors="replace"), now)

        self._thread = threading.Thread(target=read, name=f"feed {self.name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._close_fd:
            with contextlib.suppress(OSError):
                os.close(self._fd)


def open_line_feed(path: str, on_line: LineSink, on_note: NoteSink) -> LineFeed:
    """``-``: standard input; a regular file (or one not there yet): followed; anything
    else (a named pipe): read as a stream."""
    if path == "-":
        return StreamFeed("standard input", sys.stdin.fileno(), on_line, on_note,
                          close_fd=False)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = stat.S_IFREG
    if stat.S_ISREG(mode):
        return FileFollower(path, on_line, on_note)
    # a named pipe: opened read-write, so that the open does not wait for a writer and the
    # reads do not end when one writer goes (another, a restarted journalctl, may come)
    fd = os.open(path, os.O_RDWR if stat.S_ISFIFO(mode) else os.O_RDONLY)
    return StreamFeed(path, fd, on_line, on_note, close_fd=True)


class BusFeed:
    """Frames from a python-can bus, read on a thread; ``on_frame(t, can_id, data)`` on the
    loop with the frame's own timestamp (the wall clock's when it has none)."""

    def __init__(self, bus: Any, on_frame: Callable[[float, int, bytes], None],
                 on_note: NoteSink) -> None:
        self._bus = bus
        self._on_frame = on_frame
        self._on_note = on_note
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        def read() -> None:
            import can

            while not self._stop.is_set():
                try:
                    msg = self._bus.recv(timeout=0.1)
                except (can.CanError, OSError, ValueError) as exc:
                    with contextlib.suppress(RuntimeError):
                        loop.call_soon_threadsafe(self._on_note, f"reading the bus: {exc}")
                    self._stop.wait(0.5)
                    continue
                if msg is None or msg.is_error_frame or msg.is_remote_frame \
                        or msg.is_extended_id:
                    continue
                t = msg.timestamp or time.time()
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(self._on_frame, t, msg.arbitration_id,
                                              bytes(msg.data))

        self._thread = threading.Thread(target=read, name="feed bus", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._bus.shutdown()

