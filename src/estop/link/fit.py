"""The Gilbert fit behind ``estop link``: the stop rule (packets lost in a row that trip a
deadline), the closed form of false stops per hour, and the maximum likelihood fit of the burst
law to gap cells (:mod:`estop.link.gaps`), with the choice of the runs it is fitted to."""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from estop.errors import UsageError
from estop.link.gaps import I64, Gaps, check_rate

__all__ = ["Fit", "choose_tail", "false_stops_per_hour", "fit", "lost_in_row"]

Z95 = 1.959963984540054


def lost_in_row(timeout_ms: int | float | Fraction, rate_hz: float) -> int:
    """Packets lost in a row that trip a timeout of ``timeout_ms`` at ``rate_hz``: the number
    of packets due strictly before the deadline, ceil(D/P) - 1 for send period P (the stop
    comes at the deadline, so a packet due exactly then is too late). Exact rational
    arithmetic: 200 ms at 50 Hz is 9, not 10 through a rounding error. The same rule gives the
    slow time S its n."""
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
    check_rate(rate_hz)
    n_gaps = gaps.total
    bursts = int(gaps.counts[gaps.k_lo >= 1].sum())
    if tail_from is None:
        k0, note = choose_tail(gaps)
    else:
        if tail_from < 1:
            raise UsageError("--tail-from must be at least 1")
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


