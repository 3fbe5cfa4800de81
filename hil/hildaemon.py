"""The daemon under test as the HIL harness runs it: its process, and its JSON log (stderr)
read by a thread.
"""

from __future__ import annotations

import json
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass
class LogLine:
    t_wall: float  # when the harness read it
    raw: str
    rec: dict | None


class Daemon:
    """The daemon under test, with its JSON log (stderr) read by a thread."""

    def __init__(self, argv: list[str], log_path: Path) -> None:
        self.argv = argv
        self.log_path = log_path
        self.lines: list[LogLine] = []
        self.lock = threading.Lock()
        self._log = open(log_path, "a")  # noqa: SIM115 - closed by the reader thread
        self._log.write(f"# {' '.join(argv)}\n")
        self._log.flush()
        self.t_start = time.time()
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, name="daemon-log", daemon=True)
        self._reader.start()
        self.signal_time: float | None = None
        self.signal_mono: float | None = None  # the daemon's clock (t_mono) at the signal
        self.keyed = "--key-file" in argv  # the unit has a key (spec section 5)
        self.opts: dict[str, str] = {}  # the options a row asked for (Run.want_opts)

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for raw in self.proc.stderr:
            t = time.time()
            line = raw.rstrip("\n")
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict):
                    rec = None
            except ValueError:
                rec = None
            with self.lock:
                self.lines.append(LogLine(t, line, rec))
            self._log.write(f"{t:.6f} {line}\n")
            self._log.flush()
        self._log.close()

    def events(self, name: str | None = None, since: float = 0.0) -> list[dict]:
        with self.lock:
            return [ln.rec for ln in self.lines if ln.rec is not None and ln.t_wall >= since
                    and (name is None or ln.rec.get("event") == name)]

    def non_json(self) -> list[str]:
        with self.lock:
            return [ln.raw for ln in self.lines if ln.rec is None]

    def wait_event(self, pred: Callable[[dict], bool], since: float,
                   timeout: float) -> dict | None:
        end = time.monotonic() + timeout
        while True:
            for rec in self.events(since=since):
                if pred(rec):
                    return rec
            if time.monotonic() >= end:
                return None
            time.sleep(0.005)

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def signal(self, sig: int) -> float:
        t = time.time()
        self.signal_mono = time.monotonic()  # CLOCK_MONOTONIC, as estopd's t_mono
        self.proc.send_signal(sig)
        self.signal_time = t
        return t

    def wait(self, timeout: float) -> int | None:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def kill_hard(self) -> None:
        if self.alive:
            self.proc.kill()
            self.proc.wait(timeout=5)
        self._reader.join(timeout=2)
