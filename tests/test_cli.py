"""The ``estop`` command line against real sockets on 127.0.0.1 (a small fake unit).

Everything here is loopback-only, bounded in time, and closes what it opens.
"""

from __future__ import annotations

import io
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from estop import cli
from estop.client.sender import Remote
from estop.model.wifi import WIFI, LinkConfig, LinkModel
from estop.protocol import auth, tcp, udp
from estop.protocol.can import BrakeFrame, StatusFrame
from estop.protocol.canlog import CanLogRecord, format_line
from estop.protocol.tcp import FrameAssembler, Reply, Request
from estop.protocol.udp import ControlPacket, Gear
from estop.remote import keys as remoteterm
from estop.remote.script import ScriptError, parse_script
from net_util import LOCAL, FakeUnitPorts, chunks, connections, datagrams, wait_until
from stall_probe import StallProbe

pytestmark = pytest.mark.timeout(60)

SRC = Path(__file__).resolve().parents[1] / "src"


# --------------------------------------------------------------------------- a fake unit

@dataclass
class FakeUnit(FakeUnitPorts):
    """Just enough of the unit for the CLI: a UDP port recording control packets (and stop and
    lift datagrams, which stop it) and a TCP stop port answering per spec section 3 (STOPPED
    latched, RELEASE needs a live, neutral link of >= 5 valid packets, udp timeout 200 ms).
    ``mode`` breaks the replies on purpose: ``silent`` (no reply), ``close`` (hang up),
    ``badcrc``, ``wrongseq``, ``split`` (reply in two pieces)."""

    mode: str = "normal"
    timeout: float = 0.2
    stop_id: int = tcp.DEFAULT_STOP_ID
    packets: list[tuple[float, bytes]] = field(default_factory=list)
    stop_datagrams: list[bytes] = field(default_factory=list)
    requests: list[Request] = field(default_factory=list)
    raw_requests: list[bytes] = field(default_factory=list)
    state: int = 0
    reason: int = 1
    valid_run: int = 0
    last_valid: ControlPacket | None = None
    last_valid_t: float = -1e9

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self._open_ports(0.05)

    # UDP side
    def _udp_loop(self) -> None:
        for data in datagrams(self.udp, self._stop):
            now = time.monotonic()
            with self.lock:
                if len(data) == auth.REQUEST_SIZE and data[:4] == auth.REQUEST_MAGIC:
                    self.stop_datagrams.append(data)
                    kind = auth.AuthRequest.decode(data, None).kind(self.stop_id)
                    if kind in ("stop", "lift"):
                        self._enter_stop(2 if kind == "stop" else 5)
                    continue
                self.packets.append((now, data))
                self._expire(now)
                if udp.is_valid(data):
                    self.last_valid = udp.decode(data)
                    self.last_valid_t = now
                    if self.state == 0:
                        self.valid_run += 1

    def _expire(self, now: float) -> None:
        if self.state == 1 and now - self.last_valid_t >= self.timeout:
            self._enter_stop(3)

    def _enter_stop(self, reason: int) -> None:
        if self.state == 1:
            self.state, self.reason = 0, reason
        self.valid_run = 0

    # TCP side
    def _tcp_loop(self) -> None:
        for conn in connections(self.tcp, self._stop):
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        asm = FrameAssembler()
        with conn:
            for chunk in chunks(conn, self._stop, 0.05):
                for frame in asm.feed(chunk):
                    self.raw_requests.append(frame)
                    try:
                        req = Request.decode(frame)
                    except tcp.CrcMismatch:
                        return
                    self.requests.append(req)
                    if self.mode == "silent":
                        continue
                    if self.mode == "close":
                        return
                    data = self.answer(req).encode()
                    if self.mode == "badcrc":
                        data = data[:12] + bytes(4)
                    if self.mode == "wrongseq":
                        data = Reply(True, req.seq + 1, self.state, self.reason).encode()
                    if self.mode == "split":
                        conn.sendall(data[:5])
                        time.sleep(0.05)
                        conn.sendall(data[5:])
                    else:
                        conn.sendall(data)

    def answer(self, req: Request) -> Reply:
        now = time.monotonic()
        with self.lock:
            self._expire(now)
            kind = req.kind(self.stop_id)
            nak = 0
            if kind in ("stop", "lift"):
                self._enter_stop(2 if kind == "stop" else 5)
            elif kind == "release" and self.state == 0:
                live = now - self.last_valid_t < self.timeout and self.valid_run >= 5
                if not live:
                    nak = tcp.NakCode.NO_LIVE_LINK
                elif self.last_valid is None or not self.last_valid.is_neutral:
                    nak = tcp.NakCode.NOT_NEUTRAL
                else:
                    self.state, self.reason = 1, 0
            elif kind == "unknown":
                nak = tcp.NakCode.UNKNOWN_MSG_ID
            return Reply(nak == 0, req.seq, self.state, self.reason, 0, nak)


@pytest.fixture
def unit() -> Iterator[FakeUnit]:
    u = FakeUnit()
    yield u
    u.close()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("estop: error: ")
    assert "Traceback" not in err
    return lines[0]


# ------------------------------------------------------------------------ one-shot commands

def test_stop_sends_the_spec_frame_and_prints_ack(unit: FakeUnit, capsys) -> None:
    code, out, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unit.tcp_port),
                             "--udp-port", str(unit.udp_port))
    assert code == 0 and err == ""
    assert unit.raw_requests == [bytes.fromhex("70E570E5010000000000000" "0DC09BF43")]
    assert out.strip() == "ACK seq=1 state=STOPPED reason=boot flags=0x00 (after 1 attempt)"
    wait_until(lambda: bool(unit.stop_datagrams))
    assert len(unit.stop_datagrams) == 1


def test_stop_seq_and_stop_id(unit: FakeUnit, capsys) -> None:
    unit.stop_id = 0x12345678
    code, out, _ = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--udp-port", str(unit.udp_port), "--seq", "0xFFFFFFFF",
                           "--stop-id", "0x12345678")
    assert code == 0
    assert unit.requests == [Request(0x12345678, 0xFFFFFFFF, 0)]
    assert "seq=4294967295" in out


def test_release_nak_exit_1(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--seq", "2")
    assert code == 1
    assert unit.raw_requests == [bytes.fromhex("02000000020000000000000" "08D5FCBD5")]
    assert out.strip() == "NAK seq=2 state=STOPPED reason=boot flags=0x00 nak=no_live_link"


def test_status_json(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "status", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["request"] == "status" and doc["reply"] == "ACK"
    assert doc["state"] == "STOPPED" and doc["reason"] == "boot" and doc["nak"] == "none"
    assert unit.requests == [Request(tcp.STATUS, 1)]


def test_reply_split_across_reads(capsys) -> None:
    u = FakeUnit(mode="split")
    try:
        code, out, _ = run_cli(capsys, "status", "--host", LOCAL, "--port", str(u.tcp_port))
    finally:
        u.close()
    assert code == 0 and out.startswith("ACK seq=1")


@pytest.mark.parametrize(("mode", "message"), [
    ("silent", "no reply"),
    ("close", "closed the connection"),
    ("badcrc", "CRC mismatch"),
    ("wrongseq", "does not match"),
])
@pytest.mark.parametrize("kind", ["status", "stop"])
def test_broken_replies_exit_3(mode: str, message: str, kind: str, capsys) -> None:
    u = FakeUnit(mode=mode)
    # Only the silent unit is waited out; the others answer (or close) at once, so a status
    # gives them 2 s, not 0.3: the fake unit is a thread of this process, and at load 10 it
    # was once later than 0.3 s ("no reply" instead of "closed the connection"). A tool that
    # missed the answer would wait the 2 s out and say "no reply", which fails the message.
    timeout = "0.3" if mode == "silent" or kind == "stop" else "2"
    argv = [kind, "--host", LOCAL, "--port", str(u.tcp_port), "--timeout", timeout]
    if kind == "stop":
        argv += ["--udp-port", str(u.udp_port), "--stop-deadline", "0.5"]
    try:
        t0 = time.monotonic()
        code, out, err = run_cli(capsys, *argv)
        assert time.monotonic() - t0 < 3
        if kind == "stop":
            wait_until(lambda: bool(u.stop_datagrams))
    finally:
        u.close()
    assert code == 3 and out == ""
    line = one_error_line(err)
    assert message in line
    if kind == "stop":  # the stop button tried again until its deadline
        assert "no ACK within 0.5 s: " in line and u.stop_datagrams
        assert len(u.requests) >= (1 if mode == "silent" else 2)


def test_connection_refused_exit_3(capsys) -> None:
    code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", str(free_port()))
    assert code == 3 and out == ""
    assert "cannot connect" in one_error_line(err)


@pytest.mark.parametrize("argv", [
    ["stop"],
    ["stop", "--host", LOCAL, "--port", "0"],
    ["stop", "--host", LOCAL, "--port", "70000"],
    ["stop", "--host", LOCAL, "--stop-id", "1"],
    ["stop", "--host", LOCAL, "--stop-id", "0x100000000"],
    ["release", "--host", LOCAL, "--seq", "-1"],
    ["status", "--host", LOCAL, "--timeout", "0"],
    ["status", "--host", LOCAL, "--timeout", "nan"],
    ["lift", "--host", LOCAL, "--udp-port", "0"],
    ["lift", "--host", LOCAL, "--tcp-port", "x"],
    ["lift", "--host", LOCAL, "--stop-deadline", "1"],  # no retries: a stop button's option
    ["frobnicate"],
    [],
    ["monitor"],
    ["monitor", "--log", "x", "--interface", "virtual"],
    ["remote", "--host", LOCAL, "--script", "hold 1; fly"],
    ["remote", "--host", LOCAL, "--script", "gas 2"],
    ["remote", "--host", LOCAL, "--loss", "60", "--burst", "1", "--script", "hold 1"],
    ["remote", "--host", LOCAL, "--rate", "-5", "--script", "hold 1"],
    ["remote", "--host", LOCAL, "--rate-hz", "0", "--script", "hold 1"],
    ["monitor", "-c", "vcan0", "--log", "x"],  # a channel needs an interface
])
def test_usage_errors_one_line_exit_2(argv: list[str], capsys) -> None:
    code = cli.main(argv)
    cap = capsys.readouterr()
    assert code == 2, cap
    one_error_line(cap.err)
    assert cap.out == ""


def test_subprocess_entry_point_no_traceback() -> None:
    env = {**os.environ, "PYTHONPATH": str(SRC) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for argv, want in ((["status", "--host", LOCAL, "--port", str(free_port())], 3),
                       (["stop", "--host", LOCAL, "--stop-id", "zz"], 2),
                       (["monitor", "--log", "/nonexistent/estop.log"], 4)):
        proc = subprocess.run([sys.executable, "-m", "estop", *argv], env=env, timeout=30,
                              capture_output=True, text=True, check=False)
        assert proc.returncode == want, proc
        one_error_line(proc.stderr)


def test_version(capsys) -> None:
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == "estop 1.0.0"
    assert cli.main(["monitor", "--help"]) == 0
    assert "-i IF, --interface IF" in capsys.readouterr().out
    assert cli.main(["lift", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--tcp-port PORT" in text and "--port" not in text  # the older name works, unlisted


# ------------------------------------------------------------------------------ demo slot

def test_demo_slot_dispatches_to_estop_demo(monkeypatch, capsys) -> None:
    from estop.commands import demo

    seen: list[list[str]] = []
    monkeypatch.setattr(demo, "main", lambda argv=None: seen.append(argv) or 5)
    assert cli.main(["demo", "--fast", "x"]) == 5
    assert seen == [["--fast", "x"]]


# ------------------------------------------------------------------------------- monitor

T0 = 1_700_000_000.0


def brake(t: float, counter: int, state: int = 1, reason: int = 0) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x050,
                           BrakeFrame.for_state(state, reason, 0, counter % 15).encode())


def status(t: float, counter: int) -> CanLogRecord:
    return CanLogRecord.at(t, "vcan0", 0x051,
                           StatusFrame(5, 0, 0, 1, 12, counter % 15).encode())


def clean_log(n: int = 40) -> list[CanLogRecord]:
    recs = []
    for i in range(n):
        recs.append(brake(T0 + i * 0.010, i))
        if i % 10 == 0:
            recs.append(status(T0 + i * 0.010 + 0.001, i // 10))
    return recs


def write_log(path: Path, recs: list[CanLogRecord]) -> str:
    path.write_text("".join(format_line(r) + "\n" for r in recs))
    return str(path)


def test_monitor_clean_log(tmp_path: Path, capsys) -> None:
    code, out, err = run_cli(capsys, "monitor", "--log", write_log(tmp_path / "a.log",
                                                                   clean_log()))
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert lines[-1] == "summary: 44 frames, 44 accepted; problems: none"
    assert lines[-2] == "brake commands: release 40, controlled 0, emergency 0"
    # v3: each ESTOP_BRAKE line ends with what the brake controller does on it
    assert lines[0] == ("(1700000000.000000) 050 ESTOP_BRAKE ARMED reason=none brake=0 "
                        "level=0 flags=0x00 ctr=0 => release")
    assert lines[1] == ("(1700000000.001000) 051 ESTOP_STATUS valid=5 invalid=0 auth_failures=0 "
                        "stops=1 link_age=12ms ctr=0")
    assert "!" not in out


def test_monitor_flags_crc_jump_gap(tmp_path: Path, capsys) -> None:
    recs = [brake(T0 + i * 0.010, i) for i in range(10)]            # counters 0..9, fine
    bad = bytearray(brake(T0 + 0.095, 10).data)
    bad[7] ^= 0x5A
    recs.append(CanLogRecord.at(T0 + 0.095, "vcan0", 0x050, bytes(bad)))  # extra, bad CRC
    recs += [brake(T0 + 0.100, 10), brake(T0 + 0.110, 13)]           # jump: 11, 12 lost
    recs += [brake(T0 + 0.120, 14), brake(T0 + 0.180, 0)]            # 60 ms gap
    recs += [brake(T0 + 0.190, 1, 0, 2)]                             # state change
    recs += [CanLogRecord.at(T0 + 0.2, "vcan0", 0x123, b"\x00")]     # other ID: ignored
    code, out, _ = run_cli(capsys, "monitor", "--log", write_log(tmp_path / "b.log", recs))
    assert code == 1
    assert "(1700000000.095000) 050 ! bad_crc: CRC " in out
    assert "(1700000000.110000) 050 ! counter_jump: counter 11 expected, got 13 (2 lost)" in out
    assert "(1700000000.180000) 050 ! gap: 60.0 ms without a good frame (limit 50 ms)" in out
    assert ("STOPPED reason=tcp_stop brake=1 level=100 flags=0x00 ctr=1 => EMERGENCY  "
            "<- state change") in out
    # the frame with the bad CRC did not come whole from the unit: it commands nothing
    assert "flags=0x00 ctr=10  [rejected]" in out
    assert out.splitlines()[-1] == ("summary: 16 frames, 15 accepted; problems: bad_crc 1, "
                                    "counter_jump 1, gap 1")


def test_monitor_bad_crc_in_place_also_costs_a_counter(tmp_path: Path, capsys) -> None:
    recs = clean_log(10)
    bad = bytearray(recs[5].data)
    bad[7] ^= 1
    recs[5] = CanLogRecord(recs[5].timestamp_us, "vcan0", 0x050, bytes(bad))
    code, out, _ = run_cli(capsys, "monitor", "-q", "--log", write_log(tmp_path / "c.log", recs))
    assert code == 1
    assert out.splitlines()[-1].endswith("problems: bad_crc 1, counter_jump 1")
    assert "ESTOP_BRAKE" not in out  # quiet: only problems and the summary


def test_monitor_stdin_and_timeout_option(monkeypatch, capsys) -> None:
    recs = [brake(T0, 0), brake(T0 + 0.030, 1)]
    monkeypatch.setattr(sys, "stdin", io.StringIO("".join(format_line(r) + "\n" for r in recs)))
    code, out, _ = run_cli(capsys, "monitor", "--log", "-", "--timeout-ms", "25")
    assert code == 1 and "! gap: 30.0 ms" in out


def test_monitor_bad_inputs(tmp_path: Path, capsys) -> None:
    path = tmp_path / "junk.log"
    path.write_text(format_line(brake(T0, 0)) + "\nthis is not a log line\n")
    code, _, err = run_cli(capsys, "monitor", "--log", str(path))
    assert code == 4 and "line 2" in one_error_line(err)
    code, _, err = run_cli(capsys, "monitor", "--log", str(tmp_path / "missing.log"))
    assert code == 4 and "No such file" in one_error_line(err)
    code, _, err = run_cli(capsys, "monitor", "--interface", "no_such_interface_xyz")
    assert code == 2 and one_error_line(err)  # python-can knows no such interface


def test_monitor_virtual_bus(capsys) -> None:
    can = pytest.importorskip("can")
    channel = f"estop_test_{os.getpid()}_{time.monotonic_ns()}"
    sent_at: list[float] = []  # the frames' own stamps, as the monitor reads them

    def monitor_listening() -> bool:
        # python-can's virtual bus keeps one queue per open end, by channel
        from can.interfaces import virtual
        return len(getattr(virtual, "channels", {}).get(channel, ())) >= 2

    def send() -> None:
        with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
            deadline = time.monotonic() + 5
            while not monitor_listening() and time.monotonic() < deadline:
                time.sleep(0.01)
            for i in range(5):
                sent_at.append(time.time())
                bus.send(can.Message(arbitration_id=0x050, is_extended_id=False,
                                     timestamp=sent_at[-1],
                                     data=BrakeFrame.for_state(1, 0, 0, i).encode()))
                time.sleep(0.01)
            # then silence: the monitor reports a timeout while it lasts

    sender = threading.Thread(target=send)
    with StallProbe() as probe:
        sender.start()
        try:
            code, out, _ = run_cli(capsys, "monitor", "--interface", "virtual", "--channel",
                                   channel, "--duration", "0.8")
        finally:
            sender.join(timeout=5)
    assert code == 1
    assert out.count("ESTOP_BRAKE ARMED") == 5
    assert "! timeout: no good ESTOP_BRAKE for" in out
    summary = out.splitlines()[-1]
    # The sender sleeps 10 ms between frames; a gap of 50 ms between their own stamps is a
    # gap the monitor must count, whoever caused it (on a loaded machine, the sender stalls).
    gaps = sum(b - a >= 0.05 for a, b in zip(sent_at, sent_at[1:], strict=False))
    if gaps == 0 and probe.worst_s < 0.03:
        assert summary == "summary: 5 frames, 5 accepted; problems: timeout 1"
    else:
        # A stalled machine: the gaps exactly, and the timeouts that silences of the sender
        # (before its first frame, in a gap) or a late monitor add to the final one.
        assert summary.startswith("summary: 5 frames, 5 accepted; problems: "), summary
        found = dict(p.split(" ") for p in summary.split("problems: ")[1].split(", "))
        assert set(found) <= {"gap", "timeout"}, (summary, str(probe))
        assert int(found.get("gap", 0)) == gaps, (summary, sent_at, str(probe))
        assert int(found["timeout"]) >= 1, (summary, str(probe))


# -------------------------------------------------------------------------------- remote

def intervals(times: list[float]) -> list[float]:
    return [b - a for a, b in zip(times, times[1:], strict=False)]


def test_remote_script_sends_at_rate_with_exact_content(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script", "hold 1.0; lift 0.1")
    assert code == 0
    wait_until(lambda: len(unit.packets) >= 35)
    datas = [d for _, d in unit.packets]
    assert 35 <= len(datas) <= 60  # 50 Hz for 1 s, roughly
    assert set(datas) == {bytes.fromhex("00000000 00000000 04000000 00000000 00000000")}
    gaps = intervals([t for t, _ in unit.packets])
    assert 0.016 <= statistics.median(gaps) <= 0.024
    assert f"summary: {len(datas)} packets sent, {len(datas)} delivered, 0 lost" in out


def test_remote_full_script_against_fake_unit(unit: FakeUnit, capsys) -> None:
    script = ("hold 0.3; release; expect ack armed; drive 0.3 0.2; steer -0.25; signal left; "
              "horn on; wait 0.1; lift; wait 0.1; status; expect stopped lift; "
              "stop; expect ack stopped lift")
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--rate", "100", "--script", script)
    assert code == 0, out
    assert "release -> ACK seq=1 state=ARMED reason=none flags=0x00" in out
    # v3: the lift datagrams stop the unit at once, with reason lift
    assert "lift: lift sent x3" in out
    assert "status -> ACK seq=2 state=STOPPED reason=lift" in out
    assert "stop -> ACK seq=3 state=STOPPED reason=lift" in out
    assert [r.msg_id for r in unit.requests] == [tcp.RELEASE, tcp.STATUS, tcp.DEFAULT_STOP_ID]
    pkts = [udp.decode(d) for _, d in unit.packets]
    # neutral, then drive at 0.3, back to gas 0 in drive, then steering/signal/horn
    distinct = list(dict.fromkeys(pkts))
    f32 = udp.decode(ControlPacket(0.3).encode()).gas_brake
    expected = [ControlPacket(), ControlPacket(f32, 0.0, Gear.DRIVE),
                ControlPacket(0.0, 0.0, Gear.DRIVE), ControlPacket(0.0, -0.25, Gear.DRIVE),
                ControlPacket(0.0, -0.25, Gear.DRIVE, 1),
                ControlPacket(0.0, -0.25, Gear.DRIVE, 1, 1)]
    # the quick steer/signal/horn changes may fall between two packets: a subsequence
    assert distinct[:2] == expected[:2] and distinct[-1] == expected[-1]
    assert [p for p in expected if p in distinct] == distinct
    assert unit.packets[-1][1] == bytes.fromhex("00000000 000080BE 08000000 01000000 01000000")


def test_remote_expect_failure_exit_1(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script",
                           "release; expect ack; status")
    assert code == 1
    assert "expect failed: expect ack: got NAK seq=1" in out
    assert len(unit.requests) == 1  # the script stopped at the failed expect


def test_remote_script_file_and_legacy(unit: FakeUnit, tmp_path: Path, capsys) -> None:
    script = tmp_path / "drive.txt"
    script.write_text("# a comment line\nhold 0.2   # finger down\n\nlift\n")
    code, _, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                         "--tcp-port", str(unit.tcp_port), "--legacy", "-q",
                         "--script-file", str(script))
    assert code == 0
    wait_until(lambda: bool(unit.packets))
    assert unit.packets and all(len(d) == 16 and udp.is_valid(d) for _, d in unit.packets)


def test_remote_bad_script_sends_nothing(unit: FakeUnit, capsys) -> None:
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--script", "hold 0.2; gear sport")
    assert code == 2 and "'gear sport'" in one_error_line(err)
    time.sleep(0.1)
    assert unit.packets == [] and unit.requests == []


def test_remote_tcp_refused_exit_3(unit: FakeUnit, capsys) -> None:
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(free_port()), "--stop-deadline", "0.5",
                           "--script", "hold 0.1; stop")
    line = one_error_line(err)
    assert code == 3 and "cannot connect" in line and "no ACK within 0.5 s" in line
    wait_until(lambda: bool(unit.stop_datagrams))
    assert unit.stop_datagrams  # the stop datagram went out all the same


def test_remote_interactive_needs_a_terminal(monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL)
    assert code == 2 and "terminal" in one_error_line(err)


def test_remote_loss_via_cli(unit: FakeUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--rate", "200", "--loss", "30",
                           "--burst", "2", "--seed", "7", "--script", "hold 1.0; lift 0.05")
    assert code == 0
    summary = out.splitlines()[-1]
    sent = int(summary.split()[1])
    delivered = int(summary.split()[4])
    wait_until(lambda: len(unit.packets) >= delivered)
    assert delivered == len(unit.packets)
    assert 0.15 <= 1 - delivered / sent <= 0.45


def test_remote_api_delay_and_hook(unit: FakeUnit) -> None:
    log: list[tuple[float, bytes, float | None]] = []
    cfg = LinkConfig(delay=0.1, jitter=0.02)
    with Remote(LOCAL, unit.udp_port, unit.tcp_port, rate_hz=50, link=cfg, seed=1,
                on_packet=lambda t, d, td: log.append((t, d, td))) as r:
        t_hold = time.monotonic()
        r.hold()
        time.sleep(0.3)
        r.lift()
        assert r.held is False
    # close() flushed the packets in flight
    wait_until(lambda: len(unit.packets) >= r.stats.delivered)
    assert len(unit.packets) == len(log) == r.stats.delivered
    first_arrival = unit.packets[0][0]
    assert first_arrival - t_hold >= 0.1
    for t, _, td in log:
        assert td is not None and 0.1 <= td - t <= 0.12 + 1e-9


def test_remote_api_control_and_requests(unit: FakeUnit) -> None:
    with Remote(LOCAL, unit.udp_port, unit.tcp_port, rate_hz=100) as r:
        assert r.status().state == 0
        r.hold()
        time.sleep(0.15)
        reply = r.release()
        assert reply.ack and reply.state == 1
        r.set_control(gas_brake=0.5, gear=Gear.DRIVE)
        time.sleep(0.05)
        again = r.release()  # RELEASE while ARMED: acknowledged, changes nothing
        assert again.ack and again.state == 1
        with pytest.raises(udp.InvalidPacket):
            r.set_control(steering=3.0)
        with pytest.raises(udp.InvalidPacket):
            r.set_control(gear=3)
        assert r.control == ControlPacket(0.5, 0.0, Gear.DRIVE)
        r.rate_hz = 20
        assert r.rate_hz == 20
        stop = r.stop()
        assert stop.ack and (stop.state, stop.reason) == (0, 2)
        assert r.stats.requests == 4
    assert unit.requests[-1] == Request(tcp.DEFAULT_STOP_ID, 4)


def test_remote_handle_key(unit: FakeUnit) -> None:
    r = Remote(LOCAL, unit.udp_port, unit.tcp_port)
    try:
        assert remoteterm.handle_key(r, " ") is None and r.held
        remoteterm.handle_key(r, " ")
        assert not r.held
        remoteterm.handle_key(r, "\x1b[A")
        remoteterm.handle_key(r, "\x1b[A")
        remoteterm.handle_key(r, "\x1b[D")
        assert (r.control.gas_brake, r.control.steering) == (0.2, -0.1)
        for _ in range(30):
            remoteterm.handle_key(r, "\x1b[B")
        assert r.control.gas_brake == -1.0
        remoteterm.handle_key(r, "g")
        assert r.control.gear == Gear.DRIVE
        remoteterm.handle_key(r, "g")
        assert r.control.gear == Gear.PARK
        remoteterm.handle_key(r, "h")
        remoteterm.handle_key(r, "2")
        assert (r.control.horn, r.control.turn_signal) == (1, 2)
        remoteterm.handle_key(r, "n")
        assert (r.control.gas_brake, r.control.gear) == (0.0, Gear.NEUTRAL)
        line = remoteterm.handle_key(r, "t")
        assert line == "status -> ACK seq=1 state=STOPPED reason=boot flags=0x00"
        assert remoteterm.handle_key(r, "q") == "quit"
        assert list(remoteterm._split_keys("a\x1b[Ab")) == ["a", "\x1b[A", "b"]
    finally:
        r.close()


def test_parse_script() -> None:
    steps = parse_script("hold 1.0; release\n drive 0.3 2.0 # go\nlift; wait 0.5; stop; "
                         "gear P; signal both; horn off; rate 20; expect NAK no_live_link")
    assert [s.op for s in steps] == ["hold", "release", "drive", "lift", "wait", "stop", "gear",
                                     "signal", "horn", "rate", "expect"]
    assert steps[0].args == (1.0,) and steps[2].args == (0.3, 2.0) and steps[3].args == ()
    assert steps[6].args == (1,) and steps[7].args == (3,) and steps[8].args == (0,)
    assert steps[10].words == ("nak", "no_live_link")
    for bad, msg in [("", "empty"), ("hold -1", "out of range"), ("wait", "takes 1"),
                     ("gas nan", "out of range"), ("steer x", "not a number"),
                     ("expect maybe", "unknown word"), ("stop now", "takes 0"),
                     ("drive 0.1 1 2", "takes 1 or 2"), ("launch", "unknown command"),
                     ("signal up", "unknown"), ("rate 0", "out of range")]:
        with pytest.raises(ScriptError, match=msg):
            parse_script(bad)


# ---------------------------------------------------------------------------- link model

def burst_lengths(lost: list[bool]) -> list[int]:
    runs, n = [], 0
    for x in lost:
        if x:
            n += 1
        elif n:
            runs.append(n)
            n = 0
    return runs


@pytest.mark.parametrize(("loss", "burst"), [(0.09, 1.0), (0.09, 2.0), (0.3, 3.0), (0.5, 1.0)])
def test_link_model_loss_statistics(loss: float, burst: float) -> None:
    model = LinkModel(LinkConfig(loss=loss, burst=burst), seed=12345)
    lost = [model.lose_next() for _ in range(40_000)]
    frac = sum(lost) / len(lost)
    assert abs(frac - loss) < 0.15 * loss
    assert model.stats.loss_fraction == frac and model.stats.sent == 40_000
    assert abs(statistics.mean(burst_lengths(lost)) - burst) < 0.1 * burst
    assert model.stats.longest_burst == max(burst_lengths(lost))


def test_link_model_wifi_delay_and_order() -> None:
    model = LinkModel(WIFI, seed=3)
    times = [model.transmit(i * 0.02) for i in range(5000)]
    got = [(i * 0.02, t) for i, t in enumerate(times) if t is not None]
    assert all(WIFI.delay <= t - s <= WIFI.delay + WIFI.jitter + 0.02 for s, t in got)
    arrivals = [t for _, t in got]
    assert arrivals == sorted(arrivals)  # never reordered
    assert abs(1 - len(got) / 5000 - 0.09) < 0.02


def test_link_model_seeded_and_edge_cases() -> None:
    a = LinkModel(WIFI, seed=99)
    b = LinkModel(WIFI, seed=99)
    assert [a.transmit(i / 50) for i in range(500)] == [b.transmit(i / 50) for i in range(500)]
    ideal = LinkModel()
    assert all(ideal.transmit(float(i)) == float(i) for i in range(100))
    dead = LinkModel(LinkConfig(loss=1.0))
    assert all(dead.transmit(0.0) is None for _ in range(100)) and dead.stats.lost == 100
    for cfg, msg in [(LinkConfig(loss=1.5), "loss"), (LinkConfig(burst=0.5), "burst"),
                     (LinkConfig(delay=-1), "delay"), (LinkConfig(loss=0.6), "impossible")]:
        with pytest.raises(ValueError, match=msg):
            LinkModel(cfg)
    LinkModel(LinkConfig(loss=0.6, burst=2.0))  # possible with longer bursts
