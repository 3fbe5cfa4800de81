"""The demo's end: the timeline (every state change on the bus with its cause from the unit's
own log, and what the demo did), the table of stops (latency from the moment that mattered,
distance to standstill), the burst, the attacker's tally and the checks of the frames.

Every figure comes from the run: the unit's can-log stamps against the send times (both
CLOCK_REALTIME), the roll-outs from the logged frames through the brake controller emulation
and the vehicle model (docs/VEHICLE.md).
"""

from __future__ import annotations

import time
from typing import TextIO

from estop.demo.bus import BusWatch, Change
from estop.demo.result import BurstMeasure, Result, StopMeasure
from estop.demo.view import View
from estop.model.vehicle import DEFAULT_PARAMS
from estop.protocol import can, tcp
from estop.unit.events import StateChange

__all__ = ["match_causes", "timeline", "write_report"]

MATCH_S = 0.5  # a state line and its frame are at most this far apart


def match_causes(changes: list[Change], lines: list[StateChange],
                 clock: float) -> dict[int, StateChange]:
    """Each change of state or reason on the bus (by ``id``) with the unit's ``state`` line for
    it: the same new state and reason, the first not yet taken, within :data:`MATCH_S`.
    ``clock`` is realtime - monotonic. The boot frame has none."""
    out: dict[int, StateChange] = {}
    used: set[int] = set()
    for c in changes:
        if c.flags_only:
            continue
        to, reason = can.state_name(c.state), can.reason_name(c.reason)
        for i, ln in enumerate(lines):
            if (i not in used and ln.to == to and ln.reason == reason
                    and abs(ln.t_mono + clock - c.t) < MATCH_S):
                out[id(c)] = ln
                used.add(i)
                break
    return out


def timeline(view: View, buses: list[tuple[str, BusWatch, dict[int, StateChange]]]
             ) -> list[tuple[float, str]]:
    """The demo's events and every change on each bus (``(who, watch, causes)``), in order."""
    entries = list(view.events)
    for who, watch, causes in buses:
        for c in watch.changes:
            text = f"{who}: {c.text()}"
            line = causes.get(id(c))
            if line is not None:
                text += f"; unit's log: {line.frm}->{line.to} cause={line.cause}"
            entries.append((c.t, text))
    return sorted(entries, key=lambda e: e[0])


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f} ms"


def _answer(c: Change | None, causes: dict[int, StateChange]) -> str:
    """``STOPPED lift (lift_datagram)``, ``SLOWING brake 30 % (udp_silence)``."""
    if c is None:
        return "none seen"
    line = causes.get(id(c))
    if c.state == can.State.SLOWING:
        what = f"SLOWING brake {c.frame.brake_level} %"
    elif c.state == can.State.ARMED:
        what = "ARMED"
    else:
        what = f"{can.state_name(c.state)} {can.reason_name(c.reason)}"
    return what + (f" ({line.cause})" if line is not None else "")


def _distance(m: StopMeasure) -> str:
    r = m.rollout
    if r is None:
        return "-"
    text = f"{r.distance:.3f} m in {r.time_to_standstill * 1000:.0f} ms"
    if r.reaction_time is not None and r.reaction_time > 0.0005:
        text += f", braking from +{r.reaction_time * 1000:.1f} ms"
    return text


WHAT_W, ANSWER_W, LATENCY_W = 48, 34, 11


def _stop_rows(m: StopMeasure, causes: dict[int, StateChange]) -> list[str]:
    lost = (f"not measured: {m.lost} can-log line{'s' if m.lost != 1 else ''} lost"
            if m.lost else None)
    what = f"{m.what}, from {m.moment_name}"
    rows = []
    if m.slowing is not None:
        rows.append(f"  {what:{WHAT_W}}  {_answer(m.slowing, causes):{ANSWER_W}}  "
                    f"{lost or _ms(m.latency_ms(m.slowing)):>{LATENCY_W}}")
        what = ""
    rows.append(f"  {what:{WHAT_W}}  {_answer(m.stop, causes):{ANSWER_W}}  "
                f"{lost or _ms(m.latency_ms(m.stop)):>{LATENCY_W}}  "
                f"{'' if lost else _distance(m)}")
    return rows


def _lift_line(res: Result) -> str | None:
    lift, v2 = res.lift, res.v2
    if (lift is None or v2 is None or lift.rollout is None or v2.rollout is None
            or lift.lost or v2.lost):
        return None
    saved = v2.rollout.distance - lift.rollout.distance
    return (f"  The lift: the car stood still {lift.rollout.distance:.3f} m from where the finger "
            f"lifted; a version-2 unit, waiting for its timeout, let it roll "
            f"{v2.rollout.distance:.3f} m ({saved:.3f} m further).")


def _burst_line(b: BurstMeasure, res: Result, causes: dict[int, StateChange]) -> str:
    s = res.settings
    silence = "-" if b.silence_ms is None else f"{b.silence_ms:.0f} ms"
    head = (f"Bursty link: every packet lost for {(b.end - b.cut) * 1000:.0f} ms "
            f"({b.packets_lost} packets; {silence} without a packet, S {s.slow_ms} ms, "
            f"T {s.timeout_ms} ms): ")
    if b.lost:
        return head + f"not measured: {b.lost} can-log lines lost"
    if b.stops:
        return head + (f"a latched stop, reason {can.reason_name(b.stops[0].reason)} "
                       f"{_ms(b.after_last_ms(b.stops[0]))} after the last packet")
    if b.slowing is None:
        return head + "no SLOWING"
    text = (head + f"{_answer(b.slowing, causes)} {_ms(b.after_last_ms(b.slowing))} after the "
            f"last packet, ")
    if b.armed is None:
        return text + "not ARMED again"
    return text + (f"{_answer(b.armed, causes)} again {_ms(b.after_last_ms(b.armed))} after it, "
                   f"no latched stop; the car slowed from {b.speed_before * 3.6:.1f} to "
                   f"{b.speed_low * 3.6:.1f} km/h and drove on.")


def _attacker_text(res: Result) -> str:
    """What the heartbeats achieved, as the bus showed it."""
    loss = res.loss
    if loss is None or loss.stop is None:
        return "its heartbeats while the link was down: no stop seen"
    armed = any(c.state == can.State.ARMED for c in loss.between)
    if loss.slowing is not None and not armed:
        return ("its heartbeats held off neither the SLOWING nor the emergency stop while the "
                "link was down")
    return ("its heartbeats did not hold off the emergency stop while the link was down"
            + ("; the unit went ARMED in between" if armed else ""))


def _datagram_text(res: Result) -> str:
    m = res.datagram
    if m is None or m.stop is None:
        return "its stop datagram: no stop seen"
    return "its stop datagram stopped the car, because anyone may stop"


def write_report(out: TextIO, view: View, res: Result, causes: dict[int, StateChange],
                 v2: tuple[BusWatch, dict[int, StateChange]] | None = None,
                 dropped: int = 0) -> None:
    """The timeline and the summary. ``causes`` matches the unit's changes to its state
    lines (:func:`match_causes`), ``v2`` the same for the version-2 unit."""
    buses = [("bus", view.watch, causes)]
    if v2 is not None:
        buses.append(("v2 unit bus", v2[0], v2[1]))
    out.write("\nTimeline (each change on the bus, with its cause from the unit's log)\n")
    for t, text in timeline(view, buses):
        out.write(f"  {t - view.t0:7.3f}s  {text}\n")

    s = res.settings
    out.write(f"\nStops (the car at {s.speed * 3.6:.1f} km/h at each moment; the vehicle model, "
              f"{DEFAULT_PARAMS.emergency_decel:g} m/s^2 at full braking, replayed from the "
              f"logged frames)\n")
    out.write(f"  {'what happened, from when':{WHAT_W}}  {'the unit answered (cause)':{ANSWER_W}}  "
              f"{'latency':>{LATENCY_W}}  distance to standstill\n")
    for m in res.stops():
        for row in _stop_rows(m, v2[1] if (v2 is not None and m.unit == "v2") else causes):
            out.write(row.rstrip() + "\n")
    lift = _lift_line(res)
    if lift is not None:
        out.write(lift + "\n")
    if res.burst is not None:
        out.write("\n" + _burst_line(res.burst, res, causes) + "\n")

    sent = ", ".join(f"{n} {kind}" for kind, n in res.attacker_sent.items()) or "-"
    nak = ("-" if res.forged_release_nak is None else
           f"NAK {res.forged_release_nak} "
           f"({tcp.NAK_NAMES.get(res.forged_release_nak, res.forged_release_nak)})")
    out.write(f"\nThe attacker (no key): {_attacker_text(res)} ({sent}); its forged RELEASE "
              f"got {nak}; {_datagram_text(res)}.\n")
    w = view.watch
    out.write(f"  frames checked: {w.frames} (bad CRC or content: {w.bad_frames}, alive counter "
              f"jumps: {w.counter_jumps}, lines the daemon reported dropped: {dropped})\n")
    if any(m.lost for m in res.stops()):
        out.write("  (a figure is only given when no can-log line was lost around it: a lost "
                  "first stop frame would make the next one look late)\n")


def clock() -> float:
    """realtime - monotonic, now (to place the unit's log lines on the can-log's clock)."""
    return time.time() - time.monotonic()
