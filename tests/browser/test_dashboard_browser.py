"""``estop dashboard`` in a real browser: Debian's chromium, driven headless by Playwright
through the system executable (nothing downloaded), against a real estopd on loopback whose
can-log and --log-json log the dashboard follows as files being written.

The page notes every state it draws in ``window.estopShown`` with the frame's time (for NO
SIGNAL: when the 50 ms silence began) and the wall-clock moment it drew it; each state must
be on the page within 300 ms of its frame. Screenshots of every state land in
build/dashboard/ (docs/dashboard.png is one of them).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from daemon_util import ACK, MSG_LIFT, MSG_RELEASE, ROOT, Daemon, udp_packet
from estop.protocol.can import BRAKE_DATA_ID
from estop.protocol.crc import e2e_crc8

try:
    from playwright import sync_api as playwright_api
except ImportError:  # said by the fixture: the test extra (make setup) installs it
    playwright_api = None  # type: ignore[assignment]

SLOW_MS, TIMEOUT_MS = 300, 1800  # S < T, with time enough between them for a screenshot
WITHIN_S = 0.300  # the page shows a state at most this long after its frame
SHOTS = ROOT / "build" / "dashboard"
pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]


def chromium_path() -> str:
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    pytest.fail("Debian's chromium is missing: scripts/ensure-debs browser (make test does it)")


class Sender:
    """The remote's control packets at 50 Hz, on a thread, until stopped."""

    def __init__(self, daemon: Daemon) -> None:
        self.daemon = daemon
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self.daemon.send_udp(udp_packet())

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


class Dashboard:
    """``estop dashboard`` as a process, following the daemon's two files."""

    def __init__(self, can_log: Path, log: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "estop", "dashboard", "--can-log", str(can_log), "--log",
             str(log), "--listen", "127.0.0.1:0"],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # bounded: the process prints it or dies
        m = re.search(r"listening on (http://127\.0\.0\.1:\d+/)", line)
        assert m, f"no address from estop dashboard: {line!r} {self.stop_and_read()}"
        self.url = m[1]

    def stop_and_read(self) -> str:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        return self.proc.stderr.read() if self.proc.stderr else ""


@pytest.fixture
def daemon(tmp_path: Path, estopd: str) -> Iterator[Daemon]:
    with Daemon(tmp_path, "--log-json", "--slow-ms", str(SLOW_MS), "--timeout-ms",
                str(TIMEOUT_MS)) as d:
        yield d


@pytest.fixture
def dashboard(daemon: Daemon) -> Iterator[Dashboard]:
    dash = Dashboard(daemon.out_path, daemon.err_path)
    try:
        yield dash
    finally:
        dash.stop_and_read()


@pytest.fixture
def page() -> Iterator[Any]:
    if playwright_api is None:
        pytest.fail("playwright is missing: make setup installs the test extra")
    with playwright_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_path(), headless=True,
                                     args=["--no-sandbox"])
        try:
            pg = browser.new_page(viewport={"width": 1280, "height": 860})
            pg.set_default_timeout(10_000)
            yield pg
        finally:
            browser.close()


def mark(page: Any) -> int:
    """How many states the page has shown so far (before an action)."""
    return int(page.evaluate("window.estopShown.length"))


def wait_state(page: Any, state: str, reason: str = "", after: int = 0,
               timeout_s: float = 10.0) -> dict[str, Any]:
    """Wait until the page has shown ``state`` (and ``reason``) as its ``after``-th state or
    later; return that estopShown entry (the first such)."""
    find = ("([s, r, n]) => window.estopShown.slice(n).find("
            "(x) => x.state === s && x.reason === r) || null")
    page.wait_for_function(find, arg=[state, reason, after], timeout=timeout_s * 1000)
    entry: dict[str, Any] = page.evaluate(find, [state, reason, after])
    return entry


def assert_prompt(entry: dict[str, Any], limit: float = WITHIN_S) -> float:
    late = entry["shown"] - entry["frame_t"]
    sent = entry.get("sent") or entry["shown"]
    assert late <= limit, (f"{entry['state']} shown {late * 1000:.0f} ms after its frame (sent "
                           f"by the server after {(sent - entry['frame_t']) * 1000:.0f} ms)")
    return late


def shoot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def bad_crc_line() -> str:
    """An ESTOP_BRAKE that says ARMED, with its CRC off by one: a brake controller drops it."""
    payload = bytes([0, 0, 1, 0, 0, 0, 3])
    crc = e2e_crc8(BRAKE_DATA_ID, payload) ^ 0x01
    return f"({time.time():.6f}) estop 050#{(payload + bytes([crc])).hex().upper()}\n"


def append(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_APPEND)  # whole lines, as the daemon writes
    try:
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def test_dashboard_follows_the_unit_in_a_real_browser(daemon: Daemon, dashboard: Dashboard,
                                                      page: Any) -> None:
    page.goto(dashboard.url)
    wait_state(page, "STOPPED", "boot")
    lates = {}

    # release -> ARMED
    sender = Sender(daemon)
    try:
        time.sleep(0.15)
        n = mark(page)
        assert daemon.request(MSG_RELEASE, 1).msg == ACK
        lates["armed"] = assert_prompt(wait_state(page, "ARMED", after=n))
        shoot(page, "armed")
        n = mark(page)
    finally:
        sender.stop()
    # silence, S < T: SLOWING at S, then STOPPED udp timeout at T
    lates["slowing"] = assert_prompt(wait_state(page, "SLOWING", after=n))
    shoot(page, "slowing")
    lates["udp timeout"] = assert_prompt(wait_state(page, "STOPPED", "udp timeout", after=n))
    shoot(page, "stopped-udp-timeout")

    # release again, then the finger lifts -> STOPPED lift
    sender = Sender(daemon)
    try:
        time.sleep(0.15)
        n = mark(page)
        assert daemon.request(MSG_RELEASE, 2).msg == ACK
        wait_state(page, "ARMED", after=n)
        n = mark(page)
        assert daemon.request(MSG_LIFT, 3).msg == ACK
        lates["lift"] = assert_prompt(wait_state(page, "STOPPED", "lift", after=n))
    finally:
        sender.stop()
    # the timeline names estopd's cause and the stop's source, from its log
    page.wait_for_function(r"/STOPPED\s*lift\s*lift\s*127\.0\.0\.1:\d+/.test("
                           "document.querySelector('#timeline tbody').textContent)")
    counts = page.inner_text("#stops")
    assert re.search(r"udp timeout\s+1", counts) and re.search(r"lift\s+1", counts), counts

    # bad input: counted, shown, and the page goes on
    n = mark(page)
    append(daemon.out_path, "this is not a can-log line\n" + bad_crc_line())
    append(daemon.err_path, "this is not JSON\n")
    page.wait_for_function(
        "() => { const t = document.body.textContent; return /bad crc\\s*1/.test(t)"
        " && /can-log lines \\(bad\\)\\s*\\d+ \\(1\\)/.test(t)"
        " && /log lines \\(not JSON\\)\\s*\\d+ \\(1\\)/.test(t); }")
    # the link box: estopd's first link_histogram comes 10 s after its start
    page.wait_for_function("document.querySelectorAll('#hist rect').length > 0",
                           timeout=15_000)
    assert "loss" in page.inner_text("#link")
    states = page.evaluate("window.estopShown")[n:]
    assert all(x["state"] != "ARMED" for x in states), states  # the forged frame did nothing
    wait_state(page, "STOPPED", "lift", after=mark(page) - 1)
    shoot(page, "stopped-lift")
    assert dashboard.proc.poll() is None, "the dashboard's server died on bad input"

    # the unit dies: no good ESTOP_BRAKE for 50 ms -> NO SIGNAL
    assert daemon.proc is not None
    n = mark(page)
    daemon.proc.send_signal(signal.SIGKILL)
    daemon.proc.wait(10)
    lates["no signal"] = assert_prompt(wait_state(page, "NO SIGNAL", after=n))
    shoot(page, "no-signal")

    # the dashboard's server hangs: 500 ms without an update, the page says it lost its feed
    n = mark(page)
    dashboard.proc.send_signal(signal.SIGSTOP)
    hung = time.time()
    try:
        entry = wait_state(page, "LOST FEED", "state unknown", after=n)
        assert entry["shown"] - hung <= 0.5 + WITHIN_S, entry
        shoot(page, "lost-feed")
        n = mark(page)
    finally:
        dashboard.proc.send_signal(signal.SIGCONT)
    wait_state(page, "NO SIGNAL", after=n)  # back, with the state as it is now

    # the dashboard's server goes away: the page says so at once (the stream closed)
    n = mark(page)
    gone = time.time()
    dashboard.proc.terminate()
    dashboard.proc.wait(10)
    entry = wait_state(page, "LOST FEED", "state unknown", after=n)
    assert entry["shown"] - gone <= 0.5 + WITHIN_S, entry
    assert page.evaluate("window.estopRenderErrors") == 0
    (SHOTS / "shown-after-frame.txt").write_text(
        "".join(f"{k}: {v * 1000:.0f} ms\n" for k, v in lates.items()))
    (SHOTS / "shown.json").write_text(json.dumps(page.evaluate("window.estopShown"), indent=1))
