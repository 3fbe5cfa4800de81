"""``estop demo``: a scripted drive against a real ``estopd`` on loopback (no root, no CAN).

The demo makes a fresh key, starts ``estopd`` with it (free loopback ports, CAN frames logged to
a pipe), and plays two parts: the operator's remote, which holds the key, and an attacker on
the same network, which does not but has recorded the operator's traffic. The story: release,
drive; the finger lifts while the attacker sends plain heartbeats, heartbeats under a wrong key
and replays of the recording, and the unit stops at the deadline all the same; the attacker's
forged RELEASE gets NAK 4; the operator releases and drives; the attacker's stop datagram (a
garbage tag) stops the car, because anyone may stop; the operator releases, drives and presses
the stop button. A live line shows what the brake frames on the (logged) bus say; the end
prints a timeline and the measured stop latencies, taken from the daemon's own can-log
timestamps against the send times (both CLOCK_REALTIME):

- timeout overshoot = first stop frame - (last valid packet sent + timeout)
- stop latency      = first stop frame - STOP (or stop datagram) sent

A figure is only given when no can-log line went missing between the send and the stop frame
(alive counters, and the daemon's own ``output_dropped`` count, checked once it has exited):
a lost first stop frame would make the next one look like a late stop. Otherwise the report
says how many lines were lost instead of a figure.

The daemon runner lives in :mod:`estop.loopback`, shared with the benchmarks.
"""

from __future__ import annotations

import argparse
import math
import os
import queue
import secrets
import shutil
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

from estop.cliutil import EXIT_USAGE, ErrorOnlyParser
from estop.loopback import Daemon, DaemonError, Link, find_estopd, stamp
from estop.protocol import auth, can, canlog, tcp, udp

__all__ = ["find_estopd", "main"]


# --------------------------------------------------------------------------------------------
# The demo itself

Packet = tuple[float, float, int]  # gas_brake, steering, gear


@dataclass
class Stop:
    """A brake frame that started a stop: its realtime stamp and its decoded fields."""

    t: float
    frame: can.BrakeFrame


@dataclass
class View:
    """What the logged bus says, checked frame by frame, and how it is shown."""

    out: TextIO
    live: bool
    t0: float
    phase: str = "boot"
    remote: str = "silent"
    brake: can.BrakeFrame | None = None
    link_age_ms: int | None = None
    auth_failures: int = 0  # ESTOP_STATUS byte 2, the latest window
    frames: int = 0
    bad_frames: int = 0
    counter_jumps: int = 0
    events: list[tuple[float, str]] = field(default_factory=list)
    stops: list[Stop] = field(default_factory=list)
    _brake_ctr: can.CounterChecker = field(default_factory=can.CounterChecker)
    _status_ctr: can.CounterChecker = field(default_factory=can.CounterChecker)
    _last_draw: float = 0.0
    _last_plain: float = -10.0
    _prev: tuple[int, int, int] | None = None

    def event(self, t: float, text: str) -> None:
        self.events.append((t, text))
        self._clear()
        self.out.write(f"  {t - self.t0:7.3f}s  {text}\n")
        self.out.flush()
        self._last_draw = 0.0

    def take(self, rec: canlog.CanLogRecord) -> None:
        self.frames += 1
        if rec.can_id == can.STATUS_ID:
            if can.StatusFrame.check(rec.data):
                self.bad_frames += 1
                return
            status = can.StatusFrame.parse(rec.data)
            self.counter_jumps += not self._status_ctr.check(status.counter).ok
            self.link_age_ms = status.link_age
            self.auth_failures = status.auth_failures
            return
        if rec.can_id != can.BRAKE_ID:
            return
        if can.BrakeFrame.check(rec.data):
            self.bad_frames += 1
            return
        b = can.BrakeFrame.parse(rec.data)
        self.counter_jumps += not self._brake_ctr.check(b.counter).ok
        self.brake = b
        key = (b.state, b.reason, b.flags)
        if key == self._prev:
            return
        prev, self._prev = self._prev, key
        if prev is not None and prev[:2] == key[:2]:
            self.event(stamp(rec), "bus: flags " + (",".join(can.flag_names(b.flags)) or "none"))
            return
        if b.brakes:
            self.stops.append(Stop(stamp(rec), b))
        self.event(stamp(rec), f"bus: {can.state_name(b.state)} reason={can.reason_name(b.reason)}"
                               f" brake_request={b.brake_request} (counter {b.counter})")

    def line(self) -> str:
        """The live status line, most important fields first (it is cut to the terminal)."""
        now = time.time() - self.t0
        b = self.brake
        if b is None:
            bus = "no brake frame yet"
        else:
            flags = "degraded" if b.flags & can.FLAG_LINK_DEGRADED else "-"
            bus = (f"{can.state_name(b.state):7} {can.reason_name(b.reason):11} "
                   f"brake={b.brake_request} flags={flags:8} | ctr {b.counter:2}")
        age = "-" if self.link_age_ms is None else f"{self.link_age_ms} ms"
        return (f"[{now:5.2f}s] {self.phase:13} | {bus} | link age {age:>6} | auth failures "
                f"{self.auth_failures:3}/100 ms | frames {self.frames:4} | remote {self.remote}")

    def draw(self) -> None:
        now = time.monotonic()
        if self.live:
            if now - self._last_draw >= 0.05:
                width = shutil.get_terminal_size().columns - 1
                self.out.write("\r\x1b[2K" + self.line()[:width])
                self.out.flush()
                self._last_draw = now
        elif now - self._last_plain >= 1.0:
            self.out.write("  " + self.line() + "\n")
            self.out.flush()
            self._last_plain = now

    def _clear(self) -> None:
        if self.live:
            self.out.write("\r\x1b[2K")

    def finish(self) -> None:
        self._clear()
        self.out.flush()


class Script:
    """Plays the remote against a running daemon, feeding every logged frame to the view."""

    def __init__(self, daemon: Daemon, link: Link, view: View) -> None:
        self.daemon = daemon
        self.link = link
        self.view = view
        self.last_valid_sent = 0.0

    def pump(self, until: Callable[[], bool], max_s: float,
             packet: Callable[[float], Packet] | None = None, period_s: float = 0.02,
             side: Callable[[], None] | None = None) -> bool:
        """Drain frames (and send a packet every period, and call ``side`` every 10 ms: the
        attacker) until ``until()`` or max_s passes."""
        start = time.monotonic()
        next_send = start
        next_side = start
        while True:
            now = time.monotonic()
            if side is not None and now >= next_side:
                side()
                next_side += 0.01
            if packet is not None and now >= next_send:
                gas, steer, gear = packet(now - start)
                self.last_valid_sent = self.link.send_control(gas, steer, gear)
                self.view.remote = f"gas {gas:+.2f} steer {steer:+.2f}"
                next_send += period_s
            elif packet is None:
                self.view.remote = "silent"
            while True:
                try:
                    self.view.take(self.daemon.frames.get_nowait())
                except queue.Empty:
                    break
            self.view.draw()
            if until():
                return True
            if now - start >= max_s:
                return False
            if not self.daemon.alive():
                raise DaemonError("estopd exited during the demo")
            time.sleep(0.002)

    def wait(self, seconds: float, packet: Callable[[float], Packet] | None = None) -> None:
        self.pump(lambda: False, seconds, packet)

    def request(self, name: str, msg_id: int) -> tuple[tcp.Reply, float]:
        reply, t = self.link.request(msg_id)
        self.view.event(t, f"remote: {name} -> {_reply_text(reply)}")
        return reply, t

    def first_stop_after(self, t: float, max_s: float,
                         side: Callable[[], None] | None = None) -> Stop | None:
        def found() -> bool:
            return any(s.t >= t for s in self.view.stops)

        if not self.pump(found, max_s, side=side):
            return None
        return next(s for s in self.view.stops if s.t >= t)

    def release(self) -> bool:
        self.view.phase = "release"
        self.wait(0.3, _neutral)
        reply, _ = self.request("RELEASE", tcp.RELEASE)
        return reply.ack and reply.state == can.State.ARMED


def _reply_text(reply: tcp.Reply) -> str:
    what = ("ACK" if reply.ack else
            f"NAK {reply.nak_code} ({tcp.NAK_NAMES.get(tcp.NakCode(reply.nak_code))})")
    return f"{what}, unit {can.state_name(reply.state)} reason={can.reason_name(reply.reason)}"


class Attacker:
    """Someone on the car's network without the key, who has recorded the operator's packets:
    plain heartbeats, heartbeats under a wrong key, replays, a forged RELEASE, a stop datagram
    with a garbage tag. Counts what it sent."""

    def __init__(self, daemon: Daemon, session: int, recording: list[bytes]) -> None:
        self.addr = ("127.0.0.1", daemon.udp_port)
        self.tcp_port = daemon.tcp_port
        self.session = session  # no secret: every reply carries it
        self.recording = recording
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.wrong_key = secrets.token_bytes(auth.KEY_SIZE)
        self.counter = 1 << 40  # far above the operator's: only the tag can refuse it
        self.sent = {"plain": 0, "wrong key": 0, "replayed": 0}

    def keep_alive(self) -> None:
        """One round of heartbeats the unit must not count (called every 10 ms)."""
        self.counter += 1
        body = udp.ControlPacket(0.2, 0.0, udp.Gear.DRIVE)
        forged = auth.AuthControlPacket(1, self.session, self.counter, body).encode(self.wrong_key)
        replay = self.recording[self.sent["replayed"] % len(self.recording)]
        for kind, data in (("plain", body.encode()), ("wrong key", forged), ("replayed", replay)):
            self.udp.sendto(data, self.addr)
            self.sent[kind] += 1

    def forged_release(self) -> auth.AuthReply:
        """A RELEASE request frame under the wrong key; the unit answers it all the same."""
        self.counter += 1
        frame = auth.AuthRequest(tcp.RELEASE, 1, 1, self.session, self.counter).encode(
            self.wrong_key)
        with socket.create_connection(("127.0.0.1", self.tcp_port), timeout=2.0) as s:
            s.sendall(frame)
            raw = b""
            while len(raw) < auth.REPLY_SIZE:
                chunk = s.recv(auth.REPLY_SIZE - len(raw))
                if not chunk:
                    raise DaemonError("the daemon closed the attacker's connection")
                raw += chunk
        # The attacker cannot verify the tag (no key); it reads the fields.
        return auth.AuthReply.decode(raw, None, strict=False)

    def stop_datagram(self) -> float:
        """A stop datagram with a garbage tag; returns the time just before sending it."""
        data = auth.stop_datagram(1, 0)[:32] + secrets.token_bytes(auth.TAG_SIZE)
        t = time.time()
        self.udp.sendto(data, self.addr)
        return t

    def close(self) -> None:
        self.udp.close()


def _neutral(_t: float) -> Packet:
    return 0.0, 0.0, udp.Gear.NEUTRAL


def _drive(t: float) -> Packet:
    return round(min(0.4, 0.2 * t), 3), round(0.3 * math.sin(2.0 * t), 3), udp.Gear.DRIVE


Span = tuple[tuple[float, float], tuple[float, float]]  # (realtime, monotonic) from, to


def _span(t_from: float, t_to: float) -> Span:
    """A stretch between two realtime stamps, and the same stretch in monotonic time (the
    clock of the daemon's event log), as Daemon.lines_lost wants it."""
    offset = time.time() - time.monotonic()
    return (t_from, t_to), (t_from - offset, time.time() - offset)


@dataclass
class Result:
    overshoot_ms: float | None = None
    tcp_latency_ms: float | None = None
    timeout_reason: int | None = None
    tcp_reason: int | None = None
    overshoot_span: Span | None = None
    tcp_span: Span | None = None
    overshoot_lost: int = 0  # can-log lines lost around the measurement: no figure
    tcp_lost: int = 0
    attacker_sent: dict[str, int] = field(default_factory=dict)
    forged_release_nak: int | None = None
    datagram_latency_ms: float | None = None
    datagram_reason: int | None = None
    datagram_span: Span | None = None
    datagram_lost: int = 0
    problems: list[str] = field(default_factory=list)

    def check_lost_lines(self, daemon: Daemon) -> None:
        """Once the daemon has exited (every line and drop report in): lines lost around
        each measurement."""
        if self.overshoot_span is not None:
            self.overshoot_lost = daemon.lines_lost(*self.overshoot_span)
        if self.tcp_span is not None:
            self.tcp_lost = daemon.lines_lost(*self.tcp_span)
        if self.datagram_span is not None:
            self.datagram_lost = daemon.lines_lost(*self.datagram_span)


def _still_armed(view: View, res: Result) -> bool:
    b = view.brake
    if b is not None and b.state == can.State.ARMED:
        return True
    reason = can.reason_name(b.reason) if b is not None else "-"
    res.problems.append(f"the unit stopped during the drive (reason {reason}): the demo's "
                        f"packets were held up longer than the timeout (a very busy machine?)")
    return False


def _release_and_drive(s: Script, view: View, res: Result, which: str, seconds: float) -> bool:
    """The operator's RELEASE, then a drive of `seconds`; False (a problem noted) when the
    RELEASE was refused or the unit did not stay ARMED."""
    if not s.release():
        res.problems.append(f"{which} RELEASE was refused")
        return False
    view.phase = "drive"
    s.wait(seconds, _drive)
    return _still_armed(view, res)


def run_script(daemon: Daemon, view: View, timeout_ms: int, res: Result, key: bytes) -> None:
    """The scripted drive with an attacker; fills ``res`` as it goes."""
    link = Link(daemon.udp_port, daemon.tcp_port, key=key)
    link.recording = []
    s = Script(daemon, link, view)
    attacker: Attacker | None = None
    try:
        view.phase = "boot"
        view.event(time.time(), f"remote: holds the key; the unit's session {link.session:#018x}"
                                f" learnt from a STATUS")
        s.wait(0.3)
        s.request("RELEASE (no packets yet)", tcp.RELEASE)

        if not _release_and_drive(s, view, res, "the first", 2.0):
            return

        # The finger lifts; the attacker tries to keep the car alive.
        attacker = Attacker(daemon, link.session, list(link.recording))
        view.phase = "finger lifted"
        t_last = s.last_valid_sent
        view.event(time.time(), f"remote: finger lifted (last valid packet sent at "
                                f"{t_last - view.t0:.3f}s), timeout {timeout_ms} ms")
        view.event(time.time(), "attacker: sends plain heartbeats, heartbeats under a wrong key "
                                "and replays of the operator's recording, 100 Hz each")
        stop = s.first_stop_after(t_last, timeout_ms / 1000.0 + 2.0, side=attacker.keep_alive)
        s.pump(lambda: False, 0.1, side=attacker.keep_alive)
        res.attacker_sent = dict(attacker.sent)
        view.event(time.time(), "attacker: sent " + ", ".join(
            f"{n} {kind}" for kind, n in attacker.sent.items()) + " heartbeats")
        if stop is None:
            res.problems.append("no stop frame after the finger was lifted (the attacker kept "
                                "the unit alive)")
            return
        res.timeout_reason = stop.frame.reason
        res.overshoot_ms = (stop.t - (t_last + timeout_ms / 1000.0)) * 1000.0
        res.overshoot_span = _span(t_last, stop.t)
        s.wait(0.2)

        # The attacker tries to release the car while the operator holds neutral.
        view.phase = "forged RELEASE"
        s.wait(0.3, _neutral)
        forged = attacker.forged_release()
        res.forged_release_nak = forged.nak_code if not forged.ack else 0
        view.event(time.time(),
                   f"attacker: RELEASE under a wrong key -> {_reply_text(forged.reply)}")
        if not _release_and_drive(s, view, res, "the operator's", 1.0):
            return

        # Anyone may stop: the attacker's stop datagram, whatever its tag.
        view.phase = "stop datagram"
        t_dgram = attacker.stop_datagram()
        view.event(t_dgram, "attacker: stop datagram with a garbage tag (anyone may stop)")
        stop = s.first_stop_after(t_dgram, 2.0)
        if stop is None:
            res.problems.append("no stop frame after the stop datagram")
            return
        res.datagram_reason = stop.frame.reason
        res.datagram_latency_ms = (stop.t - t_dgram) * 1000.0
        res.datagram_span = _span(t_dgram, stop.t)
        s.wait(0.2)

        if not _release_and_drive(s, view, res, "the third", 1.0):
            return

        view.phase = "stop button"
        _reply, t_stop = s.request("STOP button", tcp.DEFAULT_STOP_ID)
        stop = s.first_stop_after(t_stop, 2.0)
        if stop is None:
            res.problems.append("no stop frame after the STOP button")
            return
        res.tcp_reason = stop.frame.reason
        res.tcp_latency_ms = (stop.t - t_stop) * 1000.0
        res.tcp_span = _span(t_stop, stop.t)
        view.phase = "latched"
        s.wait(0.4, _drive)
        s.request("RELEASE (gas still pressed)", tcp.RELEASE)
        s.wait(0.2, _drive)
    finally:
        link.close()
        if attacker is not None:
            attacker.close()


def _fmt_ms(v: float | None, lost: int = 0) -> str:
    if lost:
        return f"not measured: {lost} can-log line{'s' if lost != 1 else ''} lost"
    return "-" if v is None else f"{v:.3f} ms"


def _report(out: TextIO, view: View, res: Result, timeout_ms: int,
            daemon_dropped: int = 0) -> None:
    out.write("\nTimeline\n")
    for t, text in sorted(view.events, key=lambda e: e[0]):
        out.write(f"  {t - view.t0:7.3f}s  {text}\n")
    out.write("\nStops measured (the daemon's can-log stamps against the send times, both "
              "CLOCK_REALTIME)\n")
    reasons = (can.reason_name(res.timeout_reason) if res.timeout_reason is not None else "-",
               can.reason_name(res.tcp_reason) if res.tcp_reason is not None else "-")
    out.write(f"  finger lifted: stop reason {reasons[0]:11}  timeout overshoot "
              f"{_fmt_ms(res.overshoot_ms, res.overshoot_lost):>10}  (stop frame - (last "
              f"valid packet + {timeout_ms} ms))\n")
    dgram = can.reason_name(res.datagram_reason) if res.datagram_reason is not None else "-"
    out.write(f"  stop datagram: stop reason {dgram:11}  stop latency      "
              f"{_fmt_ms(res.datagram_latency_ms, res.datagram_lost):>10}  (stop frame - "
              f"datagram sent; sent by the attacker, garbage tag)\n")
    out.write(f"  stop button:   stop reason {reasons[1]:11}  TCP stop latency  "
              f"{_fmt_ms(res.tcp_latency_ms, res.tcp_lost):>10}  (stop frame - STOP sent)\n")
    sent = ", ".join(f"{n} {kind}" for kind, n in res.attacker_sent.items()) or "-"
    nak = ("-" if res.forged_release_nak is None else
           f"NAK {res.forged_release_nak} "
           f"({tcp.NAK_NAMES.get(res.forged_release_nak, res.forged_release_nak)})")
    out.write(f"\nThe attacker (no key) was refused: its heartbeats ({sent}) did not keep "
              f"the unit alive past the deadline; its forged RELEASE got {nak}; its stop "
              f"datagram stopped the car, because anyone may stop.\n")
    out.write(f"  frames checked: {view.frames} (bad CRC or content: {view.bad_frames}, alive "
              f"counter jumps: {view.counter_jumps}, lines the daemon reported dropped: "
              f"{daemon_dropped})\n")
    if res.overshoot_lost or res.tcp_lost:
        out.write("  (a figure is only given when no can-log line was lost around it: a lost "
                  "first stop frame would make the next one look late)\n")


TIMEOUT_MS_MIN = 1
TIMEOUT_MS_MAX = 60000  # the range estopd accepts for --timeout-ms


def timeout_ms(text: str) -> int:
    """argparse type of ``--timeout-ms``: whole milliseconds in the daemon's range."""
    want = f"must be whole milliseconds {TIMEOUT_MS_MIN}..{TIMEOUT_MS_MAX} (estopd's range)"
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{want}, got {text!r}") from None
    if not TIMEOUT_MS_MIN <= value <= TIMEOUT_MS_MAX:
        raise argparse.ArgumentTypeError(f"{want}, got {value}")
    return value


def main(argv: list[str] | None = None) -> int:
    """Run the demo; return its exit code (0 ok, 1 a problem, 2 usage error or no estopd).
    Usage errors are one line, as for every other ``estop`` tool."""
    ap = ErrorOnlyParser(prog="estop demo", description=(
        "Run estopd with a fresh key on loopback and play a scripted drive with an attacker "
        "on the network: release, drive, finger lifted while the attacker sends forged and "
        "replayed heartbeats (timeout stop all the same), a forged RELEASE (NAK 4), the "
        "attacker's stop datagram (it stops: anyone may), release, drive, stop button. No "
        "root, no CAN needed."))
    ap.add_argument("--estopd", metavar="PATH", help="the estopd binary (default: beside "
                    "this Python, on PATH, or firmware/build/estopd)")
    ap.add_argument("--timeout-ms", type=timeout_ms, default=200,
                    help=f"the daemon's UDP timeout, {TIMEOUT_MS_MIN}..{TIMEOUT_MS_MAX} "
                         f"(default 200)")
    ap.add_argument("--plain", action="store_true",
                    help="plain lines instead of a refreshing status line (default off a TTY)")
    try:
        args = ap.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error, already reported in one line
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    out = sys.stdout

    exe = find_estopd(args.estopd)
    if exe is None:
        sys.stderr.write("estop demo: estopd not found (run `make setup`, or build it with "
                         "`make -C firmware`, or pass --estopd PATH)\n")
        return 2

    live = out.isatty() and not args.plain and os.environ.get("TERM", "") != "dumb"
    view = View(out=out, live=live, t0=time.time())
    out.write(f"estop demo: {exe} on 127.0.0.1 with a fresh key, UDP timeout {args.timeout_ms} "
              f"ms, CAN frames logged to a pipe (no CAN hardware, no root)\n")
    keydir = tempfile.TemporaryDirectory(prefix="estop-demo-")
    key = secrets.token_bytes(auth.KEY_SIZE)
    key_path = os.path.join(keydir.name, "key")
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(auth.format_key(key))
    daemon = Daemon([exe], timeout_ms=args.timeout_ms, key_file=key_path)
    res = Result()
    try:
        daemon.start()
        view.event(time.time(), f"estopd started (pid {daemon.pid}), UDP port "
                                f"{daemon.udp_port}, TCP port {daemon.tcp_port}")
        run_script(daemon, view, args.timeout_ms, res, key)
    except (DaemonError, OSError, tcp.FrameError) as exc:
        res.problems.append(f"demo aborted: {exc}")
    finally:
        rc = daemon.stop()
        while True:
            try:
                view.take(daemon.frames.get_nowait())
            except queue.Empty:
                break
        view.finish()
        res.check_lost_lines(daemon)
        keydir.cleanup()
    final = view.brake.brake_request if view.brake is not None else None
    view.event(time.time(), f"estopd ended (pid {daemon.pid}, exit code {rc}); its last brake "
                            f"frame: brake_request={final}")
    _report(out, view, res, args.timeout_ms, daemon.dropped_total)

    if res.timeout_reason not in (None, can.Reason.UDP_TIMEOUT):
        res.problems.append(f"the finger-lifted stop had reason "
                            f"{can.reason_name(res.timeout_reason)}")
    if res.tcp_reason not in (None, can.Reason.TCP_STOP):
        res.problems.append(f"the stop button's stop had reason {can.reason_name(res.tcp_reason)}")
    if res.datagram_reason not in (None, can.Reason.TCP_STOP):
        res.problems.append(f"the stop datagram's stop had reason "
                            f"{can.reason_name(res.datagram_reason)}")
    if res.forged_release_nak not in (None, tcp.NakCode.NOT_AUTHENTICATED):
        res.problems.append(f"the attacker's forged RELEASE was not refused with NAK 4 "
                            f"(got {res.forged_release_nak})")
    if (res.overshoot_ms is None or res.tcp_latency_ms is None
            or res.datagram_latency_ms is None) and not res.problems:
        res.problems.append("a stop was not observed")
    if final != 1:
        res.problems.append("the daemon's last frame did not request the brake")
    if view.bad_frames:
        res.problems.append(f"{view.bad_frames} logged frames failed their checks")
    if rc not in (0, -signal.SIGTERM):
        res.problems.append(f"estopd ended abnormally (exit code {rc})")
    for p in res.problems:
        out.write(f"PROBLEM: {p}\n")
    out.write("demo " + ("FAILED" if res.problems else "ok") + "\n")
    out.flush()
    return 1 if res.problems else 0


if __name__ == "__main__":
    sys.exit(main())
