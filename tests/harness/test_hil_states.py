"""The HIL harness's states and logs (v3, hil/hilstates.py, hiljudge): state changes on the
bus, sequences, the log's changes and causes, drops, rolls and state lines."""

from __future__ import annotations

import pytest
from hil_util import bus_frames, stopped

import hilcheck
from estop.protocol.can import StatusFrame
from hilcheck import Frame

# --------------------------------------------------------------------------- states and logs (v3)

def test_state_changes_on_the_bus() -> None:
    import hilstates

    frames = bus_frames([(0.0, 0.5, "ARMED", 0), (0.5, 0.62, "SLOWING", 0), (0.62, 0.9, "ARMED", 0),
                   (0.9, 1.0, "SLOWING", 0), (1.0, 1.2, "STOPPED", 3)])
    bad = bytearray(stopped(3, reason=5))
    bad[7] ^= 1
    frames.insert(30, Frame(frames[29].ts + 0.001, 0x050, bytes(bad)))  # not a change: bad CRC
    frames.insert(10, Frame(frames[9].ts + 0.001, 0x051, StatusFrame(0, 0, 0, 0, 5, 0).encode()))
    ch = hilstates.state_changes(frames, 1000.45)
    assert [(c.state, c.reason) for c in ch] == [(2, 0), (1, 0), (2, 0), (0, 3)]
    assert ch[0].ts == pytest.approx(1000.5) and ch[0].data[:4] == bytes((2, 30, 2, 0))
    assert ch[-1].text() == "STOPPED/udp_timeout"
    # the state before the window counts: no change at the window's start
    assert [(c.state, c.reason) for c in hilstates.state_changes(frames, 1000.7, 1000.95)] == \
        [(2, 0)]
    # with nothing before, the first frame in the window is a change
    late = [f for f in frames if f.ts > 1000.7]
    assert [c.text() for c in hilstates.state_changes(late, 0.0, 1000.89)] == ["ARMED/none"]


def test_sequence_and_frame_problems() -> None:
    import hilstates

    frames = bus_frames([(0.0, 0.1, "ARMED", 0), (0.1, 0.2, "STOPPED", 5)])
    ch = hilstates.state_changes(frames, 1000.05)
    assert hilstates.sequence_problem(ch, [(0, 5)], "run 0") is None
    text = hilstates.sequence_problem(ch, [(2, 0), (0, 5)], "run 0")
    assert text == "run 0: the bus showed STOPPED/lift, want SLOWING/none -> STOPPED/lift"
    assert "showed none" in str(hilstates.sequence_problem([], [(0, 5)], "x"))
    assert hilstates.frame_problem(ch[0].data, bytes((1, 100, 0, 5)), "stop") is None
    assert "want 01 64 00 03" in str(hilstates.frame_problem(ch[0].data, bytes((1, 100, 0, 3)),
                                                             "stop"))
    bad = bytearray(ch[0].data)
    bad[7] ^= 1
    assert "fails the frame checks" in str(hilstates.frame_problem(bytes(bad), b"", "stop"))


def _state(frm: str, to: str, reason: str, cause: str | None, src: str = "-") -> dict:
    rec = {"t_mono": 1.0, "event": "state", "from": frm, "to": to, "reason": reason, "src": src}
    return rec if cause is None else {**rec, "cause": cause}


def test_log_changes_and_problems() -> None:
    import hilstates

    recs = [{"event": "start"}, _state("ARMED", "SLOWING", "none", "udp_silence"),
            _state("SLOWING", "ARMED", "none", "link_back", "127.0.0.1:5")]
    got = hilstates.log_changes(recs)
    assert [c.text() for c in got] == ["ARMED->SLOWING none cause=udp_silence",
                                       "SLOWING->ARMED none cause=link_back"]
    assert got[1].src == "127.0.0.1:5"
    want = [("ARMED", "SLOWING", "none", "udp_silence"), ("SLOWING", "ARMED", "none",
                                                          "link_back")]
    assert hilstates.log_problem(got, want, "run 1") is None
    text = hilstates.log_problem(got[:1], want, "run 1")
    assert text is not None and text.startswith("run 1: log ARMED->SLOWING none cause=")
    assert "log none" in str(hilstates.log_problem([], want[:1], "x"))


@pytest.mark.parametrize("rec,ok", [
    (_state("ARMED", "STOPPED", "lift", "lift_datagram"), True),
    (_state("SLOWING", "STOPPED", "lift", "lift"), True),
    (_state("ARMED", "STOPPED", "tcp_stop", "stop_datagram"), True),
    (_state("SLOWING", "STOPPED", "udp_timeout", "udp_timeout"), True),
    (_state("ARMED", "STOPPED", "fault", "clock_backwards"), True),
    (_state("ARMED", "SLOWING", "none", "udp_silence"), True),
    (_state("SLOWING", "ARMED", "none", "link_back"), True),
    (_state("STOPPED", "SLOWING", "none", "release"), True),
    (_state("ARMED", "STOPPED", "lift", "tcp_stop"), False),
    (_state("ARMED", "STOPPED", "udp_timeout", "lift"), False),
    (_state("ARMED", "SLOWING", "none", "link_back"), False),
    (_state("SLOWING", "ARMED", "none", "release"), False),
    (_state("ARMED", "ARMED", "none", "release"), False),
    (_state("ARMED", "STOPPED", "lift", None), False),
])
def test_cause_fits_the_change(rec: dict, ok: bool) -> None:
    import hilstates

    (change,) = hilstates.log_changes([rec])
    assert (hilstates.cause_problem(change) is None) is ok


def test_bus_transitions_count_slowing() -> None:
    import hilstates

    frames = bus_frames([(0.0, 0.1, "STOPPED", 1), (0.1, 0.3, "ARMED", 0), (0.3, 0.4, "SLOWING", 0),
                   (0.4, 0.5, "ARMED", 0), (0.5, 0.6, "SLOWING", 0), (0.6, 0.7, "STOPPED", 3)])
    assert hilstates.bus_transitions(frames) == {
        "STOPPED->ARMED": 1, "ARMED->SLOWING": 2, "SLOWING->ARMED": 1, "SLOWING->STOPPED": 1}


def test_judge_drops() -> None:
    assert hilcheck.judge_drops(0, 0.5, "the flood") == hilcheck.Verdict([])
    v = hilcheck.judge_drops(12, 0.0, "the flood")
    assert v.fails == ["the kernel dropped 12 datagrams of the flood"] and v.inconclusive is None
    v = hilcheck.judge_drops(12, 0.004, "the flood")  # a CPU stood still: never a pass
    assert v.inconclusive is not None and v.fails[0].startswith("kernel drops not judged")
    assert hilcheck.judge_drops(None, 0.0, "the flood").fails


def test_judge_rolls_and_state_lines() -> None:
    from types import SimpleNamespace

    import hiljudge
    import hilroll
    from hilrun import Result

    frames = bus_frames([(0.0, 1.004, "ARMED", 0), (1.004, 1.5, "STOPPED", 5)])
    good = hilroll.roll(frames, 1001.0)
    bad = hilroll.Roll(good.moment, good.bus, hilroll.EmulatorRoll(2.0, None, 1.0))
    res = Result("lift", "t", "c")
    hiljudge.judge_rolls(res, "distance_m", "from the lift", [good, good], 1.085, "ideal",
                         [("no lift", 1.918, 0.833)])
    assert res.rollouts == {"from the lift": {
        "distance_m": [1.1017, 1.1017], "braking_after_ms": [4.0, 4.0],
        "before_braking_m": [0.0167, 0.0167], "model_m": 1.085,
        "model": "ideal", "compare": [["no lift", 1.918, 0.833]]}}
    assert not res.notes
    assert res.figures["distance_m"]["p50"] == pytest.approx(1.102, abs=1e-3)
    hiljudge.judge_rolls(res, "distance_m", "from the lift", [bad], 1.085, "ideal")
    assert res.figures["distance_m"] == pytest.approx(1.102, abs=1e-3)
    assert res.notes[0].startswith("FAIL: from the lift: the two ways to the distance disagree")
    d = SimpleNamespace(events=lambda name=None, since=0.0: [
        {**_state("STOPPED", "ARMED", "none", "release"), "t_mono": 5.0},
        {**_state("ARMED", "STOPPED", "lift", "lift_datagram"), "t_mono": 7.0}])
    lines = hiljudge.wait_state_lines(d, 6.0, 1, timeout=0.1)  # type: ignore[arg-type]
    assert [c.text() for c in lines] == ["ARMED->STOPPED lift cause=lift_datagram"]
    assert len(hiljudge.wait_state_lines(d, 6.0, 2, timeout=0.05)) == 1  # type: ignore[arg-type]
