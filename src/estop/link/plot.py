"""``estop link --plot``: the model's silences per hour against time, on a log scale, with
both targets: false emergency stops (read as the timeout T) and slow-downs (read as the slow
time S). matplotlib is imported only here."""

from __future__ import annotations

import numpy as np

from estop.link.gaps import LinkInputError
from estop.link.report import Report

__all__ = ["write_plot"]


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
    ax.axhline(rep.target, color="red", linestyle="--",
               label=f"target {rep.target:g} false stops/h (T)")
    ax.axhline(rep.slow_target, color="orange", linestyle="--",
               label=f"slow target {rep.slow_target:g} slow-downs/h (S)")
    if rep.fit.hours > 0:
        ax.axhline(1.0 / rep.fit.hours, color="gray", linestyle=":",
                   label="one event in the recording")
    if rep.recommended_ms is not None:
        ax.axvline(rep.recommended_ms, color="green", linestyle="-.",
                   label=f"recommended T {rep.recommended_ms} ms")
    if rep.two_stage and rep.recommended_slow_ms is not None:
        ax.axvline(rep.recommended_slow_ms, color="olive", linestyle=":",
                   label=f"recommended S {rep.recommended_slow_ms} ms")
    ax.set_yscale("log")
    ax.set_ylim(bottom=bottom)
    ax.set_xlabel("time after the last packet (ms): S or T")
    ax.set_ylabel("silences per hour: slow-downs at S, false stops at T")
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
