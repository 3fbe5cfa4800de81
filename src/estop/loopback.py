"""Runs ``estopd`` on loopback and talks to it: the part shared by ``estop demo`` and the
stop-latency and memory benchmarks in ``bench/``.

:class:`Daemon` starts the binary with free loopback ports and reads its can-log (stdout) and
its log (stderr) on threads; :class:`Link` is the remote's side (UDP control packets, one TCP
connection for requests; with a key, the authenticated packets and frames of spec section 5).

A tool that times frames from the can-log must not mistake a lost line for a late frame:
estopd drops can-log lines when its reader is slow (``output_dropped`` in its event log). Every
line read passes :class:`CanLogLoss` (alive counters) and every ``output_dropped`` report is
kept; :meth:`Daemon.lines_lost` says whether lines may be missing from a stretch of time.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from estop.protocol import auth, can, canlog, tcp, udp

__all__ = [
    "DROP_REPORT_REACH_S",
    "CanLogLoss",
    "Daemon",
    "DaemonError",
    "Gap",
    "Link",
    "OutputDropped",
    "drop_windows",
    "find_estopd",
    "is_stop_frame",
    "parse_output_dropped",
    "parse_start_ports",
    "parse_start_session",
    "set_realtime",
    "stamp",
]


# --------------------------------------------------------------------------------------------
# Reading the daemon's output


def stamp(rec: canlog.CanLogRecord) -> float:
    """A can-log record's realtime stamp in seconds (comparable with time.time())."""
    return rec.timestamp_us / 1_000_000


def is_stop_frame(rec: canlog.CanLogRecord) -> bool:
    """An ESTOP_BRAKE frame that requests the brake."""
    return rec.can_id == can.BRAKE_ID and len(rec.data) == can.DLC and rec.data[0] == 1


_PORT_RE = {
    kind: re.compile(kind + r"[A-Za-z_]*\"?\s*[=:]\s*\"?(?:[0-9A-Za-z.\[\]:]*:)?(\d{1,5})\b")
    for kind in ("udp", "tcp")
}


def parse_start_ports(line: str) -> tuple[int, int] | None:
    """(udp_port, tcp_port) from a daemon's ``start`` log line, text or JSON; else None.

    Accepts ``udp=5700``, ``udp_port=5700``, ``udp=127.0.0.1:5700``, ``"udp_port": 5700`` ...
    """
    if not re.search(r"\bstart\b", line):
        return None
    found = []
    for kind in ("udp", "tcp"):
        m = _PORT_RE[kind].search(line)
        if m is None:
            return None
        found.append(int(m.group(1)))
    return found[0], found[1]


def parse_start_session(line: str) -> int | None:
    """The unit's session from a ``start`` line (``session=0x...``, text or JSON); else None."""
    m = re.search(r"\bsession\"?\s*[=:]\s*\"?0x([0-9A-Fa-f]{1,16})\b", line)
    return int(m.group(1), 16) if m else None


# --------------------------------------------------------------------------------------------
# Lines missing from the can-log


@dataclass(frozen=True, slots=True)
class Gap:
    """Frames of one CAN ID missing from the can-log, found by the alive counter of the frame
    logged after them: their stamps lie between ``after`` and ``before`` (realtime seconds)."""

    can_id: int
    after: float  # stamp of the last frame of this ID before the gap
    before: float  # stamp of the frame whose counter showed it
    lost: int  # frames missing, modulo 15 (a repeated counter counts as 14)


class CanLogLoss:
    """Follows the alive counters of ESTOP_BRAKE and ESTOP_STATUS (0..14, wrapping) in a
    can-log, line by line, and keeps every gap.

    The counters see a loss at the next frame of the same ID; they cannot see exactly 15 (or
    30, ...) lost frames of one ID, which is why the daemon's own count is needed as well.
    """

    IDS = (can.BRAKE_ID, can.STATUS_ID)

    def __init__(self) -> None:
        self._ctr = {i: can.CounterChecker() for i in self.IDS}
        self._last: dict[int, float] = {}
        self.gaps: list[Gap] = []
        self.frames = 0

    @property
    def lines_lost(self) -> int:
        """Frames the counters found missing so far (a lower bound, see above)."""
        return sum(g.lost for g in self.gaps)

    def take(self, rec: canlog.CanLogRecord) -> Gap | None:
        """Follow one logged frame; the gap it shows, if any."""
        checker = self._ctr.get(rec.can_id)
        if checker is None or len(rec.data) != can.DLC or rec.data[6] & 0xF0:
            return None
        self.frames += 1
        t = stamp(rec)
        prev = self._last.get(rec.can_id)
        status = checker.check(rec.data[6] & 0x0F)
        if status.result is can.CounterResult.INVALID:
            return None
        self._last[rec.can_id] = t
        gap = None
        if status.result is can.CounterResult.JUMP:
            gap = Gap(rec.can_id, -math.inf if prev is None else prev, t, status.lost)
        elif status.result is can.CounterResult.REPEAT:
            gap = Gap(rec.can_id, -math.inf if prev is None else prev, t, can.COUNTER_MODULO - 1)
        if gap is not None:
            self.gaps.append(gap)
        return gap

    def lost_between(self, t0: float, t1: float) -> int:
        """Frames missing with stamps that may lie in [t0, t1] (realtime seconds)."""
        return sum(g.lost for g in self.gaps if g.after < t1 and g.before > t0)

    def seen_after(self, t: float) -> bool:
        """Both IDs have been logged after ``t``: a gap around ``t`` would have shown."""
        return all(self._last.get(i, -math.inf) > t for i in self.IDS)


@dataclass(frozen=True, slots=True)
class OutputDropped:
    """One ``output_dropped`` event of estopd's log: ``dropped`` lines of ``stream`` lost since
    the previous report, ``total`` since start; ``t_mono`` is the daemon's CLOCK_MONOTONIC in
    seconds (the clock of Python's time.monotonic() on Linux)."""

    t_mono: float
    stream: str
    dropped: int
    total: int
    err: str


_TEXT_DROPPED = re.compile(
    r"^\S+\s+(?P<t>\d+(?:\.\d+)?)\s+output_dropped\b(?P<kv>.*)$")


def parse_output_dropped(line: str) -> OutputDropped | None:
    """An ``output_dropped`` event from one event-log line (text or ``--log-json``); else None."""
    text = line.strip()
    if "output_dropped" not in text:
        return None
    fields: dict[str, object]
    if text.startswith("{"):
        try:
            fields = json.loads(text)
        except ValueError:
            return None
        if not isinstance(fields, dict) or fields.get("event") != "output_dropped":
            return None
    else:
        m = _TEXT_DROPPED.match(text)
        if m is None:
            return None
        fields = {"t_mono": m["t"]}
        for kv in m["kv"].split():
            k, _, v = kv.partition("=")
            fields[k] = v
    try:
        return OutputDropped(float(str(fields["t_mono"])), str(fields["stream"]),
                             int(str(fields["dropped"])), int(str(fields["total"])),
                             str(fields.get("err", "")))
    except (KeyError, ValueError):
        return None


DROP_REPORT_REACH_S = 2.0
"""How far back an ``output_dropped`` report reaches. estopd reports lost lines at most once a
second (and at exit), from a loop that wakes at least every brake period (10 ms): the lines of
a report were dropped less than about 1 s before it. 2 s leaves room for a loop held up."""


def drop_windows(reports: Iterable[OutputDropped], stream: str = "can_log", *,
                 reach_s: float = DROP_REPORT_REACH_S) -> list[tuple[float, float, int]]:
    """(from, to, lines): daemon-monotonic stretches in which the daemon dropped lines of
    ``stream``, from its reports in order. A report whose ``total`` shows that an earlier
    report is missing (the event log lost lines too) reaches back to the report before it.
    Reports of the event log's own losses (stream ``log``) may hide a ``stream`` report: each
    counts as a window twice as long."""
    out: list[tuple[float, float, int]] = []
    prev_t = -math.inf
    prev_total = 0
    for r in reports:
        if r.dropped <= 0:
            continue
        if r.stream == stream:
            missing = r.total - prev_total > r.dropped
            lo = prev_t if missing else max(prev_t, r.t_mono - reach_s)
            out.append((lo, r.t_mono, r.total - prev_total if missing else r.dropped))
            prev_t, prev_total = r.t_mono, r.total
        elif r.stream == "log" and stream != "log":
            out.append((r.t_mono - 2.0 * reach_s, r.t_mono, r.dropped))
    return out


def set_realtime(prio: int, tid: int = 0) -> None:
    """SCHED_FIFO ``prio`` for one thread (``tid`` 0: the calling one), with
    SCHED_RESET_ON_FORK so that processes started from it run at normal priority. 0 puts it
    back to normal. Raises OSError (EPERM without CAP_SYS_NICE or RLIMIT_RTPRIO)."""
    if prio > 0:
        os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(prio))
    else:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


# --------------------------------------------------------------------------------------------
# Finding and running the daemon


class DaemonError(RuntimeError):
    """The daemon could not be found, started, or it died. ``str()`` is one line."""


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
            if not self._started.is_set():
                ports = parse_start_ports(line)
                if ports is not None:
                    self.udp_port, self.tcp_port = ports
                    self.session = parse_start_session(line)
                    self._started.set()
                    continue
            dropped = parse_output_dropped(line)
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


# --------------------------------------------------------------------------------------------
# The remote's side: UDP control packets and the TCP stop channel


class Link:
    """Raw sockets to a daemon on loopback; every send returns time.time() just before it.

    Without a key: 20-byte control packets and 16-byte request frames. With ``key``: the
    60-byte authenticated control packets and 48-byte request frames of spec section 5, under
    ``remote_id``, with one counter that rises with every message; the session is learnt with
    a STATUS request at once, and every reply's tag is verified (a reply that fails raises
    :class:`DaemonError`).
    """

    def __init__(self, udp_port: int, tcp_port: int, host: str = "127.0.0.1",
                 reply_timeout_s: float = 2.0, *, key: bytes | None = None,
                 remote_id: int = 1) -> None:
        self.addr = (host, udp_port)
        self.key = None if key is None else auth.check_key(key)
        self.remote_id = remote_id
        self.session = 0
        self.counter = 0
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.tcp = socket.create_connection((host, tcp_port), timeout=reply_timeout_s)
        except OSError:
            self.udp.close()
            raise
        self.tcp.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._asm = tcp.FrameAssembler(auth.REPLY_SIZE if self.key else tcp.FRAME_SIZE)
        self._seq = 0
        self._packets: dict[tuple[float, float, int], bytes] = {}
        self._tags: dict[int, bytes] = {}
        self.recording: list[bytes] | None = None  # a list here collects every datagram sent
        if self.key is not None:
            try:
                self.request(tcp.STATUS)  # the reply carries the session
            except BaseException:
                self.close()
                raise

    def _next_counter(self) -> int:
        self.counter += 1
        return self.counter

    def send_control(self, gas: float = 0.0, steering: float = 0.0,
                     gear: int = udp.Gear.NEUTRAL) -> float:
        if self.key is not None:
            body = udp.ControlPacket(gas, steering, gear)
            data = auth.AuthControlPacket(self.remote_id, self.session, self._next_counter(),
                                          body).encode(self.key)
        else:
            key = (gas, steering, gear)
            cached = self._packets.get(key)
            if cached is None:
                cached = udp.ControlPacket(gas, steering, gear).encode()
                if len(self._packets) < 256:
                    self._packets[key] = cached
            data = cached
        t = time.time()
        self.udp.sendto(data, self.addr)
        if self.recording is not None:
            self.recording.append(data)
        return t

    def send_request(self, msg_id: int) -> tuple[int, float]:
        """Send one request; return (seq, time just before sending)."""
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        if self.key is not None:
            data = auth.AuthRequest(msg_id, self._seq, self.remote_id, self.session,
                                    self._next_counter()).encode(self.key)
            self._tags[self._seq] = auth.request_tag(data)
        else:
            data = tcp.Request(msg_id, self._seq).encode()
        t = time.time()
        self.tcp.sendall(data)
        return self._seq, t

    def _decode(self, frame: bytes) -> tcp.Reply:
        if self.key is None:
            return tcp.Reply.decode(frame)
        seq = int.from_bytes(frame[8:12], "little")
        tag = self._tags.pop(seq, None)
        if tag is None:
            raise DaemonError(f"a reply to seq {seq}, which was never asked")
        try:
            reply = auth.AuthReply.decode(frame, self.key, tag)
        except auth.TagMismatch as exc:
            raise DaemonError(f"the daemon's reply did not verify: {exc}") from None
        self.session = reply.session  # a verified reply: the unit's session (new after a restart)
        return reply.reply

    def read_reply(self, seq: int) -> tcp.Reply:
        while True:
            for frame in self._asm.feed(b""):
                reply = self._decode(frame)
                if reply.seq == seq:
                    return reply
            chunk = self.tcp.recv(4096)
            if not chunk:
                raise DaemonError("the daemon closed the TCP connection")
            for frame in self._asm.feed(chunk):
                reply = self._decode(frame)
                if reply.seq == seq:
                    return reply

    def request(self, msg_id: int) -> tuple[tcp.Reply, float]:
        seq, t = self.send_request(msg_id)
        return self.read_reply(seq), t

    def close(self) -> None:
        self.udp.close()
        self.tcp.close()
