"""The load the HIL harness puts on the daemon from processes of its own, and what it watches
of it: the UDP flooder (flood.py) and the daemon's UDP receive queue.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

from hilrig import RigError
from hilstats import udp_socket_drops


class Flooder:
    """``flood.py`` in a process of its own (see there): bursts and floods of invalid UDP."""

    def __init__(self, port: int, rate: float, python: str = sys.executable) -> None:
        script = str(Path(__file__).resolve().parent / "flood.py")
        self.proc = subprocess.Popen([python, "-B", script, str(port), "--rate", str(rate)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     bufsize=1)
        self.t_start = time.time()
        self.t_ready: float | None = None
        self._answers: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, name="flood-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._answers.put(line)

    def _say(self, line: str) -> None:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            raise RigError(f"flooder gone ({exc})") from exc

    def _answer(self, timeout: float) -> dict:
        try:
            rec = json.loads(self._answers.get(timeout=timeout))
        except queue.Empty:
            raise RigError(f"flooder did not answer within {timeout} s "
                           f"(exit code {self.proc.poll()})") from None
        if not isinstance(rec, dict) or "error" in rec:
            raise RigError(f"flooder: {rec}")
        return rec

    def ready(self, timeout: float = 20.0) -> float:
        """Wait for the line the flooder writes once it is up; returns its time."""
        if self.t_ready is None:
            self.t_ready = float(self._answer(timeout)["t"])
        return self.t_ready

    def burst(self, n: int, timeout: float = 10.0) -> dict:
        self._say(f"burst {n}")
        return self._answer(timeout)

    def start(self) -> None:
        self._say("flood")

    def stop(self, timeout: float = 10.0) -> dict:
        self._say("stop")
        return self._answer(timeout)

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self._say("quit")
                self.proc.wait(timeout=3)
            except (RigError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=3)
        self._reader.join(timeout=2)


class QueueWatch:
    """A thread that reads the daemon's UDP receive queue (/proc/net/udp) every ``period`` s:
    how full it got (bytes of the receive buffer in use, the kernel's count)."""

    def __init__(self, port: int, period: float = 0.005) -> None:
        self.port = port
        self.period = period
        self.max_bytes: int | None = None
        self.reads = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="queue-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            got = udp_drops(self.port)
            if got is not None:
                self.reads += 1
                self.max_bytes = max(self.max_bytes or 0, got[0])
            self._stop.wait(self.period)

    def stop(self) -> int | None:
        self._stop.set()
        self._thread.join(timeout=2)
        return self.max_bytes


def udp_drops(port: int) -> tuple[int, int] | None:
    """(rx_queue bytes, kernel drops) of the daemon's UDP socket, from /proc/net/udp (this
    network namespace)."""
    try:
        return udp_socket_drops(Path("/proc/net/udp").read_text(), port)
    except OSError:
        return None
