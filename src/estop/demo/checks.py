"""Did the demo's story happen? Each check names what did not, in one line; the demo fails
(exit 1) on any. They judge outcomes (states, reasons, order), never how fast: timing goals
live in the bench."""

from __future__ import annotations

import signal

from estop.client.button import LIFT_SENDS
from estop.demo.bus import BusWatch
from estop.demo.result import Result, StopMeasure
from estop.protocol import can, tcp

__all__ = ["check"]

_OK_EXIT = (0, -signal.SIGTERM)


def _nak(name: str, got: int | None, want: int) -> list[str]:
    if got is None or got == want:
        return []
    what = "an ACK" if got == 0 else f"NAK {got}"
    return [f"{name} was not refused with NAK {want} ({tcp.NAK_NAMES.get(want)}): got {what}"]


def _stop(m: StopMeasure | None, reason: int, name: str) -> list[str]:
    if m is None:
        return []
    if m.stop is None:
        return [f"no stop after {name}"]
    if m.stop.reason != reason:
        return [f"{name} stopped the car with reason {can.reason_name(m.stop.reason)}, not "
                f"{can.reason_name(reason)}"]
    return []


def _lift(res: Result) -> list[str]:
    m = res.lift
    if m is None:
        return []
    out = _stop(m, can.Reason.LIFT, "the finger lift")
    if res.lift_datagrams != LIFT_SENDS:
        out.append(f"the remote sent {res.lift_datagrams} lift datagrams, not {LIFT_SENDS}")
    if m.stop is not None and any(c.state == can.State.SLOWING for c in m.between):
        out.append("the unit slowed before the lift stopped it: it waited for the silence")
    return out


def _burst(res: Result) -> list[str]:
    b = res.burst
    if b is None:
        return []
    ms = res.settings.burst_ms
    if b.stops:
        return [f"the burst of {ms} ms (shorter than the timeout) latched a stop, reason "
                f"{can.reason_name(b.stops[0].reason)}"]
    if b.slowing is None:
        return [f"the burst of {ms} ms (longer than the slow time) did not slow the car: no "
                f"SLOWING"]
    if b.armed is None:
        return [f"the unit did not come back to ARMED after the burst of {ms} ms"]
    return []


def _loss(res: Result) -> list[str]:
    m = res.loss
    if m is None:
        return []
    out = _stop(m, can.Reason.UDP_TIMEOUT, "the loss of the link")
    if m.stop is None:
        return out
    if m.slowing is None or m.slowing.t > m.stop.t:
        out.append("the loss of the link did not slow the car first: no SLOWING before the "
                   "stop")
    if any(c.state == can.State.ARMED for c in m.between):
        out.append("the unit went back to ARMED while the link was down: the attacker's "
                   "heartbeats counted")
    return out


def check(res: Result, watch: BusWatch, rc: int | None, v2_rc: int | None = None) -> list[str]:
    """Every way the story did not happen, given the result, the unit's bus and the exit
    codes of the unit and of the version-2 unit (None: not run)."""
    out = _nak("the RELEASE before any packet", res.boot_release_nak,
               tcp.NakCode.NO_LIVE_LINK)
    out += _lift(res)
    out += _stop(res.v2, can.Reason.UDP_TIMEOUT, "the lift on the version-2 unit")
    out += _nak("the attacker's forged RELEASE", res.forged_release_nak,
                tcp.NakCode.NOT_AUTHENTICATED)
    out += _burst(res)
    out += _loss(res)
    out += _stop(res.datagram, can.Reason.TCP_STOP, "the attacker's stop datagram")
    out += _stop(res.button, can.Reason.TCP_STOP, "the stop button")
    out += _nak("the RELEASE with the gas pressed", res.latched_release_nak,
                tcp.NakCode.NOT_NEUTRAL)
    if res.button is None and not (res.problems or out):
        out.append("the story did not reach its end")
    final = watch.brake
    if final is None or final.brake_request != can.BrakeRequest.EMERGENCY:
        out.append("the unit's last frame did not request the emergency brake")
    if watch.bad_frames:
        out.append(f"{watch.bad_frames} logged frames failed their checks")
    if rc not in _OK_EXIT:
        out.append(f"estopd ended abnormally (exit code {rc})")
    if v2_rc is not None and v2_rc not in _OK_EXIT:
        out.append(f"the version-2 estopd ended abnormally (exit code {v2_rc})")
    return out
