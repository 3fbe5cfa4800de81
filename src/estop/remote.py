"""``estop remote``: plays the tablet.

While *held* (a finger on the screen) the remote sends control packets over UDP at a fixed
rate (default 50 Hz); when the finger lifts it sends nothing, so the unit times out. The stop
button, RELEASE and STATUS go over the TCP stop channel, one connection kept open. The stop
button also sends a stop datagram to the UDP port at once, and keeps trying (a fresh
connection and another datagram each time) until the unit answers or ``stop_deadline``
(default 3 s) passes.

With a key (``--key-file``, spec section 5) the packets are the 60-byte authenticated form and
the requests 48-byte frames whose replies must verify; the remote learns the unit's session
from replies (``hold`` asks STATUS first when it does not know it yet) and raises one counter
with every message it sends.

An optional :class:`estop.linkmodel.LinkModel` makes the UDP link lossy and slow like Wi-Fi;
its one-way delay (not its loss) is also applied to each TCP request and its reply.

Library use (the demo, benchmarks, HIL harness)::

    with Remote("127.0.0.1", link=WIFI, seed=1) as r:
        r.hold(); time.sleep(0.5)
        print(r.release())              # tcp.Reply
        r.set_control(gas_brake=0.3, gear=Gear.DRIVE)
        ...
        r.lift()

Script mode (``--script TEXT`` or ``--script-file FILE``): commands separated by ``;`` or new
lines, ``#`` starts a comment. Times are seconds.

====================  ========================================================================
``hold [T]``          finger down: start sending (then wait T)
``lift [T]``          finger up: stop sending (then wait T)
``wait T``            do nothing else for T
``gas X``             gas_brake X (-1.0 full brake .. 1.0 full gas)
``steer X``           steering X (-1.0 left .. 1.0 right)
``gear G``            park, reverse, neutral, drive (or 1, 2, 4, 8)
``signal S``          off, left, right, both
``horn on|off``
``drive X [T]``       gear drive and gas X; with T: after T seconds gas back to 0
``neutral``           gas 0, steering 0, gear neutral
``rate HZ``           change the send rate (0.1..1000 Hz)
``stop``              press the stop button (stop datagram + TCP STOP, tried again until an
                      answer or the stop deadline), print the reply and the attempts
``release``           TCP RELEASE, print the reply
``status``            TCP STATUS, print the reply
``expect W...``       the last reply must match every word: ack, nak, stopped, armed, a reason
                      (none, boot, tcp_stop, udp_timeout, fault), a NAK reason (unknown_msg_id,
                      no_live_link, not_neutral, not_authenticated) or link_degraded /
                      link_ok; else exit 1
====================  ========================================================================

Example: ``hold 1.0; release; expect ack armed; drive 0.3 2.0; lift; wait 0.5; status;
expect stopped udp_timeout; stop``.

Interactive keys (a terminal): space hold/lift, s stop, r release, t status, arrows gas and
steering (0.1 steps), n neutral, g next gear, h horn, 0-3 turn signal, q quit.

Exit code: 0 done, 1 an ``expect`` failed, 2 usage error or bad script, 3 the stop channel
failed (connection refused or closed, timeout, malformed reply).
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import math
import os
import select
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

from estop.cliutil import (
    EXIT_OK,
    EXIT_PROBLEM,
    ConnectionFailure,
    UsageError,
    add_key_arguments,
    non_negative_float,
    out,
    parse_u32,
    port,
    positive_float,
)
from estop.keyfile import key_from_args
from estop.linkmodel import IDEAL, WIFI, LinkConfig, LinkModel
from estop.protocol import tcp, udp
from estop.protocol.auth import AuthControlPacket
from estop.protocol.can import REASON_NAMES, STATE_NAMES
from estop.protocol.tcp import Reply
from estop.protocol.udp import ControlPacket, Gear, TurnSignal
from estop.stopchannel import (
    DEFAULT_REMOTE_ID,
    DEFAULT_STOP_DEADLINE,
    MessageCounter,
    StopChannel,
    StopChannelError,
    StopDatagram,
    StopOutcome,
    format_reply,
    press_stop,
)

__all__ = [
    "DESCRIPTION",
    "EPILOG",
    "MAX_RATE_HZ",
    "MIN_RATE_HZ",
    "Remote",
    "RemoteStats",
    "ExpectFailed",
    "ScriptError",
    "ScriptRunner",
    "Step",
    "add_arguments",
    "check_rate",
    "handle_key",
    "link_config",
    "parse_script",
    "rate_arg",
    "run",
    "run_interactive",
]

DESCRIPTION = ("Play the tablet: send control packets over UDP while held (a finger on the "
               "screen), and STOP/RELEASE/STATUS over the TCP stop channel; keys in a "
               "terminal, or a script.")
EPILOG = """\
script (--script TEXT or --script-file FILE): commands separated by ';' or new lines,
'#' starts a comment, times in seconds:
  hold [T]        finger down: start sending (then wait T)
  lift [T]        finger up: stop sending (then wait T)
  wait T          wait
  gas X           gas_brake X (-1.0 full brake .. 1.0 full gas)
  steer X         steering X (-1.0 left .. 1.0 right)
  gear G          park, reverse, neutral, drive
  signal S        off, left, right, both
  horn on|off
  drive X [T]     gear drive and gas X; with T: after T seconds gas back to 0
  neutral         gas 0, steering 0, gear neutral
  rate HZ         change the send rate (0.1..1000)
  stop            the stop button: stop datagram + TCP STOP, tried again until an
                  answer or --stop-deadline; prints the reply and the attempts
  release | status             TCP request, prints the reply
  expect W...     the last reply must match every word (ack nak stopped armed none boot
                  tcp_stop udp_timeout fault unknown_msg_id no_live_link not_neutral
                  not_authenticated link_degraded link_ok), else exit 1
example: --script "hold 1.0; release; expect ack armed; drive 0.3 2.0; lift; wait 0.5;
  status; expect stopped udp_timeout; stop"

keys (terminal): space hold/lift, s stop, r release, t status, arrows gas/steering,
n neutral, g next gear, h horn, 0-3 turn signal, q quit

exit codes: 0 done, 1 an expect failed, 2 usage error or bad script,
3 stop channel failed (refused, closed, timeout, malformed reply; for stop: no answer
by --stop-deadline)"""

PacketHook = Callable[[float, bytes, float | None], None]

MIN_RATE_HZ = 0.1
MAX_RATE_HZ = 1000.0
# The sender thread always waits at least this long between two turns, even when it is behind
# its schedule, so hold()/lift()/close() get its lock at once at any rate.
_MIN_WAIT = 0.0002


def check_rate(rate_hz: float) -> float:
    """Return ``rate_hz`` if it is a send rate the remote supports (0.1..1000 Hz), else raise
    ValueError with a one-line message."""
    if not isinstance(rate_hz, int | float) or not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise ValueError(f"rate must be {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz, got {rate_hz!r}")
    return float(rate_hz)


def rate_arg(text: str) -> float:
    """argparse type of ``--rate``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    try:
        return check_rate(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@dataclass(slots=True)
class RemoteStats:
    sent: int = 0  # packets handed to the link (lost ones included)
    lost: int = 0  # dropped by the link model
    delivered: int = 0  # written to the UDP socket
    send_errors: int = 0  # sendto() failed
    requests: int = 0  # TCP requests answered
    stop_datagrams: int = 0  # stop datagrams handed to the link (lost ones included)

    @property
    def loss_fraction(self) -> float:
        return self.lost / self.sent if self.sent else 0.0


class Remote:
    """The tablet: a sender thread for UDP control packets plus a TCP stop channel.

    ``hold()``/``lift()`` start and stop sending; ``set_control()`` changes what is sent from
    the next packet on; ``stop()``/``release()``/``status()`` return the unit's
    :class:`~estop.protocol.tcp.Reply` (or raise :class:`~estop.stopchannel.StopChannelError`).
    The sender thread starts with ``start()`` or the ``with`` block and ends with ``close()``.
    ``on_packet(t_send, data, t_deliver_or_None)`` is called from the sender thread for every
    packet (times on ``time.monotonic()``).
    """

    def __init__(self, host: str, udp_port: int = udp.DEFAULT_PORT,
                 tcp_port: int = tcp.DEFAULT_PORT, *, rate_hz: float = 50.0,
                 link: LinkConfig = IDEAL, seed: int | None = None,
                 stop_id: int = tcp.DEFAULT_STOP_ID, tcp_timeout: float = 2.0,
                 stop_deadline: float = DEFAULT_STOP_DEADLINE, legacy: bool = False,
                 on_packet: PacketHook | None = None, key: bytes | None = None,
                 remote_id: int = DEFAULT_REMOTE_ID) -> None:
        self._period = 1.0 / check_rate(rate_hz)
        if not stop_deadline > 0 or not math.isfinite(stop_deadline):
            raise ValueError(f"stop deadline must be > 0 s, got {stop_deadline!r}")
        self.stop_deadline = stop_deadline
        if key is not None and legacy:
            raise ValueError("with a key the remote sends 60-byte packets, not the 16-byte form")
        self.key = key
        self.remote_id = remote_id
        self.counter = MessageCounter()  # one counter for all its messages: each channel rises
        self.addr = (host, udp_port)
        self.legacy = legacy
        self.on_packet = on_packet
        self.link = LinkModel(link, seed)
        self.channel = StopChannel(host, tcp_port, timeout=tcp_timeout, stop_id=stop_id,
                                   key=key, remote_id=remote_id, counter=self.counter)
        self.datagram = StopDatagram(host, udp_port, stop_id=stop_id, key=key,
                                     remote_id=remote_id, counter=self.counter,
                                     session=lambda: self.channel.session,
                                     transmit=self._send_datagram)
        self.stats = RemoteStats()
        self._control = ControlPacket()
        self._held = False
        self._next_send = 0.0
        self._inflight: list[tuple[float, int, bytes, bool]] = []  # (due, n, data, control)
        self._n = 0
        self._closing = False
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._udp = socket.socket(family, socket.SOCK_DGRAM)

    # --------------------------------------------------------------------- life cycle

    def start(self) -> Remote:
        with self._cond:
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="estop-remote-udp",
                                                daemon=True)
                self._thread.start()
        return self

    def close(self, *, flush: bool = True) -> None:
        """Stop sending; with ``flush`` wait for packets still in flight (link delay) first."""
        with self._cond:
            self._held = False
            self._cond.notify_all()
            if flush and self._thread is not None:
                self._cond.wait_for(lambda: not self._inflight, timeout=5.0)
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._udp.close()
        self.channel.close()

    def __enter__(self) -> Remote:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the dead man

    @property
    def held(self) -> bool:
        return self._held

    @property
    def rate_hz(self) -> float:
        return 1.0 / self._period

    @rate_hz.setter
    def rate_hz(self, value: float) -> None:
        period = 1.0 / check_rate(value)
        with self._cond:
            self._period = period
            self._cond.notify_all()

    def hold(self) -> None:
        """Finger down: send a packet now and then one every period. With a key and the
        unit's session not known yet, ask STATUS first to learn it (a packet with another
        session keeps nothing alive); that may raise
        :class:`~estop.stopchannel.StopChannelError`."""
        if self.key is not None and not self.channel.session and not self._held:
            self.status()
        with self._cond:
            if not self._held:
                self._held = True
                self._next_send = time.monotonic()
                self._cond.notify_all()

    def lift(self) -> None:
        """Finger up: once this returns, no further packet is sent (those already in flight
        in the link model still arrive, as on a real network)."""
        with self._cond:
            self._held = False
            self._cond.notify_all()

    @property
    def control(self) -> ControlPacket:
        return self._control

    def set_control(self, packet: ControlPacket | None = None, **fields: Any) -> ControlPacket:
        """Replace the packet sent from now on, or change some of its fields
        (``gas_brake``, ``steering``, ``gear``, ``turn_signal``, ``horn``). Raises
        :class:`~estop.protocol.udp.InvalidPacket` for values the unit would reject."""
        with self._cond:
            new = replace(packet or self._control, **fields)
            new.validate()
            self._control = new
            return new

    # -------------------------------------------------------------------- stop channel

    def _tcp_delay(self) -> None:
        if self.link.config.delay > 0 or self.link.config.jitter > 0:
            with self._cond:
                d = self.link.sample_delay()
            time.sleep(d)

    def request(self, msg_id: int) -> Reply:
        self._tcp_delay()
        reply = self.channel.request(msg_id)
        self._tcp_delay()
        self.stats.requests += 1
        return reply

    def press_stop(self) -> StopOutcome:
        """The stop button: STOP with the vehicle's stop ID, tried again on a fresh connection
        until the unit answers or ``stop_deadline`` passes, with a stop datagram on the UDP
        port at the first try and each retry (see :func:`estop.stopchannel.press_stop`)."""
        linked = self.link.config.delay > 0 or self.link.config.jitter > 0
        outcome = press_stop(self.channel, deadline=self.stop_deadline,
                             datagram=self.datagram, delay=self._tcp_delay if linked else None)
        if outcome.reply is not None:
            self.stats.requests += 1
        return outcome

    def stop(self) -> Reply:
        """The stop button (:meth:`press_stop`); the unit's reply, or
        :class:`~estop.stopchannel.StopChannelError` saying how many tries failed by the
        deadline."""
        outcome = self.press_stop()
        if outcome.reply is None:
            raise StopChannelError(outcome.summary())
        return outcome.reply

    def release(self) -> Reply:
        return self.request(tcp.RELEASE)

    def status(self) -> Reply:
        return self.request(tcp.STATUS)

    # ------------------------------------------------------------------- sender thread

    def _loop(self) -> None:
        # Everything is decided and sent under the lock, so once lift() has held it no packet
        # goes out; and every turn ends in a wait of at least _MIN_WAIT, which lets go of the
        # lock even when the sender is behind its schedule (a slow machine, a slow hook).
        with self._cond:
            while not self._closing:
                now = time.monotonic()
                while self._inflight and self._inflight[0][0] <= now:
                    _, _, data, control = heapq.heappop(self._inflight)
                    self._write(data, control)
                if not self._inflight:
                    self._cond.notify_all()  # close(flush=True) may be waiting
                if self._held and self._next_send <= now:
                    self._send_one(now)
                    self._next_send += self._period
                    if self._next_send < now:  # fell behind (paused): no burst, restart
                        self._next_send = now + self._period
                wake = math.inf
                if self._held:
                    wake = self._next_send
                if self._inflight:
                    wake = min(wake, self._inflight[0][0])
                timeout = 0.5 if wake == math.inf else wake - time.monotonic()
                self._cond.wait(min(0.5, max(_MIN_WAIT, timeout)))

    def _send_one(self, now: float) -> None:
        if self.key is None:
            data = self._control.encode(legacy=self.legacy)
        else:
            data = AuthControlPacket(self.remote_id, self.channel.session, self.counter.next(),
                                     self._control).encode(self.key)
        self.stats.sent += 1
        t_deliver = self._transmit(now, data, True)
        if t_deliver is None:
            self.stats.lost += 1
        if self.on_packet is not None:
            self.on_packet(now, data, t_deliver)

    def _send_datagram(self, data: bytes) -> None:
        """A stop datagram, through the same link as the control packets."""
        with self._cond:
            self.stats.stop_datagrams += 1
            self._transmit(time.monotonic(), data, False)
            self._cond.notify_all()

    def _transmit(self, now: float, data: bytes, control: bool) -> float | None:
        t_deliver = self.link.transmit(now)
        if t_deliver is not None and t_deliver <= now:
            self._write(data, control)
        elif t_deliver is not None:
            self._n += 1
            heapq.heappush(self._inflight, (t_deliver, self._n, data, control))
        return t_deliver

    def _write(self, data: bytes, control: bool) -> None:
        try:
            self._udp.sendto(data, self.addr)
            if control:
                self.stats.delivered += 1
        except OSError:
            self.stats.send_errors += 1


# ------------------------------------------------------------------------------ scripts

class ScriptError(ValueError):
    """A script that cannot be run; ``str()`` names the step."""


class ExpectFailed(Exception):
    """A script's ``expect`` did not match the last reply (or there was none)."""


@dataclass(frozen=True, slots=True)
class Step:
    """One parsed script command: ``op`` with numeric ``args`` (times, values, codes) or, for
    ``expect``, ``words``; ``text`` is the command as written."""

    op: str
    args: tuple[float, ...] = ()
    words: tuple[str, ...] = ()
    text: str = ""


_GEARS: dict[str, int] = {
    "park": Gear.PARK, "p": Gear.PARK, "reverse": Gear.REVERSE, "r": Gear.REVERSE,
    "neutral": Gear.NEUTRAL, "n": Gear.NEUTRAL, "drive": Gear.DRIVE, "d": Gear.DRIVE,
    "1": Gear.PARK, "2": Gear.REVERSE, "4": Gear.NEUTRAL, "8": Gear.DRIVE,
}
_SIGNALS: dict[str, int] = {
    "off": TurnSignal.OFF, "left": TurnSignal.LEFT, "right": TurnSignal.RIGHT,
    "both": TurnSignal.BOTH, "0": TurnSignal.OFF, "1": TurnSignal.LEFT,
    "2": TurnSignal.RIGHT, "3": TurnSignal.BOTH,
}
_HORN: dict[str, int] = {"on": 1, "1": 1, "off": 0, "0": 0}
_EXPECT_WORDS = ({"ack", "nak", "link_degraded", "link_ok"}
                 | {n.lower() for n in STATE_NAMES.values()} | set(REASON_NAMES.values())
                 | {v for k, v in tcp.NAK_NAMES.items() if k})
_MAX_SECONDS = 24 * 3600.0
# op -> (min args, max args, kind of each argument)
_SYNTAX: dict[str, tuple[int, int, tuple[str, ...]]] = {
    "hold": (0, 1, ("secs",)), "lift": (0, 1, ("secs",)), "wait": (1, 1, ("secs",)),
    "gas": (1, 1, ("axis",)), "steer": (1, 1, ("axis",)), "drive": (1, 2, ("axis", "secs")),
    "gear": (1, 1, ("gear",)), "signal": (1, 1, ("signal",)), "horn": (1, 1, ("horn",)),
    "rate": (1, 1, ("rate",)), "neutral": (0, 0, ()), "stop": (0, 0, ()),
    "release": (0, 0, ()), "status": (0, 0, ()),
}


def _number(word: str, what: str, lo: float, hi: float) -> float:
    try:
        value = float(word)
    except ValueError:
        raise ScriptError(f"{what}: not a number: {word!r}") from None
    if not math.isfinite(value) or not lo <= value <= hi:
        raise ScriptError(f"{what}: {word} out of range {lo:g}..{hi:g}")
    return value


def _code(word: str, what: str, table: dict[str, int]) -> float:
    try:
        return table[word.lower()]
    except KeyError:
        names = ", ".join(k for k in table if not k.isdigit() and len(k) > 1)
        raise ScriptError(f"{what}: {word!r} unknown ({names})") from None


def _arg(kind: str, word: str, op: str) -> float:
    if kind == "secs":
        return _number(word, op, 0.0, _MAX_SECONDS)
    if kind == "axis":
        return _number(word, op, -1.0, 1.0)
    if kind == "rate":
        return _number(word, op, MIN_RATE_HZ, MAX_RATE_HZ)
    tables = {"gear": _GEARS, "signal": _SIGNALS, "horn": _HORN}
    return _code(word, op, tables[kind])


def _parts(text: str) -> Iterator[str]:
    for line in text.splitlines():
        for part in line.split("#", 1)[0].split(";"):
            if part.strip():
                yield part.strip()


def _parse_step(part: str) -> Step:
    words = part.split()
    op, rest = words[0].lower(), words[1:]
    if op == "expect":
        if not rest:
            raise ScriptError("expect needs at least one word")
        bad = [w for w in rest if w.lower() not in _EXPECT_WORDS]
        if bad:
            raise ScriptError(f"expect: unknown word {bad[0]!r} "
                              f"(valid: {', '.join(sorted(_EXPECT_WORDS))})")
        return Step(op, words=tuple(w.lower() for w in rest), text=part)
    if op not in _SYNTAX:
        raise ScriptError(f"unknown command {words[0]!r}")
    lo, hi, kinds = _SYNTAX[op]
    if not lo <= len(rest) <= hi:
        want = str(lo) if lo == hi else f"{lo} or {hi}"
        raise ScriptError(f"{op} takes {want} argument(s), got {len(rest)}")
    return Step(op, tuple(_arg(k, w, op) for k, w in zip(kinds, rest, strict=False)), text=part)


def parse_script(text: str) -> list[Step]:
    """Parse a script (syntax in this module's docstring); raise :class:`ScriptError`
    naming the bad command. Nothing runs before the whole script has parsed."""
    steps = []
    for part in _parts(text):
        try:
            steps.append(_parse_step(part))
        except ScriptError as exc:
            raise ScriptError(f"{part!r}: {exc}") from None
    if not steps:
        raise ScriptError("the script is empty")
    return steps


def _reply_words(reply: Reply) -> set[str]:
    words = {"ack" if reply.ack else "nak",
             STATE_NAMES.get(reply.state, "?").lower(),
             REASON_NAMES.get(reply.reason, "?"),
             "link_degraded" if reply.flags & 1 else "link_ok"}
    if not reply.ack:
        words.add(tcp.NAK_NAMES.get(reply.nak_code, "?"))
    return words


class ScriptRunner:
    """Run parsed steps on a started :class:`Remote`; ``log(line)`` gets one line per step
    (seconds since the start, then the command, or ``op -> reply`` for TCP commands)."""

    def __init__(self, remote: Remote, log: Callable[[str], None] | None = None) -> None:
        self.remote = remote
        self.log = log or (lambda _line: None)
        self.last_reply: Reply | None = None
        self.replies: list[tuple[str, Reply]] = []
        self._t0 = time.monotonic()

    def _say(self, text: str) -> None:
        self.log(f"{time.monotonic() - self._t0:8.3f} {text}")

    def run(self, steps: list[Step]) -> None:
        """Run every step. Raises :class:`ExpectFailed` at a failed ``expect`` and
        :class:`~estop.stopchannel.StopChannelError` when the stop channel fails."""
        self._t0 = time.monotonic()
        for step in steps:
            self.step(step)

    def step(self, step: Step) -> None:
        r = self.remote
        op, args = step.op, step.args
        if op == "stop":
            outcome = r.press_stop()
            if outcome.reply is None:
                raise StopChannelError(f"stop: {outcome.summary()}")
            self.last_reply = outcome.reply
            self.replies.append((op, outcome.reply))
            self._say(f"{op} -> {outcome.line()}")
            return
        if op in ("release", "status"):
            reply = {"release": r.release, "status": r.status}[op]()
            self.last_reply = reply
            self.replies.append((op, reply))
            self._say(f"{op} -> {format_reply(reply)}")
            return
        if op == "expect":
            if self.last_reply is None:
                raise ExpectFailed(f"{step.text}: no reply yet")
            if not set(step.words) <= _reply_words(self.last_reply):
                raise ExpectFailed(f"{step.text}: got {format_reply(self.last_reply)}")
            self._say(f"{step.text}: ok")
            return
        self._say(step.text)
        if op == "hold":
            r.hold()
        elif op == "lift":
            r.lift()
        elif op == "gas":
            r.set_control(gas_brake=args[0])
        elif op == "steer":
            r.set_control(steering=args[0])
        elif op == "gear":
            r.set_control(gear=int(args[0]))
        elif op == "signal":
            r.set_control(turn_signal=int(args[0]))
        elif op == "horn":
            r.set_control(horn=int(args[0]))
        elif op == "neutral":
            r.set_control(gas_brake=0.0, steering=0.0, gear=Gear.NEUTRAL)
        elif op == "rate":
            r.rate_hz = args[0]
        elif op == "drive":
            r.set_control(gas_brake=args[0], gear=Gear.DRIVE)
            if len(args) > 1:
                time.sleep(args[1])
                r.set_control(gas_brake=0.0)
            return
        if op in ("hold", "lift", "wait") and args:
            time.sleep(args[0])


# ------------------------------------------------------------------------- interactive

_HELP = ("keys: space hold/lift  s stop  r release  t status  arrows gas/steer  n neutral  "
         "g gear  h horn  0-3 signal  q quit")
_GEAR_CYCLE = [Gear.PARK, Gear.REVERSE, Gear.NEUTRAL, Gear.DRIVE]


@contextlib.contextmanager
def _raw_terminal(fd: int) -> Iterator[None]:
    import termios
    import tty

    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def _read_keys(fd: int, timeout: float) -> str:
    ready, _, _ = select.select([fd], [], [], timeout)
    if not ready:
        return ""
    return os.read(fd, 64).decode(errors="replace")


def _status_line(remote: Remote) -> str:
    c = remote.control
    gear = Gear(c.gear).name.lower() if c.gear in _GEAR_CYCLE else str(c.gear)
    return (f"\r[{'HELD' if remote.held else 'lifted'}] gas {c.gas_brake:+.1f} "
            f"steer {c.steering:+.1f} gear {gear} signal {TurnSignal(c.turn_signal).name.lower()}"
            f" horn {'on' if c.horn else 'off'} | sent {remote.stats.sent} "
            f"lost {remote.stats.lost}   ")


_ARROWS = {"\x1b[A": ("gas_brake", 0.1), "\x1b[B": ("gas_brake", -0.1),
           "\x1b[C": ("steering", 0.1), "\x1b[D": ("steering", -0.1)}


def _split_keys(text: str) -> Iterator[str]:
    while text:
        key = next((k for k in _ARROWS if text.startswith(k)), text[0])
        yield key
        text = text[len(key):]


def handle_key(remote: Remote, key: str) -> str | None:
    """Act on one key of the interactive mode; return a line to print, or ``"quit"``."""
    c = remote.control
    if key in ("q", "\x03", "\x04"):
        return "quit"
    if key == " ":
        if remote.held:
            remote.lift()
        else:
            try:
                remote.hold()
            except StopChannelError as exc:  # with a key: the session could not be learned
                return f"hold -> error: {exc}"
    elif key == "s":
        return f"stop -> {remote.press_stop().line()}"
    elif key in ("r", "t"):
        op = {"r": "release", "t": "status"}[key]
        try:
            return f"{op} -> {format_reply(remote.request(_OPS[op](remote)))}"
        except StopChannelError as exc:
            return f"{op} -> error: {exc}"
    elif key in _ARROWS:
        name, step = _ARROWS[key]
        value = round(max(-1.0, min(1.0, getattr(c, name) + step)), 1)
        remote.set_control(**{name: value})
    elif key == "n":
        remote.set_control(gas_brake=0.0, steering=0.0, gear=Gear.NEUTRAL)
    elif key == "g":
        i = _GEAR_CYCLE.index(Gear(c.gear)) if c.gear in _GEAR_CYCLE else 0
        remote.set_control(gear=_GEAR_CYCLE[(i + 1) % len(_GEAR_CYCLE)])
    elif key == "h":
        remote.set_control(horn=1 - c.horn)
    elif key in ("0", "1", "2", "3"):
        remote.set_control(turn_signal=int(key))
    return None


_OPS: dict[str, Callable[[Remote], int]] = {
    "release": lambda r: tcp.RELEASE,
    "status": lambda r: tcp.STATUS,
}


def run_interactive(remote: Remote) -> None:
    """Keys from the terminal (cbreak mode, restored on exit) until q or Ctrl-C."""
    fd = sys.stdin.fileno()
    out(_HELP)
    with _raw_terminal(fd):
        while True:
            sys.stdout.write(_status_line(remote))
            sys.stdout.flush()
            for key in _split_keys(_read_keys(fd, 0.1)):
                line = handle_key(remote, key)
                if line == "quit":
                    out()
                    return
                if line:
                    out("\n" + line)


# ------------------------------------------------------------------------------ the CLI

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", required=True, help="the unit's address")
    parser.add_argument("--udp-port", type=port, default=udp.DEFAULT_PORT,
                        help=f"control packet port (default {udp.DEFAULT_PORT})")
    parser.add_argument("--tcp-port", type=port, default=tcp.DEFAULT_PORT,
                        help=f"stop channel port (default {tcp.DEFAULT_PORT})")
    parser.add_argument("--rate", type=rate_arg, default=50.0,
                        help=f"packets per second while held, {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} "
                             f"(default 50)")
    parser.add_argument("--wifi", action="store_true",
                        help=f"link like the original Wi-Fi: {WIFI.loss * 100:g} %% loss, "
                             f"bursts of {WIFI.burst:g}, {WIFI.delay * 1000:g}+0..."
                             f"{WIFI.jitter * 1000:g} ms delay (options below override)")
    parser.add_argument("--loss", type=non_negative_float, default=None, metavar="PCT",
                        help="UDP packets lost, percent (default 0)")
    parser.add_argument("--burst", type=positive_float, default=None, metavar="N",
                        help="mean number of packets lost in a row (default 1)")
    parser.add_argument("--delay-ms", type=non_negative_float, default=None,
                        help="one-way delay, ms (default 0)")
    parser.add_argument("--jitter-ms", type=non_negative_float, default=None,
                        help="extra random delay 0..N ms (default 0)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the link model")
    parser.add_argument("--stop-id", type=parse_u32, default=tcp.DEFAULT_STOP_ID,
                        help=f"the vehicle's stop ID (default {tcp.DEFAULT_STOP_ID:#010X})")
    parser.add_argument("--timeout", type=positive_float, default=2.0,
                        help="seconds to wait for a TCP reply (default 2)")
    parser.add_argument("--stop-deadline", type=positive_float, default=DEFAULT_STOP_DEADLINE,
                        metavar="S", help="the stop button tries again (fresh connection, "
                        f"another stop datagram) until an ACK or S seconds "
                        f"(default {DEFAULT_STOP_DEADLINE:g})")
    parser.add_argument("--legacy", action="store_true",
                        help="send the older 16-byte packets (no horn; not with a key)")
    add_key_arguments(parser)
    script = parser.add_mutually_exclusive_group()
    script.add_argument("--script", metavar="TEXT", help="run this script instead of keys")
    script.add_argument("--script-file", metavar="FILE", help="run the script in FILE")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="script mode: print only replies and the summary")


def link_config(args: argparse.Namespace) -> LinkConfig:
    base = WIFI if args.wifi else IDEAL
    cfg = LinkConfig(
        loss=base.loss if args.loss is None else args.loss / 100.0,
        burst=base.burst if args.burst is None else args.burst,
        delay=base.delay if args.delay_ms is None else args.delay_ms / 1000.0,
        jitter=base.jitter if args.jitter_ms is None else args.jitter_ms / 1000.0,
    )
    try:
        cfg.validate()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return cfg


def _summary(remote: Remote) -> str:
    s = remote.stats
    return (f"summary: {s.sent} packets sent, {s.delivered} delivered, {s.lost} lost "
            f"({s.loss_fraction * 100:.1f} %), longest loss burst "
            f"{remote.link.stats.longest_burst}, {s.requests} TCP replies")


def run(args: argparse.Namespace) -> int:
    cfg = link_config(args)
    try:
        tcp.check_stop_id(args.stop_id)
    except ValueError as exc:
        raise UsageError(f"--stop-id: {exc}") from None
    text: str | None = args.script
    if args.script_file is not None:
        try:
            with open(args.script_file, encoding="utf-8") as f:
                text = f.read()
        except OSError as exc:
            raise UsageError(f"cannot read {args.script_file}: {exc.strerror or exc}") from None
    steps: list[Step] | None = None
    if text is not None:
        try:
            steps = parse_script(text)
        except ScriptError as exc:
            raise UsageError(f"script: {exc}") from None
    elif not sys.stdin.isatty():
        raise UsageError("interactive mode needs a terminal; use --script or --script-file")
    key = key_from_args(args)
    if key is not None and args.legacy:
        raise UsageError("--legacy: with --key-file the remote sends 60-byte packets")
    try:
        remote = Remote(args.host, args.udp_port, args.tcp_port, rate_hz=args.rate, link=cfg,
                        seed=args.seed, stop_id=args.stop_id, tcp_timeout=args.timeout,
                        stop_deadline=args.stop_deadline, legacy=args.legacy, key=key,
                        remote_id=args.remote_id)
    except OSError as exc:
        raise ConnectionFailure(f"cannot open a UDP socket: {exc}") from None
    code = EXIT_OK
    with remote:
        if steps is None:
            run_interactive(remote)
        else:
            quiet: bool = args.quiet

            def log(line: str) -> None:
                if not quiet or " -> " in line:
                    out(line)

            runner = ScriptRunner(remote, log=log)
            try:
                runner.run(steps)
            except ExpectFailed as exc:
                out(f"expect failed: {exc}")
                code = EXIT_PROBLEM
            except StopChannelError as exc:
                remote.lift()
                raise ConnectionFailure(str(exc)) from None
            finally:
                remote.lift()
    out(_summary(remote))
    return code
