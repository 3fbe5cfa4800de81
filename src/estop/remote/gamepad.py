"""``estop remote --gamepad [DEVICE]``: a game controller as the remote, read through Linux
evdev (python-evdev, the ``gamepad`` extra), with a real dead-man.

A terminal cannot see a key being let go, so the keyboard remote's space bar is a toggle; a
game controller reports every press and release. Holding the dead-man (the left trigger by
default, :mod:`estop.remote.gamepadmap`) sends control packets through :class:`~estop.client.sender.
Remote`; letting go lifts at once: the lift datagram goes out from the event that reported
the release, and two more 10 ms apart, as at the end of any hold. When the device goes away
(unplugged, a read error) the remote lifts the same way, sends nothing more and the command
ends with exit code 3.

The stop button, RELEASE and STATUS (B, START, SELECT) go over TCP from a thread of their
own, so a slow or dead stop channel never delays the reading of the pad (and so a lift).
With a key the unit's session is learnt (STATUS) before the pad is read: a hold then never
waits for the network.
"""

from __future__ import annotations

import queue
import select
import signal
import threading
from collections.abc import Callable
from types import ModuleType
from typing import Any

from estop.client.channel import StopChannelError, format_reply
from estop.client.sender import Remote
from estop.errors import EXIT_UNREACHABLE, ConnectionFailure, UsageError
from estop.extras import require_extra
from estop.protocol.udp import InvalidPacket
from estop.remote import actions
from estop.remote.gamepadmap import (
    ABS_NAMES,
    DEADMAN_PREFERENCE,
    EV_ABS,
    EV_KEY,
    Act,
    Action,
    AxisRange,
    PadLayout,
    PadMapper,
    choose_deadman,
)

__all__ = ["load_evdev", "open_pad", "run_gamepad"]

Log = Callable[[str], None]


def load_evdev() -> ModuleType:
    """python-evdev, or a one-line error (exit 5, not installed) naming the extra."""
    require_extra("gamepad", "evdev")
    import evdev

    module: ModuleType = evdev
    return module


def _layout(device: Any, deadman: str | None) -> PadLayout:
    caps = device.capabilities(absinfo=True)
    keys = set(caps.get(EV_KEY, []))
    axes = {code: AxisRange(info.min, info.max, info.flat) for code, info in caps.get(EV_ABS, [])}
    return PadLayout(deadman=choose_deadman(keys, axes, deadman), axes=axes)


def _is_pad(device: Any) -> bool:
    caps = device.capabilities(absinfo=False)
    keys = set(caps.get(EV_KEY, []))
    axes = set(caps.get(EV_ABS, []))
    if ABS_NAMES["ABS_X"] not in axes:
        return False
    try:
        choose_deadman(keys, {a: AxisRange(0, 1) for a in axes})
    except ValueError:
        return False
    return True


def open_pad(evdev: ModuleType, path: str | None, deadman: str | None) -> tuple[Any, PadLayout]:
    """The device at ``path`` (or the first game controller found) and its layout; a
    one-line error when there is none or it cannot be opened."""
    if path is None:
        found = []
        for p in sorted(evdev.list_devices()):
            try:
                dev = evdev.InputDevice(p)
            except OSError:
                continue
            if _is_pad(dev):
                found.append(dev)
            else:
                dev.close()
        if not found:
            raise ConnectionFailure("no game controller found in /dev/input (one with a left "
                                    f"stick and one of {', '.join(DEADMAN_PREFERENCE)}); "
                                    "name it: --gamepad /dev/input/eventN")
        for extra in found[1:]:
            extra.close()
        device = found[0]
    else:
        try:
            device = evdev.InputDevice(path)
        except OSError as exc:
            raise ConnectionFailure(f"cannot open {path}: {exc.strerror or exc}") from None
    try:
        return device, _layout(device, deadman)
    except ValueError as exc:
        device.close()
        raise UsageError(f"{device.path} ({device.name}): {exc}") from None


def _state(device: Any, layout: PadLayout) -> tuple[set[int], dict[int, int]]:
    keys = set(device.active_keys())
    values = {code: device.absinfo(code).value for code in layout.axes}
    return keys, values


class _Requests:
    """The TCP requests of the pad's buttons, one at a time, in a thread of their own."""

    def __init__(self, remote: Remote, log: Log) -> None:
        self.remote = remote
        self.log = log
        self._queue: queue.Queue[Act | None] = queue.Queue()
        self._thread = threading.Thread(target=self._loop, name="estop-pad-tcp", daemon=True)
        self._thread.start()

    def submit(self, act: Act) -> None:
        self._queue.put(act)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=self.remote.stop_deadline + 5.0)

    def _loop(self) -> None:
        while (act := self._queue.get()) is not None:
            self.log(actions.try_request(self.remote, act.value))


class _PadRun:
    def __init__(self, remote: Remote, device: Any, layout: PadLayout, log: Log) -> None:
        self.remote = remote
        self.device = device
        self.layout = layout
        self.mapper = PadMapper(layout)
        self.log = log
        self.requests = _Requests(remote, log)

    def apply(self, todo: list[Action]) -> None:
        for action in todo:
            act = action.act
            if act is Act.LIFT:
                n = actions.lift(self.remote)  # the first lift datagram is out on return
                self.log(f"dead-man released: lift sent x{n}" if n else "dead-man released")
            elif act is Act.HOLD:
                self.log(actions.hold(self.remote) or "dead-man held: sending")
            elif act is Act.CONTROL:
                try:
                    self.remote.set_control(None, **action.fields)
                except InvalidPacket as exc:  # cannot happen with clamped axes; never fatal
                    self.log(f"control ignored: {exc}")
            elif act is Act.NEXT_GEAR:
                self.log(f"gear {actions.next_gear(self.remote).name.lower()}")
            elif act is Act.RESYNC:
                self.log("events lost (SYN_DROPPED): state read again from the device")
                self.apply(self.mapper.sync(*_state(self.device, self.layout)))
            else:
                self.requests.submit(act)

    def run(self) -> int:
        try:
            self.apply(self.mapper.sync(*_state(self.device, self.layout)))
            dev = self.device
            self.log(f"gamepad {dev.path} ({dev.name}): {self.layout.describe()}")
            if not self.mapper.armed:
                self.log("the dead-man is held already: let go of it, then hold it to drive")
            while True:
                ready, _, _ = select.select([self.device.fd], [], [], 0.5)
                if not ready:
                    continue
                try:
                    events = list(self.device.read())
                except BlockingIOError:
                    continue
                for ev in events:
                    self.apply(self.mapper.event(ev.type, ev.code, ev.value))
        except OSError as exc:  # unplugged (ENODEV), a read error: lift, send nothing more
            return self._lost(exc)
        finally:
            self.requests.close()

    def _lost(self, exc: OSError) -> int:
        n = self.remote.lift()
        self.remote.wait_lift_sent()
        what = exc.strerror or str(exc)
        lifted = f"lift sent x{self.remote.lift_sent}" if n else "was not held"
        self.log(f"gamepad lost ({what}): {lifted}; no more control packets")
        return EXIT_UNREACHABLE


def _interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def run_gamepad(remote: Remote, path: str | None, deadman: str | None, log: Log) -> int:
    """Drive ``remote`` from the pad until it goes away (exit code 3) or Ctrl-C (the caller
    lifts a hold still on)."""
    evdev = load_evdev()
    device, layout = open_pad(evdev, path, deadman)
    # SIGTERM and SIGHUP (a closed terminal, a session ending) end the run like Ctrl-C: the
    # caller's clean-up lifts a hold still on, rather than the unit waiting for its timeout.
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _interrupt)
    try:
        if remote.identity.keyed:
            try:
                log(f"status -> {format_reply(remote.status())}")  # learn the session first
            except StopChannelError as exc:
                raise ConnectionFailure(f"status (to learn the session): {exc}") from None
        return _PadRun(remote, device, layout, log).run()
    finally:
        try:
            device.close()
        except OSError:
            pass

