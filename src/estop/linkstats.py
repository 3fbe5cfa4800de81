"""The analysis behind ``estop link`` (:mod:`estop.link`): a recording of the control link
turned into false stops per hour per timeout.

Inputs (one file; the kind is recognised from its first bytes, or named with ``--format``):

- ``log``: estopd's ``--log-json`` log. Its ``link_histogram`` events hold the gaps between
  consecutive valid control packets, binned in half-octaves (cumulative since the daemon
  started); each ``start`` event begins a new run and the runs are added up.
- ``times``: arrival times, one float (seconds) per line; blank lines and ``#`` comments skipped.
- ``pcap``: a capture (pcap or pcapng) of the control port: UDP datagrams to ``--port`` of a
  control packet's length (20, 16 or 60 bytes) are the packets.

The model is a two-state Gilbert channel at the known send rate: every packet the remote sends
is either received (good state) or lost (bad state); ``p_gb`` = P(good -> bad), ``p_bg`` =
P(bad -> good). A gap between two received packets of (k+1) send periods means k lost in a row.
Loss = p_gb / (p_gb + p_bg), mean burst = 1 / p_bg.

A stop comes at the deadline: with send period T and timeout D, after a packet at t0 the next
ones are due at t0 + T, t0 + 2T, ...; only those due strictly before t0 + D can keep the unit
alive, and there are n = ceil(D / T) - 1 of them. The unit stops when those n are all lost
(50 Hz, 200 ms: packets due at 20 .. 180 ms, n = 9; the 10th is due at the deadline itself,
when the stop has already come). False stops per hour = bursts of n or more losses per hour =
packets per hour x (1 - loss) x p_gb x (1 - p_bg)^(n - 1).
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np
import numpy.typing as npt

from estop.cliutil import UsageError

__all__ = [
    "Fit",
    "Gaps",
    "Histogram",
    "LinkInputError",
    "Report",
    "Row",
    "TIMEOUTS_MS",
    "detect_format",
    "false_stops_per_hour",
    "fit",
    "format_report",
    "gaps_from_histogram",
    "gaps_from_times",
    "load",
    "lost_in_row",
    "poisson_lower95",
    "poisson_upper95",
    "read_histogram_log",
    "read_pcap_times",
    "read_times",
    "report",
    "report_json",
    "write_plot",
]

# every 10 ms to 200 ms, then coarser up to 2 s (100 ms .. 1 s all present)
TIMEOUTS_MS: tuple[int, ...] = (*range(50, 201, 10), 250, 300, 350, 400, 450, 500, 600, 700,
                                800, 900, 1000, 1200, 1500, 2000)
ENOUGH = 10  # gaps at least this many before the recording "can say" a rate (Poisson +-30 %)
Z95 = 1.959963984540054
U32_MAX = 0xFFFFFFFF
CONTROL_LENGTHS = frozenset({20, 16, 60})
I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]


class LinkInputError(UsageError):
    """Bad input file or option: one line, exit 2."""


# --------------------------------------------------------------------------- timeouts


def lost_in_row(timeout_ms: int | float, rate_hz: float) -> int:
    """Packets lost in a row that trip a timeout of ``timeout_ms`` at ``rate_hz``: the number
    of packets due strictly before the deadline, ceil(D/T) - 1 (the stop comes at the deadline,
    so a packet due exactly then is too late). Exact rational arithmetic: 200 ms at 50 Hz is 9,
    not 10 through a rounding error."""
    periods = Fraction(timeout_ms) / 1000 * Fraction(rate_hz)
    return max(0, math.ceil(periods) - 1)


def false_stops_per_hour(loss: float, mean_burst: float, n: int, rate_hz: float) -> float:
    """The closed form for a Gilbert channel: bursts of at least n losses per hour,
    packets per hour x (1 - loss) x q x (1 - r)^(n-1), r = 1/burst, q = loss r / (1 - loss).
    n = 0 (timeout shorter than a send period): every received packet's gap trips it."""
    per_hour = rate_hz * 3600.0
    if n <= 0:
        return per_hour * (1.0 - loss)
    if loss <= 0.0:
        return 0.0
    if loss >= 1.0:
        return 0.0  # one endless burst: a single stop, not a rate
    r = 1.0 / mean_burst
    q = loss * r / (1.0 - loss)
    return per_hour * (1.0 - loss) * q * (1.0 - r) ** (n - 1)


# --------------------------------------------------------------------------- gap cells


@dataclass(frozen=True)
class Gaps:
    """Gaps between consecutive received packets, as counts over cells of k (packets lost in
    the gap): a cell holds every gap with ``k_lo <= k <= k_hi`` (``k_hi`` -1: no upper end).
    Arrival times give one exact cell per k; the daemon's histogram gives one cell per bin."""

    k_lo: I64
    k_hi: I64
    counts: I64
    pauses: int  # gaps of --max-gap or longer, taken as the sender pausing (finger lifted)
    source: str
    hours_measured: float | None = None  # time covered by the gaps, when measured (not binned)
    notes: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def exact(self) -> bool:
        return bool(np.all(self.k_lo == self.k_hi))

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def at_least(self, n: int) -> tuple[int, int]:
        """Gaps with at least n lost: (surely, possibly), different only for coarse cells."""
        hi_open = (self.k_hi < 0) | (self.k_hi >= n)
        sure = int(self.counts[self.k_lo >= n].sum())
        return sure, int(self.counts[hi_open].sum())


def _check_rate(rate_hz: float) -> None:
    if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 100_000.0):
        raise LinkInputError(f"--rate-hz must be a send rate in Hz (0 .. 100000], got {rate_hz}")


def gaps_from_times(times: Sequence[float] | F64, rate_hz: float, max_gap: float = 5.0,
                    source: str = "arrival times") -> Gaps:
    """Cells from arrival times (seconds, not decreasing): a gap g holds
    k = round(g / T) - 1 lost packets (at least 0: early or bunched arrivals count as none).
    Gaps of ``max_gap`` seconds or more (0: no limit) are sender pauses, left out."""
    _check_rate(rate_hz)
    t = np.asarray(times, dtype=np.float64)
    if t.size < 2:
        raise LinkInputError(f"{source}: need at least 2 packets, got {t.size}")
    g = np.diff(t)
    if np.any(g < 0):
        raise LinkInputError(f"{source}: arrival times go backwards")
    pause = g >= max_gap if max_gap > 0 else np.zeros(g.shape, dtype=bool)
    g = g[~pause]
    if g.size == 0:
        raise LinkInputError(f"{source}: every gap is a pause (>= {max_gap:g} s)")
    periods = g * rate_hz
    k = np.maximum(np.rint(periods).astype(np.int64) - 1, 0)
    ks, counts = np.unique(k, return_counts=True)
    # share of gaps more than a quarter period off the send grid: arrival jitter
    off_grid = float(np.mean(np.abs(periods - np.rint(periods)) > 0.25))
    notes: tuple[str, ...] = ()
    if off_grid > 0.05:
        notes = (f"{off_grid * 100:.0f} % of gaps are more than T/4 off the send grid: arrival "
                 "jitter, so short gaps are misread as losses or as none",)
    return Gaps(ks.astype(np.int64), ks.astype(np.int64), counts.astype(np.int64),
                int(pause.sum()), source, hours_measured=float(g.sum()) / 3600.0,
                notes=notes, extra={"packets": int(t.size), "off_grid": off_grid,
                                    "longest_gap_s": float(np.diff(t).max())})


@dataclass(frozen=True)
class Histogram:
    """The sum over runs of the last ``link_histogram`` event of each run."""

    edges_us: tuple[int, ...]
    counts: tuple[int, ...]
    valid: int
    invalid: int
    silences: int
    warn_us: int
    runs: int
    saturated: bool


def gaps_from_histogram(h: Histogram, rate_hz: float, max_gap: float = 5.0,
                        source: str = "estopd log") -> Gaps:
    """Cells from the daemon's bins: bin [a, b) holds the k whose nominal gap (k+1) T lies in
    it. A bin that holds no multiple of T (its gaps are jittered ones) is credited to the
    nearest multiple. Bins starting at ``max_gap`` or above are sender pauses."""
    _check_rate(rate_hz)
    edges = [Fraction(e) for e in h.edges_us]
    t_us = Fraction(1_000_000) / Fraction(rate_hz)
    if len(edges) > 1 and t_us < edges[1]:
        raise LinkInputError(f"--rate-hz {rate_hz:g} is too fast for the daemon's histogram "
                             f"(its first bin, below {h.edges_us[1]} us, would hold gaps of "
                             "several send periods)")
    max_us = Fraction(max_gap) * 1_000_000
    lo: list[int] = []
    hi: list[int] = []
    cnt: list[int] = []
    pauses = 0
    orphans: list[tuple[int, int]] = []  # (nearest k, count)
    for j, c in enumerate(h.counts):
        a = edges[j]
        b = edges[j + 1] if j + 1 < len(edges) else None
        if max_gap > 0 and a >= max_us:
            pauses += c
            continue
        k_lo = max(0, math.ceil(a / t_us) - 1)
        if b is None:
            k_hi = -1  # open last bin
        else:
            k_hi = math.ceil(b / t_us) - 2
            if k_hi < k_lo:  # no multiple of T in [a, b)
                if c:
                    orphans.append((max(0, round((a + b) / 2 / t_us) - 1), c))
                continue
        lo.append(k_lo)
        hi.append(k_hi)
        cnt.append(c)
    for k, c in orphans:
        for i in range(len(lo)):
            if lo[i] <= k and (hi[i] == -1 or k <= hi[i]):
                cnt[i] += c
                break
        else:  # nearest multiple beyond the last cell: cannot happen with an open last bin
            lo.append(k)
            hi.append(k)
            cnt.append(c)
    if not cnt or sum(cnt) == 0:
        raise LinkInputError(f"{source}: the histogram holds no gap between packets")
    if lo[0] != 0 or hi[0] != 0:
        raise LinkInputError(f"{source}: the histogram's bins cannot tell a gap of one send "
                             f"period at {rate_hz:g} Hz from longer ones")
    notes: list[str] = []
    if orphans:
        notes.append(f"{sum(c for _, c in orphans)} gaps fell in bins holding no multiple of "
                     "the send period (jitter) and were credited to the nearest multiple")
    if h.saturated:
        notes.append("some histogram counts are saturated (u32): the rates are too low")
    order = np.argsort(np.asarray(lo))
    return Gaps(np.asarray(lo, dtype=np.int64)[order], np.asarray(hi, dtype=np.int64)[order],
                np.asarray(cnt, dtype=np.int64)[order], pauses, source, None, tuple(notes),
                extra={"valid": h.valid, "invalid": h.invalid, "silences": h.silences,
                       "warn_us": h.warn_us, "runs": h.runs})


# --------------------------------------------------------------------------- the fit


@dataclass(frozen=True)
class Fit:
    rate_hz: float
    p_gb: float  # P(good -> bad): a received packet is followed by a lost one
    p_bg: float  # P(bad -> good): a lost packet is followed by a received one
    p_bg_se: float  # standard error of p_bg (observed Fisher information)
    gaps: int  # gaps between received packets (good-state steps)
    bursts: int  # gaps with at least one packet lost, as recorded
    lost: float  # packets lost (expected, for binned input)
    hours: float  # time covered by the gaps (sender pauses left out)
    tail_from: int = 1  # the fit used the gaps of at least this many lost (k0)
    tail_bursts: int = 0  # gaps of at least tail_from lost: the data the fit stands on
    tail_note: str = ""  # why tail_from is what it is

    @property
    def loss(self) -> float:
        s = self.p_gb + self.p_bg
        return self.p_gb / s if s > 0 else 0.0

    @property
    def mean_burst(self) -> float | None:
        return 1.0 / self.p_bg if self.tail_bursts and self.p_bg > 0 else None

    def false_stops(self, n: int) -> float:
        """Model false stops per hour for n lost in a row (the closed form at the fit)."""
        if n <= 0:
            return self.gaps / self.hours if self.hours > 0 else math.inf
        mb = self.mean_burst
        if mb is None:
            return 0.0
        return false_stops_per_hour(self.loss, mb, n, self.rate_hz)

    def interval95(self, n: int) -> tuple[float, float]:
        """Approximate 95 % range of the model rate: delta method on its log. The rate is
        anchored at the count of gaps of at least k0 lost (Poisson) and carried to n by
        (1 - p_bg)^(n - k0), whose error grows with n - k0."""
        mid = self.false_stops(n)
        if n <= 0 or mid <= 0 or self.tail_bursts == 0:
            return mid, mid
        r = self.p_bg
        var = 1.0 / self.tail_bursts
        if r < 1.0:
            var += ((n - self.tail_from) * self.p_bg_se / (1.0 - r)) ** 2
        spread = math.exp(Z95 * math.sqrt(var))
        return mid / spread, mid * spread


def _cell_loglik(r: float, k_lo: I64, k_hi: I64, counts: I64) -> float:
    """log-likelihood of p_bg = r, 0 < r < 1, for cells of k >= 1 (P(k) = (1-r)^(k-1) r):
    a cell [a, b] has probability (1-r)^(a-1) (1 - (1-r)^(b-a+1)); an open one (1-r)^(a-1)."""
    l1 = math.log1p(-r)
    width = (k_hi - k_lo + 1).astype(np.float64)
    head = (k_lo - 1).astype(np.float64) * l1
    tail = np.where(k_hi < 0, 0.0, np.log(-np.expm1(np.where(k_hi < 0, 1.0, width) * l1)))
    return float((counts * (head + tail)).sum())


def _argmax_r(k_lo: I64, k_hi: I64, counts: I64) -> float:
    """Maximise the binned likelihood over r in (0, 1): grid on logit(r), then golden section."""

    def f(u: float) -> float:
        r = 1.0 / (1.0 + math.exp(-u))
        if not 0.0 < r < 1.0:
            return -math.inf
        return _cell_loglik(r, k_lo, k_hi, counts)

    grid = np.linspace(-20.0, 20.0, 161)
    vals = [f(float(u)) for u in grid]
    i = int(np.argmax(vals))
    a = float(grid[max(i - 1, 0)])
    b = float(grid[min(i + 1, len(grid) - 1)])
    phi = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - phi * (b - a), a + phi * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(200):
        if b - a < 1e-12:
            break
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - phi * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + phi * (b - a)
            fd = f(d)
    u = (a + b) / 2.0
    return 1.0 / (1.0 + math.exp(-u))


def _expected_k(r: float, lo: int, hi: int) -> float:
    """E[k | lo <= k <= hi] for P(k) proportional to (1-r)^k (hi -1: no upper end)."""
    if lo == hi:
        return float(lo)
    s = 1.0 - r
    if hi < 0:
        return lo + s / r if r > 0 else float(lo)
    k = np.arange(lo, hi + 1, dtype=np.float64)
    w = s ** (k - lo)
    return float((k * w).sum() / w.sum())


def _tail_fit(gaps: Gaps, k0: int) -> tuple[float, float, int]:
    """(p_bg, its standard error, gaps in the tail) from the gaps of at least k0 lost: given
    k >= k0, k - k0 + 1 is geometric with parameter p_bg (the chain forgets how it got there)."""
    mask = gaps.k_lo >= k0
    counts = gaps.counts[mask]
    tail = int(counts.sum())
    if tail == 0:
        return 1.0, 0.0, 0
    lo = gaps.k_lo[mask] - (k0 - 1)
    hi = np.where(gaps.k_hi[mask] < 0, -1, gaps.k_hi[mask] - (k0 - 1))
    if gaps.exact:
        r = tail / float((lo * counts).sum())
        return r, r * math.sqrt((1.0 - r) / tail), tail
    r = _argmax_r(lo, hi, counts)
    return r, _se_numeric(r, lo, hi, counts), tail


MIN_TAIL = 50  # gaps a tail needs before its burst decay is compared with another's
Z_TAIL = 2.5


def choose_tail(gaps: Gaps) -> tuple[int, str]:
    """k0 for the fit: the shortest runs of losses that follow one geometric law. Gaps can be
    misread by arrival jitter (a late packet looks like a loss, a bunch of early ones like
    none), which invents short bursts and makes a fit to every run far too optimistic about
    the long ones. The smallest k0 whose decay p_bg agrees with that of the next two longer
    tails (within Z_TAIL standard errors of the difference) is taken; if the decay never
    settles, the longest tail with MIN_TAIL gaps (the more cautious estimate)."""
    cands = sorted({int(k) for k in gaps.k_lo.tolist() if k >= 1})
    fits: list[tuple[int, float, float]] = []
    for k0 in cands:
        r, se, tail = _tail_fit(gaps, k0)
        if tail < MIN_TAIL:
            break
        fits.append((k0, r, se))
    for i, (k0, r, se) in enumerate(fits):
        later = fits[i + 1:i + 3]
        if len(later) < 2:
            break
        if all(abs(r - r2) <= Z_TAIL * math.sqrt(max(se2 * se2 - se * se, 1e-300))
               for _, r2, se2 in later):
            if k0 == 1:
                return 1, "every run of losses"
            return k0, (f"runs of at least {k0} losses: shorter ones do not follow the same "
                        "geometric law (arrival jitter misreads short gaps)")
    if len(fits) < 3:
        return 1, "every run of losses (too few bursts to check the geometric law)"
    k0 = fits[-1][0]
    return k0, (f"runs of at least {k0} losses: the burst lengths do not follow one "
                "geometric law, the longest runs with enough data are used (cautious)")


def fit(gaps: Gaps, rate_hz: float, tail_from: int | None = None) -> Fit:
    """Maximum likelihood Gilbert fit to the runs of at least k0 = ``tail_from`` losses
    (None: :func:`choose_tail`). The tail decay gives p_bg (exact cells: tail gaps over
    packets lost beyond k0 - 1; binned: the likelihood of the bin counts); the share of gaps
    in the tail, P(k >= k0) = p_gb (1 - p_bg)^(k0 - 1), gives p_gb. With k0 = 1 this is the
    plain fit: p_gb = bursts / gaps, p_bg = bursts / lost."""
    _check_rate(rate_hz)
    n_gaps = gaps.total
    bursts = int(gaps.counts[gaps.k_lo >= 1].sum())
    if tail_from is None:
        k0, note = choose_tail(gaps)
    else:
        if tail_from < 1:
            raise LinkInputError("--tail-from must be at least 1")
        starts = gaps.k_lo[gaps.k_lo >= tail_from]
        k0 = int(starts.min()) if starts.size else tail_from  # binned: the next bin start
        note = f"runs of at least {k0} losses (--tail-from)"
    p_bg, se, tail = _tail_fit(gaps, k0)
    share = tail / n_gaps if n_gaps else 0.0
    if tail == 0:
        p_gb = 0.0
    elif p_bg >= 1.0:
        p_gb = min(1.0, share)  # every tail run exactly k0 long: no decay to divide by
    else:
        p_gb = min(1.0, share / (1.0 - p_bg) ** (k0 - 1))
    lost = sum(int(c) * _expected_k(p_bg, int(a), int(b))
               for a, b, c in zip(gaps.k_lo, gaps.k_hi, gaps.counts, strict=True)
               if a >= 1)
    if gaps.hours_measured is not None:
        hours = gaps.hours_measured
    else:
        hours = (n_gaps + lost) / rate_hz / 3600.0
    return Fit(rate_hz, p_gb, p_bg, se, n_gaps, bursts, lost, hours, k0, tail, note)


def _se_numeric(r: float, k_lo: I64, k_hi: I64, counts: I64) -> float:
    if not 0.0 < r < 1.0:
        return 0.0
    h = 1e-4 * min(r, 1.0 - r)
    f0 = _cell_loglik(r, k_lo, k_hi, counts)
    fp = _cell_loglik(r + h, k_lo, k_hi, counts)
    fm = _cell_loglik(r - h, k_lo, k_hi, counts)
    d2 = (fp - 2.0 * f0 + fm) / (h * h)
    return 1.0 / math.sqrt(-d2) if d2 < 0 else 0.0


# --------------------------------------------------------------------------- reading inputs


def read_times(path: str) -> F64:
    """Arrival times, one float in seconds per line (blank lines and # comments skipped)."""
    with _open_text(path) as f:
        try:
            text = f.read()
        except UnicodeDecodeError:
            raise LinkInputError(f"{path}: not a text file of times") from None
    if "#" not in text:  # fast path; any doubt goes to the line-by-line reader for its message
        tokens = text.split()
        if len(tokens) == sum(1 for line in text.splitlines() if line.strip()):
            try:
                t = np.asarray(tokens, dtype=np.float64)
            except ValueError:
                t = None
            if t is not None and np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0):
                return t
    return _read_times_slow(path, text)


def _read_times_slow(path: str, text: str) -> F64:
    values: list[float] = []
    prev = -math.inf
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            v = float(line)
        except ValueError:
            raise LinkInputError(f"{path}:{no}: not a time in seconds: {line[:40]!r}") from None
        if not math.isfinite(v):
            raise LinkInputError(f"{path}:{no}: not a finite time: {line[:40]!r}")
        if v < prev:
            raise LinkInputError(f"{path}:{no}: time goes backwards ({v:g} after {prev:g})")
        prev = v
        values.append(v)
    return np.asarray(values, dtype=np.float64)


def _open_text(path: str) -> Any:
    try:
        return open(path, encoding="utf-8", errors="strict")
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None


def _int_field(ev: dict[str, Any], key: str, where: str) -> int:
    v = ev.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise LinkInputError(f"{where}: link_histogram field {key!r} is not a count: {v!r}")
    return v


def read_histogram_log(path: str) -> Histogram:
    """Sum the last ``link_histogram`` event of every run in estopd's --log-json log. A run
    starts at a ``start`` event (or where the counts go down); other events are ignored."""
    runs: list[tuple[dict[str, Any], str]] = []
    current: tuple[dict[str, Any], str] | None = None
    edges: list[int] | None = None
    try:
        with _open_text(path) as f:
            for no, raw in enumerate(f, 1):
                line = raw.strip()
                if not line.startswith("{"):
                    continue
                try:
                    ev = json.loads(line)
                except ValueError:
                    continue
                if not isinstance(ev, dict):
                    continue
                kind = ev.get("event")
                if kind == "start":
                    if current is not None:
                        runs.append(current)
                    current = None
                    continue
                if kind != "link_histogram":
                    continue
                where = f"{path}:{no}"
                e = ev.get("edges_us")
                c = ev.get("counts")
                if not (isinstance(e, list) and isinstance(c, list) and len(e) >= 2
                        and len(c) == len(e)
                        and all(isinstance(x, int) and not isinstance(x, bool) for x in e + c)
                        and e[0] == 0 and all(b > a for a, b in zip(e, e[1:], strict=False))
                        and all(x >= 0 for x in c)):
                    raise LinkInputError(f"{where}: malformed link_histogram event (edges_us "
                                         "and counts must be equal-length integer lists, "
                                         "edges rising from 0)")
                if edges is None:
                    edges = e
                elif e != edges:
                    raise LinkInputError(f"{where}: link_histogram bins differ from earlier "
                                         "events (logs of different daemons mixed?)")
                for key in ("valid", "invalid", "silences", "warn_us"):
                    _int_field(ev, key, where)
                if current is not None and any(
                        b < a for a, b in zip(current[0]["counts"], c, strict=True)):
                    runs.append(current)  # counts went down: a restart without `start`
                current = (ev, where)
    except UnicodeDecodeError:
        raise LinkInputError(f"{path}: not a text file (use --format pcap for captures)") \
            from None
    if current is not None:
        runs.append(current)
    if not runs or edges is None:
        raise LinkInputError(f"{path}: no link_histogram event (is it estopd's --log-json log?)")
    total = [0] * len(edges)
    valid = invalid = silences = 0
    saturated = False
    for ev, _ in runs:
        for i, x in enumerate(ev["counts"]):
            total[i] += x
            saturated |= x >= U32_MAX
        valid += ev["valid"]
        invalid += ev["invalid"]
        silences += ev["silences"]
    return Histogram(tuple(edges), tuple(total), valid, invalid, silences,
                     runs[-1][0]["warn_us"], len(runs), saturated)


def read_pcap_times(path: str, udp_port: int = 5700) -> tuple[F64, int]:
    """Arrival times of the UDP datagrams to ``udp_port`` that have a control packet's length
    (20, 16 or 60 bytes), from a pcap or pcapng file; also the number of other datagrams to
    that port (stop datagrams, bad lengths). IPv4 and IPv6 over Ethernet, Linux cooked (v1,
    v2), loopback and raw IP."""
    import dpkt

    try:
        f = open(path, "rb")
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None
    times: list[float] = []
    other = 0
    with f:
        try:
            reader = dpkt.pcap.UniversalReader(f)
        except (ValueError, dpkt.Error):
            raise LinkInputError(f"{path}: not a pcap or pcapng capture") from None
        decode = _link_decoder(int(reader.datalink()), path)
        try:
            for ts, buf in reader:
                try:
                    ip = decode(buf)
                except (dpkt.Error, IndexError, ValueError, struct.error):
                    continue
                if not isinstance(ip, (dpkt.ip.IP, dpkt.ip6.IP6)):
                    continue
                udp = ip.data
                if not isinstance(udp, dpkt.udp.UDP) or udp.dport != udp_port:
                    continue
                if int(udp.ulen) - 8 in CONTROL_LENGTHS:
                    times.append(float(ts))
                else:
                    other += 1
        except (dpkt.Error, ValueError, struct.error) as exc:
            raise LinkInputError(f"{path}: capture cut short or damaged ({exc})") from None
    t = np.sort(np.asarray(times, dtype=np.float64))
    return t, other


def _link_decoder(linktype: int, path: str) -> Any:
    import dpkt

    def raw_ip(buf: bytes) -> Any:
        version = buf[0] >> 4 if buf else 0
        if version == 4:
            return dpkt.ip.IP(buf)
        if version == 6:
            return dpkt.ip6.IP6(buf)
        return None

    def data_of(cls: Any) -> Any:
        return lambda buf: cls(buf).data

    decoders: dict[int, Any] = {
        1: data_of(dpkt.ethernet.Ethernet),  # DLT_EN10MB
        0: data_of(dpkt.loopback.Loopback),  # DLT_NULL
        108: data_of(dpkt.loopback.Loopback),  # DLT_LOOP
        113: data_of(dpkt.sll.SLL),  # DLT_LINUX_SLL
        276: data_of(dpkt.sll2.SLL2),  # DLT_LINUX_SLL2
        101: raw_ip, 12: raw_ip, 14: raw_ip, 228: raw_ip, 229: raw_ip,  # raw IP forms
    }
    if linktype not in decoders:
        raise LinkInputError(f"{path}: link type {linktype} not supported (Ethernet, Linux "
                             "cooked, loopback or raw IP captures are)")
    return decoders[linktype]


def detect_format(path: str) -> str:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None
    if head[:4] in (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1",
                    b"\xa1\xb2\x3c\x4d", b"\x0a\x0d\x0d\x0a"):
        return "pcap"
    for line in head.splitlines():
        s = line.strip()
        if not s or s.startswith(b"#"):
            continue
        return "log" if s.startswith(b"{") else "times"
    raise LinkInputError(f"{path}: empty file")


def load(path: str, fmt: str, rate_hz: float, max_gap: float, udp_port: int) -> Gaps:
    """Read one input file into gap cells."""
    kind = detect_format(path) if fmt == "auto" else fmt
    name = os.path.basename(path)
    if kind == "log":
        return gaps_from_histogram(read_histogram_log(path), rate_hz, max_gap,
                                   f"estopd log {name}")
    if kind == "pcap":
        t, other = read_pcap_times(path, udp_port)
        if t.size < 2:
            raise LinkInputError(f"{path}: fewer than 2 control packets to UDP port {udp_port}")
        g = gaps_from_times(t, rate_hz, max_gap, f"capture {name}")
        g.extra["other_datagrams"] = other
        return g
    return gaps_from_times(read_times(path), rate_hz, max_gap, f"arrival times {name}")


# --------------------------------------------------------------------------- the report


@dataclass(frozen=True)
class Row:
    timeout_ms: int
    lost_in_row: int
    model: float
    model_low: float
    model_high: float
    gaps_sure: int
    gaps_possible: int
    hours: float

    @property
    def enough(self) -> bool:
        return self.gaps_sure >= ENOUGH

    @property
    def empirical(self) -> float | None:
        """Gaps per hour that long, when the recording has enough of them and says exactly."""
        if self.hours <= 0 or not self.enough or self.gaps_sure != self.gaps_possible:
            return None
        return self.gaps_sure / self.hours

    @property
    def empirical_upper95(self) -> float:
        return poisson_upper95(self.gaps_possible) / self.hours if self.hours > 0 else math.inf

    @property
    def empirical_lower95(self) -> float:
        return poisson_lower95(self.gaps_sure) / self.hours if self.hours > 0 else 0.0

    @property
    def contradicted(self) -> bool:
        """The recording holds clearly more such gaps than the model's 95 % range allows."""
        return self.empirical_lower95 > self.model_high

    def meets(self, target: float) -> bool:
        """Model below target, and the recording does not say the rate is above it."""
        return self.model < target and self.empirical_lower95 <= target


@dataclass(frozen=True)
class Report:
    gaps: Gaps
    fit: Fit
    rows: tuple[Row, ...]
    target: float
    recommended_ms: int | None
    recommended_conservative_ms: int | None


def _poisson_cdf(k: int, mu: float) -> float:
    """P(X <= k) for X ~ Poisson(mu)."""
    if k < 0:
        return 0.0
    term = math.exp(-mu)
    total = term
    for i in range(1, k + 1):
        term *= mu / i
        total += term
    return min(total, 1.0)


def _solve_mu(f: Any, a: float, b: float) -> float:
    """Bisection for the mu between a and b where the monotonic f(mu) crosses 0.05
    (f(a) > 0.05 >= f(b))."""
    for _ in range(100):
        mid = (a + b) / 2.0
        if f(mid) > 0.05:
            a = mid
        else:
            b = mid
    return (a + b) / 2.0


Z95_ONE_SIDED = 1.6448536269514722


def poisson_upper95(k: int) -> float:
    """One-sided 95 % upper limit of a Poisson mean after seeing k events (exact up to 100
    events, then the Wilson-Hilferty approximation, good to a fraction of a percent)."""
    if k > 100:
        m = k + 1
        return m * (1.0 - 1.0 / (9.0 * m) + Z95_ONE_SIDED / (3.0 * math.sqrt(m))) ** 3
    return _solve_mu(lambda mu: _poisson_cdf(k, mu), float(k),
                     float(k) + 10.0 * math.sqrt(k) + 10.0)


def poisson_lower95(k: int) -> float:
    """One-sided 95 % lower limit of a Poisson mean after seeing k events (exact; 0 for 0)."""
    if k == 0:
        return 0.0
    if k > 100:
        return k * (1.0 - 1.0 / (9.0 * k) - Z95_ONE_SIDED / (3.0 * math.sqrt(k))) ** 3
    # P(X >= k) grows with mu: above 0.05 at mu = k, below it at mu = 0
    return _solve_mu(lambda mu: 1.0 - _poisson_cdf(k - 1, mu), float(k), 0.0)


def report(gaps: Gaps, rate_hz: float, target: float = 0.01,
           timeouts_ms: Iterable[int] = TIMEOUTS_MS, tail_from: int | None = None) -> Report:
    f = fit(gaps, rate_hz, tail_from)
    rows = []
    for d in timeouts_ms:
        n = lost_in_row(d, rate_hz)
        lo, hi = f.interval95(n)
        sure, possible = gaps.at_least(n) if n > 0 else (f.gaps, f.gaps)
        rows.append(Row(d, n, f.false_stops(n), lo, hi, sure, possible, f.hours))
    rec = next((r.timeout_ms for r in rows if r.meets(target)), None) if f.bursts else None
    cons = next((r.timeout_ms for r in rows if r.meets(target) and r.model_high < target),
                None) if f.bursts else None
    return Report(gaps, f, tuple(rows), target, rec, cons)


def _num(x: float | None) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return x


def report_json(rep: Report) -> dict[str, Any]:
    f, g = rep.fit, rep.gaps
    return {
        "source": g.source,
        "rate_hz": f.rate_hz,
        "loss": f.loss,
        "mean_burst": _num(f.mean_burst),
        "p_good_to_bad": f.p_gb,
        "p_bad_to_good": f.p_bg,
        "p_bad_to_good_se": f.p_bg_se,
        "fitted_runs_from": f.tail_from,
        "fitted_runs": f.tail_bursts,
        "fit_note": f.tail_note,
        "hours": f.hours,
        "hours_measured": g.hours_measured is not None,
        "gaps": f.gaps,
        "bursts": f.bursts,
        "lost": f.lost,
        "pauses": g.pauses,
        "binned": not g.exact,
        "input": dict(g.extra),
        "notes": list(g.notes),
        "stop_rule": "a stop comes at the deadline: n = ceil(timeout * rate) - 1 packets lost "
                     "in a row trip a timeout",
        "target_per_hour": rep.target,
        "recommended_timeout_ms": rep.recommended_ms,
        "recommended_timeout_ms_upper95": rep.recommended_conservative_ms,
        "rows": [{
            "timeout_ms": r.timeout_ms,
            "lost_in_row": r.lost_in_row,
            "false_stops_per_hour": r.model,
            "false_stops_per_hour_95": [r.model_low, r.model_high],
            "gaps_at_least": [r.gaps_sure, r.gaps_possible],
            "gaps_per_hour": _num(r.empirical),
            "gaps_per_hour_upper95": _num(r.empirical_upper95),
            "gaps_per_hour_lower95": r.empirical_lower95,
            "model_contradicted": r.contradicted,
            "enough_data": r.enough,
        } for r in rep.rows],
    }


def _fmt_rate(x: float) -> str:
    if x == 0:
        return "0"
    if x >= 100:
        return f"{x:.0f}"
    if x >= 0.01:
        return f"{x:.3g}"
    return f"{x:.2e}"


def format_report(rep: Report) -> list[str]:
    f, g = rep.fit, rep.gaps
    lines = [f"estop link: {g.source}, {f.rate_hz:g} Hz send rate"]
    rec_h = f"{f.hours:.3g} h" + ("" if g.hours_measured is not None else
                                  " (estimated from the binned gaps)")
    lines.append(f"recording: {rec_h} of sending, {f.gaps} gaps between received packets, "
                 f"{f.lost:.0f} packets lost in {f.bursts} bursts")
    if f.bursts:
        mb = f.mean_burst or 0.0
        lines.append(f"model: loss {f.loss * 100:.3g} %, mean burst {mb:.3g} packets "
                     f"(Gilbert: P(good->bad) {f.p_gb:.4g}, P(bad->good) {f.p_bg:.4g} "
                     f"+- {f.p_bg_se:.2g})")
        lines.append(f"fitted to {f.tail_note} ({f.tail_bursts} gaps)")
    else:
        lines.append("model: no packet lost, nothing to fit (record longer)")
    extra = g.extra
    if "valid" in extra:
        lines.append(f"daemon: {extra['valid']} valid, {extra['invalid']} invalid packets, "
                     f"{extra['silences']} silences over the warn time "
                     f"({extra['warn_us'] / 1000:g} ms), {extra['runs']} run(s)")
    if extra.get("other_datagrams"):
        lines.append(f"capture: {extra['other_datagrams']} other datagrams to the port ignored")
    if g.pauses:
        lines.append(f"{g.pauses} gap(s) of --max-gap or longer left out as sender pauses "
                     "(finger lifted); each would also have been a stop")
    lines.extend(f"note: {n}" for n in g.notes)
    lines.append("A stop comes at the deadline: timeout D at send period T trips when "
                 "n = ceil(D/T) - 1 packets in a row are lost.")
    lines.append(f"'seen': gaps of n or more lost in the recording ({f.hours:.3g} h); "
                 f"'<' marks fewer than {ENOUGH} (95 % upper bound).")
    lines.append("")
    lines.append("timeout    n   seen   seen/h      model/h   model 95 % range")
    for r in rep.rows:
        seen = (str(r.gaps_sure) if r.gaps_sure == r.gaps_possible
                else f"{r.gaps_sure}-{r.gaps_possible}")
        if r.empirical is not None:
            per_h = _fmt_rate(r.empirical)
        elif r.enough:
            per_h = f"{_fmt_rate(r.gaps_sure / r.hours)}-{_fmt_rate(r.gaps_possible / r.hours)}"
        else:
            per_h = "<" + _fmt_rate(r.empirical_upper95)
        mark = "!" if r.contradicted else (" " if r.lost_in_row >= f.tail_from else "^")
        lines.append(f"{r.timeout_ms:5d} ms {r.lost_in_row:4d} {seen:>6} {per_h:>8} "
                     f"{_fmt_rate(r.model):>12}{mark}  {_fmt_rate(r.model_low)} .. "
                     f"{_fmt_rate(r.model_high)}")
    if any(r.contradicted for r in rep.rows):
        lines.append("! the recording holds more such gaps than the model allows: trust the "
                     "recording there")
    if any(r.lost_in_row < f.tail_from for r in rep.rows):
        lines.append(f"^ fewer than {f.tail_from} lost: below the runs the model was fitted to")
    lines.append("")
    if not f.bursts:
        lines.append("recommendation: none (no loss recorded: the model has nothing to "
                     "extrapolate from)")
    elif rep.recommended_ms is None:
        lines.append(f"recommendation: no timeout up to {rep.rows[-1].timeout_ms} ms keeps the "
                     f"model (and the recording) below {rep.target:g} false stops per hour")
    else:
        r = next(x for x in rep.rows if x.timeout_ms == rep.recommended_ms)
        lines.append(f"recommendation: {rep.recommended_ms} ms (model {_fmt_rate(r.model)} "
                     f"false stops per hour, target {rep.target:g}); one per "
                     f"{_fmt_hours(r.model)} against {f.hours:.3g} h recorded")
        if rep.recommended_conservative_ms is None:
            lines.append("  with the model's 95 % upper bound: none up to "
                         f"{rep.rows[-1].timeout_ms} ms")
        elif rep.recommended_conservative_ms != rep.recommended_ms:
            lines.append(f"  with the model's 95 % upper bound: "
                         f"{rep.recommended_conservative_ms} ms")
    return lines


def _fmt_hours(rate: float) -> str:
    return "never" if rate <= 0 else f"{1.0 / rate:.3g} h"


def write_plot(rep: Report, path: str) -> None:
    try:
        import matplotlib
    except ModuleNotFoundError:
        raise LinkInputError("--plot needs matplotlib (pip install matplotlib)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray([r.timeout_ms for r in rep.rows], dtype=np.float64)
    model = np.asarray([r.model for r in rep.rows], dtype=np.float64)
    lo = np.asarray([r.model_low for r in rep.rows], dtype=np.float64)
    hi = np.asarray([r.model_high for r in rep.rows], dtype=np.float64)
    positive = model[model > 0]
    # far below the target the curve says nothing more: keep the axis to 6 decades under it
    bottom = max(float(positive.min()) if positive.size else rep.target / 10.0,
                 rep.target * 1e-6) / 2.0
    model, lo, hi = (np.where(a > 0, a, np.nan) for a in (model, lo, hi))
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.fill_between(x, lo, hi, alpha=0.25, label="model, 95 % range")
    ax.plot(x, model, marker=".", label="model (Gilbert fit)")
    seen = [(r.timeout_ms, r.gaps_sure / r.hours) for r in rep.rows
            if r.gaps_sure > 0 and r.hours > 0]
    if seen:
        ax.plot([s[0] for s in seen], [s[1] for s in seen], "s", mfc="none",
                label=f"seen in the recording ({rep.fit.hours:.3g} h)")
    ax.axhline(rep.target, color="red", linestyle="--", label=f"target {rep.target:g}/h")
    if rep.fit.hours > 0:
        ax.axhline(1.0 / rep.fit.hours, color="gray", linestyle=":",
                   label="one event in the recording")
    if rep.recommended_ms is not None:
        ax.axvline(rep.recommended_ms, color="green", linestyle="-.",
                   label=f"recommended {rep.recommended_ms} ms")
    ax.set_yscale("log")
    ax.set_ylim(bottom=bottom)
    ax.set_xlabel("timeout (ms)")
    ax.set_ylabel("false stops per hour")
    ax.set_title(f"estop link: {rep.gaps.source}, loss {rep.fit.loss * 100:.3g} %, "
                 f"mean burst {rep.fit.mean_burst or 0:.3g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:
        raise LinkInputError(f"cannot write {path}: {exc.strerror}") from None
    finally:
        plt.close(fig)
