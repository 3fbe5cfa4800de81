"""Model-based test: the C core and the Python reference model take the same random operations
and must agree, after every step, on state, reason, flags, every CAN frame and every reply.

Invariants checked on the C core's output at every step:
- brake is requested whenever the unit is STOPPED (every ESTOP_BRAKE frame, and the latest one
  always shows the current state);
- no gap between ESTOP_BRAKE frames is longer than the period while the host calls on time, and
  the next call time is never later than one period after the latest ESTOP_BRAKE frame;
- the alive counter is never 15 and every CRC (CAN and TCP) is good;
- STOPPED is never left without an accepted RELEASE.
"""

from __future__ import annotations

import os
import struct

import hypothesis.strategies as st
from hypothesis import HealthCheck, event, settings
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from core_util import packet, request
from estop.core import MAX_SLOTS, Config, Step, Watchdog
from estop.protocol.crc import crc32, e2e_crc8
from reference_model import ACK, RELEASE_ID, STATUS_ID, Model, ModelConfig

CFG = ModelConfig()
BRAKE_ID, STATUS_CAN_ID = CFG.brake_can_id, CFG.status_can_id
PERIOD = CFG.brake_period_us


def control(gas: float, steer: float, gear: int, turn: int, horn: int, legacy: bool) -> bytes:
    return packet(gas, steer, gear, turn, horn, legacy=legacy)


unit = st.floats(min_value=-1.0, max_value=1.0, width=32)
valid_packets = st.builds(
    control, unit, unit, st.sampled_from([1, 2, 4, 8]), st.integers(0, 3), st.integers(0, 1),
    st.booleans(),
)
neutral_packets = st.builds(
    control, st.floats(min_value=-1.0, max_value=0.0, width=32), unit,
    st.sampled_from([1, 2, 4, 8]), st.integers(0, 3), st.integers(0, 1), st.booleans(),
)
bad_floats = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1.0000001, -1.5, 3e38])
invalid_packets = st.one_of(
    st.binary(max_size=40).filter(lambda b: len(b) not in (16, 20)),
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
)
stop_datagrams = st.builds(lambda tail: b"ESQ2" + struct.pack("<I", CFG.stop_id) + tail,
                           st.binary(min_size=40, max_size=40))
request_kinds = st.sampled_from(["stop", "status", "release", "unknown", "badcrc"])
small_dt = st.integers(0, 30_000)


class CoreVsModel(RuleBasedStateMachine):
    @initialize(start=st.integers(0, 2**32 - 1))
    def boot(self, start: int) -> None:
        self.core = Watchdog(Config(), now_us=start)
        self.model = Model(CFG, start)
        self.now = start
        self.seq = 0
        self.open_slots: set[int] = set()
        self.last_brake: tuple[int, bytes] | None = None
        self.prev_state = 0
        self.on_time = True
        self.release_acked = False
        self.next_call = start
        self._compare(self.core.tick(start), self.model.tick(start))

    # -- comparison and per-step invariants ----------------------------------------------
    def _compare(self, steps: Step | list[Step], expected_model) -> None:  # noqa: ANN001
        steps = steps if isinstance(steps, list) else [steps]
        frames = [(f.can_id, f.data) for s in steps for f in s.frames]
        replies = [s.reply for s in steps if s.reply is not None]
        assert frames == expected_model.frames
        assert replies == expected_model.replies
        assert any(s.close for s in steps) == expected_model.closed
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
                assert (data[0], data[1]) == ((1, 100) if data[2] == 0 else (0, 0))
                if self.last_brake is not None and self.on_time:
                    assert self.now - self.last_brake[0] <= PERIOD, "ESTOP_BRAKE gap over period"
                self.last_brake = (self.now, data)
        for rep in replies:
            assert crc32(rep[:12]) == struct.unpack("<I", rep[12:])[0]
            if rep[0] == ACK and rep[8] == 1 and self.prev_state == 0:
                self.release_acked = True
        if last.state == 1:
            event("reached ARMED")
        if self.prev_state == 1 and last.state == 0:
            event(f"stopped, reason {last.reason}")
        if self.prev_state == 0 and last.state == 1:
            assert self.release_acked, "left STOPPED without an accepted RELEASE"
        self.prev_state = last.state
        self.release_acked = False
        self.on_time = True

    @invariant()
    def brake_matches_state(self) -> None:
        if hasattr(self, "core"):
            assert self.last_brake is not None
            assert self.last_brake[1][2] == self.core.status().state
            assert self.next_call - self.last_brake[0] <= PERIOD

    def _later(self, dt: int) -> int:
        # A host calls back no later than it was asked to; jumps are their own rule.
        target = self.now + dt
        self.on_time = target <= self.next_call
        self.now = target
        return target

    # -- operations ----------------------------------------------------------------------
    @rule(data=valid_packets, dt=small_dt)
    def valid_packet(self, data: bytes, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self._compare(self.core.udp(data, self.now), self.model.udp(data, self.now))

    @rule(data=invalid_packets, dt=small_dt)
    def invalid_packet(self, data: bytes, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self._compare(self.core.udp(data, self.now), self.model.udp(data, self.now))

    @rule(data=stop_datagrams, dt=small_dt)
    def stop_datagram(self, data: bytes, dt: int) -> None:
        """Anyone may stop: a request frame with the stop ID over UDP, any tag."""
        self.run_host_until(self.now + dt)
        self._compare(self.core.udp(data, self.now), self.model.udp(data, self.now))

    @rule(data=st.lists(neutral_packets, min_size=1, max_size=8), gap=st.integers(1_000, 60_000))
    def drive(self, data: list[bytes], gap: int) -> None:
        """A burst of packets at a steady rate, the host ticking between them."""
        for datagram in data:
            self.run_host_until(self.now + gap)
            self._compare(self.core.udp(datagram, self.now), self.model.udp(datagram, self.now))

    @rule(data=st.lists(neutral_packets, min_size=5, max_size=8),
          gap=st.integers(1_000, 45_000), slot=st.integers(0, MAX_SLOTS - 1))
    def operator_release(self, data: list[bytes], gap: int, slot: int) -> None:
        """What an operator does: hold the finger on neutral, then press release."""
        self.drive(data, gap)
        if slot not in self.open_slots:
            self.open_slots.add(slot)
            self._compare(self.core.tcp_open(slot, self.now), self.model.tcp_open(slot, self.now))
        self.seq += 1
        frame = request(RELEASE_ID, self.seq)
        self._compare(self.core.tcp_data(slot, frame, self.now),
                      self.model.tcp_data(slot, frame, self.now))

    @rule(slot=st.integers(0, MAX_SLOTS - 1), dt=small_dt)
    def tcp_open(self, slot: int, dt: int) -> None:
        self.run_host_until(self.now + dt)
        self.open_slots.add(slot)
        self._compare(self.core.tcp_open(slot, self.now), self.model.tcp_open(slot, self.now))

    @precondition(lambda self: bool(self.open_slots))
    @rule(data=st.data(), dt=small_dt)
    def tcp_close(self, data: st.DataObject, dt: int) -> None:
        slot = data.draw(st.sampled_from(sorted(self.open_slots)))
        self.run_host_until(self.now + dt)
        self.open_slots.discard(slot)
        self._compare(self.core.tcp_close(slot, self.now), self.model.tcp_close(slot, self.now))

    @precondition(lambda self: bool(self.open_slots))
    @rule(data=st.data(), kinds=st.lists(request_kinds, min_size=1, max_size=4))
    def tcp_requests(self, data: st.DataObject, kinds: list[str]) -> None:
        """Requests as one byte stream, cut at random points, each piece at its own time."""
        slot = data.draw(st.sampled_from(sorted(self.open_slots)))
        stream = b""
        for kind in kinds:
            self.seq += 1
            msg_id = {"stop": CFG.stop_id, "status": STATUS_ID, "release": RELEASE_ID,
                      "unknown": data.draw(st.integers(3, 2**32 - 1).filter(
                          lambda i: i != CFG.stop_id)), "badcrc": STATUS_ID}[kind]
            stream += request(msg_id, self.seq, good_crc=kind != "badcrc")
        cuts = sorted(data.draw(st.sets(st.integers(1, len(stream) - 1), max_size=6)))
        pieces = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
        for piece in pieces:
            self.run_host_until(self.now + data.draw(st.integers(0, 3_000)))
            steps = self.core.tcp_data(slot, piece, self.now)
            expected = self.model.tcp_data(slot, piece, self.now)
            self._compare(steps, expected)
            if expected.closed:
                self.open_slots.discard(slot)
                break

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
    # The mutation run (tools/mutants.py) asks for fewer examples per mutant.
    max_examples=int(os.environ.get("ESTOP_STATEFUL_EXAMPLES", "2000")),
    stateful_step_count=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
test_core_matches_model = CoreVsModel.TestCase
