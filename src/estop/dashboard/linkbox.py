"""The link box of ``estop dashboard``, from estopd's ``link_histogram`` events and the same
code as ``estop link``: the events are summed by :class:`estop.link.histogram.HistogramReader`,
fitted by :func:`estop.link.fit.fit` and read at this unit's slow time S and timeout T
(:func:`estop.link.unitcheck.check_unit` when the events carry the unit's own counts, else
:func:`estop.link.fit.lost_in_row` with the S and T of the daemon's ``start`` event)."""

from __future__ import annotations

import math
from typing import Any

from estop.link.fit import Fit, fit, lost_in_row
from estop.link.gaps import Gaps, LinkInputError, gaps_from_histogram
from estop.link.histogram import HistogramReader
from estop.link.unitcheck import check_unit

__all__ = ["LinkBox"]


class LinkBox:
    """Feed it every event of the log (:meth:`feed`); :attr:`view` is what the page draws
    (None before the first ``link_histogram``). ``rate_hz`` is the remote's send rate."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz
        self.view: dict[str, Any] | None = None
        self._reader = HistogramReader()

    def feed(self, ev: dict[str, Any], unit: dict[str, Any]) -> None:
        """One event; ``unit`` holds the daemon's ``start`` settings (slow_ms, timeout_ms).
        Raises :class:`LinkInputError` for a malformed ``link_histogram``."""
        if not self._reader.feed(ev, "log"):
            return
        try:
            hist = self._reader.histogram("log")
            gaps = gaps_from_histogram(hist, self.rate_hz)
            f = fit(gaps, self.rate_hz)
            self.view = _view(hist.edges_us, hist.counts, f, gaps, unit, self.rate_hz)
        except (LinkInputError, ValueError, ArithmeticError) as exc:
            # an event the fit cannot use: said on the page, the rest goes on
            self.view = {"edges_us": [], "counts": [], "error": str(exc) or type(exc).__name__}


def _finite(x: float | None) -> float | None:
    """JSON has no NaN or infinity (the page could not parse the update): None instead."""
    return None if x is None or not math.isfinite(x) else x


def _rate(x: float) -> float | None:
    return None if not math.isfinite(x) else float(f"{x:.3g}")


def _view(edges: tuple[int, ...], counts: tuple[int, ...], f: Fit, gaps: Gaps,
          unit: dict[str, Any], rate_hz: float) -> dict[str, Any]:
    """The link box: the histogram's bins, the fit, and what it means at this unit's S and T
    (the unit's own counts beside the model's, when its events carry them)."""
    view: dict[str, Any] = {"edges_us": list(edges), "counts": list(counts),
                            "loss": _finite(f.loss), "mean_burst": _finite(f.mean_burst),
                            "hours": _finite(f.hours), "rate_hz": rate_hz, "error": ""}
    checked = check_unit(gaps, f)
    rows: list[dict[str, Any]] = []
    if checked is not None:
        for label, chk in (("slow-downs", checked.slowdowns), ("emergency stops",
                                                               checked.timeouts)):
            if chk is None:
                continue
            rows.append({"what": label, "time_ms": chk.time_ms, "lost_in_row": chk.lost_in_row,
                         "model_per_hour": _rate(chk.model), "low": _rate(chk.model_low),
                         "high": _rate(chk.model_high), "recorded": chk.recorded,
                         "recorded_per_hour": None if chk.per_hour is None
                         else _rate(chk.per_hour), "verdict": chk.verdict})
    else:
        for label, key in (("slow-downs", "slow_ms"), ("emergency stops", "timeout_ms")):
            ms = unit.get(key)
            if isinstance(ms, (int, float)) and ms > 0:
                n = lost_in_row(ms, rate_hz)
                lo, hi = f.interval95(n)
                rows.append({"what": label, "time_ms": ms, "lost_in_row": n,
                             "model_per_hour": _rate(f.false_stops(n)), "low": _rate(lo),
                             "high": _rate(hi), "recorded": None, "recorded_per_hour": None,
                             "verdict": ""})
    view["rows"] = rows
    return view
