"""The script language of ``estop remote --script`` / ``--script-file``: parse a script into
:class:`Step` objects, run them on a :class:`~estop.client.sender.Remote` with
:class:`ScriptRunner`.

Commands are separated by ``;`` or new lines, ``#`` starts a comment. Times are seconds.

====================  ========================================================================
``hold [T]``          finger down: start sending (then wait T)
``lift [T]``          finger up: stop sending, send the lift datagrams (then wait T)
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
``expect W...``       the last reply must match every word: ack, nak, a state (stopped, armed,
                      slowing), a reason (none, boot, tcp_stop, udp_timeout, fault, lift), a
                      NAK reason (unknown_msg_id, no_live_link, not_neutral,
                      not_authenticated) or link_degraded / link_ok; else
                      :class:`ExpectFailed`
====================  ========================================================================

The hold ends with ``lift`` (and with the end of the script, whatever ends it): no more control
packets, and the lift datagrams tell the unit at once; the step's line says ``lift sent x3``.

Example: ``hold 1.0; release; expect ack armed; drive 0.3 2.0; lift; wait 0.1; status;
expect stopped lift; stop``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from estop.client.channel import StopChannelError, format_reply
from estop.client.sender import MAX_RATE_HZ, MIN_RATE_HZ, Remote, lift_line
from estop.protocol import tcp
from estop.protocol.can import REASON_NAMES, STATE_NAMES
from estop.protocol.tcp import Reply
from estop.protocol.udp import Gear, TurnSignal
from estop.remote import actions

__all__ = ["ExpectFailed", "ScriptError", "ScriptRunner", "Step", "parse_script"]


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
        :class:`~estop.client.channel.StopChannelError` when the stop channel fails."""
        self._t0 = time.monotonic()
        for step in steps:
            self.step(step)

    def step(self, step: Step) -> None:
        r = self.remote
        op, args = step.op, step.args
        if op in actions.REQUESTS:
            done = actions.request(r, op)
            if done.reply is None:  # the stop button got no answer by its deadline
                raise StopChannelError(done.line)
            self.last_reply = done.reply
            self.replies.append((op, done.reply))
            self._say(done.line)
            return
        if op == "expect":
            if self.last_reply is None:
                raise ExpectFailed(f"{step.text}: no reply yet")
            if not set(step.words) <= _reply_words(self.last_reply):
                raise ExpectFailed(f"{step.text}: got {format_reply(self.last_reply)}")
            self._say(f"{step.text}: ok")
            return
        if op == "lift":
            self._say(f"{step.text}: {lift_line(r)}")
            if args:
                time.sleep(args[0])
            return
        self._say(step.text)
        if op == "hold":
            r.hold()
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
            actions.neutral(r)
        elif op == "rate":
            r.rate_hz = args[0]
        elif op == "drive":
            r.set_control(gas_brake=args[0], gear=Gear.DRIVE)
            if len(args) > 1:
                time.sleep(args[1])
                r.set_control(gas_brake=0.0)
            return
        if op in ("hold", "wait") and args:
            time.sleep(args[0])

