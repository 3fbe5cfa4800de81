"""The closing table of issue 12: ``estop link`` against the closed form on 10-hour traces.

Each trace is 10 hours of a 50 Hz remote through ``estop remote``'s own link model
(:class:`estop.model.wifi.LinkModel`, seeded) at 9 % loss with mean bursts of 1.5, 3 and 5
packets. The tool fits its Gilbert model to the arrival times (or, with ``--binned``, to the
daemon's half-octave histogram of the same gaps) and its false stops per hour for 100 ms .. 1 s
are printed beside the closed form at the true parameters
(packets per hour x (1 - p) x q x (1 - r)^(n-1), r = 1/burst, q = p r / (1 - p)) and the
stops the trace itself holds. Prints a Markdown table; takes about 10 s. ``--save DIR`` also
writes each trace's arrival times (DIR/burst-1.5.txt, burst-3.txt, burst-5.txt) for
``estop link`` itself (docs/LINK.md's example).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from estop.link.fit import false_stops_per_hour, lost_in_row
from estop.link.format import fmt_rate
from estop.link.gaps import (
    DAEMON_EDGES_US,
    Gaps,
    Histogram,
    daemon_bins,
    gaps_from_histogram,
    gaps_from_times,
)
from estop.link.report import report
from estop.model.wifi import LinkConfig, LinkModel

RATE = 50.0
LOSS = 0.09
BURSTS = (1.5, 3.0, 5.0)
TIMEOUTS = tuple(range(100, 1001, 100))


def trace(burst: float, hours: float, seed: int) -> np.ndarray:
    """Arrival times (s) of the packets a LinkModel lets through, no delay or jitter."""
    model = LinkModel(LinkConfig(loss=LOSS, burst=burst), seed=seed)
    n = int(hours * 3600 * RATE)
    lost = np.fromiter((model.lose_next() for _ in range(n)), dtype=bool, count=n)
    return np.flatnonzero(~lost) / RATE


def binned(times: np.ndarray) -> Gaps:
    """The daemon's histogram of the gaps (estop.link.gaps.daemon_bins: the core's bins)."""
    g = np.diff(np.rint(times * 1e6).astype(np.int64))
    counts = np.bincount(daemon_bins(g), minlength=32)
    h = Histogram(DAEMON_EDGES_US, tuple(int(c) for c in counts), times.size, 0, 0, 100_000, 1,
                  False)
    return gaps_from_histogram(h, RATE)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--binned", action="store_true",
                    help="fit the daemon's binned histogram instead of the arrival times")
    ap.add_argument("--save", metavar="DIR", type=Path,
                    help="write each trace's arrival times to DIR/burst-<b>.txt")
    args = ap.parse_args()
    t0 = time.perf_counter()
    reports = []
    for i, burst in enumerate(BURSTS):
        t = trace(burst, args.hours, args.seed + i)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savetxt(args.save / f"burst-{burst:g}.txt", t, fmt="%.6f")
        gaps = binned(t) if args.binned else gaps_from_times(t, RATE)
        reports.append(report(gaps, RATE, timeouts_ms=TIMEOUTS))
    form = "binned daemon histogram" if args.binned else "arrival times"
    print(f"{args.hours:g}-hour traces at {RATE:g} Hz from estop.model.wifi (seed {args.seed}+), "
          f"{LOSS * 100:g} % loss; tool fitted to the {form}. False stops per hour: tool "
          "(its Gilbert fit), closed form (true parameters), seen (gaps in the trace).")
    print()
    fits = "; ".join(f"burst {b:g}: loss {r.fit.loss * 100:.2f} %, mean burst "
                     f"{r.fit.mean_burst or 0:.3f} (runs of >= {r.fit.tail_from} fitted)"
                     for b, r in zip(BURSTS, reports, strict=True))
    print(f"Fitted: {fits}.")
    print()
    head = "| timeout | n |" + "".join(f" b={b:g} tool | b={b:g} closed | b={b:g} seen |"
                                        for b in BURSTS)
    print(head)
    print("|" + "---:|" * (2 + 3 * len(BURSTS)))
    for j, d in enumerate(TIMEOUTS):
        n = lost_in_row(d, RATE)
        cells = [f"{d} ms", str(n)]
        for burst, rep in zip(BURSTS, reports, strict=True):
            row = rep.rows[j]
            closed = false_stops_per_hour(LOSS, burst, n, RATE)
            if row.gaps_sure == row.gaps_possible:
                seen = fmt_rate(row.gaps_sure / row.hours)
            else:
                seen = (f"{fmt_rate(row.gaps_sure / row.hours)}-"
                        f"{fmt_rate(row.gaps_possible / row.hours)}")
            cells += [fmt_rate(row.model), fmt_rate(closed), seen]
        print("| " + " | ".join(cells) + " |")
    print()
    print(f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
