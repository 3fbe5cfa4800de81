"""Typed wrapper around the C watchdog core (the cffi module built from firmware/core).

Times are plain integer microseconds on the host's monotonic clock, as wide as Python ints.
The core itself counts in a wrapping 32-bit tick; this wrapper hands it the low 32 bits and
splits any gap longer than ``MAX_STEP_US`` into several ticks, as the header asks of a host.

``ESTOP_CORE_MODULE`` selects another build of the same sources (the coverage/UBSan build).
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

_MODULE_NAME = os.environ.get("ESTOP_CORE_MODULE", "estop._core")
_mod: ModuleType = importlib.import_module(_MODULE_NAME)
ffi: Any = _mod.ffi
lib: Any = _mod.lib

MAX_STEP_US: int = lib.ESTOP_MAX_STEP_US
MAX_SLOTS: int = lib.ESTOP_MAX_SLOTS
KEY_LEN: int = lib.ESTOP_KEY_LEN
# The session of the spec's test vectors (PROTOCOL.md 5.4). A real host draws a random one at
# every boot (estopd: getrandom); tests and simulations want a fixed one.
TEST_SESSION = 0x0123456789ABCDEF
_U32 = 0xFFFFFFFF


class CoreError(Exception):
    """The core refused a call (bad configuration, bad slot, ...)."""

    def __init__(self, code: int, action: str) -> None:
        self.code = code
        self.name = ffi.string(lib.estop_err_name(code)).decode()
        super().__init__(f"{action}: {self.name} ({code})")


def default_warn_us(slow_us: int) -> int:
    """The warn time W when none is given (PROTOCOL.md 3): half the slow time, rounded down to
    a whole millisecond. Where that is 0 (a slow time under 2 ms) W would break 0 < W, so it
    is 1 ms, or the slow time itself when that is shorter (the closest valid reading)."""
    half_ms = (slow_us // 2) // 1000 * 1000
    return half_ms if half_ms > 0 else min(1000, slow_us)


@dataclass(frozen=True)
class Config:
    """Core configuration. ``slow_us`` of None means the timeout (never SLOWING, as in
    protocol version 2); ``warn_us`` of None means half the slow time, rounded down to a whole
    millisecond (``default_warn_us``). ``key`` None: a unit without a key (plain packets);
    32 bytes: a unit with a key (PROTOCOL.md 5)."""

    timeout_us: int = lib.ESTOP_DEFAULT_TIMEOUT_US
    warn_us: int | None = None
    slow_us: int | None = None
    slow_level: int = lib.ESTOP_DEFAULT_SLOW_LEVEL
    stop_id: int = lib.ESTOP_DEFAULT_STOP_ID
    brake_can_id: int = lib.ESTOP_DEFAULT_BRAKE_CAN_ID
    status_can_id: int = lib.ESTOP_DEFAULT_STATUS_CAN_ID
    brake_data_id: int = lib.ESTOP_DEFAULT_BRAKE_DATA_ID
    status_data_id: int = lib.ESTOP_DEFAULT_STATUS_DATA_ID
    release_packets: int = lib.ESTOP_DEFAULT_RELEASE_PACKETS
    brake_period_us: int = lib.ESTOP_DEFAULT_BRAKE_PERIOD_US
    status_period_us: int = lib.ESTOP_DEFAULT_STATUS_PERIOD_US
    tag_checks: int = lib.ESTOP_DEFAULT_TAG_CHECKS
    tag_window_us: int = lib.ESTOP_DEFAULT_TAG_WINDOW_US
    session: int = TEST_SESSION
    key: bytes | None = None

    @property
    def effective_slow_us(self) -> int:
        return self.timeout_us if self.slow_us is None else self.slow_us

    @property
    def effective_warn_us(self) -> int:
        return default_warn_us(self.effective_slow_us) if self.warn_us is None else self.warn_us

    def to_c(self) -> Any:
        cfg = ffi.new("estop_config_t *")
        for name in (
            "timeout_us", "stop_id", "brake_can_id", "status_can_id", "brake_data_id",
            "status_data_id", "release_packets", "brake_period_us", "status_period_us",
            "slow_level", "tag_checks", "tag_window_us",
        ):
            setattr(cfg, name, getattr(self, name))
        cfg.slow_us = self.effective_slow_us
        cfg.warn_us = self.effective_warn_us
        cfg.session = self.session
        if self.key is not None:
            # Any length goes to the core, which decides (a wrong one is ESTOP_ERR_KEY).
            cfg.key_len = min(len(self.key), 255)
            ffi.memmove(cfg.key, self.key[:KEY_LEN], min(len(self.key), KEY_LEN))
        return cfg


@dataclass(frozen=True)
class CanFrame:
    can_id: int
    data: bytes


@dataclass(frozen=True)
class Step:
    """What one call into the core produced."""

    frames: tuple[CanFrame, ...]
    reply: bytes | None
    close: bool
    state_changed: bool
    changed_by_clock: bool
    state: int
    reason: int
    flags: int
    next_call_us: int
    # State and reason after the clock's part of the last call, before its input: when they
    # differ from state and reason, the clock changed the state and then the input did.
    clock_state: int = 0
    clock_reason: int = 0


@dataclass(frozen=True)
class Counters:
    udp_valid: int
    udp_invalid: int
    udp_stops: int
    tcp_frames: int
    tcp_bad_crc: int
    tcp_unknown_id: int
    releases_accepted: int
    releases_refused: int
    stops: tuple[int, ...]
    slowdowns: int
    rearms: int
    faults: int
    auth_bad_tag: int
    auth_bad_session: int
    auth_old_counter: int
    auth_table_full: int
    auth_unchecked: int


@dataclass(frozen=True)
class LinkStats:
    """The link's record: valid packets, silences of at least the warn time, those that reached
    the slow time (slow-downs) and the timeout, gap histogram."""

    valid: int
    silences: int
    slowdowns: int
    timeouts: int
    gaps: tuple[int, ...]


@dataclass(frozen=True)
class Status:
    state: int
    reason: int
    flags: int
    link_live: bool
    valid_run: int
    link_age_us: int | None
    counters: Counters


def check_config(config: Config) -> None:
    """Raises CoreError when the core would refuse this configuration."""
    err = lib.estop_config_check(config.to_c())
    if err != lib.ESTOP_OK:
        raise CoreError(err, "config")


@dataclass
class _Merged:
    """Frames gathered from the extra ticks of a split time gap."""

    frames: list[CanFrame] = field(default_factory=list)
    changed: bool = False
    by_clock: bool = False


class Watchdog:
    """One emergency-stop unit, booted STOPPED at ``now_us``."""

    def __init__(self, config: Config | None = None, now_us: int = 0) -> None:
        self.config = config or Config()
        self._core = ffi.new("estop_core_t *")
        self._out = ffi.new("estop_out_t *")
        self._consumed = ffi.new("size_t *")
        err = lib.estop_init(self._core, self.config.to_c(), now_us & _U32)
        if err != lib.ESTOP_OK:
            raise CoreError(err, "init")
        self._now = now_us

    @property
    def now_us(self) -> int:
        return self._now

    # -- time -----------------------------------------------------------------------------
    def _advance(self, now_us: int) -> _Merged:
        if now_us < self._now:
            raise ValueError(f"time went backwards: {now_us} < {self._now}")
        merged = _Merged()
        while now_us - self._now > MAX_STEP_US:
            self._now += MAX_STEP_US
            self._call(lib.estop_tick, self._now & _U32)
            step = self._step(None)
            merged.frames.extend(step.frames)
            merged.changed |= step.state_changed
            merged.by_clock |= step.changed_by_clock
        self._now = now_us
        return merged

    def _call(self, fn: Any, *args: Any) -> None:
        err = fn(self._core, *args, self._out)
        if err != lib.ESTOP_OK:
            raise CoreError(err, fn.__name__)

    def _step(self, merged: _Merged | None) -> Step:
        out = self._out
        frames = tuple(
            CanFrame(out.can[i].id, bytes(ffi.buffer(out.can[i].data, out.can[i].dlc)))
            for i in range(out.n_can)
        )
        changed = bool(out.state_changed)
        by_clock = bool(out.changed_by_clock)
        if merged is not None:
            frames = tuple(merged.frames) + frames
            changed |= merged.changed
            by_clock |= merged.by_clock
        next_call = self._now + ((out.next_call_us - (self._now & _U32)) & _U32)
        return Step(
            frames=frames,
            reply=bytes(ffi.buffer(out.reply, out.reply_len)) if out.has_reply else None,
            close=bool(out.close_slot),
            state_changed=changed,
            changed_by_clock=by_clock,
            state=out.state,
            reason=out.reason,
            flags=out.flags,
            next_call_us=next_call,
            clock_state=out.clock_state,
            clock_reason=out.clock_reason,
        )

    # -- inputs ---------------------------------------------------------------------------
    def tick(self, now_us: int) -> Step:
        merged = self._advance(now_us)
        self._call(lib.estop_tick, now_us & _U32)
        return self._step(merged)

    def udp(self, data: bytes, now_us: int) -> Step:
        merged = self._advance(now_us)
        self._call(lib.estop_udp_rx, ffi.from_buffer("uint8_t[]", data), len(data), now_us & _U32)
        return self._step(merged)

    def fault(self, now_us: int) -> Step:
        merged = self._advance(now_us)
        self._call(lib.estop_fault, now_us & _U32)
        return self._step(merged)

    def tcp_open(self, slot: int, now_us: int) -> Step:
        merged = self._advance(now_us)
        self._call(lib.estop_tcp_open, slot, now_us & _U32)
        return self._step(merged)

    def tcp_close(self, slot: int, now_us: int) -> Step:
        merged = self._advance(now_us)
        self._call(lib.estop_tcp_close, slot, now_us & _U32)
        return self._step(merged)

    def tcp_data(self, slot: int, data: bytes, now_us: int) -> list[Step]:
        """Feeds a TCP read; one Step per core call (the core takes at most a frame a call)."""
        merged: _Merged | None = self._advance(now_us)
        steps: list[Step] = []
        buf = ffi.from_buffer("uint8_t[]", data)
        offset = 0
        while True:
            err = lib.estop_tcp_rx(self._core, slot, buf + offset, len(data) - offset,
                                   self._consumed, now_us & _U32, self._out)
            if err != lib.ESTOP_OK:
                raise CoreError(err, "estop_tcp_rx")
            steps.append(self._step(merged))
            merged = None
            offset += self._consumed[0]
            if offset >= len(data) or steps[-1].close:
                break
        return steps

    # -- read-out -------------------------------------------------------------------------
    def status(self) -> Status:
        st = ffi.new("estop_status_t *")
        err = lib.estop_get_status(self._core, st)
        if err != lib.ESTOP_OK:
            raise CoreError(err, "estop_get_status")
        c = st.counters
        counters = Counters(
            udp_valid=c.udp_valid, udp_invalid=c.udp_invalid, udp_stops=c.udp_stops,
            tcp_frames=c.tcp_frames,
            tcp_bad_crc=c.tcp_bad_crc, tcp_unknown_id=c.tcp_unknown_id,
            releases_accepted=c.releases_accepted, releases_refused=c.releases_refused,
            stops=tuple(c.stops[i] for i in range(lib.ESTOP_REASON_COUNT)),
            slowdowns=c.slowdowns, rearms=c.rearms, faults=c.faults,
            auth_bad_tag=c.auth_bad_tag, auth_bad_session=c.auth_bad_session,
            auth_old_counter=c.auth_old_counter, auth_table_full=c.auth_table_full,
            auth_unchecked=c.auth_unchecked,
        )
        return Status(
            state=st.state, reason=st.reason, flags=st.flags, link_live=bool(st.link_live),
            valid_run=st.valid_run,
            link_age_us=None if st.link_age_us == _U32 else st.link_age_us,
            counters=counters,
        )

    def link_stats(self) -> LinkStats:
        ls = ffi.new("estop_link_stats_t *")
        err = lib.estop_get_link_stats(self._core, ls)
        if err != lib.ESTOP_OK:
            raise CoreError(err, "estop_get_link_stats")
        return LinkStats(valid=ls.valid, silences=ls.silences, slowdowns=ls.slowdowns,
                         timeouts=ls.timeouts,
                         gaps=tuple(ls.gaps[i] for i in range(lib.ESTOP_GAP_BINS)))
