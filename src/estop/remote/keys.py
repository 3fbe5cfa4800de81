"""The interactive terminal of ``estop remote``: one key acts at once (cbreak mode), a status
line shows what is sent.

The keyboard is a toggle, not a dead-man (a terminal never sees a key released): the screen
says so (:data:`WARNING`) and the status line reads ``HELD (toggle: space to lift)``.

Keys: space hold/lift, s stop, r release, t status, arrows gas and steering (0.1 steps),
n neutral, g next gear, h horn, 0-3 turn signal, q quit. A lift sends the lift datagrams
(spec section 8) and the status line says so (``lifted, lift sent x3``); q and Ctrl-C end a
hold the same way (the command line does that when this returns).
"""

from __future__ import annotations

import contextlib
import os
import select
import sys
from collections.abc import Callable, Iterator

from estop.client.sender import Remote
from estop.protocol.udp import Gear, TurnSignal
from estop.remote import actions

__all__ = ["WARNING", "handle_key", "run_interactive"]

_HELP = ("keys: space hold/lift  s stop  r release  t status  arrows gas/steer  n neutral  "
         "g gear  h horn  0-3 signal  q quit")
WARNING = ("NOTE: the space bar is a TOGGLE, NOT a dead-man: a terminal cannot see a key "
           "released, so packets go on until you press space again (or s, q, Ctrl-C). For a "
           "real dead-man use estop remote --gamepad.")


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
    gear = Gear(c.gear).name.lower() if c.gear in actions.GEAR_CYCLE else str(c.gear)
    if remote.held:
        hold = "HELD (toggle: space to lift)"
    elif remote.lift_sent:  # the latest hold ended: say that the unit was told
        hold = f"lifted, lift sent x{remote.lift_sent}"
    else:
        hold = "lifted"
    return (f"\r[{hold}] gas {c.gas_brake:+.1f} "
            f"steer {c.steering:+.1f} gear {gear} signal {TurnSignal(c.turn_signal).name.lower()}"
            f" horn {'on' if c.horn else 'off'} | sent {remote.stats.sent} "
            f"lost {remote.stats.lost}   ")


_REQUESTS = {"s": "stop", "r": "release", "t": "status"}
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
    if key == " ":  # the toggle
        if not remote.held:
            return actions.hold(remote)
        actions.lift(remote)
        return None
    if key in _REQUESTS:
        return actions.try_request(remote, _REQUESTS[key])
    if key in _ARROWS:
        name, step = _ARROWS[key]
        value = round(max(-1.0, min(1.0, getattr(c, name) + step)), 1)
        remote.set_control(**{name: value})
    elif key == "n":
        actions.neutral(remote)
    elif key == "g":
        actions.next_gear(remote)
    elif key == "h":
        remote.set_control(horn=1 - c.horn)
    elif key in ("0", "1", "2", "3"):
        remote.set_control(turn_signal=int(key))
    return None


def run_interactive(remote: Remote, out: Callable[..., None]) -> None:
    """Keys from the terminal (cbreak mode, restored on exit) until q or Ctrl-C; ``out``
    writes one line (the command's output)."""
    fd = sys.stdin.fileno()
    out(WARNING)
    out(_HELP)
    with _raw_terminal(fd):
        try:
            while True:
                sys.stdout.write(_status_line(remote))
                sys.stdout.flush()
                for key in _split_keys(_read_keys(fd, 0.1)):
                    line = handle_key(remote, key)
                    if line == "quit":
                        return
                    if line:
                        out("\n" + line)
        finally:
            out()  # leave the status line, whatever ended the loop (q, Ctrl-C)

