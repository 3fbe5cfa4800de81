"""A small pure-Python reference model of the stop unit, written from PROTOCOL.md alone.

It shares no code with the C core: validity is checked on decoded floats (not on bit patterns),
time is an unbounded integer (no wrapping tick, no "fresh" latch), and the CRCs come from the
Python codecs. The stateful test steps it beside the C core and demands identical output.

Like the core's host, it feeds time gaps longer than MAX_STEP_US in steps of that size.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from estop.protocol.crc import crc32, e2e_crc8

STOPPED, ARMED = 0, 1
NONE, BOOT, TCP_STOP, UDP_TIMEOUT, FAULT = range(5)
ACK, NAK = 0x80, 0x81
STATUS_ID, RELEASE_ID = 1, 2
NAK_UNKNOWN, NAK_NO_LINK, NAK_NOT_NEUTRAL = 1, 2, 3
MAX_STEP_US = 0x7FFFFFFF
REQUEST_MAGIC = b"ESQ2"


@dataclass(frozen=True)
class ModelConfig:
    timeout_us: int = 200_000
    warn_us: int = 100_000
    stop_id: int = 0xE570E570
    brake_can_id: int = 0x050
    status_can_id: int = 0x051
    brake_data_id: int = 0x0E57
    status_data_id: int = 0x0E58
    release_packets: int = 5
    brake_period_us: int = 10_000
    status_period_us: int = 100_000


@dataclass
class ModelStep:
    frames: list[tuple[int, bytes]] = field(default_factory=list)
    replies: list[bytes] = field(default_factory=list)
    closed: bool = False
    changed: bool = False


def parse_control(data: bytes) -> tuple[bool, float]:
    """(valid, gas_brake) per section 1."""
    if len(data) == 20:
        gas, steer, gear, turn, horn = struct.unpack("<ffiii", data)
    elif len(data) == 16:
        gas, steer, gear, turn = struct.unpack("<ffii", data)
        horn = 0
    else:
        return False, 0.0
    ok = (
        all(math.isfinite(v) and -1.0 <= v <= 1.0 for v in (gas, steer))
        and gear in (1, 2, 4, 8)
        and turn in (0, 1, 2, 3)
        and horn in (0, 1)
    )
    return ok, gas


class Model:
    def __init__(self, cfg: ModelConfig, now: int) -> None:
        self.cfg = cfg
        self.now = now
        self.state = STOPPED
        self.reason = BOOT
        self.last_valid: int | None = None
        self.last_gas = 1.0
        self.valid_run = 0
        self.brake_due = now
        self.status_due = now
        self.brake_counter = 0
        self.status_counter = 0
        self.window_valid = 0
        self.window_invalid = 0
        self.bad_crc = 0
        self.stops = 0
        self.valid = 0
        self.invalid = 0
        self.udp_stops = 0
        self.slots: dict[int, bytearray] = {}

    # -- derived ------------------------------------------------------------------------
    def link_age(self) -> int | None:
        if self.last_valid is None or self.now - self.last_valid >= self.cfg.timeout_us:
            return None
        return self.now - self.last_valid

    def flags(self) -> int:
        age = self.link_age()
        return int(self.state == ARMED and age is not None and age >= self.cfg.warn_us)

    def link_live(self) -> bool:
        return self.link_age() is not None and self.valid_run >= self.cfg.release_packets

    # -- frames -------------------------------------------------------------------------
    def _frame(self, step: ModelStep, can_id: int, data_id: int, body: bytes, ctr: int) -> None:
        payload = body + bytes([ctr])
        step.frames.append((can_id, payload + bytes([e2e_crc8(data_id, payload)])))

    def _brake(self, step: ModelStep) -> None:
        stopped = self.state == STOPPED
        body = bytes([int(stopped), 100 if stopped else 0, self.state, self.reason,
                      self.flags(), 0])
        self._frame(step, self.cfg.brake_can_id, self.cfg.brake_data_id, body,
                    self.brake_counter)
        self.brake_counter = (self.brake_counter + 1) % 15

    def _status(self, step: ModelStep) -> None:
        age = self.link_age()
        age_ms = 0xFFFF if age is None else age // 1000
        body = bytes([min(self.window_valid, 255), min(self.window_invalid, 255),
                      min(self.bad_crc, 255), min(self.stops, 255)]) + struct.pack("<H", age_ms)
        self._frame(step, self.cfg.status_can_id, self.cfg.status_data_id, body,
                    self.status_counter)
        self.status_counter = (self.status_counter + 1) % 15
        self.window_valid = self.window_invalid = 0

    def _change(self, step: ModelStep) -> None:
        step.changed = True
        self._brake(step)
        self.brake_due = self.now + self.cfg.brake_period_us

    def _stop(self, reason: int, step: ModelStep) -> None:
        self.valid_run = 0
        if self.state == ARMED:
            self.state, self.reason = STOPPED, reason
            self.stops += 1
            self._change(step)

    # -- time ---------------------------------------------------------------------------
    def _time(self, now: int, step: ModelStep) -> None:
        self.now = now
        if self.state == ARMED and self.link_age() is None:
            self._stop(UDP_TIMEOUT, step)
        if now >= self.brake_due:
            self._brake(step)
            nxt = self.brake_due + self.cfg.brake_period_us
            self.brake_due = nxt if now < nxt else now + self.cfg.brake_period_us
        if now >= self.status_due:
            self._status(step)
            nxt = self.status_due + self.cfg.status_period_us
            self.status_due = nxt if now < nxt else now + self.cfg.status_period_us

    def begin(self, now: int) -> ModelStep:
        assert now >= self.now
        step = ModelStep()
        while now - self.now > MAX_STEP_US:
            self._time(self.now + MAX_STEP_US, step)
        self._time(now, step)
        return step

    def next_call(self) -> int:
        nxt = min(self.brake_due, self.status_due)
        if self.state == ARMED:
            assert self.last_valid is not None
            nxt = min(nxt, self.last_valid + self.cfg.timeout_us)
        return nxt

    # -- inputs -------------------------------------------------------------------------
    def tick(self, now: int) -> ModelStep:
        return self.begin(now)

    def udp(self, data: bytes, now: int) -> ModelStep:
        step = self.begin(now)
        if (len(data) == 48 and data[:4] == REQUEST_MAGIC
                and struct.unpack_from("<I", data, 4)[0] == self.cfg.stop_id):
            self.udp_stops += 1  # a stop datagram: anyone may stop, the tag is not read
            self._stop(TCP_STOP, step)
            return step
        ok, gas = parse_control(data)
        if ok:
            if self.last_valid is None or now - self.last_valid >= self.cfg.timeout_us:
                self.valid_run = 0  # the link was silent for the timeout: count afresh
            self.valid += 1
            self.window_valid += 1
            self.valid_run += 1
            self.last_valid = now
            self.last_gas = gas
        else:
            self.invalid += 1
            self.window_invalid += 1
        return step

    def fault(self, now: int) -> ModelStep:
        step = self.begin(now)
        self._stop(FAULT, step)
        return step

    def tcp_open(self, slot: int, now: int) -> ModelStep:
        step = self.begin(now)
        self.slots[slot] = bytearray()
        return step

    def tcp_close(self, slot: int, now: int) -> ModelStep:
        step = self.begin(now)
        self.slots.pop(slot, None)
        return step

    def tcp_data(self, slot: int, data: bytes, now: int) -> ModelStep:
        step = self.begin(now)
        buf = self.slots[slot]
        buf.extend(data)
        while len(buf) >= 16:
            frame = bytes(buf[:16])
            del buf[:16]
            if not self._request(frame, step):
                step.closed = True
                del self.slots[slot]
                break
        return step

    def _request(self, frame: bytes, step: ModelStep) -> bool:
        msg_id, seq, _arg, crc = struct.unpack("<IIII", frame)
        if crc32(frame[:12]) != crc:
            self.bad_crc += 1
            return False
        nak = 0
        if msg_id == self.cfg.stop_id:
            self._stop(TCP_STOP, step)
        elif msg_id == RELEASE_ID:
            if self.state == STOPPED:
                if not self.link_live():
                    nak = NAK_NO_LINK
                elif self.last_gas > 0.0:
                    nak = NAK_NOT_NEUTRAL
                else:
                    self.state, self.reason = ARMED, NONE
                    self._change(step)
        elif msg_id != STATUS_ID:
            nak = NAK_UNKNOWN
        body = struct.pack("<IIBBBB", NAK if nak else ACK, seq, self.state, self.reason,
                           self.flags(), nak)
        step.replies.append(body + struct.pack("<I", crc32(body)))
        return True
