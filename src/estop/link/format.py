"""``estop link``'s outputs: the text report and the ``--json`` document of a
:class:`~estop.link.report.Report`."""

from __future__ import annotations

import math
from typing import Any

from estop.link.report import ENOUGH, Report
from estop.link.unitcheck import FEWER, MORE, NOT_MOVING, Check, UnitCheck

__all__ = ["REFERENCE_SPEED_KMH", "estopd_options", "fmt_rate", "format_report", "report_json"]

# the speed at which the report says how far the car rolls before it brakes
REFERENCE_SPEED_KMH = 15.0


def estopd_options(rep: Report) -> list[str] | None:
    """The daemon's options for the recommended pair (S = T is the default: no --slow-ms)."""
    s, t = rep.recommended_slow_ms, rep.recommended_ms
    if s is None or t is None:
        return None
    return (["--slow-ms", str(s)] if s < t else []) + ["--timeout-ms", str(t)]


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
        "slow_target_per_hour": rep.slow_target,
        "recommended_slow_ms": rep.recommended_slow_ms,
        "recommended_estopd_options": estopd_options(rep),
        "react_ms": rep.react_ms,
        # the two-stage contract: every pair S <= T with the model's rates, and the chosen one
        "recommendation": None if rep.recommendation is None else {
            "slow_ms": rep.recommendation[0], "timeout_ms": rep.recommendation[1]},
        "pairs": [{"slow_ms": p.slow_ms, "timeout_ms": p.timeout_ms,
                   "slowdowns_per_hour": p.slowdowns_per_hour,
                   "emergency_stops_per_hour": p.emergency_stops_per_hour}
                  for p in rep.pairs],
        "unit": _unit_json(rep.unit),
        "rows": [{
            "timeout_ms": r.timeout_ms,
            "lost_in_row": r.lost_in_row,
            "false_stops_per_hour": r.model,
            "false_stops_per_hour_95": [r.model_low, r.model_high],
            # the same silences read as the slow time S: brief slow-downs
            "slowdowns_per_hour": r.model,
            "slowdowns_per_hour_95": [r.model_low, r.model_high],
            "gaps_at_least": [r.gaps_sure, r.gaps_possible],
            "gaps_per_hour": _num(r.empirical),
            "gaps_per_hour_upper95": _num(r.empirical_upper95),
            "gaps_per_hour_lower95": r.empirical_lower95,
            "model_contradicted": r.contradicted,
            "enough_data": r.enough,
        } for r in rep.rows],
    }


def _check_json(c: Check | None) -> dict[str, Any] | None:
    if c is None:
        return None
    return {"time_ms": c.time_ms, "lost_in_row": c.lost_in_row, "recorded": c.recorded,
            "per_hour": c.per_hour, "per_hour_95": [c.lower95, c.upper95],
            "model_per_hour": c.model, "model_per_hour_95": [c.model_low, c.model_high],
            "pauses": c.pauses, "verdict": c.verdict}


def _unit_json(u: UnitCheck | None) -> dict[str, Any] | None:
    if u is None:
        return None
    return {"slow_ms": u.record.slow_us / 1000, "timeout_ms": u.record.timeout_us / 1000,
            "slowdowns": u.record.slowdowns, "timeouts": u.record.timeouts,
            "hours": u.hours, "hours_from": u.hours_from, "notes": list(u.record.notes),
            "slowdowns_check": _check_json(u.slowdowns),
            "timeouts_check": _check_json(u.timeouts)}


def fmt_rate(x: float) -> str:
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
    if "slowdowns" in extra:
        lines.append(f"unit: slow time S {extra['slow_us'] / 1000:g} ms, timeout T "
                     f"{extra['timeout_us'] / 1000:g} ms; it counted {extra['slowdowns']} "
                     f"slow-downs and {extra['timeouts']} stops by timeout")
    if extra.get("other_datagrams"):
        lines.append(f"capture: {extra['other_datagrams']} other datagrams to the port ignored")
    if g.pauses:
        lines.append(f"{g.pauses} gap(s) of --max-gap or longer left out as sender pauses "
                     "(finger lifted); each would also have been a stop")
    lines.extend(f"note: {n}" for n in g.notes)
    lines.append("A stop comes at the deadline: a time D (S or T) at send period P is reached "
                 "when n = ceil(D/P) - 1 packets in a row are lost.")
    lines.append(f"'seen': gaps of n or more lost in the recording ({f.hours:.3g} h); "
                 f"'<' marks fewer than {ENOUGH} (95 % upper bound).")
    lines.append("'model/h': the model's silences per hour that reach the time. Read as the "
                 "slow time S they are brief slow-downs (each ends when the link is back); "
                 "read as the timeout T, latched emergency stops for nothing (false stops).")
    lines.append("")
    lines.append("   time    n   seen   seen/h      model/h   model 95 % range")
    for r in rep.rows:
        seen = (str(r.gaps_sure) if r.gaps_sure == r.gaps_possible
                else f"{r.gaps_sure}-{r.gaps_possible}")
        if r.empirical is not None:
            per_h = fmt_rate(r.empirical)
        elif r.enough:
            per_h = f"{fmt_rate(r.gaps_sure / r.hours)}-{fmt_rate(r.gaps_possible / r.hours)}"
        else:
            per_h = "<" + fmt_rate(r.empirical_upper95)
        mark = "!" if r.contradicted else (" " if r.lost_in_row >= f.tail_from else "^")
        lines.append(f"{r.timeout_ms:5d} ms {r.lost_in_row:4d} {seen:>6} {per_h:>8} "
                     f"{fmt_rate(r.model):>12}{mark}  {fmt_rate(r.model_low)} .. "
                     f"{fmt_rate(r.model_high)}{_pick(rep, r.timeout_ms)}")
    if any(r.contradicted for r in rep.rows):
        lines.append("! the recording holds more such gaps than the model allows: trust the "
                     "recording there")
    if any(r.lost_in_row < f.tail_from for r in rep.rows):
        lines.append(f"^ fewer than {f.tail_from} lost: below the runs the model was fitted to")
    if rep.unit is not None:
        lines.append("")
        lines.extend(_unit_lines(rep.unit))
    lines.append("")
    if not f.bursts:
        lines.append("recommendation: none (no loss recorded: the model has nothing to "
                     "extrapolate from)")
    elif rep.recommended_ms is None:
        lines.append(f"recommendation: no timeout up to {rep.rows[-1].timeout_ms} ms keeps the "
                     f"model (and the recording) below {rep.target:g} false stops per hour")
    else:
        r = rep.row(rep.recommended_ms)
        lines.append(f"recommendation: timeout T {rep.recommended_ms} ms (model "
                     f"{fmt_rate(r.model)} false stops per hour, target {rep.target:g}); one "
                     f"per {_fmt_hours(r.model)} against {f.hours:.3g} h recorded")
        if rep.recommended_conservative_ms is None:
            lines.append("  with the model's 95 % upper bound: none up to "
                         f"{rep.rows[-1].timeout_ms} ms")
        elif rep.recommended_conservative_ms != rep.recommended_ms:
            lines.append(f"  with the model's 95 % upper bound: "
                         f"{rep.recommended_conservative_ms} ms")
    lines.extend(_two_stage_lines(rep))
    return lines


def _pick(rep: Report, time_ms: int) -> str:
    s, t = rep.recommended_slow_ms, rep.recommended_ms
    if time_ms == s == t:
        return "  <- S = T"
    if time_ms == s:
        return "  <- S"
    if time_ms == t:
        return "  <- T"
    return ""


def _shortest(rep: Report) -> int | None:
    return next((r.timeout_ms for r in rep.rows if r.lost_in_row >= 1), None)


def _metres(ms: int) -> str:
    return f"{ms / 1000 * REFERENCE_SPEED_KMH / 3.6:.2f} m"


def _two_stage_lines(rep: Report) -> list[str]:
    """The slow time S, the daemon's options and what a real loss of the link costs."""
    s, t = rep.recommended_slow_ms, rep.recommended_ms
    if s is None:
        if t is not None:
            return [f"slow time: none within --react-ms {rep.react_ms:g} (the shortest time "
                    f"longer than one send period is {_shortest(rep)} ms): no options for "
                    "estopd recommended"]
        return []
    lines = []
    r = rep.row(s)
    react = f"--react-ms {rep.react_ms:g}"
    if t is not None and s == t:
        lines.append(f"slow time: S = T = {t} ms: no slow time shorter than the timeout keeps "
                     f"slow-downs below {rep.slow_target:g} per hour (--slow-target); the link "
                     "needs no two-stage stop")
    elif not rep.slow_target_met:
        lines.append(f"slow time: S {s} ms, the longest within {react}: no slow time up to it "
                     f"keeps slow-downs below {rep.slow_target:g} per hour (--slow-target); "
                     f"model {fmt_rate(r.model)} slow-downs per hour")
    else:
        every = f"one every {3600.0 / r.model:.3g} s" if r.model > 0 else "none"
        lines.append(f"slow time: S {s} ms (model {fmt_rate(r.model)} slow-downs per hour, "
                     f"--slow-target {rep.slow_target:g}; {every}, each ended by the link's "
                     "return)")
    if t is None:
        lines.append("  no timeout meets the target: no options for estopd recommended")
        return lines
    lines.append("estopd options: " + " ".join(estopd_options(rep) or []))
    speed = f"at {REFERENCE_SPEED_KMH:g} km/h ({REFERENCE_SPEED_KMH / 3.6:.2f} m/s)"
    if s < t:
        lines.append(f"a real loss of the link: braking starts S = {s} ms after the last "
                     f"packet (the slow level), the emergency brake at T = {t} ms; {speed} the "
                     f"car rolls {_metres(s)} before braking begins ({_metres(t)} with a "
                     "single-stage stop at T)")
    else:
        lines.append(f"a real loss of the link: the emergency brake starts T = {t} ms after the "
                     f"last packet; {speed} the car rolls {_metres(t)} before braking begins")
    return lines


def _unit_lines(u: UnitCheck) -> list[str]:
    """The unit's own counts against the model at its S and T."""
    rec = u.record
    per = (f"per hour moving (ARMED or SLOWING: {u.hours:.3g} h, from its state events)"
           if u.hours_from == "state events" else
           f"per hour recorded ({u.hours:.3g} h; the log does not show every run from its "
           "start, so the time the unit moved is unknown)")
    lines = [f"the unit's own counts (S {rec.slow_us / 1000:g} ms, T {rec.timeout_us / 1000:g} "
             f"ms) against the model, {per}:"]
    if u.slowdowns is None:
        lines.append("  slow-downs: none possible, the unit ran with S = T (one stage)")
    else:
        lines.append("  slow-downs    " + _check_line(u.slowdowns, u.hours_from))
    lines.append("  timeout stops " + _check_line(u.timeouts, u.hours_from))
    lines.extend(f"note: {n}" for n in rec.notes)
    return lines


def _check_line(c: Check, hours_from: str) -> str:
    model = (f"model at {c.time_ms:g} ms: {fmt_rate(c.model)} ({fmt_rate(c.model_low)} .. "
             f"{fmt_rate(c.model_high)})")
    verdict = c.verdict
    if verdict == NOT_MOVING:
        return f"{c.recorded:6d}; the unit never moved (never ARMED): nothing to compare"
    lo, hi, per_h = c.lower95 or 0.0, c.upper95 or 0.0, c.per_hour or 0.0
    seen = (f"{c.recorded:6d}: {fmt_rate(per_h)}/h (95 % bounds {fmt_rate(lo)} .. "
            f"{fmt_rate(hi)})")
    if verdict == MORE:
        say = "! more than the model allows: trust the unit's count"
        if c.pauses:
            say += f" (even if {c.pauses} of them were sender pauses)"
    elif verdict == FEWER:
        say = "fewer than the model"
        say += (": the model is cautious here" if hours_from == "state events" else
                " (a unit STOPPED part of the recording counts none there)")
    else:
        say = "agrees"
    return f"{seen}; {model}: {say}"


def _fmt_hours(rate: float) -> str:
    return "never" if rate <= 0 else f"{1.0 / rate:.3g} h"


