"""``estop monitor --log`` reads python-can's log formats (written here by python-can's own
writers) as it reads can-utils lines, and ``--dbc`` decodes each frame with cantools from the
unit's DBC, flagging a frame the DBC and estop's codecs read differently."""

from __future__ import annotations

from pathlib import Path

import pytest

from estop import cli
from estop.protocol import can as estop_can
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.canlog import CanLogRecord, format_line

can = pytest.importorskip("can")
pytest.importorskip("cantools")
pytestmark = pytest.mark.timeout(60)

T0 = 1_700_000_000.0


def frames(n: int = 30) -> list[tuple[float, int, bytes]]:
    out = []
    for i in range(n):
        stopped = i < 10  # STOPPED at boot, then ARMED
        state, reason = (estop_can.State.STOPPED, 1) if stopped else (estop_can.State.ARMED, 0)
        out.append((T0 + i * 0.010, estop_can.BRAKE_ID,
                    BrakeFrame.for_state(state, reason, 0, i % 15).encode()))
        if i % 10 == 0:
            out.append((T0 + i * 0.010 + 0.001, estop_can.STATUS_ID,
                        StatusFrame(5, 0, 0, 1, 12, (i // 10) % 15).encode()))
    out.append((T0 + n * 0.010, 0x123, b"\x01\x02"))  # another ECU's frame
    return out


def write_python_can(path: Path, recs: list[tuple[float, int, bytes]]) -> str:
    with can.Logger(str(path)) as log:
        for t, can_id, data in recs:
            log.on_message_received(can.Message(timestamp=t, arbitration_id=can_id,
                                                data=data, is_extended_id=False,
                                                channel="vcan0"))
    return str(path)


def write_canutils(path: Path, recs: list[tuple[float, int, bytes]]) -> str:
    path.write_text("".join(format_line(CanLogRecord.at(t, "vcan0", i, d)) + "\n"
                            for t, i, d in recs))
    return str(path)


def monitor(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(["monitor", *argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def verdicts(out: str) -> list[str]:
    """The frame lines without their stamps (formats keep time to different precisions)."""
    return [line.split(") ", 1)[1] for line in out.splitlines() if line.startswith("(")]


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc"])
def test_python_can_logs_read_as_can_utils_lines(suffix: str, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    recs = frames()
    code, want, err = monitor(capsys, "--log", write_canutils(tmp_path / "a.log", recs))
    assert code == 0 and err == ""
    code, out, err = monitor(capsys, "--log", write_python_can(tmp_path / f"a{suffix}", recs))
    assert (code, err) == (0, ""), out
    assert verdicts(out) == verdicts(want)
    assert out.splitlines()[-2:] == want.splitlines()[-2:]  # the same commands and summary


def test_dbc_decodes_every_frame_it_knows(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = monitor(capsys, "--log", write_python_can(tmp_path / "a.blf", frames()),
                             "--dbc")
    assert (code, err) == (0, ""), out
    dbc = [line for line in out.splitlines() if line.startswith("  dbc: ")]
    assert len(dbc) == 33  # 30 ESTOP_BRAKE, 3 ESTOP_STATUS; the DBC does not know 0x123
    assert dbc[0].startswith("  dbc: ESTOP_BRAKE brake_request=emergency_brake brake_level=100 "
                             "state=STOPPED reason=boot")
    assert any(line.startswith("  dbc: ESTOP_STATUS valid_packets=5") for line in dbc)
    assert "MISMATCH" not in out


def test_a_dbc_that_reads_a_frame_otherwise_is_flagged(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """A DBC with the state and reason bytes swapped: every ESTOP_BRAKE here (the two differ
    in each) is read otherwise by the DBC than by the unit's codecs, and the watch fails."""
    text = estop_can.dbc_text()
    swapped = (text.replace(" SG_ state : 16|8@1+", " SG_ state : 24|8@1+", 1)
               .replace(" SG_ reason : 24|8@1+", " SG_ reason : 16|8@1+", 1))
    assert swapped != text
    other = tmp_path / "other.dbc"
    other.write_text(swapped)
    code, out, _ = monitor(capsys, "--log", write_python_can(tmp_path / "a.asc", frames()),
                           "-q", "--dbc", str(other))
    assert code == 1
    assert "MISMATCH(state,reason)" in out
    assert out.splitlines()[-1].endswith("dbc_mismatch 30")


def test_a_log_python_can_cannot_read_is_a_file_error(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    bad = tmp_path / "junk.blf"
    bad.write_bytes(b"not a blf file at all" * 10)
    code, out, err = monitor(capsys, "--log", str(bad))
    assert code == 4 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("estop: error: --log ") and str(bad) in err
    code, _, err = monitor(capsys, "--log", str(bad.with_suffix(".xyz")))
    assert code == 4 and err.count("\n") == 1


@pytest.mark.parametrize("where", ["environment", "canrc"])
def test_the_bus_comes_from_python_cans_own_configuration(where: str, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """No --interface: python-can's CAN_INTERFACE/CAN_CHANNEL, or its ~/.canrc, name the bus
    (here python-can's virtual bus, with nothing on it: a silent bus is a failure, exit 1)."""
    channel = f"estop_cfg_{where}_{id(tmp_path)}"
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.chdir(tmp_path)  # python-can also reads ./can.ini
    monkeypatch.setenv("HOME", str(tmp_path))
    if where == "environment":
        monkeypatch.setenv("CAN_INTERFACE", "virtual")
        monkeypatch.setenv("CAN_CHANNEL", channel)
    else:
        (tmp_path / ".canrc").write_text(f"[default]\ninterface = virtual\nchannel = {channel}\n")
    code, out, err = monitor(capsys, "--duration-s", "0.2")
    assert (code, err) == (1, ""), err
    assert "no_brake_frame" in out.splitlines()[-1]
    # with none of them, the one-line error says where a bus is named
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.delenv("CAN_CHANNEL", raising=False)
    (tmp_path / ".canrc").unlink(missing_ok=True)
    code, out, err = monitor(capsys, "--duration-s", "0.2")
    assert code == 2 and out == "" and "--interface" in err and "~/.canrc" in err
