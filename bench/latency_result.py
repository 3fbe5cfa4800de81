"""What one daemon's run of the stop-latency bench measured (:class:`RunResult`), and the names
of its metrics. Pure data: filled by ``latency_trials`` and ``latency_run``, read by the report.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

from latency_flood import FloodStats

# Every metric a run may measure (ms), in report order:
# - overshoot: first emergency stop frame - (last valid packet sent + timeout T)
# - tcp_stop:  first stop frame - STOP sent over TCP
# - lift:      first stop frame with reason lift - first lift datagram sent
# - slowing:   first SLOWING frame - (last valid packet sent + slow time S), two-stage units
METRICS = ("overshoot", "tcp_stop", "lift", "slowing")
METRIC_TITLES = {"overshoot": "timeout overshoot", "tcp_stop": "TCP stop latency",
                 "lift": "lift stop latency", "slowing": "slow-down overshoot"}
TRIAL_KINDS = ("overshoot", "tcp_stop", "lift")  # metrics with trials of their own
ROLL_METRICS = ("overshoot", "lift")  # trials whose roll-out to standstill is computed
PLAIN_METRICS = ("overshoot", "tcp_stop", "lift")  # a version 3 daemon, one stage
V2_METRICS = ("overshoot", "tcp_stop")  # a daemon without LIFT (protocol version 2)
TWO_STAGE_METRICS = ("overshoot", "slowing")  # silence trials of a two-stage unit
LOST_LINES = "log lines lost"  # the discard reason of issue 11
TIMEOUT_FIRST = "the timeout stopped it first"  # a lift trial whose lift was never handled

# What a daemon is in a run: the unit under test, its peers, the same unit before a change
ROLE_MAIN, ROLE_BASELINE, ROLE_KEYLESS = "main", "baseline", "keyless"
ROLE_BEFORE, ROLE_SINGLE = "before", "single-stage"

T = TypeVar("T")
Span = tuple[tuple[float, float], tuple[float, float]]  # ((first, last) realtime, monotonic)


def _pick(values: list[T], keep: list[int]) -> list[T]:
    return [values[i] for i in keep]


def _per_metric() -> dict[str, int]:
    return {m: 0 for m in METRICS}


def _lists() -> dict[str, list[float]]:
    return {m: [] for m in METRICS}


@dataclass
class RunResult:
    daemon: str
    load: str
    timeout_ms: int
    metrics: tuple[str, ...] = V2_METRICS  # what this run measured (rows of the report)
    role: str = ""  # ROLE_*; by default from the name: "baseline", else the unit under test
    slow_ms: int | None = None  # the slow time S of a two-stage unit
    samples: dict[str, list[float]] = field(default_factory=_lists)
    missed: dict[str, int] = field(default_factory=_per_metric)
    wrong_reason: dict[str, int] = field(default_factory=_per_metric)
    discarded: dict[str, int] = field(default_factory=_per_metric)
    release_failures: int = 0
    release_naks: int = 0
    discard_reasons: dict[str, int] = field(default_factory=dict)
    sample_times: dict[str, list[float]] = field(default_factory=_lists)
    # metres the car rolled (at the run's speed) from the moment that mattered to standstill,
    # one per sample of the ROLL_METRICS, in the same order
    distances: dict[str, list[float]] = field(default_factory=_lists)
    blocks: list[dict[str, float]] = field(default_factory=list)  # per block: t, s, other, steal
    status_frames: int = 0
    status_invalid_saturated: int = 0  # STATUS frames counting >= 255 invalid packets / 100 ms
    status_auth_saturated: int = 0  # ... >= 255 authentication failures / 100 ms
    # per sample: ((first, last) realtime, (first, last) monotonic) of its trial, so that a
    # loss found later (a counter, the daemon's report) can still discard it
    spans: dict[str, list[Span]] = field(default_factory=lambda: {m: [] for m in METRICS})
    log_frames: int = 0  # can-log frames whose alive counters were followed
    log_gaps: int = 0  # counter jumps among them
    log_gap_lines: int = 0  # frames missing by the counters
    daemon_dropped: int = 0  # can-log lines the daemon reported dropped (its total)
    floor_ms: list[float] = field(default_factory=list)  # timer wake-ups before its blocks
    udp_rcvbuf: int | None = None  # the receive buffer the daemon's start line reports
    daemon_udp_drops: int | None = None  # kernel drops the daemon itself reported (udp_drops)
    deadline_cuts: int | None = None  # drains cut short by a silence deadline (udp_reads)
    wall_s: float = 0.0
    flood: FloodStats | None = None
    other_cpu: float | None = None  # cores used by other processes during the run
    steal_cpu: float | None = None  # cores stolen by the hypervisor during the run
    metered_s: float = 0.0
    error: str | None = None

    def __post_init__(self) -> None:
        if not self.role:
            self.role = ROLE_BASELINE if self.daemon == "baseline" else ROLE_MAIN

    @property
    def trial_kinds(self) -> tuple[str, ...]:
        """The kinds of trial this run makes (``slowing`` comes with the silence trials)."""
        return tuple(m for m in TRIAL_KINDS if m in self.metrics)

    def early(self, metric: str) -> int:
        return sum(1 for v in self.samples[metric] if v < 0)

    def discard(self, metric: str, why: str) -> None:
        self.discarded[metric] += 1
        key = f"{METRIC_TITLES[metric]}: {why}"
        self.discard_reasons[key] = self.discard_reasons.get(key, 0) + 1

    def lost_discards(self, metric: str) -> int:
        return self.discards_for(metric, LOST_LINES)

    def discards_for(self, metric: str, why: str) -> int:
        return self.discard_reasons.get(f"{METRIC_TITLES[metric]}: {why}", 0)

    def add_sample(self, metric: str, value_ms: float, span: Span | None = None,
                   distance: float | None = None) -> None:
        self.samples[metric].append(value_ms)
        self.sample_times[metric].append(round(time.time(), 3))
        if span is not None:
            self.spans[metric].append(span)
        if distance is not None:
            self.distances[metric].append(distance)

    def settle(self, lines_lost: Callable[[tuple[float, float], tuple[float, float]], int]
               ) -> int:
        """Discard, as "log lines lost", every sample whose trial has lost lines by what is
        known now (``lines_lost(real, mono)``, e.g. :meth:`Daemon.lines_lost`); return how
        many. Called after every block and once the daemon has exited."""
        moved = 0
        for m in METRICS:
            spans = self.spans[m]
            n = len(self.samples[m])
            if len(spans) != n:
                continue  # samples made without spans (synthetic runs): nothing to check
            keep = [i for i, (real, mono) in enumerate(spans) if not lines_lost(real, mono)]
            if len(keep) == n:
                continue
            for _ in range(n - len(keep)):
                self.discard(m, LOST_LINES)
                moved += 1
            # every list kept beside the samples loses the same entries
            self.samples[m] = _pick(self.samples[m], keep)
            self.spans[m] = _pick(spans, keep)
            if len(self.sample_times[m]) == n:
                self.sample_times[m] = _pick(self.sample_times[m], keep)
            if len(self.distances[m]) == n:
                self.distances[m] = _pick(self.distances[m], keep)
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


def from_document(run: dict[str, Any]) -> RunResult:
    """A run back from its JSON (``stop_latency.json``'s ``runs``), for tables made later;
    metrics an older report lacks come back empty."""
    names = {f.name for f in fields(RunResult)}
    kw = {k: v for k, v in run.items() if k in names}
    for k in ("samples", "sample_times", "distances", "spans"):
        kw[k] = {**_lists(), **kw.get(k, {})}
    for k in ("missed", "wrong_reason", "discarded"):
        kw[k] = {**_per_metric(), **kw.get(k, {})}
    kw["metrics"] = tuple(kw.get("metrics", V2_METRICS))
    flood = kw.get("flood")
    if flood:
        kw["flood"] = FloodStats(**{k: v for k, v in flood.items() if k != "rate"})
    return RunResult(**kw)
