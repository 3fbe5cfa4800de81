"""The stop-latency bench never mistakes a lost can-log line for a late stop (issue 11).

estopd writes every CAN frame to its can-log through a queue; when the reader is slow, lines
are dropped and counted (``output_dropped``). A lost first stop frame makes the next one look
like a late stop. These tests give the bench's measuring code a can-log with lines missing
around a stop and check that the trial is discarded with the reason "log lines lost", never
timed:

- a real estopd whose can-log loses lines on the way to the bench (the pipe is the only
  simulated part): 3 lines (the alive counter jumps at the stop frame the bench sees) and 15
  brake lines (the brake counter wraps round to look continuous; the STATUS counter shows
  the gap a little later, and the discard comes afterwards);
- recorded lines fed to a daemon object that never ran, with the daemon's own
  ``output_dropped`` report (text and JSON) as the only sign of the loss.

No timing is asserted: the trials use a long timeout and a loose send slack so that a busy
machine cannot turn them into discards of another kind.
"""

from __future__ import annotations

import io
import re
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import ModuleType
from typing import IO

import pytest

from estop.protocol import can, canlog
from estop.unit.daemon import Daemon
from estop.unit.looplink import Link

TIMEOUT_MS = 300  # packets > 150 ms apart would be discarded as a gap: far from any hiccup
LOST = "timeout overshoot: log lines lost"


class LossyPipe(Daemon):
    """The real estopd, with its can-log losing lines on the way to the bench as a full pipe
    would: at the first stop frame after an ARMED frame, that frame and the next ``drop - 1``
    brake frames, and every STATUS frame logged meanwhile, never reach the reader."""

    def __init__(self, command: list[str], drop: int, **kw: object) -> None:
        super().__init__(command, **kw)  # type: ignore[arg-type]
        self.drop = drop
        self.lost: list[str] = []

    def _read_frames(self, stream: IO[str]) -> None:
        super()._read_frames(self._lossy(stream))  # type: ignore[arg-type]

    def _lossy(self, stream: Iterable[str]) -> Iterator[str]:
        armed = False
        left = 0
        for line in stream:
            try:
                rec = canlog.parse_line(line)
            except canlog.CanLogError:
                yield line
                continue
            if rec.can_id == can.BRAKE_ID and len(rec.data) == can.DLC:
                if left == 0 and armed and rec.data[0] == 1:
                    left = self.drop
                armed = rec.data[2] == can.State.ARMED
                if left:
                    left -= 1
                    self.lost.append(line)
                    continue
            elif rec.can_id == can.STATUS_ID and left:
                self.lost.append(line)
                continue
            yield line


def _one_timeout_trial(bench: ModuleType, drop: int,
                       estopd: str) -> tuple[object, LossyPipe, bool]:
    d = LossyPipe([estopd], drop, timeout_ms=TIMEOUT_MS)
    r = bench.RunResult("estopd", "idle", TIMEOUT_MS)
    d.start()
    try:
        link = Link(d.udp_port, d.tcp_port)
        try:
            trials = bench.Trials(d, link, TIMEOUT_MS, 1.0, r)
            took = trials.timeout_trial()
        finally:
            link.close()
        time.sleep(0.25)  # let the STATUS frame after the stop reach the log
    finally:
        d.stop()
    return r, d, took


def test_a_stop_frame_lost_from_the_log_is_discarded_not_timed(bench: ModuleType,
                                                              estopd: str) -> None:
    r, d, took = _one_timeout_trial(bench, drop=3, estopd=estopd)
    assert len([ln for ln in d.lost if " 050#" in ln]) == 3, d.lost  # the loss did happen
    assert r.missed["overshoot"] == 0 and r.wrong_reason["overshoot"] == 0
    # the bench saw the 4th stop frame, 30 ms late; it must not count it as a late stop
    assert r.samples["overshoot"] == [], r.samples
    assert not took
    assert r.discarded["overshoot"] == 1
    assert r.discard_reasons == {LOST: 1}


def test_fifteen_lost_brake_lines_are_found_by_the_status_counter(bench: ModuleType,
                                                                 estopd: str) -> None:
    r, d, _took = _one_timeout_trial(bench, drop=15, estopd=estopd)
    assert len([ln for ln in d.lost if " 050#" in ln]) == 15, d.lost
    assert any(" 051#" in ln for ln in d.lost), d.lost
    # the brake counter wrapped round: the first stop frame seen looks continuous ...
    assert not any(g.can_id == can.BRAKE_ID for g in d.loss.gaps), d.loss.gaps
    assert any(g.can_id == can.STATUS_ID for g in d.loss.gaps), d.loss.gaps
    # ... and the trial, timed at once or not, ends as a discard once the log is read
    r.settle(d.lines_lost)
    assert r.samples["overshoot"] == [], r.samples
    assert r.discard_reasons == {LOST: 1}


# --------------------------------------------------------------------------------------------
# Recorded lines, no daemon running


def _brake(t: float, state: int, reason: int, ctr: int) -> str:
    frame = can.BrakeFrame.for_state(state, reason, 0, ctr)
    return canlog.format_line(canlog.CanLogRecord.at(t, "estop", can.BRAKE_ID, frame.encode()))


def _status(t: float, ctr: int) -> str:
    frame = can.StatusFrame(10, 0, 0, 0, 5, ctr)
    return canlog.format_line(canlog.CanLogRecord.at(t, "estop", can.STATUS_ID, frame.encode()))


def _recorded_stop(t0: float, timeout_s: float) -> tuple[list[str], float]:
    """A can-log of an ARMED unit whose link times out at t0 + timeout_s: brake frames every
    10 ms, a STATUS every 100 ms, the stop frame at the deadline + 0.2 ms, then STOPPED
    frames. Nothing missing. Returns the lines and the stop frame's stamp."""
    lines = []
    ctr = sctr = 0
    t = t0 - 0.05
    while t < t0 + timeout_s:
        lines.append(_brake(t, can.State.ARMED, 0, ctr))
        ctr = (ctr + 1) % 15
        if round((t - t0) * 100) % 10 == 0:
            lines.append(_status(t + 0.000005, sctr))
            sctr = (sctr + 1) % 15
        t += 0.010
    t_stop = t0 + timeout_s + 0.0002
    for i in range(30):
        lines.append(_brake(t_stop + 0.010 * i, can.State.STOPPED, can.Reason.UDP_TIMEOUT, ctr))
        ctr = (ctr + 1) % 15
        if i % 10 == 5:
            lines.append(_status(t_stop + 0.010 * i + 0.000005, sctr))
            sctr = (sctr + 1) % 15
    return lines, t_stop


def _fed(lines: list[str], log: str = "") -> Daemon:
    """A daemon object that never ran, fed recorded can-log and event-log lines."""
    d = Daemon(["estopd-not-run"])
    d._read_log(io.StringIO(log))
    d._read_frames(io.StringIO("".join(ln + "\n" for ln in lines)))
    return d


def _judge(bench: ModuleType, d: Daemon, t0: float, timeout_s: float) -> object:
    r = bench.RunResult("estopd", "idle", round(timeout_s * 1000))
    trials = bench.Trials(d, None, round(timeout_s * 1000), 0.001, r)
    m0 = time.monotonic()
    trials.judge_timeout(bench.TimeoutSent(mono=m0, t_ack=t0 - 0.004, t_last=t0))
    return r


def test_recorded_log_without_gaps_is_timed(bench: ModuleType) -> None:
    t0 = time.time() - 5.0
    lines, t_stop = _recorded_stop(t0, 0.020)
    r = _judge(bench, _fed(lines), t0, 0.020)
    assert r.samples["overshoot"] == [pytest.approx((t_stop - t0 - 0.020) * 1000, abs=1e-3)]
    assert r.discard_reasons == {}


def test_recorded_log_with_a_counter_gap_at_the_stop_is_discarded(bench: ModuleType) -> None:
    t0 = time.time() - 5.0
    lines, t_stop = _recorded_stop(t0, 0.020)
    first = next(i for i, ln in enumerate(lines) if "#0164" in ln)
    del lines[first:first + 2]  # the first two stop frames never reached the reader
    r = _judge(bench, _fed(lines), t0, 0.020)
    assert r.samples["overshoot"] == [] and r.discard_reasons == {LOST: 1}


@pytest.mark.parametrize("json_log", [False, True])
def test_the_daemons_own_drop_count_discards_a_trial(bench: ModuleType, json_log: bool) -> None:
    """15 lines lost: the counters look continuous; only the daemon's report tells."""
    t0 = time.time() - 5.0
    lines, _t_stop = _recorded_stop(t0, 0.020)
    first = next(i for i, ln in enumerate(lines) if "#0164" in ln)
    brake = [i for i in range(first, len(lines)) if " 050#" in lines[i]][:15]
    kept = [ln for i, ln in enumerate(lines) if i not in brake]  # STATUS lines all kept
    d = _fed(kept)
    assert d.loss.gaps == []  # the alive counters cannot see 15 lost brake lines
    r = _judge(bench, d, t0, 0.020)
    assert len(r.samples["overshoot"]) == 1  # timed at first: 150 ms "late"
    # the daemon's report arrives later, within a second of the loss
    t_rep = time.monotonic() + 0.5
    line = (f'{{"t_mono":{t_rep:.6f},"event":"output_dropped","stream":"can_log",'
            f'"dropped":15,"total":15,"err":"full"}}' if json_log else
            f"estopd {t_rep:.6f} output_dropped stream=can_log dropped=15 total=15 err=full")
    d._read_log(io.StringIO(line + "\n"))
    assert r.settle(d.lines_lost) == 1
    assert r.samples["overshoot"] == [] and r.discard_reasons == {LOST: 1}


def test_a_report_long_after_the_trial_leaves_it_alone(bench: ModuleType) -> None:
    t0 = time.time() - 5.0
    lines, _ = _recorded_stop(t0, 0.020)
    d = _fed(lines)
    r = _judge(bench, d, t0, 0.020)
    t_rep = time.monotonic() + 10.0  # covers the 2 s before it only
    d._read_log(io.StringIO(f"estopd {t_rep:.6f} output_dropped stream=can_log dropped=4 "
                            f"total=4 err=full\n"))
    assert r.settle(d.lines_lost) == 0 and len(r.samples["overshoot"]) == 1


def test_the_demo_gives_no_figure_for_a_stop_with_lost_lines(tmp_path: Path, estopd: str) -> None:
    """estop demo times its stops and replays its distances from the can-log too: with the
    first stop frames of each stop from ARMED lost (the lift, the stop datagram, the stop
    button), it says so instead of printing a late figure; the loss of the link, which stops
    from SLOWING, loses nothing and keeps its figures."""
    from estop.demo.bus import BusWatch
    from estop.demo.car import LiveCar
    from estop.demo.checks import check
    from estop.demo.report import write_report
    from estop.demo.result import Result, Settings
    from estop.demo.story import finish_run, run_story
    from estop.demo.view import View
    from estop.protocol import auth

    key = bytes(range(32))
    key_file = tmp_path / "key"
    key_file.write_bytes(auth.format_key(key))
    key_file.chmod(0o600)
    settings = Settings()
    d = LossyPipe([estopd], 3, timeout_ms=settings.timeout_ms,
                  extra_args=settings.unit_args(), key_file=str(key_file))
    car = LiveCar(settings.speed)
    view = View(out=io.StringIO(), live=False, t0=time.time(), watch=BusWatch(car), car=car)
    res = Result(settings)
    d.start()
    try:
        run_story(d, view, settings, key, res)
    finally:
        rc, _ = finish_run(d, view, res)
    assert res.problems == [] and check(res, view.watch, rc) == []
    assert len([ln for ln in d.lost if " 050#" in ln]) == 9, d.lost  # 3 at each of 3 stops
    for m in (res.lift, res.datagram, res.button):
        assert m is not None and m.stop is not None and m.lost >= 3, m
    assert res.loss is not None and res.loss.lost == 0
    out = io.StringIO()
    write_report(out, view, res, {}, None, d.dropped_total)
    rows = out.getvalue().splitlines()
    # 3 brake lines each, and a STATUS line when one fell among them
    for what in ("the finger lifts, from", "the attacker's stop datagram, from",
                 "the stop button, from"):
        row = next(r for r in rows if r.strip().startswith(what))
        m = re.search(r"not measured: (\d+) can-log lines lost", row)
        assert m is not None and int(m.group(1)) >= 3 and " m in " not in row, row
    loss = next(r for r in rows if "STOPPED udp_timeout" in r)
    assert "not measured" not in loss and re.search(r" \d+\.\d+ m in \d+ ms", loss), loss
