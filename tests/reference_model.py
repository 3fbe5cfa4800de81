"""A small pure-Python reference model of the stop unit, written from PROTOCOL.md alone.

It shares no code with the C core: validity is checked on decoded floats (not on bit patterns),
time is an unbounded integer (no wrapping tick, no "fresh" latch), the CRCs come from the
Python codecs, and authentication (section 5) is its own: tags from hashlib, its own table of
remote ids and counters, its own framing by magic. The stateful test steps it beside the C core
and demands identical output.

Like the core's host, it feeds time gaps longer than MAX_STEP_US in steps of that size.

Where the spec leaves a choice open, the model follows the choices the core's header states:
- only control packets and RELEASE request frames are authenticated; STATUS and STOP request
  frames (and stop datagrams) never touch the counters;
- a control packet's body is checked before its tag, so a packet with a bad body keeps no
  counter and takes no place;
- authentication checks tag, then session, then the remote id's place, then the counter;
- with a tag-check budget, a control packet dropped unchecked under a remote id that has a place
  uses up its counter there as an authenticated one would (it may have been genuine); a RELEASE
  must be above its remote's newest authenticated counter on either channel, and one that is
  authenticated while the unit is STOPPED brings the remote's UDP counter back down to its own
  when unchecked packets had raised it higher (docs/PROTOCOL.md 5, issue 25).
"""

from __future__ import annotations

import hashlib
import hmac
import math
import struct
from dataclasses import dataclass, field

from estop.protocol.crc import crc32, e2e_crc8

STOPPED, ARMED, SLOWING = 0, 1, 2
NONE, BOOT, TCP_STOP, UDP_TIMEOUT, FAULT, LIFT = range(6)
ACK, NAK = 0x80, 0x81
STATUS_ID, RELEASE_ID, LIFT_ID = 1, 2, 3
REARM_PACKETS = 3  # valid packets since SLOWING began that end it (section 3)
NAK_UNKNOWN, NAK_NO_LINK, NAK_NOT_NEUTRAL, NAK_NOT_AUTH = 1, 2, 3, 4
MAX_STEP_US = 0x7FFFFFFF
REQUEST_MAGIC = b"ESQ2"
CONTROL_MAGIC = b"ESU2"
REPLY_MAGIC = b"ESR2"
MAX_REMOTES = 8
UDP, TCP = "udp", "tcp"  # the two channels a counter is kept for
COUNTER_AHEAD = 65536  # a remote's next counters, for its own tag-check allowance


def tag_of(key: bytes, message: bytes) -> bytes:
    """MAC(K, m) of section 5: keyed BLAKE2s, 16-byte digest."""
    return hashlib.blake2s(message, key=key, digest_size=16).digest()


@dataclass(frozen=True)
class ModelConfig:
    timeout_us: int = 200_000
    warn_us: int = 100_000
    slow_us: int | None = None  # None: the timeout (never SLOWING)
    slow_level: int = 30
    stop_id: int = 0xE570E570
    brake_can_id: int = 0x050
    status_can_id: int = 0x051
    brake_data_id: int = 0x0E57
    status_data_id: int = 0x0E58
    release_packets: int = 5
    brake_period_us: int = 10_000
    status_period_us: int = 100_000
    tag_checks: int = 10  # tag checks of control packets per remote id (and for new ids) ...
    tag_window_us: int = 100_000  # ... in each window (docs/PROTOCOL.md 5, bounded cost);
    # tag_checks 0: no budget, every tag checked
    session: int = 0x0123456789ABCDEF
    key: bytes | None = None  # None: a unit without a key


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
        self.window_auth_failed = 0
        self.bad_crc = 0
        self.window_stops = 0
        self.window_slowdowns = 0
        self.slow_run = 0
        self.slowdowns = 0
        self.valid = 0
        self.invalid = 0
        self.udp_stops = 0
        self.slots: dict[int, bytearray] = {}
        # remote id -> channel -> highest counter authenticated this session (at most 8 ids):
        # UDP: of control packets, or dropped unchecked; TCP: on either channel
        self.remotes: dict[int, dict[str, int]] = {}
        # Why messages that needed authentication failed it (for the test's statistics).
        self.auth_failures: dict[str, int] = {}
        # The tag-check budget: the window's start, checks per remote id (None: ids without a
        # place) in it, and the control packets dropped unchecked.
        self.tag_window = now
        self.tag_checks: dict[int | None, int] = {}
        self.unchecked = 0

    # -- derived ------------------------------------------------------------------------
    @property
    def slow_us(self) -> int:
        return self.cfg.timeout_us if self.cfg.slow_us is None else self.cfg.slow_us

    def link_age(self) -> int | None:
        if self.last_valid is None or self.now - self.last_valid >= self.cfg.timeout_us:
            return None
        return self.now - self.last_valid

    def flags(self) -> int:
        age = self.link_age()
        return int(self.state != STOPPED and age is not None and age >= self.cfg.warn_us)

    def link_live(self) -> bool:
        return self.link_age() is not None and self.valid_run >= self.cfg.release_packets

    # -- frames -------------------------------------------------------------------------
    def _frame(self, step: ModelStep, can_id: int, data_id: int, body: bytes, ctr: int) -> None:
        payload = body + bytes([ctr])
        step.frames.append((can_id, payload + bytes([e2e_crc8(data_id, payload)])))

    def _brake(self, step: ModelStep) -> None:
        request, level = {STOPPED: (1, 100), ARMED: (0, 0),
                          SLOWING: (2, self.cfg.slow_level)}[self.state]
        body = bytes([request, level, self.state, self.reason, self.flags(), 0])
        self._frame(step, self.cfg.brake_can_id, self.cfg.brake_data_id, body,
                    self.brake_counter)
        self.brake_counter = (self.brake_counter + 1) % 15

    def _status(self, step: ModelStep) -> None:
        age = self.link_age()
        age_ms = 0xFFFF if age is None else age // 1000
        body = bytes([min(self.window_valid, 255), min(self.window_invalid, 255),
                      min(self.window_auth_failed, 255),  # authentication failures
                      min(self.window_stops, 15) | min(self.window_slowdowns, 15) << 4,
                      ]) + struct.pack("<H", age_ms)
        self._frame(step, self.cfg.status_can_id, self.cfg.status_data_id, body,
                    self.status_counter)
        self.status_counter = (self.status_counter + 1) % 15
        self.window_valid = self.window_invalid = self.window_auth_failed = 0
        self.window_stops = self.window_slowdowns = 0

    def _change(self, step: ModelStep) -> None:
        step.changed = True
        self._brake(step)
        self.brake_due = self.now + self.cfg.brake_period_us

    def _stop(self, reason: int, step: ModelStep) -> None:
        self.valid_run = 0
        if self.state != STOPPED:
            self.state, self.reason = STOPPED, reason
            self.window_stops += 1
            self._change(step)

    def _slow_down(self) -> None:
        self.state = SLOWING  # the first stage: a controlled stop, not latched
        self.slow_run = 0
        self.slowdowns += 1
        self.window_slowdowns += 1

    # -- time ---------------------------------------------------------------------------
    def _time(self, now: int, step: ModelStep) -> None:
        self.now = now
        if self.state != STOPPED and self.link_age() is None:
            self._stop(UDP_TIMEOUT, step)
        elif self.state == ARMED and self.last_valid is not None \
                and now - self.last_valid >= self.slow_us:
            self._slow_down()
            self._change(step)
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
        if self.state != STOPPED:
            assert self.last_valid is not None
            nxt = min(nxt, self.last_valid + (self.slow_us if self.state == ARMED
                                              else self.cfg.timeout_us))
        return nxt

    # -- inputs -------------------------------------------------------------------------
    def tick(self, now: int) -> ModelStep:
        return self.begin(now)

    def udp(self, data: bytes, now: int) -> ModelStep:
        step = self.begin(now)
        reason = self._stop_reason(struct.unpack_from("<I", data, 4)[0]) \
            if len(data) == 48 and data[:4] == REQUEST_MAGIC else None
        if reason is not None:
            self.udp_stops += 1  # a stop or lift datagram: anyone may stop, the tag is not read
            self._stop(reason, step)
            return step
        ok, gas = self._control(data)
        if ok:
            if self.last_valid is None or now - self.last_valid >= self.cfg.timeout_us:
                self.valid_run = 0  # the link was silent for the timeout: count afresh
            self.valid += 1
            self.window_valid += 1
            self.valid_run += 1
            self.last_valid = now
            self.last_gas = gas
            if self.state == SLOWING:
                self.slow_run += 1
                if self.slow_run >= REARM_PACKETS:  # the link is back: the controlled stop ends
                    self.state = ARMED
                    self._change(step)
        else:
            self.invalid += 1
            self.window_invalid += 1
        return step

    def _control(self, data: bytes) -> tuple[bool, float]:
        """(valid, gas_brake) of a control datagram in the form this unit expects."""
        if self.cfg.key is None:
            return parse_control(data)
        if len(data) != 60:
            if parse_control(data)[0]:
                self._fail("bad tag")  # a plain packet: the key holder's are tagged
            return False, 0.0
        ok, gas = parse_control(data[24:44])  # the body first: a bad one keeps no counter
        if not ok:
            return False, 0.0
        if data[:4] != CONTROL_MAGIC:
            return self._fail("bad tag"), 0.0  # no tag the unit can check
        remote_id, session, counter = struct.unpack_from("<IQQ", data, 4)
        return self._authenticate(data[:44], data[44:], remote_id, session, counter, UDP), gas

    def _fail(self, why: str) -> bool:
        self.auth_failures[why] = self.auth_failures.get(why, 0) + 1
        self.window_auth_failed += 1  # ESTOP_STATUS byte 2 (docs/DESIGN.md)
        return False

    def _authenticate(self, signed: bytes, tag: bytes, remote_id: int, session: int,
                      counter: int, channel: str) -> bool:
        """Section 5: this session, a counter above the one kept for (remote id, channel), a
        place for the remote id, then (control packets only) a tag check within the budget,
        then the right tag. The cheap checks come first, so no MAC is spent on what they
        refuse. Keeps the counter when all hold."""
        assert self.cfg.key is not None
        kept = self.remotes.get(remote_id)
        if session != self.cfg.session:
            return self._fail("bad session")
        if kept is not None and channel in kept and counter <= kept[channel]:
            return self._fail("old counter")
        if kept is None and len(self.remotes) >= MAX_REMOTES:
            return self._fail("table full")
        # A remote's own allowance serves its next counters (at most 65536 above the one
        # kept on UDP); new ids and counters far ahead share one allowance.
        near = kept is not None and UDP in kept and counter - kept[UDP] <= COUNTER_AHEAD
        if channel == UDP and self.cfg.tag_checks != 0 \
                and not self._take_check(remote_id if near else None):
            self.unchecked += 1  # dropped unchecked: invalid, but no authentication failure
            if kept is not None:
                kept[UDP] = counter  # it may have been genuine: never taken later
            return False
        if not hmac.compare_digest(tag_of(self.cfg.key, signed), tag):
            return self._fail("bad tag")
        if kept is None:
            kept = self.remotes[remote_id] = {}
        kept[channel] = counter
        if channel == UDP:
            kept[TCP] = max(kept.get(TCP, counter), counter)  # a RELEASE must be above it
        elif self.state == STOPPED and kept.get(UDP, -1) > counter:
            kept[UDP] = counter  # a RELEASE of a STOPPED unit forgives what lies above it
        return True

    def _take_check(self, who: int | None) -> bool:
        """One tag check from the allowance of a remote id (None: the shared one) in the
        current window; a window begins at the first check after the previous one ended (a
        window ends once it has lasted its length, however long the gap: time is unbounded
        here)."""
        if self.now - self.tag_window >= self.cfg.tag_window_us:
            self.tag_window = self.now
            self.tag_checks.clear()
        used = self.tag_checks.get(who, 0)
        if used >= self.cfg.tag_checks:
            return False
        self.tag_checks[who] = used + 1
        return True

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
        while True:
            # Section 2: the first 4 bytes decide the form.
            size = 48 if buf[:4] == REQUEST_MAGIC else 16
            if len(buf) < size:
                break
            frame = bytes(buf[:size])
            del buf[:size]
            if size == 48:
                self._request_frame(frame, step)
            elif not self._plain_frame(frame, step):
                step.closed = True
                del self.slots[slot]
                break
        return step

    def _stop_reason(self, msg_id: int) -> int | None:
        """The reason a stop request stops with (STOP or LIFT); None for any other msg_id."""
        return {self.cfg.stop_id: TCP_STOP, LIFT_ID: LIFT}.get(msg_id)

    def _message(self, msg_id: int, release_authenticated: bool, step: ModelStep) -> int:
        """What a frame of either form asks for; returns the NAK code."""
        nak = 0
        reason = self._stop_reason(msg_id)
        if reason is not None:
            self._stop(reason, step)
        elif msg_id == RELEASE_ID:
            if not release_authenticated:
                nak = NAK_NOT_AUTH
            elif self.state == STOPPED:
                if not self.link_live():
                    nak = NAK_NO_LINK
                elif self.last_gas > 0.0:
                    nak = NAK_NOT_NEUTRAL
                else:
                    self.state, self.reason = ARMED, NONE
                    if self.last_valid is not None and self.now - self.last_valid >= self.slow_us:
                        self._slow_down()  # its deadline has passed: no frame releases first
                    self._change(step)
        elif msg_id != STATUS_ID:
            nak = NAK_UNKNOWN
        return nak

    def _plain_frame(self, frame: bytes, step: ModelStep) -> bool:
        msg_id, seq, _arg, crc = struct.unpack("<IIII", frame)
        if crc32(frame[:12]) != crc:
            self.bad_crc += 1
            return False
        # A plain RELEASE is the keyless unit's; a unit with a key wants it authenticated, and
        # counts a plain one as an authentication failure.
        if msg_id == RELEASE_ID and self.cfg.key is not None:
            self._fail("bad tag")
        nak = self._message(msg_id, self.cfg.key is None, step)
        body = struct.pack("<IIBBBB", NAK if nak else ACK, seq, self.state, self.reason,
                           self.flags(), nak)
        step.replies.append(body + struct.pack("<I", crc32(body)))
        return True

    def _request_frame(self, frame: bytes, step: ModelStep) -> None:
        """Section 5.2: only a RELEASE is authenticated (never on a keyless unit)."""
        msg_id, seq, remote_id, session, counter = struct.unpack_from("<IIIQQ", frame, 4)
        authenticated = False
        if msg_id == RELEASE_ID and self.cfg.key is not None:
            authenticated = self._authenticate(frame[:32], frame[32:], remote_id, session,
                                               counter, TCP)
        nak = self._message(msg_id, authenticated, step)
        head = REPLY_MAGIC + struct.pack("<IIBBBBQQ", NAK if nak else ACK, seq, self.state,
                                         self.reason, self.flags(), nak, self.cfg.session,
                                         counter)
        tag = bytes(16) if self.cfg.key is None else tag_of(self.cfg.key, frame[32:] + head)
        step.replies.append(head + tag)
