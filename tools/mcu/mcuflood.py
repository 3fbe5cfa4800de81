"""A flood of forged authenticated packets on a Cortex-M0+ at 48 MHz (issue 16, defect 10).

The M0+ -Os image of the core runs in the emulator, every call counted exactly (block
counting, mcuemu.CortexM), inside a simulated bare-metal host: one CPU, a receive queue of
RX_QUEUE datagrams (what a small Ethernet or Wi-Fi driver holds; a datagram that finds it full
is dropped, as the hardware would), and a main loop that calls estop_tick when the core's
next_call_us is reached (deadlines first) and otherwise hands the oldest queued datagram to
estop_udp_rx. Each call takes its instructions times CPI cycles at F_CPU.

The scenario: a unit with a key armed by its remote (remote id 7, 50 Hz, RELEASE over TCP),
then `seconds` of flood at `rate` forged 60-byte packets a second (the right session, a tag
under a wrong key: every one reaches the tag check unless the budget stops it) while the remote
keeps sending, then the remote falls silent (the finger lifts, its lift datagram lost) and the
flood goes on: the unit must stop by timeout at its deadline. Reported: CPU share, the remote's
packets that got through, the longest gap between ESTOP_BRAKE frames and how late the timeout
stop came.

Two attacks (`attack`):
- "new_ids": the forgeries carry new remote ids and fresh counters far ahead (an attacker who
  has never seen the link);
- "sniffer" (issue 25): an attacker who reads the link. The forgeries carry the remote's id and
  its next counters, and at the start of every 100 ms window it sends back, once, the oldest
  genuine packet of the remote that the unit has not taken (left unchecked by the budget, or
  dropped from the full receive queue), as long as it has one. Then the remote's last packet
  that reached the unit must still end the motion at T: reported are the control packets taken
  after the remote fell silent and the stop's time after the remote's last packet.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Any

from mcubuild import Variant
from mcuemu import ArmCore

F_CPU = 48_000_000
# Cycles per instruction assumed on the M0+: most instructions take one cycle, loads, stores
# and taken branches two, BL three; 1.5 errs on the slow side for this code (BLAKE2s is mostly
# register arithmetic).
CPI = 1.5
RX_QUEUE = 8
KEY = bytes(range(32))
WRONG_KEY = bytes(32)
SESSION = 0x0123456789ABCDEF
RID = 7
STOP_ID, STATUS, RELEASE = 0xE570E570, 1, 2
REMOTE_PERIOD_US = 20_000
UNBOUNDED = {"tag_checks": 100, "tag_window_us": 1000}  # 100,000 checks a second: no budget


@dataclass
class FloodResult:
    rate: int                  # forged datagrams a second offered
    budget: str
    cpu_share: float           # of the flood phase, at F_CPU and CPI
    insns_per_s: float         # instructions a second in the flood phase
    genuine_sent: int
    genuine_valid: int
    forged_checked: int        # forged packets that cost a tag check (auth_bad_tag)
    forged_unchecked: int      # dropped unchecked by the budget (auth_unchecked)
    rx_dropped: int            # datagrams the full receive queue dropped
    max_brake_gap_us: int      # longest time between two ESTOP_BRAKE frames sent
    max_tick_late_us: int      # longest delay of a tick past the time the core asked for
    armed_throughout: bool     # ARMED from the flood's start until the remote fell silent
    stop_late_us: int | None   # the timeout stop after its deadline (None: it never came)
    attack: str = "new_ids"
    taken_after_silence: int = 0       # control packets valid after the remote fell silent
    stop_after_last_us: int | None = None  # the stop, after the remote's last packet arrived


class _Out:
    """Fields of estop_out_t and estop_status_t read from the emulated bytes."""

    def __init__(self, arm: ArmCore) -> None:
        self.at = {ctype: {name: (off, size) for name, off, size in arm.layouts[ctype]}
                   for ctype in ("estop_out_t", "estop_status_t")}

    def get(self, ctype: str, raw: bytes, name: str) -> int:
        off, size = self.at[ctype][name]
        return int.from_bytes(raw[off:off + size], "little")


def _config(ffi: Any, lib: Any, budget: dict[str, int] | None) -> bytes:
    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)
    cfg.session = SESSION
    cfg.key_len = len(KEY)
    ffi.memmove(cfg.key, KEY, len(KEY))
    for name, value in (budget or {}).items():
        setattr(cfg, name, value)
    return bytes(ffi.buffer(cfg))


def run(v: Variant, ffi: Any, lib: Any, rate: int, seconds: float = 0.5,
        budget: dict[str, int] | None = None, cpi: float = CPI,
        attack: str = "new_ids") -> FloodResult:
    """One flood at `rate` forged datagrams a second; budget None: the core's defaults."""
    if attack not in ("new_ids", "sniffer"):
        raise ValueError(f"unknown attack {attack!r}")
    from estop.protocol import auth
    from estop.protocol.udp import ControlPacket

    arm = ArmCore(v, ffi, count="block")
    out = _Out(arm)
    body = ControlPacket()
    us_per_insn = cpi * 1e6 / F_CPU
    t_cpu = 0.0                 # the CPU is busy until then (us)
    busy = {"flood": 0.0}
    brake_times: list[float] = []
    late = {"tick": 0.0}
    state: dict[str, Any] = {"next_call": 0, "state": 0, "reason": 0, "stop_at": None,
                             "left_armed": False}
    counters = {"genuine": 0, "forged": 0}

    def call(fn: str, now: int, phase: bool, **values: Any) -> Any:
        nonlocal t_cpu
        res = arm.call(fn, {**values, "now_us": now & 0xFFFFFFFF})
        if res.ret != 0:
            raise AssertionError(f"{fn} returned {res.ret}")
        cost = arm.cpu.instructions * us_per_insn
        t_cpu = max(t_cpu, float(now)) + cost
        if phase:
            busy["flood"] += cost
        raw = res.objects.get("estop_out_t")
        if not isinstance(raw, bytes) or fn == "estop_init":
            return raw
        for i in range(out.get("estop_out_t", raw, "n_can")):
            if out.get("estop_out_t", raw, f"can[{i}].id") == 0x050:
                brake_times.append(t_cpu)
        nxt = out.get("estop_out_t", raw, "next_call_us")
        state["next_call"] = now + ((nxt - now) & 0xFFFFFFFF)
        new_state = out.get("estop_out_t", raw, "state")
        if phase and state["state"] == 1 and new_state != 1:
            state["left_armed"] = True
        if new_state == 0 and state["state"] != 0 and state["stop_at"] is None:
            state["stop_at"] = t_cpu
            state["reason"] = out.get("estop_out_t", raw, "reason")
        state["state"] = new_state
        return raw

    def genuine() -> bytes:
        counters["genuine"] += 1
        return auth.AuthControlPacket(RID, SESSION, counters["genuine"], body).encode(KEY)

    def forged() -> bytes:
        counters["forged"] += 1
        n = counters["forged"]
        if attack == "sniffer":  # the remote's id and its next counters, read off the link
            return auth.AuthControlPacket(RID, SESSION, counters["genuine"] + 1 + n % 12,
                                          body).encode(WRONG_KEY)
        return auth.AuthControlPacket(1000 + n, SESSION, 10**6 + n, body).encode(WRONG_KEY)

    call("estop_init", 0, False, cfg=_config(ffi, lib, budget))
    call("estop_tick", 0, False)
    # Arming: five packets at the remote's rate, then an authenticated RELEASE.
    now = 0
    for _ in range(5):
        now += REMOTE_PERIOD_US
        call("estop_udp_rx", now, False, data=genuine())
    call("estop_tcp_open", now, False, slot=0)
    counters["genuine"] += 1  # the remote's one counter, for both channels (PROTOCOL.md 5)
    req = auth.AuthRequest(RELEASE, 1, RID, SESSION, counters["genuine"]).encode(KEY)
    call("estop_tcp_rx", now, False, slot=0, data=req)
    if state["state"] != 1:
        raise AssertionError("the unit did not arm")
    # The flood: arrivals (time, order, kind) in a heap; the remote stops after `seconds`.
    t0 = now + 1000
    t_silent = t0 + int(seconds * 1e6)
    t_end = t_silent + 400_000
    arrivals: list[tuple[float, int, str]] = []
    seq = 0
    t = float(t0)
    while t < t_end and rate > 0:
        heapq.heappush(arrivals, (t, seq, "forged"))
        seq += 1
        t += 1e6 / rate
    t = float(t0 + REMOTE_PERIOD_US // 2)
    t_last_genuine = t
    while t < t_silent:
        heapq.heappush(arrivals, (t, seq, "genuine"))
        t_last_genuine = t
        seq += 1
        t += REMOTE_PERIOD_US
    if attack == "sniffer":  # a recorded packet fed back at the start of every window
        t = float(t0)
        while t < t_end:
            heapq.heappush(arrivals, (t, -1, "replay"))
            t += 100_000
    recorded: list[bytes] = []  # the remote's packets the unit did not take
    taken_after = 0
    queue: list[tuple[float, str, bytes]] = []
    dropped = 0
    sent_genuine = 0
    t_cpu = float(t0)
    brake_times.clear()
    raw_status = arm.call("estop_get_status", {}).objects["estop_status_t"]
    valid_before = out.get("estop_status_t", raw_status, "counters.udp_valid")
    status_before = valid_before
    last_valid_us = float(now)
    while True:
        # Whatever arrived by the time the CPU is free goes into the queue (or is dropped).
        while arrivals and arrivals[0][0] <= t_cpu:
            at, _, kind = heapq.heappop(arrivals)
            sent_genuine += kind == "genuine"
            if kind == "replay" and not recorded:
                continue
            # the bytes as sent, in the order sent (the remote's counter rises with each)
            data = (genuine() if kind == "genuine" else forged() if kind == "forged"
                    else recorded.pop(0))
            if len(queue) < RX_QUEUE:
                queue.append((at, kind, data))
            else:
                dropped += 1
                if kind == "genuine" and attack == "sniffer":
                    recorded.append(data)  # lost in the queue, but on the air
        due = state["next_call"]
        if due <= t_cpu or (not queue and (not arrivals or due <= arrivals[0][0])):
            if due > t_end:
                break
            start = max(t_cpu, float(due))
            late["tick"] = max(late["tick"], start - due)
            call("estop_tick", int(start), start < t_silent)
        elif queue:
            at, kind, data = queue.pop(0)
            start = max(t_cpu, at)
            call("estop_udp_rx", int(start), start < t_silent, data=data)
            if kind != "forged":
                st = arm.call("estop_get_status", {}).objects["estop_status_t"]
                valid = out.get("estop_status_t", st, "counters.udp_valid")
                if valid > status_before and state["stop_at"] is None:
                    last_valid_us = start  # the latest valid packet before the stop
                if valid > status_before and at > t_last_genuine:
                    taken_after += 1
                if valid == status_before and kind == "genuine" and attack == "sniffer":
                    recorded.append(data)  # left unchecked (or refused): the attacker keeps it
                status_before = valid
        else:
            t_cpu = arrivals[0][0]
    st = arm.call("estop_get_status", {}).objects["estop_status_t"]
    gaps = [b - a for a, b in zip(brake_times, brake_times[1:], strict=False)]
    timeout_us = 200_000
    stop_late = None
    if state["stop_at"] is not None and state["reason"] == 3:
        stop_late = int(state["stop_at"] - (last_valid_us + timeout_us))
    flood_us = t_silent - t0
    stop_after = (None if state["stop_at"] is None
                  else int(state["stop_at"] - t_last_genuine))
    return FloodResult(
        rate=rate,
        budget="none" if budget == UNBOUNDED else "default",
        cpu_share=busy["flood"] / flood_us,
        insns_per_s=busy["flood"] / us_per_insn / (flood_us / 1e6),
        genuine_sent=sent_genuine,
        genuine_valid=out.get("estop_status_t", st, "counters.udp_valid") - valid_before,
        forged_checked=out.get("estop_status_t", st, "counters.auth_bad_tag"),
        forged_unchecked=out.get("estop_status_t", st, "counters.auth_unchecked"),
        rx_dropped=dropped,
        max_brake_gap_us=int(max(gaps)) if gaps else 0,
        max_tick_late_us=int(late["tick"]),
        armed_throughout=not state["left_armed"],
        stop_late_us=stop_late,
        attack=attack,
        taken_after_silence=taken_after,
        stop_after_last_us=stop_after,
    )


def table(results: list[FloodResult]) -> list[str]:
    lines = [f"Cortex-M0+ -Os at {F_CPU // 1_000_000} MHz ({CPI} cycles an instruction), "
             f"receive queue of {RX_QUEUE}, remote at 50 Hz",
             "| attack | forged/s | budget | CPU | remote's packets valid | tag checks (forged) | "
             "unchecked | queue drops | longest ESTOP_BRAKE gap | tick late | ARMED | "
             "timeout stop late | taken after the remote fell silent | "
             "stop after its last packet |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | "
             "---: | ---: |"]
    for r in results:
        stop = "never" if r.stop_late_us is None else f"{r.stop_late_us / 1000:.2f} ms"
        after = ("never" if r.stop_after_last_us is None
                 else f"{r.stop_after_last_us / 1000:.1f} ms")
        lines.append(
            f"| {r.attack} | {r.rate} | {r.budget} | {100 * r.cpu_share:.1f} % | "
            f"{r.genuine_valid}/{r.genuine_sent} | {r.forged_checked} | {r.forged_unchecked} | "
            f"{r.rx_dropped} | {r.max_brake_gap_us / 1000:.2f} ms | "
            f"{r.max_tick_late_us / 1000:.2f} ms | {'yes' if r.armed_throughout else 'no'} | "
            f"{stop} | {r.taken_after_silence} | {after} |")
    return lines
