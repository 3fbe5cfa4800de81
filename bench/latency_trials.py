"""The trials of the stop-latency bench: driving one daemon and judging its stops from its
can-log (:class:`Trials`). What they measured goes into a :class:`~latency_result.RunResult`.

Three kinds of trial, each after a random pause of 0..10 ms and a RELEASE (retried if
refused):

- silence: drive 3 packets 1 ms apart and go silent; the first emergency stop frame (reason
  udp timeout) times the overshoot past T, and on a two-stage unit the first SLOWING frame the
  overshoot past S; the roll-out runs from the last packet;
- TCP: drive 1 packet and send STOP over TCP;
- lift: drive 3 packets 1 ms apart, then the remote's lift (three lift datagrams 10 ms apart,
  ``estop.client.button.send_lift``); the first stop frame (reason lift) times it from the first
  datagram, and the roll-out runs from there.
"""

from __future__ import annotations

import queue
import random
import time
from dataclasses import dataclass

from estop.client.button import LiftDatagram, send_lift
from estop.model.vehicle import DEFAULT_PARAMS, VehicleParams
from estop.protocol import can, tcp, udp
from estop.protocol.canlog import CanLogRecord
from estop.unit.canlog import DaemonError, is_stop_frame, stamp
from estop.unit.daemon import Daemon
from estop.unit.looplink import Link
from latency_result import LOST_LINES, TIMEOUT_FIRST, RunResult, Span
from latency_roll import DEFAULT_SPEED_KMH, roll_from_record


@dataclass(frozen=True)
class TimeoutSent:
    """What a silence trial sent: the bench's time.monotonic() when it began, time.time()
    after the RELEASE ACK and before the last packet, and whether a send call was late or the
    packets left a gap."""

    mono: float
    t_ack: float
    t_last: float
    late: bool = False
    gap: bool = False


@dataclass(frozen=True)
class TcpSent:
    """What a TCP trial sent: as :class:`TimeoutSent`, with the time before the STOP."""

    mono: float
    t_ack: float
    t_stop: float
    quick: bool = True


@dataclass(frozen=True)
class LiftSent:
    """What a lift trial sent: as :class:`TimeoutSent`, with the time before the first lift
    datagram and whether that send was quick."""

    mono: float
    t_ack: float
    t_last: float
    t_lift: float
    quick: bool = True
    gap: bool = False


def first_slowing(record: list[CanLogRecord], after: float) -> float | None:
    """The stamp of the first ESTOP_BRAKE frame in SLOWING stamped at or after ``after``."""
    for rec in record:
        if (rec.can_id == can.BRAKE_ID and len(rec.data) == can.DLC
                and rec.data[2] == can.State.SLOWING and stamp(rec) >= after):
            return stamp(rec)
    return None


class Trials:
    """Drives trials against one daemon (``link``) and measures them from its can-log
    (``daemon.frames``, checked with ``daemon.lines_lost``). The measuring half
    (:meth:`judge_timeout`, :meth:`judge_tcp`, :meth:`judge_lift`) needs no link: it can be
    fed recorded lines. ``slow_ms``: the unit's slow time S when it is a two-stage unit;
    distances at ``speed_kmh`` with ``vehicle``."""

    def __init__(self, daemon: Daemon, link: Link | None, timeout_ms: int, send_slack_s: float,
                 result: RunResult, seed: int = 1, *, slow_ms: int | None = None,
                 speed_kmh: float = DEFAULT_SPEED_KMH,
                 vehicle: VehicleParams = DEFAULT_PARAMS) -> None:
        self.d = daemon
        self.link = link
        self.timeout_s = timeout_ms / 1000.0
        self.slow_s = (slow_ms if slow_ms is not None else timeout_ms) / 1000.0
        self.two_stage = self.slow_s < self.timeout_s
        self.slack = send_slack_s
        self.r = result
        self.rng = random.Random(seed)
        self.speed_kmh = speed_kmh
        self.vehicle = vehicle
        self.record: list[CanLogRecord] = []  # frames read since the last stop frame taken
        self.last_record: list[CanLogRecord] = []  # ... up to and including that stop frame
        self._lift: LiftDatagram | None = None
        self._lift_sends: list[tuple[float, bool]] = []  # (time before, quick) per datagram
        self._lift_seq = 0

    @property
    def _link(self) -> Link:
        if self.link is None:
            raise DaemonError("no link to drive trials with")
        return self.link

    def send(self, gas: float, gear: int) -> tuple[float, bool]:
        """Send one control packet; (time before the send, send took <= slack)."""
        t = self._link.send_control(gas, 0.0, gear)
        return t, time.time() - t <= self.slack

    def release(self) -> float | None:
        """Bring the unit to ARMED; time.time() after the ACK, None if it keeps refusing.

        First a random pause of 0..10 ms (one brake period), so that trials do not lock onto
        the phase of the daemon's periodic work (each trial starts right after a stop frame).
        """
        time.sleep(self.rng.uniform(0.0, 0.010))
        link = self._link
        for _ in range(50):
            for _ in range(5):
                link.send_control(0.0, 0.0, udp.Gear.NEUTRAL)
            time.sleep(0.0005)
            reply, _t = link.request(tcp.RELEASE)
            if reply.ack and reply.state == 1:
                return time.time()
            self.r.release_naks += 1
            time.sleep(0.002)
        self.r.release_failures += 1
        return None

    def wait_stop(self, after: float, max_s: float) -> tuple[float, int] | None:
        """(stamp, reason) of the first brake frame with brake_request 1 stamped at or after
        ``after``; None if none comes within max_s. The frames read on the way, that one
        included, are :attr:`last_record` afterwards (the roll-out's input)."""
        deadline = time.monotonic() + max_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                rec = self.d.frames.get(timeout=min(left, 0.1))
            except queue.Empty:
                if not self.d.alive():
                    raise DaemonError("the daemon died") from None
                continue
            self.record.append(rec)
            if rec.can_id == can.STATUS_ID and len(rec.data) == can.DLC:
                self.r.status_frames += 1
                st = can.StatusFrame.parse(rec.data)
                self.r.status_invalid_saturated += st.invalid_packets == 255
                self.r.status_auth_saturated += st.auth_failures == 255
            elif is_stop_frame(rec) and stamp(rec) >= after:
                self.last_record, self.record = self.record, []
                return stamp(rec), can.BrakeFrame.parse(rec.data).reason

    def forget_frames(self) -> None:
        """The frames read so far are no trial's (the daemon waited while another was
        tested, and its queue was drained)."""
        self.record = []

    def _roll(self, moment: float) -> float:
        return roll_from_record(self.last_record, moment, self.speed_kmh,
                                params=self.vehicle).distance

    def _drive(self, t_ack: float) -> tuple[float, bool, bool]:
        """3 drive packets 1 ms apart: (time before the last, a send was late, a gap)."""
        prev, late, gap = t_ack, False, False
        t_last = t_ack
        for i in range(3):
            if i:
                time.sleep(0.001)
            t_last, quick = self.send(0.3, udp.Gear.DRIVE)
            late = late or not quick
            gap = gap or t_last - prev >= min(self.slow_s, self.timeout_s) / 2
            prev = t_last
        return t_last, late, gap

    # -- silence --------------------------------------------------------------------------

    def timeout_trial(self) -> bool:
        """One silence trial; True when it produced a sample."""
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        t_last, late, gap = self._drive(t_ack)
        return self.judge_timeout(TimeoutSent(mono, t_ack, t_last, late, gap))

    def judge_timeout(self, sent: TimeoutSent) -> bool:
        """Find the timeout stop (and, on a two-stage unit, the slow-down before it) in the
        can-log and count it: samples, a discard (with its reason), a miss or a wrong reason.
        True when it produced a sample."""
        metrics = ("overshoot", "slowing") if self.two_stage else ("overshoot",)
        stop = self.wait_stop(sent.t_ack, self.timeout_s + 2.0)
        if stop is None:
            for m in metrics:
                self.r.missed[m] += 1
            return False
        t_stop, reason = stop
        t_slow = first_slowing(self.last_record, sent.t_ack) if self.two_stage else None
        span: Span = ((sent.t_ack, t_stop), (sent.mono, time.monotonic()))
        why = (LOST_LINES if self.d.lines_lost(*span) else "late send" if sent.late
               else "gap between packets" if sent.gap
               else "stop before the last packet" if t_stop < sent.t_last
               else "slow-down before the last packet" if t_slow is not None
               and t_slow < sent.t_last else None)
        if why is not None:
            for m in metrics:
                self.r.discard(m, why)
            return False
        if reason != can.Reason.UDP_TIMEOUT:
            for m in metrics:
                self.r.wrong_reason[m] += 1
            return False
        if self.two_stage:
            if t_slow is None:
                self.r.missed["slowing"] += 1  # straight to STOPPED: no slow-down seen
            else:
                self.r.add_sample("slowing", (t_slow - (sent.t_last + self.slow_s)) * 1000.0,
                                  span)
        self.r.add_sample("overshoot", (t_stop - (sent.t_last + self.timeout_s)) * 1000.0,
                          span, self._roll(sent.t_last))
        return True

    # -- TCP STOP -------------------------------------------------------------------------

    def tcp_trial(self) -> bool:
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        _t_pkt, quick = self.send(0.3, udp.Gear.DRIVE)
        seq, t_stop = self._link.send_request(tcp.DEFAULT_STOP_ID)
        quick = quick and time.time() - t_stop <= self.slack
        took = self.judge_tcp(TcpSent(mono, t_ack, t_stop, quick))
        self._link.read_reply(seq)
        return took

    def judge_tcp(self, sent: TcpSent) -> bool:
        """Find the STOP's stop frame in the can-log and count it (see judge_timeout)."""
        stop = self.wait_stop(sent.t_ack, 2.0)
        if stop is None:
            self.r.missed["tcp_stop"] += 1
            return False
        t_frame, reason = stop
        span: Span = ((sent.t_ack, t_frame), (sent.mono, time.monotonic()))
        if reason == can.Reason.UDP_TIMEOUT:
            # the link timed out before the STOP was handled (the bench or the daemon was
            # held up, or the kernel dropped the drive packet): a stop, but not the TCP path
            self.r.discard("tcp_stop", "link timed out first")
            return False
        if reason != can.Reason.TCP_STOP:
            self.r.wrong_reason["tcp_stop"] += 1
            return False
        why = (LOST_LINES if self.d.lines_lost(*span) else None if sent.quick
               else "late send")
        if why is not None:
            self.r.discard("tcp_stop", why)
            return False
        self.r.add_sample("tcp_stop", (t_frame - sent.t_stop) * 1000.0, span)
        return True

    # -- lift -----------------------------------------------------------------------------

    def _transmit_lift(self, data: bytes) -> None:
        link = self._link
        t = time.time()
        link.udp.sendto(data, link.addr)
        self._lift_sends.append((t, time.time() - t <= self.slack))

    def lift(self) -> tuple[float, bool]:
        """The remote's lift: three lift datagrams 10 ms apart (made with the link's key and
        session, if any; the unit honours them either way). (time before the first, that send
        was quick)."""
        link = self._link
        if self._lift is None:
            self._lift = LiftDatagram(link.addr[0], link.addr[1], identity=link.identity,
                                      transmit=self._transmit_lift)
        self._lift_sends = []
        self._lift_seq += 1
        _sent, errors = send_lift(self._lift, self._lift_seq)
        if errors or not self._lift_sends:
            raise DaemonError(errors[0] if errors else "no lift datagram sent")
        return self._lift_sends[0]

    def lift_trial(self) -> bool:
        """One lift trial; True when it produced a sample."""
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        t_last, late, gap = self._drive(t_ack)
        t_lift, quick = self.lift()
        return self.judge_lift(LiftSent(mono, t_ack, t_last, t_lift, quick and not late, gap))

    def judge_lift(self, sent: LiftSent) -> bool:
        """Find the lift's stop frame in the can-log and count it (see judge_timeout)."""
        stop = self.wait_stop(sent.t_ack, 2.0)
        if stop is None:
            self.r.missed["lift"] += 1
            return False
        t_frame, reason = stop
        span: Span = ((sent.t_ack, t_frame), (sent.mono, time.monotonic()))
        if reason == can.Reason.UDP_TIMEOUT:
            # no lift datagram was handled before the deadline (all lost, or queued behind
            # others): the silence rule stopped the car (spec section 8); not a lift latency
            self.r.discard("lift", TIMEOUT_FIRST)
            return False
        if reason != can.Reason.LIFT:
            self.r.wrong_reason["lift"] += 1
            return False
        why = (LOST_LINES if self.d.lines_lost(*span) else "late send" if not sent.quick
               else "gap between packets" if sent.gap else None)
        if why is not None:
            self.r.discard("lift", why)
            return False
        self.r.add_sample("lift", (t_frame - sent.t_lift) * 1000.0, span,
                          self._roll(sent.t_lift))
        return True

    # -------------------------------------------------------------------------------------

    def run(self, n: int, deadline: float, max_attempts: int) -> int:
        """Trials until each kind has n samples, the monotonic deadline passes, or
        max_attempts rounds were tried; returns the rounds made."""
        trial = {"overshoot": self.timeout_trial, "tcp_stop": self.tcp_trial,
                 "lift": self.lift_trial}
        kinds = self.r.trial_kinds
        attempts = 0
        while attempts < max_attempts and time.monotonic() < deadline:
            need = [k for k in kinds if len(self.r.samples[k]) < n]
            if not need:
                break
            attempts += 1
            for k in need:
                trial[k]()
        return attempts
