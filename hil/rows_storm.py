"""The stop that needs no connection: ``estop stop`` under a connect storm.

The unit keeps 8 stop-channel connections and closes the quietest when a new one comes
(docs/PROTOCOL.md section 2). An attacker can game that: eight connections that send STATUS
every few ms keep any genuine idle connection the quietest, so each new connect of the
attacker closes it. What still stops the car is the stop datagram, which needs no connection:
``estop stop`` sends one with every try, beside STOP over TCP. This row proves it end to end.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time

from estop.protocol import tcp
from hiljudge import judge, judge_spoiled, show_ex, wait_state_lines
from hilload import UdpTap
from hilrig import RigError
from hilrun import (
    KEEPALIVE_GAP_S,
    STORM_BUSY,
    STORM_BUSY_MS,
    STORM_CONNECT_MS,
    Result,
    Row,
    Run,
    ms,
)
from hilstats import summary

STORM_RUNS = 3  # presses of the stop button (each a start of the real command)
STORM_SETTLE_S = 0.15  # the storm runs this long before the press: the idle clients are gone
STOP_DEADLINE_MS = 3000  # estop stop's own deadline (its default)
COMMAND_LIMIT_S = 60.0  # a Python start under TCG on a busy host can take tens of seconds
STOPPED, TCP_STOP = 0, 2


def evicted(run: Run) -> int:
    """How many of the harness's idle stop clients the unit has closed (EOF or reset)."""
    n = 0
    for c in run.clients:
        try:
            data = c.sock.recv(16, socket.MSG_DONTWAIT | socket.MSG_PEEK)
            n += data == b""
        except BlockingIOError:
            pass
        except OSError:
            n += 1
    return n


def is_stop_datagram(payload: bytes) -> bool:
    """A 48-byte request frame (spec section 5.2) with the default stop ID."""
    return (len(payload) == 48 and payload[:4] == tcp.REQUEST_MAGIC
            and int.from_bytes(payload[4:8], "little") == tcp.DEFAULT_STOP_ID)


def press(run: Run, estop: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """``estop stop`` as an operator runs it (datagram and TCP, tried again until an answer or
    its deadline); returns its outcome and the time it was started."""
    argv = [estop, "stop", "--host", "127.0.0.1", "--tcp-port", str(run.tcp_port),
            "--udp-port", str(run.udp_port), "--stop-deadline-ms", str(STOP_DEADLINE_MS),
            "--json"]
    t0 = time.time()
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=COMMAND_LIMIT_S,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        raise RigError(f"estop stop did not end within {COMMAND_LIMIT_S:g} s") from exc
    return proc, t0


def sc_storm_stop(run: Run, res: Result) -> None:
    estop = shutil.which("estop")
    if estop is None:
        raise RigError("the estop command is not on PATH (make setup)")
    assert run.storm is not None
    run.storm.ready()
    d = run.daemon
    lat: list[tuple[float, float]] = []
    cmd_ms: list[float] = []
    acks = idle_gone = spoiled = 0
    counts: dict[str, int] = {}
    tap = UdpTap(run.udp_port)
    try:
        for i in range(STORM_RUNS):
            if i:
                run.reconnect_clients()  # the storm closed them
            t_arm = time.time()
            run.arm(res)
            since = time.monotonic()
            start = run.mon.index()
            tap.read()  # what came before this press
            busy = run.storm.start()
            res.check(bool(busy.get("busy")), f"run {i}: the storm's busy connections did not "
                                              f"all get a reply: {busy}")
            time.sleep(STORM_SETTLE_S)
            idle_gone += evicted(run)
            try:
                proc, t_cmd = press(run, estop)
            finally:
                figures = run.storm.stop()
            for k in ("connects", "status_sent", "busy_closed_by_unit", "refused"):
                counts[k] = counts.get(k, 0) + int(figures[k])
            counts["storm_ms"] = counts.get("storm_ms", 0) + int(
                (figures["t1"] - figures["t0"]) * 1000)
            sent = [ts for ts, p in tap.read() if ts >= t_cmd and is_stop_datagram(p)]
            got = run.brake_after(start, lambda b: b.state == STOPPED, 1.0)
            run.udp.stop()
            if not sent:
                res.check(False, f"run {i}: no stop datagram from estop stop seen on loopback")
                continue
            t_first = min(sent)
            if got is not None and got[1].reason != TCP_STOP and \
                    run.udp.max_gap(t_arm, t_first) >= KEEPALIVE_GAP_S:
                spoiled += 1  # the harness let the link die before the press: not a sample
                continue
            if got is None:
                res.check(False, f"run {i}: no STOPPED frame within 1 s of the stop datagram")
                continue
            fr, b = got
            res.check(b.reason == TCP_STOP, f"run {i}: bus reason {b.reason}, want 2 (stop)")
            lat.append((t_first, fr.ts))
            cmd_ms.append(ms(t_first - t_cmd))
            res.check(fr.ts - t_first <= STOP_DEADLINE_MS / 1000,
                      f"run {i}: stopped {ms(fr.ts - t_first)} ms after the first datagram, "
                      f"past the command's deadline")
            if proc.returncode == 0:
                acks += 1
            else:
                res.notes.append(f"run {i}: estop stop exit {proc.returncode}: "
                                 f"{(proc.stdout or proc.stderr).strip()[:160]}")
            if i == 0:
                res.figures["command_reply"] = proc.stdout.strip()[:200]
                res.figures["log"] = ", ".join(c.text() for c in wait_state_lines(d, since, 1))
    finally:
        tap.close()
        run.reconnect_clients()  # the storm has closed them
    judge(run, res, "stop_frame_latency_ms", "estop stop: first stop datagram -> stop frame", lat)
    res.figures["command_start_to_first_datagram_ms"] = summary(cmd_ms)
    res.figures["command_acked"] = f"{acks} of {len(lat)}"
    res.figures["idle_clients_closed_by_the_storm"] = f"{idle_gone} of {4 * STORM_RUNS}"
    secs = max(counts.get("storm_ms", 0), 1) / 1000
    res.figures["storm"] = (f"{STORM_BUSY} busy connections (STATUS every {STORM_BUSY_MS:g} ms "
                            f"asked, {counts.get('status_sent', 0) / secs:.0f}/s sent), new "
                            f"connections every {STORM_CONNECT_MS:g} ms asked "
                            f"({counts.get('connects', 0) / secs:.0f}/s made, "
                            f"{counts.get('refused', 0)} refused), busy ones the unit closed "
                            f"{counts.get('busy_closed_by_unit', 0)}; {secs:.2f} s of storm")
    # The storm must really have held every place: the genuine idle clients were closed.
    res.check(idle_gone == 4 * STORM_RUNS,
              f"the storm did not close every idle client ({idle_gone} of "
              f"{4 * STORM_RUNS}): the attack this row is about did not happen")
    ex = run.clients[0].status()
    res.figures["status_after"] = show_ex(ex)
    res.check(ex.reply.state == STOPPED and ex.reply.reason == TCP_STOP,
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
