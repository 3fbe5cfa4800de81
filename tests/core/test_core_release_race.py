"""A keyed RELEASE against the remote's own control packets (issue 25, item 2's rule, and the
race it opened): the unit refuses a RELEASE not above the newest counter of its remote on
either channel, and a remote raises one counter for both. A unit reads its UDP and TCP sockets
apart (estopd drains the control port before each stop-channel frame), so a control packet
made after the RELEASE (a higher counter) that came while the RELEASE waited is read first and
makes the RELEASE stale: NAK 4 at random for an operator who did everything right. The remote's
side of the rule (docs/REMOTE.md section 4): no control packet above a RELEASE in flight, from
taking its counter until its reply, for at most :data:`RELEASE_QUIET_S`.

The core through cffi; the remote is the real one (:class:`estop.client.sender.Remote`) over
loopback sockets, against a unit on the same core that reads in the worst order."""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Iterator

import pytest

from core_util import ARMED, MS, STOPPED, Unit
from estop.client.sender import Remote
from estop.core import Config, Watchdog
from estop.protocol import auth, tcp
from estop.protocol.udp import ControlPacket, Gear

K = bytes(range(32))
N = 0x0123456789ABCDEF
RID = 7
NAK_NOT_AUTH = 4


class Keyed(Unit):
    """A keyed unit and one remote with one counter for both channels."""

    def __init__(self) -> None:
        super().__init__(Config(key=K, session=N))
        self.counter = 0

    def take(self) -> int:
        self.counter += 1
        return self.counter

    def heartbeat(self) -> bytes:
        return auth.AuthControlPacket(RID, N, self.take(),
                                      ControlPacket(gear=Gear.NEUTRAL)).encode(K)

    def release(self) -> bytes:
        return auth.AuthRequest(tcp.RELEASE, 1, RID, N, self.take()).encode(K)

    def ask(self, frame: bytes) -> auth.AuthReply:  # type: ignore[override]
        replies = [s.reply for s in self.send(frame) if s.reply is not None]
        assert len(replies) == 1
        return auth.AuthReply.decode(replies[0], K, auth.request_tag(frame))


@pytest.mark.parametrize("order", ["as sent", "udp first"])
def test_a_release_read_after_the_control_packet_made_after_it_is_refused(order: str) -> None:
    """The cause, at core level: RELEASE c on TCP, control packet c+1 on UDP a millisecond
    later. Read in the order sent the RELEASE arms the unit; read UDP first (another socket,
    the same or the next round of the unit's loop) it is refused as an old counter, NAK 4: the
    core's rule (a sniffed RELEASE that was never delivered is stale once anything later of
    its remote was taken) cannot tell the two apart. So the remote must not make c+1 while c
    is in flight."""
    u = Keyed()
    for _ in range(5):  # a live, neutral link: counters 1..5
        u.wait(20 * MS)
        u.udp(u.heartbeat())
    release = u.release()  # counter 6, written to the stop channel
    u.wait(1 * MS)
    after = u.heartbeat()  # counter 7, the control sender's next tick
    if order == "as sent":
        reply = u.ask(release)
        u.udp(after)
        assert (reply.ack, reply.state) == (True, ARMED)
    else:
        before = u.wd.status().counters.auth_old_counter
        u.udp(after)
        reply = u.ask(release)
        assert (reply.ack, reply.nak_code, reply.state) == (False, NAK_NOT_AUTH, STOPPED)
        assert u.wd.status().counters.auth_old_counter == before + 1


class WorstOrderUnit:
    """A keyed unit on the cffi core behind loopback sockets (one UDP socket, one TCP
    connection), reading in the worst order for a RELEASE: a RELEASE frame is handled only
    ``hold_s`` after it was read (a busy unit), and after every datagram that came meanwhile
    (as estopd reads the control port before each stop-channel frame). Other frames are
    answered at once. ``seen`` collects (time.monotonic(), counter) of each control packet."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self.t0 = time.monotonic()
        self.wd = Watchdog(Config(key=K, session=N), now_us=0)
        self.wd.tcp_open(0, 0)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.udp_port = self.udp.getsockname()[1]
        self.tcp_port = self.listener.getsockname()[1]
        self.seen: list[tuple[float, int]] = []
        self.held_packets: list[int] = []  # counters of the packets read while a RELEASE waited
        self.release_counters: list[int] = []  # the counter of each RELEASE frame read
        self.error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _now(self) -> int:
        return int((time.monotonic() - self.t0) * 1e6)

    def _datagram(self, data: bytes) -> int:
        self.wd.udp(data, self._now())
        counter = int.from_bytes(data[16:24], "little") if len(data) == 60 else -1
        if len(data) == 60:
            self.seen.append((time.monotonic(), counter))
        return counter

    def _drain_udp(self) -> list[int]:
        got = []
        while select.select([self.udp], [], [], 0)[0]:
            got.append(self._datagram(self.udp.recv(2048)))
        return got

    def _run(self) -> None:
        try:
            self.listener.settimeout(5.0)
            conn, _ = self.listener.accept()
            buf = b""
            while not self._stop:
                ready = select.select([self.udp, conn], [], [], 0.05)[0]
                if self.udp in ready:
                    self._drain_udp()
                if conn not in ready:
                    continue
                chunk = conn.recv(4096)
                if not chunk:
                    return
                buf += chunk
                while len(buf) >= auth.REQUEST_SIZE:
                    frame, buf = buf[:auth.REQUEST_SIZE], buf[auth.REQUEST_SIZE:]
                    request = auth.AuthRequest.decode(frame, K)
                    if request.msg_id == tcp.RELEASE:
                        self.release_counters.append(request.counter)
                        time.sleep(self.hold_s)
                        self.held_packets += self._drain_udp()
                    for step in self.wd.tcp_data(0, frame, self._now()):
                        if step.reply is not None:
                            conn.sendall(step.reply)
        except BaseException as exc:  # the test reports it
            self.error = exc

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=5)
        self.udp.close()
        self.listener.close()


@pytest.fixture
def slow_unit(request: pytest.FixtureRequest) -> Iterator[WorstOrderUnit]:
    unit = WorstOrderUnit(request.param)
    yield unit
    unit.close()
    assert unit.error is None, unit.error


def _release_after_hold(unit: WorstOrderUnit, **remote: float) -> tuple[tcp.Reply, float]:
    """The remote's RELEASE after a live link; its reply, and the quiet left once release()
    has returned (0.0: the reply ended it)."""
    with Remote("127.0.0.1", unit.udp_port, unit.tcp_port, key=K, remote_id=RID,
                rate_hz=200.0, **remote) as r:  # type: ignore[arg-type]
        r.hold()  # STATUS first: the session
        time.sleep(0.1)  # 20 packets: a live, neutral link
        reply = r.release()
        quiet_left = r.identity.quiet_until()
        r.lift()
    return reply, quiet_left


@pytest.mark.parametrize("slow_unit", [0.03], indirect=True)
def test_the_remote_makes_no_control_packet_above_its_release_in_flight(
        slow_unit: WorstOrderUnit) -> None:
    """The real remote (200 Hz) against a unit that holds the RELEASE 30 ms and then reads
    every datagram that came meanwhile first. Failed before (NAK 4 every time: the sender made
    6 packets above the RELEASE's counter while it waited); now the sender makes none above
    the RELEASE's counter until the reply, and the RELEASE arms the unit. (The quiet's bound is
    raised to 1 s here so that a loaded machine cannot end it before the unit has read the
    frame; the bound itself is the next test's.)

    A packet below the RELEASE's counter may still be read while it waits: the sender takes
    its counter before the RELEASE takes the next and may write it after the RELEASE's frame
    (a thread switch between the two). The unit takes it and then the RELEASE, as it must; a
    CI run on a loaded machine once read one such packet, which an earlier form of this test
    (no packet at all read meanwhile) took for a fault."""
    reply, quiet_left = _release_after_hold(slow_unit, release_quiet_s=1.0)
    assert len(slow_unit.release_counters) == 1, slow_unit.release_counters
    above = [c for c in slow_unit.held_packets if c > slow_unit.release_counters[0]]
    assert above == [], (above, slow_unit.release_counters)
    assert (reply.ack, reply.state) == (True, ARMED), reply
    assert quiet_left == 0.0  # the reply ended the quiet, not its bound


@pytest.mark.parametrize("slow_unit", [0.3], indirect=True)
def test_the_quiet_for_a_release_in_flight_ends_at_its_bound(
        slow_unit: WorstOrderUnit) -> None:
    """The dead-man's silence rules still hold while a RELEASE waits: a unit that holds it
    300 ms gets control packets again once the quiet's bound (RELEASE_QUIET_S, 50 ms) is up,
    long before the reply. The RELEASE is then refused (NAK 4), a fail-safe refusal the
    operator answers with another press; the remote never re-sends it on its own."""
    reply, _ = _release_after_hold(slow_unit)
    assert len(slow_unit.held_packets) >= 10, slow_unit.held_packets
    assert (reply.ack, reply.nak_code) == (False, NAK_NOT_AUTH)
