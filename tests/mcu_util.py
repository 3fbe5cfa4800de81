"""Shared parts of the MCU tests: the build (once per session), and a twin that runs every call
on the host build (the cffi module) and on Cortex-M images in the emulator, and compares the
return value and every object byte for byte after each call."""

from __future__ import annotations

import sys
from collections import defaultdict
from functools import cache
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools" / "mcu"))

import mcubuild  # noqa: E402
from mcubuild import McuError, Variant  # noqa: E402
from mcuemu import ArmCore, CortexM, HostCore, Result, difference  # noqa: E402

from estop.core import TEST_SESSION, ffi, lib  # noqa: E402

__all__ = ["ArmCore", "CortexM", "HostCore", "Mismatch", "Twin", "TwinUnit", "config_bytes",
           "ensure_built", "mcubuild"]

U32 = 0xFFFFFFFF
# The differential runs on the smallest and the fastest build; the other two are built and
# held to the budget (test_mcu_footprint.py).
DIFF_VARIANTS = ("m0plus-Os", "m4-O2")


@cache
def _build() -> str:
    try:
        mcubuild.build()
    except McuError as exc:
        return str(exc)
    return ""


def ensure_built() -> None:
    """Builds the images once per session; a missing toolchain or a core that needs libc fails
    the test with the reason (never a skip: make test installs the toolchain)."""
    problem = _build()
    if problem:
        pytest.fail(problem, pytrace=False)


CONFIG_FIELDS = {name for name, _ in ffi.typeof("estop_config_t").fields}


def config_bytes(auth_key: bytes | None = None, **changes: Any) -> bytes:
    """An estop_config_t as bytes: the core's defaults with the test session (a host draws one
    at boot), auth_key if given (key and key_len), and some fields changed; laid out by the
    host's cffi module (test_mcu_layout.py checks that ARM lays it out the same)."""
    cfg = ffi.new("estop_config_t *")
    lib.estop_config_default(cfg)
    if "session" in CONFIG_FIELDS:
        cfg.session = TEST_SESSION
    if auth_key is not None:
        cfg.key_len = len(auth_key)
        ffi.memmove(cfg.key, auth_key, len(auth_key))
    for name, value in changes.items():
        if isinstance(value, bytes):
            ffi.memmove(getattr(cfg, name), value, len(value))
        else:
            setattr(cfg, name, value)
    return bytes(ffi.buffer(cfg))


class Mismatch(AssertionError):
    pass


class Twin:
    """The host build and Cortex-M builds side by side, compared after every call."""

    def __init__(self, variants: tuple[str | Variant, ...] = DIFF_VARIANTS,
                 measure_stack: bool = False) -> None:
        if any(isinstance(v, str) for v in variants):
            ensure_built()
        self.host = HostCore(ffi, lib)
        self.arms = [ArmCore(mcubuild.variant(v) if isinstance(v, str) else v, ffi)
                     for v in variants]
        self.calls = 0
        self.measure_stack = measure_stack
        self.max_stack: dict[tuple[str, str], int] = defaultdict(int)
        self.history: list[str] = []

    def reset(self) -> None:
        self.host.reset()
        for arm in self.arms:
            arm.reset()
        self.history.clear()

    def call(self, fn: str, **values: Any) -> Result:
        self.history.append(f"{fn}({', '.join(f'{k}={_short(v)}' for k, v in values.items())})")
        host = self.host.call(fn, values)
        for arm in self.arms:
            got = arm.call(fn, values, measure_stack=self.measure_stack)
            problem = difference(arm, host, got)
            if problem is not None:
                recent = "\n  ".join(self.history[-8:])
                raise Mismatch(f"{problem}\n after call {len(self.history)}:\n  {recent}")
            if self.measure_stack:
                key = (arm.variant.name, fn)
                self.max_stack[key] = max(self.max_stack[key], arm.cpu.stack_used)
        self.calls += 1
        return host

    def out(self) -> Any:
        """The host's estop_out_t (equal to every ARM one byte for byte after each call)."""
        return self.host.objects["estop_out_t"]


def _short(v: Any) -> str:
    if isinstance(v, bytes):
        return v.hex() if len(v) <= 24 else f"{v[:24].hex()}..({len(v)} B)"
    if isinstance(v, int) and v > 9999:
        return hex(v)
    return repr(v)


def reply_len(out: Any) -> int:
    """Bytes of the reply: reply_len where the output has it (version 2), else all."""
    names = {name for name, _ in ffi.typeof(out).item.fields}
    return int(out.reply_len) if "reply_len" in names else len(out.reply)


def frames_of(out: Any) -> list[tuple[int, bytes]]:
    return [(out.can[i].id, bytes(out.can[i].data[0:out.can[i].dlc])) for i in range(out.n_can)]


class TwinUnit:
    """A host loop on the twin: wide time (wrapping to 32 bits for the core), ticks whenever the
    core asks, TCP bytes fed until consumed. Keeps every CAN frame and reply."""

    def __init__(self, twin: Twin, start: int = 0, cfg: bytes | None = None) -> None:
        self.udp_counter = self.tcp_counter = 0
        self.twin = twin
        self.t = start
        self.frames: list[tuple[int, int, bytes]] = []
        self.replies: list[bytes] = []
        res = twin.call("estop_init", cfg=cfg or config_bytes(), now_us=start & U32)
        assert res.ret == lib.ESTOP_OK
        self._after(twin.call("estop_tick", now_us=start & U32))

    def _after(self, res: Result) -> Result:
        out = self.twin.out()
        if res.ret == lib.ESTOP_OK:
            self.frames.extend((self.t, i, d) for i, d in frames_of(out))
            if out.has_reply:
                self.replies.append(bytes(out.reply)[:reply_len(out)])
            self.next_call = self.t + ((out.next_call_us - self.t) & U32)
        return res

    @property
    def state(self) -> int:
        return int(self.twin.out().state)

    @property
    def reason(self) -> int:
        return int(self.twin.out().reason)

    def at(self, t: int) -> None:
        while self.next_call <= t:
            self.t = max(self.t, self.next_call)
            self._after(self.twin.call("estop_tick", now_us=self.t & U32))
        self.t = t
        self._after(self.twin.call("estop_tick", now_us=t & U32))

    def jump(self, t: int) -> None:
        """One tick at t, however much is due before it (a host that slept)."""
        self.t = t
        self._after(self.twin.call("estop_tick", now_us=t & U32))

    def wait(self, dt: int) -> None:
        self.at(self.t + dt)

    def udp(self, data: bytes | None) -> Result:
        return self._after(self.twin.call("estop_udp_rx", data=data, now_us=self.t & U32))

    def open(self, slot: int) -> Result:
        return self._after(self.twin.call("estop_tcp_open", slot=slot, now_us=self.t & U32))

    def close(self, slot: int) -> Result:
        return self._after(self.twin.call("estop_tcp_close", slot=slot, now_us=self.t & U32))

    def fault(self) -> Result:
        return self._after(self.twin.call("estop_fault", now_us=self.t & U32))

    def tcp(self, slot: int, data: bytes) -> list[bytes]:
        """Feeds data until consumed (or refused); returns the replies it produced."""
        before = len(self.replies)
        for _ in range(len(data) + 1):
            res = self._after(self.twin.call("estop_tcp_rx", slot=slot, data=data,
                                             now_us=self.t & U32))
            taken = int(res.objects["scalar:consumed"])
            if res.ret != lib.ESTOP_OK or taken >= len(data) or self.twin.out().close_slot:
                break
            data = data[taken:]
        return self.replies[before:]
