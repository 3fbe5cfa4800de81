"""Runs ``estopd`` on loopback and talks to it: the part shared by ``estop demo`` and the
stop-latency and memory benchmarks in ``bench/``.

:class:`Daemon` starts the binary with free loopback ports and reads its can-log (stdout) and
its log (stderr) on threads, through :mod:`estop.unit.canlog` (the start line, lost can-log
lines, ``output_dropped`` reports); :class:`~estop.unit.looplink.Link` is the remote's side (UDP
control packets, and the TCP stop channel of :class:`estop.client.channel.StopChannel`).
"""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO

from estop.protocol import canlog
from estop.unit import events
from estop.unit.canlog import CanLogLoss, DaemonError, drop_windows
from estop.unit.events import OutputDropped

__all__ = ["Daemon", "find_estopd", "set_realtime"]


def set_realtime(prio: int, tid: int = 0) -> None:
    """SCHED_FIFO ``prio`` for one thread (``tid`` 0: the calling one), with
    SCHED_RESET_ON_FORK so that processes started from it run at normal priority. 0 puts it
    back to normal. Raises OSError (EPERM without CAP_SYS_NICE or RLIMIT_RTPRIO)."""
    if prio > 0:
        os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(prio))
    else:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))



def find_estopd(explicit: str | None = None) -> str | None:
    """Path of the estopd binary: ``explicit``, $ESTOPD, beside this Python (the venv's bin),
    on PATH, or the repo's firmware/build/estopd. None when there is none."""
    candidates: list[Path] = []
    for given in (explicit, os.environ.get("ESTOPD")):
        if given:
            return given if Path(given).is_file() or shutil.which(given) else None
    candidates.append(Path(sys.executable).parent / "estopd")
    on_path = shutil.which("estopd")
    if on_path:
        candidates.append(Path(on_path))
    candidates.append(Path(__file__).resolve().parents[2] / "firmware" / "build" / "estopd")
    for cand in candidates:
        if cand.is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


class Daemon:
    """An estopd-compatible daemon on loopback with free ports and its can-log on a pipe.

    ``command`` is the program (and any leading arguments, e.g. ``[python, baseline.py]``).
    Every can-log line arrives as a :class:`canlog.CanLogRecord` on :attr:`frames`, after it
    has passed :attr:`loss` (the alive counters); stderr lines are kept in :attr:`log_lines`,
    ``output_dropped`` events in :attr:`drop_reports`. ``reader_rt_prio`` > 0 runs both reader
    threads under SCHED_FIFO at that priority (so they keep up with a real-time daemon on a
    busy machine). Use as a context manager: the process is always ended. The unit has the
    key in ``key_file``, or none (``--no-auth``).
    """

    def __init__(self, command: Sequence[str], *, timeout_ms: int = 200,
                 extra_args: Sequence[str] = (), key_file: str | None = None,
                 reader_rt_prio: int = 0, tee: Callable[[str, str], None] | None = None) -> None:
        auth_args = ["--key-file", key_file] if key_file is not None else ["--no-auth"]
        self.argv = [*command, "--bind", "127.0.0.1", "--udp-port", "0", "--tcp-port", "0",
                     "--timeout-ms", str(timeout_ms), "--can-log", "-", *auth_args,
                     *extra_args]
        self.timeout_ms = timeout_ms
        self.reader_rt_prio = reader_rt_prio
        self.tee = tee  # also given every line: ("can_log", line) and ("log", line)
        self.frames: queue.Queue[canlog.CanLogRecord] = queue.Queue()
        self.log_lines: list[str] = []
        self.loss = CanLogLoss()
        self.drop_reports: list[OutputDropped] = []
        self.udp_port = 0
        self.tcp_port = 0
        self.session: int | None = None  # from the start line, where the daemon prints it
        self.returncode: int | None = None
        self.bad_lines = 0
        self._proc: subprocess.Popen[str] | None = None
        self._started = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc else None

    def start(self, wait_s: float = 10.0) -> None:
        try:
            self._proc = subprocess.Popen(
                self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE, text=True, bufsize=1)
        except OSError as exc:
            raise DaemonError(f"cannot run {self.argv[0]}: {exc.strerror}") from exc
        assert self._proc.stdout is not None and self._proc.stderr is not None
        for target, stream in ((self._read_frames, self._proc.stdout),
                               (self._read_log, self._proc.stderr)):
            th = threading.Thread(target=target, args=(stream,), daemon=True)
            th.start()
            self._threads.append(th)
            if self.reader_rt_prio > 0 and th.native_id is not None:
                try:
                    set_realtime(self.reader_rt_prio, th.native_id)
                except OSError as exc:
                    self.stop()
                    raise DaemonError(f"cannot run the can-log reader at real-time priority "
                                      f"{self.reader_rt_prio}: {exc.strerror}") from exc
        deadline = time.monotonic() + wait_s
        while not self._started.wait(0.05):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                last = self.log_lines[-1] if self.log_lines else "no output"
                raise DaemonError(f"{Path(self.argv[0]).name} did not start ({last})")

    def _read_frames(self, stream: IO[str]) -> None:
        for line in stream:
            if self.tee is not None:
                self.tee("can_log", line)
            try:
                rec = canlog.parse_line(line)
            except canlog.CanLogError:
                self.bad_lines += 1
                continue
            self.loss.take(rec)
            self.frames.put(rec)

    def _read_log(self, stream: IO[str]) -> None:
        for line in stream:
            if self.tee is not None:
                self.tee("log", line)
            self.log_lines.append(line.rstrip("\n"))
            ev = events.parse(line)
            began = events.start(ev)
            if began is not None and not self._started.is_set():
                self.udp_port, self.tcp_port = began.udp_port, began.tcp_port
                self.session = began.session or None
                self._started.set()
                continue
            dropped = events.output_dropped(ev)
            if dropped is not None:
                self.drop_reports.append(dropped)

    @property
    def dropped_total(self) -> int:
        """Can-log lines the daemon reported dropped so far (its ``total``)."""
        return max((r.total for r in self.drop_reports if r.stream == "can_log"), default=0)

    def lines_lost(self, real: tuple[float, float], mono: tuple[float, float]) -> int:
        """Can-log lines that may be missing from a stretch of time, given in realtime
        (can-log stamps, time.time()) and in monotonic time (time.monotonic()): frames the
        alive counters found missing between the stamps, plus the lines of every daemon report
        whose window meets the monotonic stretch. 0: nothing known to be missing. Reports come
        up to a second late, the counters at the next frame of an ID: ask again later (after
        :meth:`stop` everything is in) for a final answer."""
        n = self.loss.lost_between(real[0], real[1])
        for lo, hi, lines in drop_windows(self.drop_reports):
            if lo < mono[1] and hi > mono[0]:
                n += lines
        return n

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, wait_s: float = 3.0) -> int | None:
        """SIGTERM, wait (SIGKILL if it hangs), collect the output; return the exit code."""
        proc = self._proc
        if proc is None:
            return None
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(wait_s)
        for th in self._threads:
            th.join(wait_s)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
        self.returncode = proc.returncode
        return self.returncode

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
