"""``estop monitor``: silence is a failure (spec section 7), in log mode and on a live
python-can bus (the real python-can ``virtual`` interface); the grade of each ESTOP_BRAKE
(an unknown brake_request is an emergency brake); the roll-out of ``--speed-kmh``."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

from estop import cli
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.canlog import CanLogRecord, format_line
from estop.protocol.crc import e2e_crc8

pytestmark = pytest.mark.timeout(60)

T0 = 1_700_000_000.0


def brake(t: float, counter: int) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x050, BrakeFrame.for_state(1, 0, 0, counter % 15).encode())


def status(t: float, counter: int) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x051, StatusFrame(5, 0, 0, 1, 12, counter % 15).encode())


def write_log(path: Path, recs: list[CanLogRecord]) -> str:
    path.write_text("".join(format_line(r) + "\n" for r in recs))
    return str(path)


def monitor(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(["monitor", *argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


# ------------------------------------------------------------------------------ log mode

def test_empty_log_is_not_a_working_unit(tmp_path: Path, capsys) -> None:
    code, out, err = monitor(capsys, "--log", write_log(tmp_path / "empty.log", []))
    assert code == 1 and err == ""
    assert "! no_brake_frame: no good ESTOP_BRAKE frame at all" in out
    assert out.splitlines()[-1] == "summary: 0 frames, 0 accepted; problems: no_brake_frame 1"


def test_log_of_other_frames_only_fails(tmp_path: Path, capsys) -> None:
    recs = [CanLogRecord.at(T0 + i * 0.01, "vcan0", 0x123, b"\x01") for i in range(20)]
    recs += [status(T0 + i * 0.1, i) for i in range(5)]
    code, out, _ = monitor(capsys, "-q", "--log", write_log(tmp_path / "other.log", recs))
    assert code == 1
    assert out.splitlines()[-1] == "summary: 5 frames, 5 accepted; problems: no_brake_frame 1"


def test_brake_frames_stop_while_status_goes_on(tmp_path: Path, capsys) -> None:
    recs = [brake(T0 + i * 0.010, i) for i in range(30)]  # last good ESTOP_BRAKE at +0.29
    recs += [status(T0 + 0.29 + i * 0.1, i) for i in range(1, 10)]  # +0.39 .. +1.19
    code, out, _ = monitor(capsys, "-q", "--log", write_log(tmp_path / "b.log", recs))
    assert code == 1
    assert ("(1700000001.190000) 050 ! timeout: no good ESTOP_BRAKE for 900.0 ms up to the end "
            "of the record (limit 50 ms)") in out
    assert out.splitlines()[-1] == "summary: 39 frames, 39 accepted; problems: timeout 1"


def test_the_last_line_of_any_id_counts(tmp_path: Path, capsys) -> None:
    recs = [brake(T0 + i * 0.010, i) for i in range(10)]
    recs.append(CanLogRecord.at(T0 + 0.5, "vcan0", 0x7FF, b""))  # another ECU, 410 ms later
    code, out, _ = monitor(capsys, "-q", "--log", write_log(tmp_path / "c.log", recs))
    assert code == 1 and "410.0 ms up to the end of the record" in out
    recs[-1] = CanLogRecord.at(T0 + 0.09 + 0.045, "vcan0", 0x1ABCDEF, b"", extended=True)
    code, out, _ = monitor(capsys, "-q", "--log", write_log(tmp_path / "d.log", recs))
    assert code == 0 and out.splitlines()[-1].endswith("problems: none")


def test_clean_log_still_passes(tmp_path: Path, capsys) -> None:
    recs = []
    for i in range(40):
        recs.append(brake(T0 + i * 0.010, i))
        if i % 10 == 0:
            recs.append(status(T0 + i * 0.010 + 0.001, i // 10))
    code, out, _ = monitor(capsys, "-q", "--log", write_log(tmp_path / "ok.log", recs))
    assert code == 0
    assert out.splitlines()[-1] == "summary: 44 frames, 44 accepted; problems: none"


# ----------------------------------------------------------------------------- live mode

def _channel() -> str:
    return f"estop_monitor_{os.getpid()}_{time.monotonic_ns()}"


def test_live_bus_without_frames_fails(capsys) -> None:
    pytest.importorskip("can")
    code, out, err = monitor(capsys, "-i", "virtual", "-c", _channel(), "--duration", "0.3",
                             "--speed-kmh", "15")
    assert code == 1 and err == ""
    assert "! timeout: no good ESTOP_BRAKE since the watch began" in out
    assert "! no_brake_frame: no good ESTOP_BRAKE frame at all" in out
    # no frame at all: the car brakes 50 ms after the watch began, as a controller would
    assert ("roll-out at 15.0 km/h: braking began +50.0 ms (after the end of the record: "
            "silence), standstill +570.8 ms, rolled 1.293 m") in out
    assert out.splitlines()[-1] == ("summary: 0 frames, 0 accepted; problems: timeout 1, "
                                    "no_brake_frame 1")


def test_live_bus_brake_stops_status_goes_on(capsys) -> None:
    can = pytest.importorskip("can")
    from can.interfaces import virtual

    channel = _channel()

    def listening() -> bool:
        return len(getattr(virtual, "channels", {}).get(channel, ())) >= 2

    def send() -> None:
        with can.Bus(interface="virtual", channel=channel) as bus:
            deadline = time.monotonic() + 5
            while not listening() and time.monotonic() < deadline:
                time.sleep(0.01)
            for i in range(5):
                bus.send(can.Message(arbitration_id=0x050, is_extended_id=False,
                                     data=BrakeFrame.for_state(1, 0, 0, i).encode()))
                time.sleep(0.01)
            for i in range(6):  # ESTOP_STATUS goes on, ESTOP_BRAKE does not
                bus.send(can.Message(arbitration_id=0x051, is_extended_id=False,
                                     data=StatusFrame(5, 0, 0, 1, 12, i).encode()))
                time.sleep(0.05)

    sender = threading.Thread(target=send)
    sender.start()
    try:
        code, out, _ = monitor(capsys, "-q", "--interface", "virtual", "--channel", channel,
                               "--duration", "1.0")
    finally:
        sender.join(timeout=10)
    assert code == 1
    assert "! timeout: no good ESTOP_BRAKE for" in out
    assert out.splitlines()[-1] == "summary: 11 frames, 11 accepted; problems: timeout 1"


# ------------------------------------------------------------- grades (spec section 7)

def brake_as(t: float, counter: int, state: int, reason: int = 0,
             level: int = 30) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x050, BrakeFrame.for_state(
        state, reason, 0, counter % 15, slow_level=level).encode())


def raw_brake(t: float, counter: int, brake_request: int) -> CanLogRecord:
    """Right CRC, counter in order, any brake_request (the rest as ARMED)."""
    payload = bytes((brake_request, 0, 1, 0, 0, 0, counter % 15))
    return CanLogRecord.at(t, "vcan0", 0x050, payload + bytes((e2e_crc8(0x0E57, payload),)))


def test_each_brake_frame_shows_its_grade(tmp_path: Path, capsys) -> None:
    recs = [brake_as(T0, 0, 1), brake_as(T0 + 0.01, 1, 2, level=30),
            brake_as(T0 + 0.02, 2, 0, reason=5)]
    code, out, _ = monitor(capsys, "--log", write_log(tmp_path / "g.log", recs))
    lines = out.splitlines()
    assert code == 0
    assert lines[0].endswith("ESTOP_BRAKE ARMED reason=none brake=0 level=0 flags=0x00 ctr=0 "
                             "=> release")
    assert lines[1].endswith("ESTOP_BRAKE SLOWING reason=none brake=2 level=30 flags=0x00 "
                             "ctr=1 => controlled 30 %  <- state change")
    assert lines[2].endswith("ESTOP_BRAKE STOPPED reason=lift brake=1 level=100 flags=0x00 "
                             "ctr=2 => EMERGENCY  <- state change")
    assert lines[-2] == "brake commands: release 1, controlled 1, emergency 1"


@pytest.mark.parametrize("unknown", [3, 255])
def test_an_unknown_brake_request_is_printed_and_counted_as_emergency(
        unknown: int, tmp_path: Path, capsys) -> None:
    recs = [brake_as(T0, 0, 1), raw_brake(T0 + 0.01, 1, unknown), brake_as(T0 + 0.02, 2, 1)]
    code, out, _ = monitor(capsys, "--log", write_log(tmp_path / "u.log", recs))
    lines = out.splitlines()
    assert code == 1
    assert lines[1].endswith(f"brake={unknown} level=0 flags=0x00 ctr=1 => EMERGENCY "
                             f"(brake_request {unknown} unknown)  [rejected]")
    assert "! bad_content: brake_request" in lines[2]
    assert lines[-2] == "brake commands: release 2, controlled 0, emergency 1"
    assert lines[-1] == "summary: 3 frames, 2 accepted; problems: bad_content 1"


# ------------------------------------------------------------------ roll-out (--speed-kmh)

def test_speed_kmh_prints_the_roll_out_from_the_start_of_the_log(tmp_path: Path,
                                                                 capsys) -> None:
    # released for 300 ms, then STOPPED: at 15 km/h, 1.25 m rolled, then 1.085 m of braking
    recs = [brake_as(T0 + i * 0.01, i, 1) for i in range(30)]
    recs += [brake_as(T0 + 0.3 + i * 0.01, 30 + i, 0, reason=5) for i in range(80)]
    code, out, _ = monitor(capsys, "-q", "--speed-kmh", "15", "--log",
                           write_log(tmp_path / "r.log", recs))
    assert code == 0
    assert out.splitlines()[-3] == (
        "roll-out at 15.0 km/h: braking began +300.0 ms, standstill +820.8 ms, rolled "
        "2.335 m, from the start of the watch (1700000000.000000)")
    code, out, _ = monitor(capsys, "-q", "--speed-kmh", "15", "--actuator-delay-ms", "200",
                           "--decel-ms2", "8", "--log", write_log(tmp_path / "r.log", recs))
    assert "braking began +500.0 ms, standstill +1020.8 ms, rolled 3.168 m" in out


def test_speed_kmh_when_the_log_ends_released(tmp_path: Path, capsys) -> None:
    recs = [brake_as(T0 + i * 0.01, i, 1) for i in range(10)]
    code, out, _ = monitor(capsys, "-q", "--speed-kmh", "15", "--log",
                           write_log(tmp_path / "s.log", recs))
    assert code == 0  # 0.09 s to the end: no silence flagged yet
    assert ("roll-out at 15.0 km/h: braking began +140.0 ms (after the end of the record: "
            "silence), standstill +660.8 ms") in out


def test_roll_out_options_need_a_speed(tmp_path: Path, capsys) -> None:
    code, out, err = monitor(capsys, "--decel-ms2", "6", "--log", str(tmp_path / "x.log"))
    assert code == 2 and out == "" and "--speed-kmh" in err and err.count("\n") == 1
    code, _, err = monitor(capsys, "--speed-kmh", "-1", "--log", str(tmp_path / "x.log"))
    assert code == 2 and err.count("\n") == 1
