"""Instructions the Cortex-M builds execute per call, counted in the emulator (one unicorn code
hook per instruction, so the counts are exact and repeatable), for the calls that matter on a
unit in service: a plain control packet, a TCP request, a tick with frames due.

The scenario drives one core through boot, six heartbeats, a RELEASE, STATUS and STOP at fixed
times (brake period 10 ms, status period 100 ms), and checks the number of CAN frames of each
counted call, so that a label like "2 frames due" stays true when the core changes.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Any

from mcubuild import Variant
from mcuemu import ArmCore

STOP_ID, STATUS, RELEASE = 0xE570E570, 0x00000001, 0x00000002
NEUTRAL = struct.pack("<ffIII", 0.0, 0.0, 4, 0, 0)      # PROTOCOL.md 1: no gas, gear neutral


def request(msg_id: int, seq: int) -> bytes:
    body = struct.pack("<III", msg_id, seq, 0)
    return body + struct.pack("<I", zlib.crc32(body))


@dataclass(frozen=True)
class Count:
    label: str
    fn: str
    instructions: int
    stack: int        # bytes of stack the call used (measured, not the static bound)


def _field(arm: ArmCore, ctype: str, path: str) -> int:
    for name, off, size in arm.layouts[ctype]:
        if name == path:
            addr = arm.objects[ctype][0]
            return int.from_bytes(arm.cpu.read(addr + off, size), "little")
    raise KeyError(f"{ctype}.{path}")


def scenario(v: Variant, ffi: Any, lib: Any) -> list[Count]:
    arm = ArmCore(v, ffi, count=True)
    counts: list[Count] = []

    def call(label: str | None, fn: str, frames: int | None = None, **values: Any) -> None:
        res = arm.call(fn, values, measure_stack=label is not None)
        if res.ret != 0:
            raise AssertionError(f"{v.name}: {fn} returned {res.ret} in the scenario")
        if frames is not None and _field(arm, "estop_out_t", "n_can") != frames:
            raise AssertionError(f"{v.name}: {label}: not {frames} CAN frames")
        if label is not None:
            counts.append(Count(label, fn, arm.cpu.instructions, arm.cpu.stack_used))

    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)          # the defaults of the core itself
    call("init (default config)", "estop_init", cfg=bytes(ffi.buffer(cfg)), now_us=0)
    call("tick, brake + status frames due", "estop_tick", 2, now_us=0)
    call(None, "estop_tcp_open", 0, slot=0, now_us=1)
    for i in range(6):
        label = "control packet (20 B, valid), nothing due" if i == 5 else None
        call(label, "estop_udp_rx", 0, data=NEUTRAL, now_us=2000 + 1000 * i)
    call("tick, brake frame due", "estop_tick", 1, now_us=10_000)
    call("tick, nothing due", "estop_tick", 0, now_us=10_500)
    call("TCP RELEASE (16 B): ACK, arms, brake frame", "estop_tcp_rx", 1,
         slot=0, data=request(RELEASE, 1), now_us=12_000)
    call("TCP STATUS (16 B): ACK", "estop_tcp_rx", 0, slot=0, data=request(STATUS, 2),
         now_us=13_000)
    call("control packet while ARMED", "estop_udp_rx", 0, data=NEUTRAL, now_us=15_000)
    call(None, "estop_tick", 1, now_us=22_000)
    call(None, "estop_udp_rx", 1, data=NEUTRAL, now_us=90_000)
    call("tick while ARMED, brake + status due", "estop_tick", 2, now_us=100_000)
    call("TCP STOP (16 B): ACK, stops, brake frame", "estop_tcp_rx", 1, slot=0,
         data=request(STOP_ID, 3), now_us=101_000)
    return counts
