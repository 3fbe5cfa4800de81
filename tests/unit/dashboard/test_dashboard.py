"""``estop dashboard`` without a browser: the model's rules (NO SIGNAL, bad input counted,
the timeline's causes, stops by reason), the link box against ``estop link`` on the same log,
the file follower, the server's rate limit and its STOP button against a real estopd, and the
command line. The page itself is tested in tests/browser/test_dashboard_browser.py."""

from __future__ import annotations

import argparse
import asyncio
import http.client
import json
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from daemon_util import ARMED, R_TCP_STOP, STOPPED, Daemon
from estop.cli import build_parser
from estop.cli import main as estop_main
from estop.commands.dashboard import bus_config
from estop.commands.options import parse_listen
from estop.commands.settings import resolve_settings
from estop.dashboard.feed import FileFollower
from estop.dashboard.model import NO_SIGNAL, DashboardModel
from estop.dashboard.server import MIN_INTERVAL, DashboardServer, stop_action_for
from estop.protocol.can import BrakeFrame, Reason, State, StatusFrame
from link_util import arrivals_us, gilbert_lost, simulate_unit, unit_log

T0 = 1_800_000_000.0


class Unit:
    """Good ESTOP_BRAKE / ESTOP_STATUS frames with running alive counters."""

    def __init__(self) -> None:
        self.ctr = {0x50: 0, 0x51: 0}

    def brake(self, state: State, reason: Reason = Reason.NONE) -> bytes:
        c = self.ctr[0x50]
        self.ctr[0x50] = (c + 1) % 15
        return BrakeFrame.for_state(state, reason, counter=c).encode()

    def status(self, invalid: int = 0) -> bytes:
        c = self.ctr[0x51]
        self.ctr[0x51] = (c + 1) % 15
        return StatusFrame(valid_packets=5, invalid_packets=invalid, auth_failures=0, stops=0,
                           slowdowns=0, link_age_ms=20, counter=c).encode()


def feed_brake(model: DashboardModel, unit: Unit, t: float, state: State,
               reason: Reason = Reason.NONE) -> None:
    model.frame(t, 0x50, unit.brake(state, reason), t + 0.002)


def test_states_no_signal_timeline_and_stops() -> None:
    m, u = DashboardModel(), Unit()
    assert m.snapshot(T0)["state"] == NO_SIGNAL  # nothing yet: silence is a failure
    feed_brake(m, u, T0, State.STOPPED, Reason.BOOT)
    assert m.snapshot(T0 + 0.01)["state"] == "STOPPED"
    t = T0
    for state, reason in ((State.ARMED, Reason.NONE), (State.SLOWING, Reason.NONE),
                          (State.STOPPED, Reason.UDP_TIMEOUT), (State.ARMED, Reason.NONE),
                          (State.STOPPED, Reason.LIFT)):
        for _ in range(3):
            t += 0.01
            feed_brake(m, u, t, state, reason)
    snap = m.snapshot(t + 0.01)
    assert (snap["state"], snap["reason"]) == ("STOPPED", "lift")
    assert snap["brake"] == "EMERGENCY"
    assert snap["stops"] == {"udp timeout": 1, "lift": 1}
    assert [(c["state"], c["reason"]) for c in snap["timeline"]][:3] == [
        ("STOPPED", "lift"), ("ARMED", ""), ("STOPPED", "udp timeout")]
    # 50 ms without a good frame: NO SIGNAL, dated when the silence began
    assert m.snapshot(t + 0.049)["state"] == "STOPPED"
    snap = m.snapshot(t + 0.0521)
    assert snap["state"] == NO_SIGNAL
    assert snap["timeline"][0]["state"] == NO_SIGNAL
    assert snap["timeline"][0]["t"] == pytest.approx(t + 0.05)
    assert m.deadline(t + 0.06) is None
    # the next frame comes late but stamped 20 ms after the last: the feed was late, not the unit
    m.frame(t + 0.02, 0x50, u.brake(State.STOPPED, Reason.LIFT), t + 0.06)
    tl = m.snapshot(t + 0.06)["timeline"]
    assert tl[0]["state"] == "STOPPED" and "the feed was late" in tl[1]["cause"]


def test_bad_input_is_counted_never_fatal() -> None:
    m, u = DashboardModel(), Unit()
    feed_brake(m, u, T0, State.ARMED)
    m.can_line("garbage\n", T0)
    m.can_line("(1800000000.010000) estop 050#0000010000000300\n", T0)  # CRC wrong
    m.can_line("(1800000000.020000) estop 050#00\n", T0)  # too short
    m.log_line("not json at all\n", T0)
    m.log_line("[1, 2]\n", T0)
    m.log_line('{"event": "link_histogram", "edges_us": "x"}\n', T0)
    snap = m.snapshot(T0 + 0.03)
    assert snap["state"] == "ARMED"  # the forged ARMED did not count; the old one still holds
    assert snap["inputs"]["can_bad"] == 1 and snap["inputs"]["log_bad"] == 2
    assert snap["inputs"]["link_bad"] == 1
    assert snap["health"]["errors"]["bad_crc"] == 1
    assert snap["health"]["errors"]["bad_length"] == 1
    json.dumps(snap)  # what the server sends


def test_status_fields_come_from_the_dbc() -> None:
    m, u = DashboardModel(), Unit()
    for i in range(3):
        m.frame(T0 + i * 0.1, 0x51, u.status(invalid=2), T0 + i * 0.1)
    rows = {r["name"]: r for r in m.snapshot(T0)["status"]}
    assert set(rows) == {"valid_packets", "invalid_packets", "auth_failures", "stops",
                         "slowdowns", "link_age"}
    assert rows["invalid_packets"]["total"] == 6 and rows["link_age"]["value"] == "20"
    assert rows["link_age"]["unit"] == "ms" and "Time since" in rows["link_age"]["comment"]


def test_log_gives_causes_and_sources() -> None:
    m, u = DashboardModel(), Unit()
    feed_brake(m, u, T0, State.STOPPED, Reason.BOOT)
    m.log_line('{"t_mono": 5.0, "event": "start", "slow_ms": 200, "timeout_ms": 1000}', T0)
    feed_brake(m, u, T0 + 0.01, State.ARMED)
    m.log_line('{"t_mono": 5.1, "event": "state", "from": "STOPPED", "to": "ARMED", '
               '"reason": "none", "src": "10.0.0.7:4000", "cause": "release"}', T0 + 0.012)
    # the log first, the frame after: still matched
    m.log_line('{"t_mono": 5.2, "event": "state", "from": "ARMED", "to": "STOPPED", '
               '"reason": "lift", "src": "10.0.0.7:4000", "cause": "lift"}', T0 + 0.019)
    feed_brake(m, u, T0 + 0.02, State.STOPPED, Reason.LIFT)
    tl = m.snapshot(T0 + 0.021)["timeline"]
    assert (tl[0]["state"], tl[0]["cause"], tl[0]["src"]) == ("STOPPED", "lift", "10.0.0.7:4000")
    assert (tl[1]["state"], tl[1]["cause"]) == ("ARMED", "release")
    assert m.snapshot(T0)["unit"]["slow_ms"] == 200


def test_a_log_read_from_its_start_is_not_silent_while_it_is_caught_up() -> None:
    m, u = DashboardModel(), Unit()
    now = T0 + 3600.0  # an hour-old log, read now at 10 000 lines a second
    for i in range(200):
        m.frame(T0 + i * 0.01, 0x50, u.brake(State.ARMED), now)
        assert m.snapshot(now)["state"] == "ARMED"
        now += 0.0001
    assert all(c["state"] != NO_SIGNAL for c in m.snapshot(now)["timeline"])
    # a silence in what was caught up is in the timeline all the same, dated when it began
    m.frame(T0 + 2.1, 0x50, u.brake(State.ARMED), now)
    tl = m.snapshot(now)["timeline"]
    assert [(c["state"], c["source"]) for c in tl[:2]] == [("ARMED", "frames"),
                                                           (NO_SIGNAL, "silence")]
    assert tl[1]["t"] == pytest.approx(T0 + 1.99 + 0.05) and "110 ms" in tl[1]["cause"]
    # and then nothing comes: NO SIGNAL 50 ms later
    assert m.snapshot(now + 0.06)["state"] == NO_SIGNAL


def test_link_box_is_estop_link_on_the_same_log(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    t_us = arrivals_us(gilbert_lost(50 * 3600, 0.05, 3.0, 7))
    text = unit_log([(t_us, simulate_unit(t_us, 200_000, 600_000))])
    path = tmp_path / "estopd.log"
    path.write_text(text)
    assert estop_main(["link", "--json", str(path)]) == 0
    want = json.loads(capsys.readouterr().out)
    m = DashboardModel()
    for line in text.splitlines():
        m.log_line(line, T0)
    link = m.snapshot(T0)["link"]
    assert link["error"] == ""
    assert link["loss"] == pytest.approx(want["loss"], rel=1e-9)
    assert link["mean_burst"] == pytest.approx(want["mean_burst"], rel=1e-9)
    rows = {r["what"]: r for r in link["rows"]}
    for what, key in (("slow-downs", "slowdowns_check"), ("emergency stops", "timeouts_check")):
        chk = want["unit"][key]
        assert rows[what]["time_ms"] == chk["time_ms"]
        assert rows[what]["model_per_hour"] == pytest.approx(chk["model_per_hour"], rel=1e-2)
        assert rows[what]["recorded"] == chk["recorded"]
        assert rows[what]["verdict"] == chk["verdict"]


def test_follower_reads_what_is_appended_and_starts_again_on_truncation(tmp_path: Path) -> None:
    path = tmp_path / "can.log"
    path.write_text("one\ntw")
    got: list[str] = []
    notes: list[str] = []

    async def go() -> None:
        f = FileFollower(str(path), lambda line, t: got.append(line), notes.append)
        f.start(asyncio.get_running_loop())
        await asyncio.sleep(0.1)
        with path.open("a") as fh:
            fh.write("o\nthree\n")
        await asyncio.sleep(0.1)
        path.write_text("new\n")  # truncated and written again
        await asyncio.sleep(0.1)
        os.replace(tmp_path / "can.log", tmp_path / "old.log")
        (tmp_path / "can.log").write_text("rotated\n")
        await asyncio.sleep(0.1)
        f.close()

    asyncio.run(asyncio.wait_for(go(), 10))
    assert got == ["one", "two", "three", "new", "rotated"], got


async def _read_events(url: str, seconds: float, enough: int = 0,
                       until: Callable[[dict[str, Any]], bool] | None = None,
                       ) -> list[dict[str, Any]]:
    """The updates of ``seconds`` (or fewer, once ``enough`` came or one met ``until``)."""
    events: list[dict[str, Any]] = []
    async with aiohttp.ClientSession() as session, session.get(url + "events") as resp:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (enough and len(events) >= enough) \
                and not (until and events and until(events[-1])):
            try:
                line = await asyncio.wait_for(resp.content.readline(), end - time.monotonic())
            except TimeoutError:
                break
            if line.startswith(b"data: "):
                events.append(json.loads(line[6:]))
    return events


def test_server_sends_at_most_20_updates_a_second() -> None:
    async def go() -> tuple[list[dict[str, Any]], int]:
        server = DashboardServer(DashboardModel(), "127.0.0.1", 0)
        await server.start()
        u = Unit()

        async def frames() -> None:
            for i in range(150):  # 100 ESTOP_BRAKE a second, a state change every 10
                state = State.ARMED if (i // 10) % 2 else State.SLOWING
                now = time.time()
                server.frame(now, 0x50, u.brake(state))
                await asyncio.sleep(0.01)

        try:
            task = asyncio.get_running_loop().create_task(frames())
            events = await _read_events(f"http://127.0.0.1:{server.port}/", 1.5)
            await task
            return events, server.pushes
        finally:
            await server.close()

    events, pushes = asyncio.run(asyncio.wait_for(go(), 20))
    assert events and pushes
    times = [e["now"] for e in events]
    # no two pushes closer than the minimum interval (a little slack for the clock's reading)
    assert min(b - a for a, b in zip(times, times[1:], strict=False)) >= MIN_INTERVAL * 0.9


def test_stop_button_only_with_allow_stop_and_it_stops(tmp_path: Path, estopd: str) -> None:
    # a timeout longer than the test, so that only the button can stop the unit
    with Daemon(tmp_path, "--timeout-ms", "60000") as d:
        d.arm()
        # the can-log comes from the daemon's output thread, behind its frames: count from
        # the first ARMED frame on (before it, the boot's STOPPED frames)
        d.wait_frame(lambda f: f.can_id == 0x50 and f.state == ARMED)
        seen = len(d.frames())

        async def go() -> tuple[int, int, int, dict[str, Any]]:
            plain = DashboardServer(DashboardModel(), "127.0.0.1", 0)
            armed = DashboardServer(DashboardModel(), "127.0.0.1", 0, stop_action=stop_action_for(
                "127.0.0.1", d.tcp_port, d.udp_port, key=None, remote_id=1,
                stop_id=0xE570E570, timeout=2.0, deadline=3.0))
            await plain.start()
            await armed.start()
            try:
                async with aiohttp.ClientSession() as s:
                    url = f"http://127.0.0.1:{plain.port}/stop"
                    async with s.post(url, headers={"X-Estop-Stop": "1"}) as r:
                        no_stop = r.status
                    url = f"http://127.0.0.1:{armed.port}/stop"
                    async with s.post(url) as r:
                        no_header = r.status
                    for path in ("/release", "/drive"):
                        async with s.post(f"http://127.0.0.1:{armed.port}{path}") as r:
                            assert r.status in (404, 405)
                    async with s.post(url, headers={"X-Estop-Stop": "1"}) as r:
                        return no_stop, no_header, r.status, await r.json()
            finally:
                await plain.close()
                await armed.close()

        no_stop, no_header, status, body = asyncio.run(asyncio.wait_for(go(), 20))
        assert (no_stop, no_header, status) == (403, 403, 200)
        assert "ACK" in body["outcome"] and "STOPPED" in body["outcome"], body
        frame = d.wait_frame(lambda f: f.can_id == 0x50 and f.state == STOPPED, after=seen)
        assert frame.reason == R_TCP_STOP
        assert d.request(1, 9).state == STOPPED != ARMED


@pytest.mark.parametrize("argv, message", [
    ([], "name an input"),
    (["--log", "x", "--channel", "vcan0"], "no CAN bus: give --interface"),
    (["--can-log", "-", "--log", "-"], "only one of --can-log and --log"),
    (["--can-log", "x", "-i", "virtual"], "--can-log reads a file"),
    (["--log", "x", "--allow-stop"], "--allow-stop needs the unit to stop: give --host, or "
                                     "set ESTOP_HOST or host in"),
    (["--log", "x", "--listen", "nowhere"], "--listen must be ADDR:PORT"),
    (["--log", "x", "--listen", "127.0.0.1:99999"], "out of range"),
])
def test_usage_errors_are_one_line(argv: list[str], message: str,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert estop_main(["dashboard", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_the_stop_button_takes_the_unit_from_the_shared_settings(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """--allow-stop's unit, the send rate and the key come as for every command: the command
    line, else the environment, else the configuration file."""
    def parsed(*argv: str) -> argparse.Namespace:
        args = build_parser().parse_args(["dashboard", "--log", "x", "--allow-stop", *argv])
        resolve_settings(args)
        return args

    config = tmp_path / "config.toml"
    config.write_text('host = "192.0.2.1"\nrate_hz = 20\ntcp_port = 6001\nremote_id = 5\n')
    monkeypatch.setenv("ESTOP_CONFIG", str(config))
    args = parsed()
    assert (args.host, args.rate_hz, args.tcp_port, args.remote_id) == ("192.0.2.1", 20.0, 6001, 5)
    monkeypatch.setenv("ESTOP_HOST", "192.0.2.2")
    monkeypatch.setenv("ESTOP_RATE_HZ", "25")
    assert (parsed().host, parsed().rate_hz) == ("192.0.2.2", 25.0)
    assert parsed("--host", "192.0.2.3").host == "192.0.2.3"


def test_the_bus_comes_from_python_cans_configuration_too(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """As estop monitor: -i/-c/--bitrate over python-can's own configuration; a log alone
    needs no bus."""
    def config(*argv: str) -> dict[str, object] | None:
        return bus_config(build_parser().parse_args(["dashboard", *argv]))

    assert config("--log", "x") is None  # python-can names no bus here
    assert config("--can-log", "x") is None
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "dash0")
    got = config("--log", "x")
    assert got is not None and (got["interface"], got["channel"]) == ("virtual", "dash0")
    got = config("-c", "other")
    assert got is not None and (got["interface"], got["channel"]) == ("virtual", "other")
    assert config("--can-log", "x") is None


def test_listen_addresses() -> None:
    assert parse_listen("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_listen("[::1]:0") == ("::1", 0)
    assert parse_listen("0.0.0.0:80") == ("0.0.0.0", 80)


def test_demo_serves_the_page_while_it_runs(estopd: str) -> None:
    """``estop demo --dashboard`` prints the page's address; the page follows the story."""
    proc = subprocess.Popen([sys.executable, "-m", "estop", "demo", "--estopd", estopd,
                             "--plain", "--dashboard", "127.0.0.1:0"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    seen: list[dict[str, Any]] = []
    try:
        assert proc.stdout is not None
        m = None
        for _ in range(5):
            m = re.search(r"dashboard on http://127\.0\.0\.1:(\d+)/", proc.stdout.readline())
            if m:
                break
        assert m, "no dashboard address from the demo"
        conn = http.client.HTTPConnection("127.0.0.1", int(m[1]), timeout=5)
        conn.request("GET", "/events")
        resp = conn.getresponse()

        def read() -> None:
            try:
                for line in resp:
                    if line.startswith(b"data: "):
                        seen.append(json.loads(line[6:]))
            except (OSError, http.client.HTTPException):
                pass

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        out, err = proc.communicate(timeout=120)
        reader.join(timeout=10)
        conn.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, "\n".join(
        line for line in (out + err).splitlines() if "PROBLEM" in line or "error" in line)
    states = {(s["state"], s["reason"]) for s in seen}
    assert {("ARMED", ""), ("SLOWING", ""), ("STOPPED", "lift"), ("STOPPED", "udp timeout"),
            ("STOPPED", "tcp stop")} <= states, states
    causes = {c["cause"] for s in seen for c in s["timeline"]}
    assert {"release", "lift_datagram", "udp_silence", "udp_timeout"} <= causes, causes
    assert seen[-1]["stops"].get("lift") == 1


def test_a_page_that_never_reads_keeps_only_the_latest_update() -> None:
    from estop.dashboard.server import _Client

    async def go() -> _Client:
        c = _Client()
        for n in range(1000):  # a stream that cannot write keeps one update, not a queue
            c.put(b"update %d" % n)
        return c

    c = asyncio.run(go())
    assert c.latest == b"update 999" and c.ready.is_set()


def test_a_client_that_never_reads_does_not_stop_the_others() -> None:
    async def go() -> tuple[int, int]:
        server = DashboardServer(DashboardModel(), "127.0.0.1", 0)
        await server.start()
        u = Unit()
        # a page that connects and never reads: its socket fills, its stream waits
        _, stuck = await asyncio.open_connection("127.0.0.1", server.port)
        stuck.write(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        await stuck.drain()

        async def frames() -> None:
            for i in range(500):
                state = State.ARMED if i % 2 else State.SLOWING  # every frame a change
                server.frame(time.time(), 0x50, u.brake(state))
                await asyncio.sleep(0.01)

        task = asyncio.get_running_loop().create_task(frames())
        try:
            events = await _read_events(f"http://127.0.0.1:{server.port}/", 10.0, enough=30)
            return len(events), len(server.clients)
        finally:
            task.cancel()
            stuck.close()
            await server.close()

    got, clients = asyncio.run(asyncio.wait_for(go(), 20))
    assert clients == 2 and got == 30, (got, clients)


def test_frames_from_a_python_can_bus() -> None:
    import can

    from estop.dashboard.feed import BusFeed

    async def go() -> dict[str, Any]:
        model = DashboardModel()
        feed = BusFeed(can.Bus(interface="virtual", channel="dash-test"),
                       lambda t, i, d: model.frame(t, i, d, time.time()), model.note)
        feed.start(asyncio.get_running_loop())
        u = Unit()
        with can.Bus(interface="virtual", channel="dash-test") as unit_bus:
            for _ in range(5):
                unit_bus.send(can.Message(arbitration_id=0x50, data=u.brake(State.ARMED),
                                          is_extended_id=False))
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.2)
        feed.close()
        return model.snapshot(time.time())

    snap = asyncio.run(asyncio.wait_for(go(), 20))
    assert snap["health"]["accepted"] == 5
    # ARMED while the frames came, NO SIGNAL since they stopped
    assert [c["state"] for c in snap["timeline"]] == [NO_SIGNAL, "ARMED"]
    assert snap["state"] == NO_SIGNAL


def test_an_input_that_breaks_the_model_is_said_and_the_feed_goes_on() -> None:
    async def go() -> dict[str, Any]:
        model = DashboardModel()
        server = DashboardServer(model, "127.0.0.1", 0)

        def broken(line: str, arrived: float) -> None:
            raise ZeroDivisionError("planted")

        model.log_line = broken  # type: ignore[method-assign]
        server.log_line('{"event": "link_histogram"}', time.time())
        server.can_line("(1800000000.000000) estop 050#0000010000000300", time.time())
        return model.snapshot(time.time())

    snap = asyncio.run(go())
    assert "ZeroDivisionError: planted" in snap["inputs"]["notes"][-1]
    assert snap["health"]["frames"] == 1  # the next input was taken


def test_a_named_pipe_is_followed_across_writers(tmp_path: Path) -> None:
    from estop.dashboard.feed import open_line_feed

    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    got: list[str] = []

    async def go() -> None:
        feed = open_line_feed(str(fifo), lambda line, t: got.append(line.strip()), got.append)
        feed.start(asyncio.get_running_loop())
        for word in ("first", "second"):  # two writers, one after the other
            fd = os.open(fifo, os.O_WRONLY)
            os.write(fd, f"{word}\n".encode())
            os.close(fd)
            await asyncio.sleep(0.2)
        feed.close()

    asyncio.run(asyncio.wait_for(go(), 10))
    assert got == ["first", "second"], got


def test_can_log_from_standard_input() -> None:
    """``candump -L can0 | estop dashboard --can-log -``: the page follows what comes in."""
    proc = subprocess.Popen([sys.executable, "-m", "estop", "dashboard", "--can-log", "-",
                             "--listen", "127.0.0.1:0"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdin is not None and proc.stdout is not None
        m = re.search(r"listening on http://127\.0\.0\.1:(\d+)/", proc.stdout.readline())
        assert m, proc.stderr.read() if proc.stderr else ""
        u = Unit()
        for _ in range(3):
            data = u.brake(State.STOPPED, Reason.LIFT).hex().upper()
            proc.stdin.write(f"({time.time():.6f}) can0 050#{data}\n")
            proc.stdin.flush()
        events = asyncio.run(_read_events(f"http://127.0.0.1:{m[1]}/", 10.0,
                                          until=lambda e: e["health"]["accepted"] == 3))
        assert events[-1]["health"]["accepted"] == 3, events[-1]["health"]
        assert events[-1]["timeline"][-1]["reason"] == "lift"
    finally:
        proc.terminate()
        assert proc.wait(10) == 0  # SIGTERM ends it as Ctrl-C does
