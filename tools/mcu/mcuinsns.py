"""Instructions the Cortex-M builds execute per call, counted in the emulator (one unicorn code
hook per instruction, so the counts are exact and repeatable), for the calls that matter on a
unit in service: a control packet (plain, or authenticated on a unit with a key), a TCP request,
a tick with frames due.

The scenario drives one core through boot, six heartbeats, a RELEASE, STATUS and STOP at fixed
times (brake period 10 ms, status period 100 ms), and checks the number of CAN frames of each
counted call, so that a label like "2 frames due" stays true when the core changes. With a key
(PROTOCOL.md 5: key and session of the 5.4 vectors) the packets and requests are the
authenticated forms (60-byte packets, 48-byte request frames), made by estop.protocol.auth.
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


def modes(ffi: Any) -> list[bool]:
    """Scenarios the core supports: without a key, and with one once the config has a key."""
    fields = {name for name, _ in ffi.typeof("estop_config_t").fields}
    return [False, True] if "key" in fields else [False]


def _field(arm: ArmCore, ctype: str, path: str) -> int:
    for name, off, size in arm.layouts[ctype]:
        if name == path:
            addr = arm.objects[ctype][0]
            return int.from_bytes(arm.cpu.read(addr + off, size), "little")
    raise KeyError(f"{ctype}.{path}")


KEY = bytes(range(32))
SESSION = 0x0123456789ABCDEF
RID = 7


def scenario(v: Variant, ffi: Any, lib: Any, keyed: bool = False,
             count: bool | str = True) -> list[Count]:
    """count: how the emulator counts (mcuemu.CortexM): every instruction, or "block"."""
    from estop.protocol import auth
    from estop.protocol.udp import ControlPacket

    arm = ArmCore(v, ffi, count=count)
    counts: list[Count] = []
    counter = {"n": 0}  # the remote's one counter, for both channels (PROTOCOL.md 5)
    kind = "authenticated " if keyed else ""

    def packet() -> bytes:
        if not keyed:
            return NEUTRAL
        counter["n"] += 1
        return auth.AuthControlPacket(RID, SESSION, counter["n"], ControlPacket()).encode(KEY)

    def req(msg_id: int, seq: int) -> bytes:
        if not keyed:
            return request(msg_id, seq)
        counter["n"] += 1
        return auth.AuthRequest(msg_id, seq, RID, SESSION, counter["n"]).encode(KEY)

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
    fields = {name for name, _ in ffi.typeof("estop_config_t").fields}
    if "session" in fields:
        cfg.session = SESSION
    if keyed:
        cfg.key_len = len(KEY)
        ffi.memmove(cfg.key, KEY, len(KEY))
    size = len(req(STATUS, 0))
    counter["n"] = 0
    call(f"init ({'with a key' if keyed else 'no key'})", "estop_init",
         cfg=bytes(ffi.buffer(cfg)), now_us=0)
    call("tick, brake + status frames due", "estop_tick", 2, now_us=0)
    call(None, "estop_tcp_open", 0, slot=0, now_us=1)
    for i in range(6):
        label = f"{kind}control packet, nothing due" if i == 5 else None
        call(label, "estop_udp_rx", 0, data=packet(), now_us=2000 + 1000 * i)
    call("tick, brake frame due", "estop_tick", 1, now_us=10_000)
    call("tick, nothing due", "estop_tick", 0, now_us=10_500)
    call(f"RELEASE ({size} B): ACK, arms, brake frame", "estop_tcp_rx", 1,
         slot=0, data=req(RELEASE, 1), now_us=12_000)
    call(f"STATUS ({size} B): ACK", "estop_tcp_rx", 0, slot=0, data=req(STATUS, 2),
         now_us=13_000)
    call(f"{kind}control packet while ARMED", "estop_udp_rx", 0, data=packet(),
         now_us=15_000)
    call(None, "estop_tick", 1, now_us=22_000)
    call(None, "estop_udp_rx", 1, data=packet(), now_us=90_000)
    call("tick while ARMED, brake + status due", "estop_tick", 2, now_us=100_000)
    call(f"STOP ({size} B): ACK, stops, brake frame", "estop_tcp_rx", 1, slot=0,
         data=req(STOP_ID, 3), now_us=101_000)
    return counts
