"""Model-based test: the C core and the Python reference model take the same random operations
and must agree, after every step, on state, reason, flags, every CAN frame, every reply (16- and
48-byte, byte for byte, reply tags included), close requests and the next call time.

Each example boots a unit with a key (drawn by hypothesis, a random nonzero session) or without
one, and plays the remotes that hold the key, an attacker that does not (a wrong key, garbage
tags, flipped bits), a recorder that replays genuine traffic later (also after a reboot, into a
new session), stale and equal counters, several remote ids with their own counters, a crowd of
new remote ids (a 9th gets no place), request frames on TCP cut at random points and mixed with
plain frames, and stop and lift datagrams with garbage tags. Messages are made with
estop.protocol.auth; the model checks them with its own hashlib code. The unit's times are drawn
too: the version 2 default (slow time = timeout) or a two-stage stop (slow time below the
timeout, protocol version 3), with any slow level.

Invariants checked on the C core's output at every step:
- brake is requested whenever the unit is STOPPED, at the slow level whenever it is SLOWING
  (every ESTOP_BRAKE frame, and the latest one always shows the current state);
- SLOWING is entered from ARMED, or from STOPPED only by an accepted RELEASE (of a link silent
  for the slow time already);
- no gap between ESTOP_BRAKE frames is longer than the period while the host calls on time, and
  the next call time is never later than one period after the latest ESTOP_BRAKE frame;
- the alive counter is never 15 and every CRC (CAN and TCP) is good;
- STOPPED is never left without an accepted RELEASE, and with a key only by a RELEASE made with
  the key for this session (never a forged or replayed one);
- with a key, nothing forged or replayed is counted as a valid packet, and a forged or replayed
  RELEASE (or a plain one) is answered NAK 4; without a key a request-frame RELEASE is NAK 4;
- every 48-byte reply carries the unit's session and verifies for its own request under the key
  (estop.protocol.auth); a keyless unit's reply tag is 16 zero bytes;
- the core's packet counters (valid, invalid, stop datagrams) and its link check match the model.

ESTOP_STATEFUL_EXAMPLES sets the number of examples (default 1500). With
--hypothesis-show-statistics the events tell how many examples had a unit with or without a key,
how many of each reached ARMED, and which authentication failures and scenarios came up.
"""

from __future__ import annotations

import dataclasses
import os
import random
import struct
from dataclasses import dataclass

import hypothesis.strategies as st
import pytest
from hypothesis import HealthCheck, event, settings
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from core_util import packet, request
from estop.core import MAX_SLOTS, Config, Step, Watchdog
from estop.protocol import auth
from estop.protocol.crc import crc32, e2e_crc8
from estop.protocol.udp import ControlPacket
from reference_model import (
    ACK,
    LIFT_ID,
    RELEASE_ID,
    STATUS_ID,
    Model,
    ModelConfig,
    ModelStep,
)

CFG = ModelConfig()
BRAKE_ID, STATUS_CAN_ID = CFG.brake_can_id, CFG.status_can_id
PERIOD = CFG.brake_period_us
STOPPED, ARMED, SLOWING = 0, 1, 2
NAK_NOT_AUTH = 4
U64 = 2**64 - 1
# The remote ids of the remotes that hold the key (edge values included).
REMOTE_IDS = (7, 0, 0xFFFFFFFF)


def control(gas: float, steer: float, gear: int, turn: int, horn: int, legacy: bool) -> bytes:
    return packet(gas, steer, gear, turn, horn, legacy=legacy)


unit = st.floats(min_value=-1.0, max_value=1.0, width=32)
valid_packets = st.builds(
    control, unit, unit, st.sampled_from([1, 2, 4, 8]), st.integers(0, 3), st.integers(0, 1),
    st.booleans(),
)
bad_floats = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1.0000001, -1.5, 3e38])
invalid_packets = st.one_of(
    st.binary(max_size=64).filter(lambda b: len(b) not in (16, 20)),
    st.builds(control, bad_floats, unit, st.just(4), st.just(0), st.just(0), st.booleans()),
    st.builds(control, unit, bad_floats, st.just(4), st.just(0), st.just(0), st.booleans()),
    st.builds(control, unit, unit, st.sampled_from([0, 3, 5, 16, -1, 2**31 - 1]), st.just(0),
              st.just(0), st.booleans()),
    st.builds(control, unit, unit, st.just(4), st.sampled_from([4, -1, 99]), st.just(0),
              st.just(False)),
    st.builds(control, unit, unit, st.just(4), st.just(0), st.sampled_from([2, -1, 7]),
              st.just(False)),
    # request frames over UDP that are not stop datagrams (another msg_id, another length)
    st.builds(lambda msg_id, tail: b"ESQ2" + struct.pack("<I", msg_id) + tail,
              st.sampled_from([0, 1, 2, CFG.stop_id ^ 1]), st.binary(min_size=40, max_size=40)),
    st.builds(lambda tail: b"ESQ2" + struct.pack("<I", CFG.stop_id) + tail,
              st.binary(max_size=48).filter(lambda b: len(b) != 40)),
    # 60 bytes that are not an authenticated control packet (magic), any tag
    st.builds(lambda head, tail: head + tail, st.sampled_from([b"ESU1", b"ESQ2", b"\0\0\0\0"]),
              st.binary(min_size=56, max_size=56)),
)
stop_datagrams = st.builds(lambda msg_id, tail: b"ESQ2" + struct.pack("<I", msg_id) + tail,
                           st.sampled_from([CFG.stop_id, LIFT_ID]),
                           st.binary(min_size=40, max_size=40))
# (timeout, slow time, warn time): the version 2 default, and two-stage stops (version 3) with
# the slow time well inside the drive gaps and host runs below, or at its smallest.
TIMINGS = [(200_000, 200_000, 100_000), (200_000, 60_000, 30_000), (1_000_000, 200_000, 100_000),
           (150_000, 1_000, 1_000), (200_000, 199_999, 199_999)]
small_dt = st.integers(0, 30_000)
seeds = st.integers(0, 2**32 - 1)  # for random.Random: many cheap choices from one draw

# Bodies for bursts and authenticated packets, drawn whole (fewer draws keep the run time down);
# the plain single-packet rules above draw every float.
_NEUTRAL_GAS = [-1.0, -0.3, -1e-45, -0.0, 0.0]
_BODY_FIELDS = [(s, gear, turn, horn) for s in (-1.0, 0.25, 1.0) for gear in (1, 2, 4, 8)
                for turn in (0, 3) for horn in (0, 1)]
NEUTRAL_BODIES = [ControlPacket(g, *f) for g in _NEUTRAL_GAS for f in _BODY_FIELDS]
ANY_BODIES = NEUTRAL_BODIES + [ControlPacket(g, *f) for g in (1e-45, 0.3, 1.0)
                               for f in _BODY_FIELDS]
BAD_BODIES = [ControlPacket(float("nan")), ControlPacket(1.5), ControlPacket(0.0, -1.0000001),
              ControlPacket(gear=3), ControlPacket(gear=0), ControlPacket(turn_signal=4),
              ControlPacket(horn=2), ControlPacket(-0.0, float("-inf"))]

AUTH_KINDS = ["genuine", "jump", "stale", "equal", "wrong_key", "garbage_tag", "flipped_bit",
              "wrong_session", "bad_body"]
TCP_KINDS = ["stop", "lift", "status", "release", "unknown", "badcrc",  # plain 16-byte frames
             "f_status", "f_release", "f_release_stale", "f_release_forged", "f_stop",
             "f_lift", "f_unknown"]  # 48-byte request frames


@dataclass(frozen=True)
class Sent:
    """A TCP request as the test sent it, to check the reply against."""

    raw: bytes
    may_release: bool = False  # a RELEASE the unit may accept: plain without a key; made with
    #                            the key for this session with one (the model judges the rest)
    must_refuse: bool = False  # a RELEASE the spec says is NAK 4 whatever else holds
    record: bool = False       # genuine: a recorder keeps it for replays once the unit took it


class CoreVsModel(RuleBasedStateMachine):
    @initialize(start=st.integers(0, 2**32 - 1), keyed=st.booleans(),
                key=st.binary(min_size=32, max_size=32), session=st.integers(1, U64),
                wrong_key=st.binary(min_size=32, max_size=32), operator_first=st.booleans(),
                timing=st.sampled_from(TIMINGS), slow_level=st.integers(1, 99),
                tag_checks=st.sampled_from([10, 10, 2, 0]))
    def boot(self, start: int, keyed: bool, key: bytes, session: int, wrong_key: bytes,
             operator_first: bool, timing: tuple[int, int, int], slow_level: int,
             tag_checks: int) -> None:
        """Power on; maybe the operator arms the unit first (initialize rules are never switched
        off by hypothesis' swarm testing, so ARMED is reached in well over half the examples)."""
        timeout, slow, warn = timing
        # tag_checks: the default budget, a tight one (packets dropped unchecked often), or none
        self.cfg = dataclasses.replace(CFG, timeout_us=timeout, slow_us=slow, warn_us=warn,
                                       slow_level=slow_level, tag_checks=tag_checks)
        self.slowing_seen = False
        self.now = start
        self.keyed = keyed
        self.key: bytes | None = key if keyed else None
        self.remote_key = key  # the remotes' key; a keyless unit's remotes send plain packets
        self.wrong_key = wrong_key if wrong_key != key else bytes(b ^ 1 for b in key)
        self.seq = 0
        self.sessions = {session}
        self.known_session = 0  # the remotes learn it from a reply (STATUS with session 0)
        # remote id -> last counter used: one counter for all a remote's messages (section 5)
        self.counters: dict[int, int] = {}
        self.new_rid = 0x100
        self.last_tcp_rid = REMOTE_IDS[0]  # the remote id of the latest request frame
        self.recording: list[tuple[str, bytes]] = []  # genuine traffic, for replays
        self.accepted: set[bytes] = set()  # datagrams the unit counted valid
        # Datagrams the budget dropped unchecked while their remote id had a place: never valid
        # later (issue 25), unless a RELEASE older than them came late (a stale one).
        self.unchecked_placed: set[bytes] = set()
        self.stale_release_sent = False
        self.last_brake: tuple[int, bytes] | None = None
        self.armed_seen = False
        self.reboots = 0
        self.replays = 0
        self.auth_failures: set[str] = set()
        self._boot_unit(session)
        if operator_first:
            self._open(0)
            self._operate(0, count=5, gap=20_000, seed=0, poll=False, eager=False)

    def _boot_unit(self, session: int) -> None:
        """A fresh unit at self.now (power on, or a reboot): STOPPED, no connections."""
        self.session = session
        cfg = self.cfg
        self.core = Watchdog(Config(key=self.key, session=session, timeout_us=cfg.timeout_us,
                                    slow_us=cfg.slow_us, warn_us=cfg.warn_us,
                                    slow_level=cfg.slow_level, tag_checks=cfg.tag_checks),
                             now_us=self.now)
        self.model = Model(dataclasses.replace(cfg, key=self.key, session=session), self.now)
        self.open_slots: set[int] = set()
        self.prev_state = STOPPED
        self.on_time = True
        self.next_call = self.now
        self._compare(self.core.tick(self.now), self.model.tick(self.now))

    def teardown(self) -> None:
        if not hasattr(self, "core"):
            return
        kind = "keyed" if self.keyed else "keyless"
        event(f"{kind} unit")
        event(f"{kind} unit: {'reached ARMED' if self.armed_seen else 'never ARMED'}")
        if self.cfg.slow_us is not None and self.cfg.slow_us < self.cfg.timeout_us:
            event(f"two-stage unit: {'reached SLOWING' if self.slowing_seen else 'never SLOWING'}")
        self.auth_failures.update(self.model.auth_failures)
        for why in sorted(self.auth_failures):
            event(f"keyed unit: refused, {why}")
        if self.reboots:
            event(f"{kind} unit: rebooted")
        if self.replays:
            event(f"{kind} unit: replayed traffic")

    # -- comparison and per-step invariants ----------------------------------------------
    def _compare(self, steps: Step | list[Step], expected: ModelStep,
                 sent: list[Sent] | None = None) -> list[bytes]:
        """Core against model after one input; returns the replies (to `sent`, in order)."""
        steps = steps if isinstance(steps, list) else [steps]
        frames = [(f.can_id, f.data) for s in steps for f in s.frames]
        replies = [s.reply for s in steps if s.reply is not None]
        assert frames == expected.frames
        assert replies == expected.replies
        assert any(s.close for s in steps) == expected.closed
        last = steps[-1]
        assert (last.state, last.reason, last.flags) == (
            self.model.state, self.model.reason, self.model.flags())
        assert last.next_call_us == self.model.next_call()
        self.next_call = last.next_call_us
        for can_id, data in frames:
            assert len(data) == 8
            assert data[6] & 0x0F != 15 and data[6] >> 4 == 0, "alive counter out of range"
            data_id = CFG.brake_data_id if can_id == BRAKE_ID else CFG.status_data_id
            assert e2e_crc8(data_id, data[:7]) == data[7], "bad CRC-8"
            if can_id == BRAKE_ID:
                assert (data[0], data[1]) == {STOPPED: (1, 100), ARMED: (0, 0),
                                              SLOWING: (2, self.cfg.slow_level)}[data[2]]
                if self.last_brake is not None and self.on_time:
                    assert self.now - self.last_brake[0] <= PERIOD, "ESTOP_BRAKE gap over period"
                self.last_brake = (self.now, data)
        state = self.prev_state
        for s in steps:
            req = None
            if s.reply is not None:
                assert sent, "a reply to no request"
                req = sent.pop(0)
                self._check_reply(s.reply, req)
            if state == STOPPED and s.state != STOPPED:
                # A RELEASE of a link silent for the slow time goes straight to SLOWING.
                assert req is not None and s.reply is not None, \
                    "left STOPPED without an accepted RELEASE"
                assert self._reply_ack_state(s.reply) == (True, s.state)
                assert req.may_release, "released by a RELEASE made without the key, or replayed"
                if s.state == SLOWING:
                    event("released straight into SLOWING")
            if s.state == STOPPED and state != STOPPED:
                event(f"stopped from {'SLOWING' if state == SLOWING else 'ARMED'}, "
                      f"reason {s.reason}")
            if state == SLOWING and s.state == ARMED:
                event("SLOWING back to ARMED")
            state = s.state
        if last.state == ARMED:
            self.armed_seen = True
        if last.state == SLOWING:
            self.slowing_seen = True
        self.prev_state = last.state
        self.on_time = True
        return replies

    @staticmethod
    def _reply_ack_state(rep: bytes) -> tuple[bool, int]:
        at = 4 if len(rep) == 48 else 0
        return struct.unpack_from("<I", rep, at)[0] == ACK, rep[at + 8]

    def _check_reply(self, rep: bytes, req: Sent) -> None:
        if len(rep) == 16:
            assert len(req.raw) == 16, "a plain reply to a request frame"
            assert crc32(rep[:12]) == struct.unpack("<I", rep[12:])[0]
            nak = rep[11]
        else:
            assert len(rep) == 48 and len(req.raw) == 48, "a 48-byte reply to a plain frame"
            # A genuine reply verifies for exactly its own request; without a key: zero tag.
            decoded = auth.AuthReply.decode(rep, self.key, auth.request_tag(req.raw))
            assert decoded.session == self.session
            assert decoded.seq == struct.unpack_from("<I", req.raw, 8)[0]
            assert decoded.counter == struct.unpack_from("<Q", req.raw, 24)[0]
            if self.key is None:
                assert rep[32:] == bytes(16)
            nak = rep[15]
        if req.must_refuse:
            assert nak == NAK_NOT_AUTH, "a forged, replayed or plain RELEASE not refused"

    @invariant()
    def brake_matches_state(self) -> None:
        if hasattr(self, "core"):
            status = self.core.status()
            assert self.last_brake is not None
            assert self.last_brake[1][2] == status.state
            assert self.next_call - self.last_brake[0] <= PERIOD
            c = status.counters
            assert (c.udp_valid, c.udp_invalid, c.udp_stops, c.slowdowns, status.link_live) == (
                self.model.valid, self.model.invalid, self.model.udp_stops,
                self.model.slowdowns, self.model.link_live())

    def _later(self, dt: int) -> int:
        # A host calls back no later than it was asked to; jumps are their own rule.
        target = self.now + dt
        self.on_time = target <= self.next_call
        self.now = target
        return target

    # -- the remotes -----------------------------------------------------------------------
    def _counter(self, rid: int, channel: str, use: bool = True) -> int:
        """The next counter of a remote id (one for both channels: `channel` says which one it
        is for); `use` False leaves it for the next one."""
        del channel
        nxt = min(self.counters.get(rid, 0) + 1, U64)
        if use:
            self.counters[rid] = nxt
        return nxt

    def _genuine(self, body: ControlPacket, rid: int) -> bytes:
        """A control packet from a remote that holds the key (plain to a keyless unit)."""
        if not self.keyed:
            return body.encode(legacy=body.horn == 0 and body.turn_signal == 0, validate=False)
        return auth.AuthControlPacket(rid, self.known_session, self._counter(rid, "udp"),
                                      body).encode(self.remote_key)

    def _udp(self, data: bytes, *, forged: bool = False) -> None:
        """One datagram; on a keyed unit a forged or replayed one is never counted valid."""
        before = self.core.status().counters.udp_valid if forged and self.keyed else None
        valid, unchecked = self.model.valid, self.model.unchecked
        placed = len(data) == 60 and struct.unpack_from("<I", data, 4)[0] in self.model.remotes
        self._compare(self.core.udp(data, self.now), self.model.udp(data, self.now))
        if self.model.valid > valid:
            self.accepted.add(data)
        if self.model.unchecked > unchecked:
            event(f"keyed unit: dropped unchecked, {'a placed' if placed else 'a new'} id")
            if placed:
                self.unchecked_placed.add(data)
        if before is not None:
            assert self.core.status().counters.udp_valid == before, "a forgery kept it alive"

    def _slot(self, data: st.DataObject) -> int:
        if self.open_slots:
            return data.draw(st.sampled_from(sorted(self.open_slots)))
        slot = data.draw(st.integers(0, MAX_SLOTS - 1))
        self._open(slot)
        return slot

    def _open(self, slot: int) -> None:
        self.open_slots.add(slot)
        self._compare(self.core.tcp_open(slot, self.now), self.model.tcp_open(slot, self.now))

    def _tcp(self, slot: int, sent: list[Sent], cuts: tuple[int, ...] = (),
             wait: int = 0) -> list[bytes]:
        """The requests as one byte stream cut at `cuts`, each piece `wait` us after the last."""
        stream = b"".join(s.raw for s in sent)
        pending = list(sent)
        bounds = [0, *cuts, len(stream)]
        replies: list[bytes] = []
        for i, (a, b) in enumerate(zip(bounds, bounds[1:], strict=False)):
            if i > 0:
                self.run_host_until(self.now + wait)
            piece = stream[a:b]
            expected = self.model.tcp_data(slot, piece, self.now)
            replies += self._compare(self.core.tcp_data(slot, piece, self.now), expected,
                                     pending)
            if expected.closed:
                self.open_slots.discard(slot)
                break
        # Only what the unit answered was heard: a frame behind one that closed the connection
        # never reached it, and sent again later it is a first delivery, not a replay.
        self.recording += [("tcp", s.raw) for s in sent
                           if s.record and not any(s is p for p in pending)]
        return replies

    def _frame(self, msg_id: int, rid: int, *, key: bytes | None, session: int,
               counter: int) -> bytes:
        self.seq += 1
        self.last_tcp_rid = rid
        return auth.AuthRequest(msg_id, self.seq & 0xFFFFFFFF, rid, session, counter).encode(key)

    def _learn_session(self, slot: int, rid: int) -> None:
        """What a remote does first: a STATUS with session 0; the reply teaches the session."""
        frame = self._frame(STATUS_ID, rid, key=self.remote_key, session=0,
                            counter=self._counter(rid, "tcp"))
        (raw,) = self._tcp(slot, [Sent(frame)])
        reply = auth.AuthReply.decode(raw, self.key, auth.request_tag(frame))
        self.known_session = reply.session
        self.recording.append(("tcp", frame))

    def _release(self, rid: int) -> Sent:
        """The remote's RELEASE: plain without a key, a request frame made with it with one."""
        if not self.keyed:
            self.seq += 1
            return Sent(request(RELEASE_ID, self.seq & 0xFFFFFFFF), may_release=True)
        frame = self._frame(RELEASE_ID, rid, key=self.remote_key, session=self.known_session,
                            counter=self._counter(rid, "tcp"))
        return Sent(frame, may_release=self.known_session == self.session, record=True)

    # -- operations ----------------------------------------------------------------------
    @rule(data=valid_packets, dt=small_dt)
    def valid_packet(self, data: bytes, dt: int) -> None:
        """A plain packet with any valid body (a keyed unit counts it invalid)."""
        self.run_host_until(self.now + dt)
        self._udp(data, forged=True)

    @rule(data=invalid_packets, dt=small_dt)
    def invalid_packet(self, data: bytes, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self._udp(data, forged=True)

    @rule(data=stop_datagrams, dt=small_dt)
    def stop_datagram(self, data: bytes, dt: int) -> None:
        """Anyone may stop: a request frame with the stop ID or LIFT over UDP, any tag."""
        self.run_host_until(self.now + dt)
        self._udp(data, forged=True)

    @rule(count=st.integers(1, 8), gap=st.integers(1_000, 60_000), seed=seeds)
    def drive(self, count: int, gap: int, seed: int) -> None:
        """A burst of genuine packets at a steady rate, the host ticking between them."""
        self._drive(count, gap, random.Random(seed), ANY_BODIES)

    def _drive(self, count: int, gap: int, rng: random.Random,
               pool: list[ControlPacket]) -> None:
        """The remotes take turns at random, each with its own counter; bodies from `pool`.
        One seed rather than two draws a packet keeps the run time down (and hypothesis' bias
        to small numbers from making every packet the same)."""
        for _ in range(count):
            datagram = self._genuine(rng.choice(pool), rng.choice(REMOTE_IDS))
            self.recording.append(("udp", datagram))
            self.run_host_until(self.now + gap)
            self._udp(datagram)

    @rule(count=st.integers(5, 8), gap=st.integers(1_000, 45_000), seed=seeds,
          poll=st.booleans(), eager=st.booleans(), data=st.data())
    def operator_release(self, count: int, gap: int, seed: int, poll: bool, eager: bool,
                         data: st.DataObject) -> None:
        """What an operator does: learn the session if need be, drive, come back to neutral,
        then press release. `eager`: release is pressed once before the last (neutral) packet
        too, while the latest packet may still give gas or the link may still lack a packet.
        `poll`: the app's status poll goes out in the same write as the RELEASE, ahead of it
        but with the later counter (a STATUS keeps no counter, so the RELEASE still
        authenticates)."""
        self._operate(self._slot(data), count, gap, seed, poll, eager)

    def _operate(self, slot: int, count: int, gap: int, seed: int, poll: bool,
                 eager: bool) -> None:
        rng = random.Random(seed)
        rid = rng.choice(REMOTE_IDS)
        if self.keyed and self.known_session != self.session:
            self._learn_session(slot, rid)
        self._drive(count - 1, gap, rng, ANY_BODIES)
        if eager:
            self._tcp(slot, [self._release(rid)])
        self._drive(1, gap, rng, NEUTRAL_BODIES)
        sent = [self._release(rid)]
        if poll and self.keyed:
            sent.insert(0, Sent(self._frame(STATUS_ID, rid, key=self.remote_key,
                                            session=self.known_session,
                                            counter=self._counter(rid, "tcp"))))
        self._tcp(slot, sent)

    @rule(kind=st.sampled_from(AUTH_KINDS), who=st.integers(0, len(REMOTE_IDS) - 1),
          body=st.sampled_from(ANY_BODIES), dt=small_dt, data=st.data())
    def auth_packet(self, kind: str, who: int, body: ControlPacket, dt: int,
                    data: st.DataObject) -> None:
        """One 60-byte packet: genuine (maybe with a counter jump), a stale or equal counter from
        the key holder, or a forgery (wrong key, garbage tag, a flipped bit, a wrong session, a
        bad body under a right tag)."""
        rid = REMOTE_IDS[who]
        self.run_host_until(self.now + dt)
        key, session = self.remote_key, self.known_session
        last = self.counters.get(rid, 0)
        forged = kind not in ("genuine", "jump", "stale", "equal")
        if kind == "jump":
            counter = data.draw(st.one_of(st.integers(last + 1, last + 2**40), st.just(U64)))
            counter = min(counter, U64)
            self.counters[rid] = counter
        elif kind in ("stale", "equal"):
            counter = last if kind == "equal" else data.draw(st.integers(0, max(last - 1, 0)))
        elif kind == "genuine":
            counter = self._counter(rid, "udp")
        else:  # a forgery: the attacker sees the traffic, so it uses a counter that is due
            counter = self._counter(rid, "udp", use=False)
        if kind == "wrong_key":
            key = self.wrong_key
        elif kind == "wrong_session":
            session = data.draw(st.sampled_from(sorted(self.sessions | {0, session ^ 1})))
            session = session if session != self.session else 0
        elif kind == "bad_body":
            body = data.draw(st.sampled_from(BAD_BODIES))
        datagram = auth.AuthControlPacket(rid, session, counter, body).encode(key, validate=False)
        if kind == "garbage_tag":
            datagram = datagram[:44] + data.draw(st.binary(min_size=16, max_size=16))
        elif kind == "flipped_bit":
            bit = data.draw(st.integers(0, 44 * 8 - 1))
            flipped = bytearray(datagram)
            flipped[bit // 8] ^= 1 << (bit % 8)
            datagram = bytes(flipped)
        elif kind in ("genuine", "jump"):
            self.recording.append(("udp", datagram))
        self._udp(datagram, forged=forged)

    @rule(count=st.integers(1, 9), forged_first=st.booleans(), dt=small_dt)
    def crowd(self, count: int, forged_first: bool, dt: int) -> None:
        """New remote ids: forged packets (wrong key, wrong session) must not take places;
        genuine ones get the free places, and one more than 8 ids gets none."""
        self.run_host_until(self.now + dt)
        rids = [self.new_rid + i for i in range(count)]
        self.new_rid += count
        body = NEUTRAL_BODIES[0]
        if forged_first:
            for i, rid in enumerate(rids):
                key, session = ((self.wrong_key, self.known_session) if i % 2 == 0
                                else (self.remote_key, self.session ^ 1))
                forgery = auth.AuthControlPacket(rid, session, 1, body).encode(key)
                self._udp(forgery, forged=True)
        for rid in rids:
            datagram = auth.AuthControlPacket(rid, self.known_session, self._counter(rid, "udp"),
                                              body).encode(self.remote_key)
            self.recording.append(("udp", datagram))
            self._udp(datagram)

    @precondition(lambda self: bool(self.recording))
    @rule(data=st.data(), dt=small_dt)
    def replay(self, data: st.DataObject, dt: int) -> None:
        """A recorder sends genuine traffic again (maybe from an earlier session)."""
        self.replays += 1
        channel, raw = self.recording[data.draw(st.integers(0, len(self.recording) - 1))]
        self.run_host_until(self.now + dt)
        if channel == "udp":
            # One the unit took once is refused again, and so is one the budget dropped
            # unchecked while its remote id had a place (issue 25). One of an id without a
            # place may be taken late (a place is given only with a right tag); the model says.
            self._udp(raw, forged=raw in self.accepted or (
                raw in self.unchecked_placed and not self.stale_release_sent))
            return
        msg_id = struct.unpack_from("<I", raw, 4)[0]
        # A keyed unit refuses a replayed RELEASE; a keyless one refuses any request frame's.
        self._tcp(self._slot(data), [Sent(raw, must_refuse=msg_id == RELEASE_ID)])

    @rule(session=st.integers(1, U64), forget=st.booleans())
    def reboot(self, session: int, forget: bool) -> None:
        """The unit restarts with a new session (the remotes find out from the next reply);
        the remotes may start their counters afresh. Recordings of the old session remain."""
        while session in self.sessions:
            session = session % U64 + 1
        self.sessions.add(session)
        self.reboots += 1
        self.auth_failures.update(self.model.auth_failures)
        if forget:
            self.counters.clear()
        self._boot_unit(session)

    @rule(slot=st.integers(0, MAX_SLOTS - 1), dt=small_dt)
    def tcp_open(self, slot: int, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self._open(slot)

    @precondition(lambda self: bool(self.open_slots))
    @rule(data=st.data(), dt=small_dt)
    def tcp_close(self, data: st.DataObject, dt: int) -> None:
        slot = data.draw(st.sampled_from(sorted(self.open_slots)))
        self.run_host_until(self.now + dt)
        self.open_slots.discard(slot)
        self._compare(self.core.tcp_close(slot, self.now), self.model.tcp_close(slot, self.now))

    def _request(self, kind: str, data: st.DataObject) -> Sent:
        """One request of the given kind (TCP_KINDS)."""
        if not kind.startswith("f_"):  # a plain 16-byte frame
            self.seq += 1
            msg_id = {"stop": CFG.stop_id, "lift": LIFT_ID, "status": STATUS_ID,
                      "release": RELEASE_ID,
                      "unknown": data.draw(st.integers(4, 2**32 - 1).filter(
                          lambda i: i not in (CFG.stop_id, 0x32515345))),
                      "badcrc": STATUS_ID}[kind]
            raw = request(msg_id, self.seq & 0xFFFFFFFF, good_crc=kind != "badcrc")
            return Sent(raw, may_release=kind == "release" and not self.keyed,
                        must_refuse=kind == "release" and self.keyed)
        rid = REMOTE_IDS[data.draw(st.integers(0, len(REMOTE_IDS) - 1))]
        if kind == "f_release" and self.keyed:
            return self._release(rid)
        if kind == "f_release_stale" and self.keyed:
            # The key holder reuses its last counter, or an older one (a RELEASE sent earlier,
            # delivered late): refused unless nothing authenticated from it on either channel
            # has kept that counter yet (a STATUS or STOP keeps none).
            self.stale_release_sent = True
            rid = self.last_tcp_rid
            last = self.counters.get(rid, 0)
            counter = last if data.draw(st.booleans()) else data.draw(st.integers(0, last))
            frame = self._frame(RELEASE_ID, rid, key=self.remote_key,
                                session=self.known_session, counter=counter)
            return Sent(frame, may_release=self.known_session == self.session)
        counter = self._counter(rid, "tcp")
        if kind.startswith("f_release"):
            # Forged, or sent to a keyless unit (which has no authenticated RELEASE): NAK 4.
            how = data.draw(st.sampled_from(["wrong_key", "garbage_tag", "old_session",
                                             "session_0"]))
            session = {"old_session": min(self.sessions - {self.session}, default=0),
                       "session_0": 0}.get(how, self.known_session)
            frame = self._frame(RELEASE_ID, rid, session=session, counter=counter,
                                key=self.wrong_key if how == "wrong_key" else self.remote_key)
            if how == "garbage_tag":
                frame = frame[:32] + data.draw(st.binary(min_size=16, max_size=16))
            return Sent(frame, must_refuse=True)
        if kind == "f_status":  # from the key holder (session 0 if it asks for it), or forged
            how = data.draw(st.sampled_from(["genuine", "session_0", "wrong_key"]))
            return Sent(self._frame(STATUS_ID, rid, counter=counter,
                                    key=self.wrong_key if how == "wrong_key" else self.remote_key,
                                    session=0 if how == "session_0" else self.known_session))
        frame = self._frame(LIFT_ID if kind == "f_lift" else CFG.stop_id, rid, key=self.remote_key,
                            session=self.known_session, counter=counter)
        if kind in ("f_stop", "f_lift") and data.draw(st.booleans()):
            return Sent(frame)  # a stop button that holds the key (keeps no counter either)
        if kind == "f_unknown":  # an unknown msg_id
            msg_id = data.draw(st.integers(0, 2**32 - 1).filter(
                lambda i: i not in (CFG.stop_id, STATUS_ID, RELEASE_ID, LIFT_ID)))
            frame = frame[:4] + struct.pack("<I", msg_id) + frame[8:]
        return Sent(frame[:32] + data.draw(st.binary(min_size=16, max_size=16)))  # garbage tag

    @rule(data=st.data(), kinds=st.lists(st.sampled_from(TCP_KINDS), min_size=1, max_size=4),
          wait=st.integers(0, 3_000), dt=small_dt)
    def tcp_requests(self, data: st.DataObject, kinds: list[str], wait: int, dt: int) -> None:
        """Plain frames and request frames as one byte stream, cut at random points, the pieces
        `wait` us apart."""
        self.run_host_until(self.now + dt)
        slot = self._slot(data)
        sent = [self._request(kind, data) for kind in kinds]
        size = sum(len(s.raw) for s in sent)
        cuts = tuple(sorted(data.draw(st.sets(st.integers(1, size - 1), max_size=5))))
        self._tcp(slot, sent, cuts, wait)

    @rule(dt=small_dt)
    def fault(self, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self._compare(self.core.fault(self.now), self.model.fault(self.now))

    @rule(duration=st.integers(0, 500_000))
    def run_host(self, duration: int) -> None:
        self.run_host_until(self.now + duration)

    @rule(dt=st.one_of(st.integers(0, 2**33), st.sampled_from(
        [2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**32 + 1, 2**32 + 150_000, 3 * 2**31])))
    def jump(self, dt: int) -> None:
        """The host was away (suspended, stuck): one late tick, up to and past 2^32 us."""
        t = self._later(dt)
        self._compare(self.core.tick(t), self.model.tick(t))

    def run_host_until(self, end: int) -> None:
        """Calls tick at every time the core asks for, as estopd does, up to `end`."""
        while self.next_call <= end:
            t = max(self.now, self.next_call)
            self._later(t - self.now)
            self._compare(self.core.tick(t), self.model.tick(t))
        self._later(end - self.now)


CoreVsModel.TestCase.settings = settings(
    # The mutation run (tools/mutants.py) asks for fewer examples per mutant. 1500 rather than
    # 2000 since the authentication rules came: about 45 s on the shared two-core machine.
    max_examples=int(os.environ.get("ESTOP_STATEFUL_EXAMPLES", "1500")),
    stateful_step_count=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
test_core_matches_model = CoreVsModel.TestCase
# A pass takes well under a minute, but a failure is shrunk for up to five minutes (hypothesis'
# own limit): the bound sits above that, so a failure is reported as its counterexample rather
# than as a timeout. Slow: make test-fast leaves it to make test.
test_core_matches_model.pytestmark = [pytest.mark.timeout(600), pytest.mark.slow]
