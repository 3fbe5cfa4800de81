"""Small helpers for stepping the core by hand in unit tests."""

from __future__ import annotations

from estop.core import Config, Step, Watchdog
from estop.protocol import tcp, udp

STOPPED, ARMED, SLOWING = 0, 1, 2
NONE, BOOT, TCP_STOP, UDP_TIMEOUT, FAULT, LIFT = range(6)
LIFT_ID = 3
STOP_ID = 0xE570E570
BRAKE_ID, STATUS_ID = 0x050, 0x051
MS = 1000


def packet(gas: float = 0.0, steer: float = 0.0, gear: int = 4, turn: int = 0,
           horn: int = 0, legacy: bool = False) -> bytes:
    """A control packet, valid or not (no validation); the 16-byte form drops horn."""
    fields = udp.ControlPacket(gas, steer, gear, turn, 0 if legacy else horn)
    return fields.encode(legacy=legacy, validate=False)


def request(msg_id: int, seq: int = 1, arg: int = 0, good_crc: bool = True) -> bytes:
    frame = tcp.Request(msg_id, seq, arg).encode()
    return frame if good_crc else frame[:12] + bytes([frame[12] ^ 0x01]) + frame[13:]


def reply_fields(raw: bytes) -> tuple[int, int, int, int, int, int]:
    """(msg_id, seq, state, reason, flags, nak) of a reply; strict decoding checks length, CRC
    and that every field is one spec version 1 allows."""
    r = tcp.Reply.decode(raw)
    return r.msg_id, r.seq, r.state, r.reason, r.flags, r.nak_code


class Unit:
    """A Watchdog plus a clock in microseconds and one open TCP slot."""

    def __init__(self, config: Config | None = None, start: int = 0) -> None:
        self.t = start
        self.wd = Watchdog(config or Config(), now_us=start)
        self.frames: list[tuple[int, int, bytes]] = []  # (time, id, data)
        self._keep(self.wd.tick(start))
        self.last_next = self._keep(self.wd.tcp_open(0, start)).next_call_us

    def _keep(self, step: Step) -> Step:
        self.frames.extend((self.t, f.can_id, f.data) for f in step.frames)
        return step

    def at(self, t: int) -> None:
        """Advances to t, ticking at every time the core asks for (as a host does)."""
        while self.last_next <= t:
            self.t = max(self.t, self.last_next)
            self.last_next = self._keep(self.wd.tick(self.t)).next_call_us
        self.t = t
        self.last_next = self._keep(self.wd.tick(t)).next_call_us

    def wait(self, dt: int) -> None:
        self.at(self.t + dt)

    def udp(self, data: bytes) -> Step:
        step = self._keep(self.wd.udp(data, self.t))
        self.last_next = step.next_call_us
        return step

    def send(self, frame: bytes, slot: int = 0) -> list[Step]:
        steps = self.wd.tcp_data(slot, frame, self.t)
        for s in steps:
            self._keep(s)
        self.last_next = steps[-1].next_call_us
        return steps

    def ask(self, msg_id: int, seq: int = 1) -> tuple[int, int, int, int, int, int]:
        steps = self.send(request(msg_id, seq))
        replies = [s.reply for s in steps if s.reply is not None]
        assert len(replies) == 1
        return reply_fields(replies[0])

    def drive(self, n: int = 5, gas: float = 0.0, gap: int = 20 * MS) -> None:
        for _ in range(n):
            self.wait(gap)
            self.udp(packet(gas))

    def arm(self) -> None:
        self.drive(5)
        assert self.ask(2)[5] == 0
        assert self.state == ARMED

    @property
    def state(self) -> int:
        return self.wd.status().state

    @property
    def reason(self) -> int:
        return self.wd.status().reason

    def brake_frames(self, since: int = 0) -> list[tuple[int, bytes]]:
        return [(t, d) for t, i, d in self.frames if i == BRAKE_ID and t >= since]
