"""The trials of the stop-latency bench: what one daemon's run measured (:class:`RunResult`)
and the driving and judging of its trials (:class:`Trials`)."""

from __future__ import annotations

import queue
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from estop.loopback import Daemon, DaemonError, Link, is_stop_frame, stamp
from estop.protocol import can, tcp, udp
from latency_flood import FloodStats

METRICS = ("overshoot", "tcp_stop")
METRIC_TITLES = {"overshoot": "timeout overshoot", "tcp_stop": "TCP stop latency"}
LOST_LINES = "log lines lost"  # the discard reason of issue 11


@dataclass
class RunResult:
    daemon: str
    load: str
    timeout_ms: int
    samples: dict[str, list[float]] = field(default_factory=lambda: {m: [] for m in METRICS})
    missed: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    wrong_reason: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    discarded: dict[str, int] = field(default_factory=lambda: {m: 0 for m in METRICS})
    release_failures: int = 0
    release_naks: int = 0
    discard_reasons: dict[str, int] = field(default_factory=dict)
    sample_times: dict[str, list[float]] = field(default_factory=lambda: {m: [] for m in METRICS})
    blocks: list[dict[str, float]] = field(default_factory=list)  # per block: t, s, other, steal
    status_frames: int = 0
    status_invalid_saturated: int = 0  # STATUS frames counting >= 255 invalid packets / 100 ms
    status_auth_saturated: int = 0  # ... >= 255 authentication failures / 100 ms
    # per sample: ((first, last) realtime, (first, last) monotonic) of its trial, so that a
    # loss found later (a counter, the daemon's report) can still discard it
    spans: dict[str, list[tuple[tuple[float, float], tuple[float, float]]]] = field(
        default_factory=lambda: {m: [] for m in METRICS})
    log_frames: int = 0  # can-log frames whose alive counters were followed
    log_gaps: int = 0  # counter jumps among them
    log_gap_lines: int = 0  # frames missing by the counters
    daemon_dropped: int = 0  # can-log lines the daemon reported dropped (its total)
    wall_s: float = 0.0
    flood: FloodStats | None = None
    other_cpu: float | None = None  # cores used by other processes during the run
    steal_cpu: float | None = None  # cores stolen by the hypervisor during the run
    metered_s: float = 0.0
    error: str | None = None

    def early(self, metric: str) -> int:
        return sum(1 for v in self.samples[metric] if v < 0)

    def discard(self, metric: str, why: str) -> None:
        self.discarded[metric] += 1
        key = f"{METRIC_TITLES[metric]}: {why}"
        self.discard_reasons[key] = self.discard_reasons.get(key, 0) + 1

    def lost_discards(self, metric: str) -> int:
        return self.discard_reasons.get(f"{METRIC_TITLES[metric]}: {LOST_LINES}", 0)

    def add_sample(self, metric: str, value_ms: float,
                   span: tuple[tuple[float, float], tuple[float, float]] | None = None) -> None:
        self.samples[metric].append(value_ms)
        self.sample_times[metric].append(round(time.time(), 3))
        if span is not None:
            self.spans[metric].append(span)

    def settle(self, lines_lost: Callable[[tuple[float, float], tuple[float, float]], int]
               ) -> int:
        """Discard, as "log lines lost", every sample whose trial has lost lines by what is
        known now (``lines_lost(real, mono)``, e.g. :meth:`Daemon.lines_lost`); return how
        many. Called after every block and once the daemon has exited."""
        moved = 0
        for m in METRICS:
            spans = self.spans[m]
            if len(spans) != len(self.samples[m]):
                continue  # samples made without spans (synthetic runs): nothing to check
            keep = [i for i, (real, mono) in enumerate(spans) if not lines_lost(real, mono)]
            if len(keep) == len(spans):
                continue
            for _ in range(len(spans) - len(keep)):
                self.discard(m, LOST_LINES)
                moved += 1
            times = self.sample_times[m]
            self.samples[m] = [self.samples[m][i] for i in keep]
            if len(times) == len(spans):
                self.sample_times[m] = [times[i] for i in keep]
            self.spans[m] = [spans[i] for i in keep]
        return moved

    def add_cpu(self, measured: tuple[float, float, float] | None) -> None:
        """Fold one block's (other, steal, seconds) into the run's time-weighted means."""
        if measured is None:
            return
        other, steal, secs = measured
        self.blocks.append({"t_end": round(time.time(), 3), "seconds": round(secs, 2),
                            "other": round(other, 3), "steal": round(steal, 3)})
        total = self.metered_s + secs
        if total <= 0:
            return
        self.other_cpu = ((self.other_cpu or 0.0) * self.metered_s + other * secs) / total
        self.steal_cpu = ((self.steal_cpu or 0.0) * self.metered_s + steal * secs) / total
        self.metered_s = total


@dataclass(frozen=True)
class TimeoutSent:
    """What a timeout trial sent: the bench's time.monotonic() when it began, time.time()
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


class Trials:
    """Drives trials against one daemon (``link``) and measures them from its can-log
    (``daemon.frames``, checked with ``daemon.lines_lost``). The measuring half
    (:meth:`judge_timeout`, :meth:`judge_tcp`) needs no link: it can be fed recorded lines."""

    def __init__(self, daemon: Daemon, link: Link | None, timeout_ms: int, send_slack_s: float,
                 result: RunResult, seed: int = 1) -> None:
        self.d = daemon
        self.link = link
        self.timeout_s = timeout_ms / 1000.0
        self.slack = send_slack_s
        self.r = result
        self.rng = random.Random(seed)

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
        ``after``; None if none comes within max_s."""
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
            if rec.can_id == can.STATUS_ID and len(rec.data) == can.DLC:
                self.r.status_frames += 1
                st = can.StatusFrame.parse(rec.data)
                self.r.status_invalid_saturated += st.invalid_packets == 255
                self.r.status_auth_saturated += st.auth_failures == 255
            elif is_stop_frame(rec) and stamp(rec) >= after:
                return stamp(rec), can.BrakeFrame.parse(rec.data).reason

    def timeout_trial(self) -> bool:
        """One timeout trial; True when it produced a sample."""
        mono = time.monotonic()
        t_ack = self.release()
        if t_ack is None:
            return False
        prev, late, gap = t_ack, False, False
        t_last = t_ack
        for i in range(3):
            if i:
                time.sleep(0.001)
            t_last, quick = self.send(0.3, udp.Gear.DRIVE)
            late = late or not quick
            gap = gap or t_last - prev >= self.timeout_s / 2
            prev = t_last
        return self.judge_timeout(TimeoutSent(mono, t_ack, t_last, late, gap))

    def judge_timeout(self, sent: TimeoutSent) -> bool:
        """Find the timeout stop in the can-log and count it: a sample, a discard (with its
        reason), a miss or a wrong reason. True when it produced a sample."""
        stop = self.wait_stop(sent.t_ack, self.timeout_s + 2.0)
        if stop is None:
            self.r.missed["overshoot"] += 1
            return False
        t_stop, reason = stop
        span = ((sent.t_ack, t_stop), (sent.mono, time.monotonic()))
        why = (LOST_LINES if self.d.lines_lost(*span) else "late send" if sent.late
               else "gap between packets" if sent.gap
               else "stop before the last packet" if t_stop < sent.t_last else None)
        if why is not None:
            self.r.discard("overshoot", why)
            return False
        if reason != can.Reason.UDP_TIMEOUT:
            self.r.wrong_reason["overshoot"] += 1
            return False
        self.r.add_sample("overshoot", (t_stop - (sent.t_last + self.timeout_s)) * 1000.0, span)
        return True

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
        span = ((sent.t_ack, t_frame), (sent.mono, time.monotonic()))
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

    def run(self, n: int, deadline: float, max_attempts: int) -> int:
        """Trials until each metric has n samples, the monotonic deadline passes, or
        max_attempts trial pairs were tried; returns the attempts made."""
        attempts = 0
        while attempts < max_attempts and time.monotonic() < deadline:
            need = [len(self.r.samples[m]) < n for m in METRICS]
            if not any(need):
                break
            attempts += 1
            if need[0]:
                self.timeout_trial()
            if need[1]:
                self.tcp_trial()
        return attempts
