"""The stop that needs no connection: ``estop stop`` under a connect storm.

The unit keeps 8 stop-channel connections and closes the quietest when a new one comes
(docs/PROTOCOL.md section 2). An attacker can game that: eight connections that send STATUS
every few ms keep any genuine idle connection the quietest, so each new connect of the
attacker closes it. What still stops the car is the stop datagram, which needs no connection:
``estop stop`` sends one with every try, beside STOP over TCP. This row proves it end to end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from estop.protocol import auth, tcp
from estop.protocol.can import BrakeFrame
from hilemu import Frame
from hiljudge import judge, judge_spoiled, link_died_first, show_ex, wait_state_lines
from hilload import UdpTap
from hilrun import (
    STOP_DEADLINE_MS,
    STORM_BUSY,
    STORM_BUSY_MS,
    STORM_CONNECT_MS,
    STORM_RUNS,
    Result,
    Row,
    Run,
    ms,
)
from hilstalls import overlap
from hilstats import summary

STORM_SETTLE_S = 0.15  # the storm runs this long before the press: the idle clients are gone
COMMAND_LIMIT_S = 60.0  # a Python start under TCG on a busy host can take tens of seconds
STOPPED, TCP_STOP = 0, 2


def evicted(run: Run) -> int:
    """How many of the harness's idle stop clients the unit has closed (EOF or reset)."""
    return sum(c.peer_closed() for c in run.clients)


def is_stop_datagram(payload: bytes) -> bool:
    """A 48-byte request frame (spec section 5.2) with the default stop ID."""
    return (len(payload) == auth.REQUEST_SIZE and payload[:4] == tcp.REQUEST_MAGIC
            and int.from_bytes(payload[4:8], "little") == tcp.DEFAULT_STOP_ID)


@dataclass
class Pressed:
    """What one press under the storm gave."""

    t_arm: float  # when the harness began to arm the unit (its keepalive from then on)
    t_go: float  # when the command was told to run
    t_first: float | None  # the kernel's time of its first stop datagram (the loopback tap)
    stop: tuple[Frame, BrakeFrame] | None  # the first STOPPED frame after the press began
    code: int | None  # the command's exit code (None: it did not end, and was killed)
    output: str  # its output line
    idle_closed: int  # the harness's idle stop clients the storm had closed before the press
    storm: dict  # storm.py's counts


def press_in_storm(run: Run, res: Result, i: int, tap: UdpTap) -> Pressed:
    """Arm, start the storm, let it close the idle clients, press the stop button, end the
    storm. The command's process was started with the run (its interpreter's start is not the
    test)."""
    assert run.storm is not None
    cmd = run.estop_stop()
    cmd.ready(COMMAND_LIMIT_S)
    t_arm = time.time()
    run.arm(res)
    start = run.mon.index()
    tap.read()  # what came before this press
    busy = run.storm.start()
    try:
        if not busy.get("busy"):  # the idle clients' fate below says whether it held
            res.notes.append(f"run {i}: not every busy connection of the storm had a reply "
                             f"within 5 s: {busy}")
        time.sleep(STORM_SETTLE_S)
        idle = evicted(run)
        code, output = cmd.go(STOP_DEADLINE_MS / 1000 + COMMAND_LIMIT_S)
    finally:
        figures = run.storm.stop()
    sent = [ts for ts, p in tap.read() if ts >= cmd.t_go and is_stop_datagram(p)]
    got = run.brake_after(start, lambda b: b.state == STOPPED, 1.0, after=cmd.t_go)
    run.udp.stop()
    return Pressed(t_arm, cmd.t_go, min(sent) if sent else None, got, code, output, idle,
                   figures)


def sc_storm_stop(run: Run, res: Result) -> None:
    assert run.storm is not None
    run.storm.ready(COMMAND_LIMIT_S)  # started with the run
    d = run.daemon
    lat: list[tuple[float, float]] = []
    cmd_ms: list[float] = []
    acks = idle_gone = spoiled = presses = 0
    counts: dict[str, float] = {}
    tap = UdpTap(run.udp_port, auth.REQUEST_SIZE)
    try:
        for i in range(STORM_RUNS):
            if i:
                run.reconnect_clients()  # the storm closed them
            since = time.monotonic()
            pr = press_in_storm(run, res, i, tap)
            presses += 1
            idle_gone += pr.idle_closed
            for k in ("connects", "status_sent", "busy_closed_by_unit", "refused"):
                counts[k] = counts.get(k, 0) + float(pr.storm[k])
            counts["storm_s"] = counts.get("storm_s", 0) + pr.storm["t1"] - pr.storm["t0"]
            if pr.code is None:
                # Not ended a minute past its deadline: with the CPUs standing still most of
                # that time (a host far too busy) it never ran: inconclusive, not a pass.
                stall = overlap(run.stalls(), pr.t_go, time.time())
                why = (f"run {i}: estop stop did not end {COMMAND_LIMIT_S:g} s after its "
                       f"deadline; a CPU stood still or the daemon queued {ms(stall)} ms meanwhile")
                if stall >= COMMAND_LIMIT_S / 2:
                    res.inconclusive = why
                    why = f"not judged: {why}"
                res.check(False, why)
                break
            if pr.t_first is None:
                res.check(False, f"run {i}: no stop datagram from estop stop seen on loopback")
                continue
            if pr.stop is not None and link_died_first(run.udp, pr.t_arm, pr.t_first,
                                                       pr.stop[1].reason):
                spoiled += 1  # the harness let the link die before the press: not a sample
                continue
            if pr.stop is None:
                res.check(False, f"run {i}: no STOPPED frame within 1 s of the stop datagram")
                continue
            fr, b = pr.stop
            res.check(b.reason == TCP_STOP, f"run {i}: bus reason {b.reason}, want 2 (stop)")
            lat.append((pr.t_first, fr.ts))
            cmd_ms.append(ms(pr.t_first - pr.t_go))
            res.check(fr.ts - pr.t_first <= STOP_DEADLINE_MS / 1000,
                      f"run {i}: stopped {ms(fr.ts - pr.t_first)} ms after the first datagram, "
                      f"past the command's deadline")
            if pr.code == 0:
                acks += 1
            else:
                res.notes.append(f"run {i}: estop stop exit {pr.code}: {pr.output[:160]}")
            if i == 0:
                res.figures["command_reply"] = pr.output[:200]
                res.figures["log"] = ", ".join(c.text() for c in wait_state_lines(d, since, 1))
    finally:
        tap.close()
        run.reconnect_clients()  # the storm has closed them
    judge(run, res, "stop_frame_latency_ms", "estop stop: first stop datagram -> stop frame", lat)
    res.figures["command_run_to_first_datagram_ms"] = summary(cmd_ms)
    res.figures["command_acked"] = f"{acks} of {len(lat)}"
    res.figures["idle_clients_closed_by_the_storm"] = f"{idle_gone} of {4 * presses}"
    secs = max(counts.get("storm_s", 0.0), 0.001)
    res.figures["storm"] = (f"{STORM_BUSY} busy connections (STATUS every {STORM_BUSY_MS:g} ms "
                            f"asked, {counts.get('status_sent', 0) / secs:.0f}/s sent), new "
                            f"connections every {STORM_CONNECT_MS:g} ms asked "
                            f"({counts.get('connects', 0) / secs:.0f}/s made, "
                            f"{counts.get('refused', 0)} refused), busy ones the unit closed "
                            f"{counts.get('busy_closed_by_unit', 0)}; {secs:.2f} s of storm")
    # The storm must really have held every place: the genuine idle clients were closed.
    res.check(idle_gone == 4 * presses,
              f"the storm did not close every idle client ({idle_gone} of "
              f"{4 * presses}): the attack this row is about did not happen")
    ex = run.clients[0].status()
    res.figures["status_after"] = show_ex(ex)
    res.check(ex.reply.state == STOPPED and (ex.reply.reason == TCP_STOP or spoiled > 0),
              "STATUS after the storm is not STOPPED reason 2")
    judge_spoiled(res, spoiled, STORM_RUNS, len(lat), "not every press stopped the unit",
                  keepalive=True)


ROWS: list[Row] = [
    ("storm_stop", "estop stop under a connect storm (all 8 places held busy)",
     f"{STORM_BUSY} attacker connections (STATUS every {STORM_BUSY_MS:g} ms) and a new "
     f"connection every {STORM_CONNECT_MS:g} ms close every idle client; x{STORM_RUNS} the "
     "real `estop stop` (stop datagram + TCP STOP, retried): STOPPED reason 2 on the bus, "
     "first stop datagram (loopback tap) -> stop frame p50 <= {p50}, max <= {max} ms; "
     "STATUS STOPPED after", sc_storm_stop),
]
