"""Test helpers for ``estop link``, written here independently of the tool: Gilbert traces,
the daemon's bin function, estopd's --log-json log, and the unit's silence rules of
PROTOCOL.md 3 (version 3: SLOWING at S, STOPPED at T) run on arrival times."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from estop.link.gaps import DAEMON_EDGES_US, daemon_bins

RATE = 50.0
PERIOD_US = 20_000
HOURS10 = 10 * 3600 * 50  # packets sent in 10 hours at 50 Hz: 1.8 M


def gilbert_lost(n: int, loss: float, burst: float, seed: int) -> np.ndarray:
    """Lost-mask of n packets through a Gilbert channel (good: received, bad: lost) with
    P(bad->good) r = 1/burst and P(good->bad) q = loss r / (1 - loss), starting good. Built
    from alternating geometric run lengths, so 1.8 M packets take milliseconds."""
    rng = np.random.default_rng(seed)
    r = 1.0 / burst
    q = loss * r / (1.0 - loss)
    m = int(n * q * 1.2) + 1000  # runs of each kind: enough with a wide margin
    runs = np.empty(2 * m, dtype=np.int64)
    runs[0::2] = rng.geometric(q, m)  # good runs: 1 + packets before the next loss
    runs[1::2] = rng.geometric(r, m)  # bad runs: packets lost in a row
    ends = np.cumsum(runs)
    assert ends[-1] > n, "generator margin too small"
    starts, stops = ends[0::2], np.minimum(ends[1::2], n)
    keep = starts < n
    edge = np.zeros(n + 1, dtype=np.int64)
    np.add.at(edge, starts[keep], 1)
    np.add.at(edge, stops[keep], -1)
    return np.cumsum(edge[:n]) > 0


def loss_runs(lost: np.ndarray) -> np.ndarray:
    """Lengths of the runs of lost packets (those closed by a received packet)."""
    x = np.concatenate(([0], lost.astype(np.int8), [0]))
    d = np.diff(x)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    runs = ends - starts
    if lost[-1]:
        runs = runs[:-1]  # a run still open at the end is not a gap between packets
    if lost[0]:
        runs = runs[1:]  # nor one before the first received packet
    return runs


def arrivals_us(lost: np.ndarray) -> np.ndarray:
    """Arrival times in integer microseconds of the received packets (no jitter)."""
    return np.flatnonzero(~lost).astype(np.int64) * PERIOD_US


EDGES_US = list(DAEMON_EDGES_US)


def histogram_log(runs: list[np.ndarray], every_s: float = 10.0, warn_us: int = 100_000,
                  noise: bool = True) -> str:
    """estopd --log-json text for runs of arrival times (us): per run a `start` event, a
    cumulative `link_histogram` every ``every_s`` and at the end, and other events between."""
    lines: list[str] = []
    t0 = 0.0
    for t_us in runs:
        lines.append(json.dumps({"t_mono": t0, "event": "start", "udp_port": 5700}))
        g = np.diff(t_us)
        bins = daemon_bins(g)
        window = ((t_us[1:] - t_us[0]) // int(every_s * 1e6)).astype(np.int64)
        nwin = int(window[-1]) + 1
        per = np.zeros((nwin, 32), dtype=np.int64)
        np.add.at(per, (window, bins), 1)
        cum = np.cumsum(per, axis=0)
        silences = np.cumsum(np.bincount(window, weights=(g > warn_us), minlength=nwin))
        for w in range(nwin):
            t = t0 + (w + 1) * every_s
            if noise and w % 7 == 3:
                lines.append(json.dumps({"t_mono": t - 1, "event": "state", "from": "ARMED",
                                         "to": "STOPPED", "reason": "udp_timeout", "src": "-"}))
            lines.append(json.dumps({
                "t_mono": t, "event": "link_histogram", "valid": int(cum[w].sum()) + 1,
                "invalid": w, "silences": int(silences[w]), "warn_us": warn_us,
                "edges_us": EDGES_US, "counts": [int(c) for c in cum[w]]}))
        t0 += nwin * every_s + 5.0
        lines.append(json.dumps({"t_mono": t0 - 4.0, "event": "exit", "signal": "TERM"}))
    return "\n".join(lines) + "\n"




# --------------------------------------------------------------------------- version 3 unit


@dataclass
class UnitRun:
    """What a version 3 unit does with a run of arrival times (us)."""

    slow_us: int
    timeout_us: int
    slowdowns_us: list[int] = field(default_factory=list)  # times of ARMED -> SLOWING
    timeouts_us: list[int] = field(default_factory=list)  # times of -> STOPPED, udp timeout
    states: list[tuple[int, str, str, str]] = field(default_factory=list)  # t, from, to, why
    moving_us: int = 0  # time ARMED or SLOWING up to the last packet


def simulate_unit(t_us: np.ndarray, slow_us: int, timeout_us: int,
                  release: bool = True) -> UnitRun:
    """PROTOCOL.md 3 on arrival times: the unit boots STOPPED; with ``release`` the operator
    releases it as soon as the rules allow (5 valid packets since the latest of the boot, the
    stop, the last silence of T). ARMED -> SLOWING when a silence reaches S (S < T only);
    SLOWING -> ARMED once 3 valid packets arrived since it began, however far apart; ARMED or
    SLOWING -> STOPPED when a silence reaches T. A deadline equal to the gap counts (the
    transition happens at the deadline itself, before the packet that ends the gap)."""
    run = UnitRun(slow_us, timeout_us)
    g = np.diff(t_us)
    state = "STOPPED"
    release_at: int | None = 4 if release else None  # packet whose arrival allows a RELEASE
    rearm_at: int | None = None  # packet whose arrival ends SLOWING

    def advance(upto: int) -> None:
        nonlocal state, release_at, rearm_at
        if state == "STOPPED" and release_at is not None and release_at <= upto:
            run.states.append((int(t_us[release_at]), "STOPPED", "ARMED", "none"))
            state, release_at = "ARMED", None
        if state == "SLOWING" and rearm_at is not None and rearm_at <= upto:
            run.states.append((int(t_us[rearm_at]), "SLOWING", "ARMED", "none"))
            state, rearm_at = "ARMED", None

    for i in np.flatnonzero(g >= min(slow_us, timeout_us)).tolist():
        advance(i)  # the state after packet i, where the silence begins
        t0, gap = int(t_us[i]), int(g[i])
        if state == "STOPPED":
            if gap >= timeout_us and release_at is not None:
                release_at = i + 5  # the link was silent for T: 5 packets after it
            continue
        if slow_us < timeout_us and gap >= slow_us and state == "ARMED":
            run.slowdowns_us.append(t0 + slow_us)
            run.states.append((t0 + slow_us, "ARMED", "SLOWING", "none"))
            state, rearm_at = "SLOWING", i + 3
        if gap >= timeout_us:
            run.timeouts_us.append(t0 + timeout_us)
            run.states.append((t0 + timeout_us, state, "STOPPED", "udp_timeout"))
            state, rearm_at = "STOPPED", None
            release_at = i + 5 if release else None
    advance(t_us.size - 1)
    since: int | None = None
    for t, _, to, _ in run.states:
        if to != "STOPPED" and since is None:
            since = t
        elif to == "STOPPED" and since is not None:
            run.moving_us += t - since
            since = None
    if since is not None:
        run.moving_us += int(t_us[-1]) - since
    return run


def unit_log(runs: list[tuple[np.ndarray, UnitRun]], every_s: float = 60.0,
             warn_us: int = 100_000, start: bool = True, unit_keys: bool = True) -> str:
    """estopd --log-json text of a version 3 daemon for runs of arrival times (us) and what
    the unit did with them: a `start` event (unless ``start`` is False: a log cut after it),
    the state changes, a cumulative `link_histogram` every ``every_s`` and after the last
    packet, with ``slowdowns``, ``timeouts``, ``slow_us``, ``timeout_us`` (unless
    ``unit_keys`` is False: an older daemon), and an `exit` event. The log's clock runs on."""
    lines: list[tuple[float, int, str]] = []  # (t_mono, order within the same time, line)
    t_base = 100.0
    for t_us, unit in runs:
        def at(us: int, base: float = t_base, t0: int = int(t_us[0])) -> float:
            return base + (us - t0) / 1e6

        if start:
            lines.append((at(int(t_us[0])) - 1.0, 0, json.dumps(
                {"t_mono": at(int(t_us[0])) - 1.0, "event": "start", "udp_port": 5700,
                 "timeout_ms": unit.timeout_us // 1000})))
        for t, frm, to, why in unit.states:
            lines.append((at(t), 1, json.dumps({"t_mono": at(t), "event": "state",
                                                "from": frm, "to": to, "reason": why,
                                                "src": "-"})))
        g = np.diff(t_us)
        bins = daemon_bins(g)
        step = int(every_s * 1e6)
        ends = [*range(int(t_us[0]) + step, int(t_us[-1]), step), int(t_us[-1])]
        slow = np.asarray(unit.slowdowns_us, dtype=np.int64)
        stops = np.asarray(unit.timeouts_us, dtype=np.int64)
        counts = np.zeros(32, dtype=np.int64)
        silences = done = 0
        for end in ends:
            upto = int(np.searchsorted(t_us, end, side="right"))  # packets up to `end`
            gaps = slice(done, max(upto - 1, done))  # the gaps closed since the last event
            counts += np.bincount(bins[gaps], minlength=32)
            silences += int((g[gaps] >= warn_us).sum())
            done = gaps.stop
            ev = {"t_mono": at(end), "event": "link_histogram", "valid": upto, "invalid": 0,
                  "silences": silences, "warn_us": warn_us}
            if unit_keys:
                ev.update(slowdowns=int((slow <= end).sum()), timeouts=int((stops <= end).sum()),
                          slow_us=unit.slow_us, timeout_us=unit.timeout_us)
            ev.update(edges_us=EDGES_US, counts=[int(c) for c in counts])
            lines.append((at(end), 2, json.dumps(ev)))
        lines.append((at(int(t_us[-1])), 3, json.dumps(
            {"t_mono": at(int(t_us[-1])), "event": "exit", "signal": "TERM"})))
        t_base = at(int(t_us[-1])) + 30.0
    lines.sort(key=lambda x: (x[0], x[1]))
    return "\n".join(line for _, _, line in lines) + "\n"
