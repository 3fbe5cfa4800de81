"""``estop link``'s outputs: the text report and the ``--json`` document of a
:class:`~estop.linkreport.Report`."""

from __future__ import annotations

import math
from typing import Any

from estop.linkreport import ENOUGH, Report

__all__ = ["format_report", "report_json"]


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


