"""What a remote's buttons do, in one place for every front-end (the terminal's keys, a
script, a game controller; a touch page too): each action on a
:class:`~estop.client.sender.Remote` and the line it reports.

The stop channel's failures are the front-end's to handle: :func:`request` raises
:class:`~estop.client.channel.StopChannelError` (a script ends on it), :func:`try_request`
says it in its line (a live front-end goes on).
"""

from __future__ import annotations

from dataclasses import dataclass

from estop.client.channel import StopChannelError, format_reply
from estop.client.sender import Remote
from estop.protocol import tcp
from estop.protocol.udp import Gear

__all__ = ["GEAR_CYCLE", "REQUESTS", "Done", "hold", "lift", "neutral", "next_gear",
           "request", "try_request"]

REQUESTS = ("stop", "release", "status")  # the requests over the stop channel
GEAR_CYCLE = (Gear.PARK, Gear.REVERSE, Gear.NEUTRAL, Gear.DRIVE)  # the next-gear button's


@dataclass(frozen=True, slots=True)
class Done:
    """What a request did: its line (``release -> ACK seq=1 ...``) and the unit's reply
    (None: the stop button got no answer by its deadline)."""

    line: str
    reply: tcp.Reply | None


def request(remote: Remote, op: str) -> Done:
    """``stop`` (the stop button: retried until an answer or the remote's deadline, never
    raising), ``release`` or ``status``. Raises :class:`StopChannelError` when a release or
    status gets no valid answer."""
    if op == "stop":
        outcome = remote.press_stop()
        return Done(f"stop -> {outcome.line()}", outcome.reply)
    if op not in REQUESTS:
        raise ValueError(f"not a request: {op!r}")
    reply = remote.release() if op == "release" else remote.status()
    return Done(f"{op} -> {format_reply(reply)}", reply)


def try_request(remote: Remote, op: str) -> str:
    """:func:`request`'s line, or ``op -> error: ...`` when the stop channel failed."""
    try:
        return request(remote, op).line
    except StopChannelError as exc:
        return f"{op} -> error: {exc}"


def hold(remote: Remote) -> str | None:
    """Finger down; None, or ``hold -> error: ...`` when a keyed remote could not learn the
    unit's session first (nothing is sent then)."""
    try:
        remote.hold()
    except StopChannelError as exc:
        return f"hold -> error: {exc}"
    return None


def lift(remote: Remote) -> int:
    """Finger up: the lift datagrams go out (spec section 8); how many this lift sends (0: the
    remote was not held)."""
    return remote.lift()


def next_gear(remote: Remote) -> Gear:
    """The next gear of :data:`GEAR_CYCLE` (from park when the gear is none of them)."""
    gear = remote.control.gear
    i = GEAR_CYCLE.index(Gear(gear)) if gear in GEAR_CYCLE else 0
    new = GEAR_CYCLE[(i + 1) % len(GEAR_CYCLE)]
    remote.set_control(gear=new)
    return new


def neutral(remote: Remote) -> None:
    """Gas and steering 0, gear neutral."""
    remote.set_control(gas_brake=0.0, steering=0.0, gear=Gear.NEUTRAL)
