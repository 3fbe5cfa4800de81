"""``estop remote --touch`` in a real browser: Debian's chromium, driven headless by Playwright
(the system executable, nothing downloaded), as a phone (a mobile viewport with touch) whose
fingers are touch events dispatched through the DevTools protocol, against a real estopd with
a key on loopback.

The remote sends to a UDP tap that keeps the kernel's receive time of every datagram and
forwards it to the unit, so the tests see each control packet and lift datagram; the unit's
states come from its can-log. Screenshots of each state land in build/touch/ (docs/touch.png
is one of them), the measured figures in build/touch/figures.txt.
"""

from __future__ import annotations

import hashlib
import os
import signal
import statistics
import time
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from daemon_util import ARMED, R_LIFT, R_TCP_STOP, R_UDP_TIMEOUT, ROOT, SLOWING, STOPPED, Daemon
from estop.client.keyfile import write_key_file
from touch_util import Phone, TcpCut, TouchRemote, UdpTap, control_of

try:
    from playwright import sync_api as playwright_api
except ImportError:  # said by the fixture: the test extra (make setup) installs it
    playwright_api = None  # type: ignore[assignment]

SLOW_MS, TIMEOUT_MS = 300, 1200  # S < T, both far above a loaded browser's timer jitter
RATE_HZ = 50
SHOTS = ROOT / "build" / "touch"
KEY = bytes(range(32))
PHONE = {"width": 412, "height": 860}  # CSS pixels, a common Android phone
pytestmark = [pytest.mark.timeout(120), pytest.mark.timing]


def chromium_path() -> str:
    import shutil

    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    pytest.fail("Debian's chromium is missing: scripts/ensure-debs browser (make test does it)")


def figure(line: str) -> None:
    """A measured figure, for the note and the docs (build/touch/figures.txt)."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    with (SHOTS / "figures.txt").open("a") as f:
        f.write(line + "\n")


def shoot(phone: Phone, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    phone.page.screenshot(path=str(SHOTS / f"{name}.png"))


# ------------------------------------------------------------------------------ fixtures

@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if playwright_api is None:
        pytest.fail("playwright is missing: make setup installs the test extra")
    (SHOTS / "figures.txt").unlink(missing_ok=True)
    with playwright_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=chromium_path(), headless=True,
                               args=["--no-sandbox"])
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "key"
    write_key_file(str(path), KEY)
    return path


@pytest.fixture
def daemon(tmp_path: Path, key_file: Path, estopd: str) -> Iterator[Daemon]:
    with Daemon(tmp_path, "--key-file", str(key_file), "--slow-ms", str(SLOW_MS),
                "--timeout-ms", str(TIMEOUT_MS)) as d:
        yield d


@pytest.fixture
def tap(daemon: Daemon) -> Iterator[UdpTap]:
    t = UdpTap(daemon.udp_port)
    yield t
    t.close()


def start_remote(daemon: Daemon, tap: UdpTap, key_file: Path, *extra: str) -> TouchRemote:
    return TouchRemote("--host", "127.0.0.1", "--udp-port", str(tap.port), "--tcp-port",
                       str(daemon.tcp_port), "--key-file", str(key_file), "--rate-hz",
                       str(RATE_HZ), *(extra or ("--listen", "127.0.0.1:0")))


@pytest.fixture
def remote(daemon: Daemon, tap: UdpTap, key_file: Path) -> Iterator[TouchRemote]:
    r = start_remote(daemon, tap, key_file)
    yield r
    r.stop()


def open_phone(browser: Any, url: str, viewport: dict[str, int] = PHONE) -> Phone:
    # bypass_csp: Playwright's waits evaluate strings, which the page's policy forbids
    context = browser.new_context(viewport=viewport, device_scale_factor=2, is_mobile=True,
                                  has_touch=True, bypass_csp=True)
    page = context.new_page()
    page.set_default_timeout(10_000)
    page.goto(url)
    phone = Phone(context, page)
    return phone


@pytest.fixture
def phone(browser: Any, remote: TouchRemote) -> Iterator[Phone]:
    p = open_phone(browser, remote.url)
    try:
        p.page.wait_for_function("window.estop.last && window.estop.last.paired")
        yield p
        if not p.page.is_closed():  # every message of the server verified, in order
            assert p.page.evaluate("[window.estop.renderErrors, window.estop.badMacs]") \
                == [0, 0]
    finally:
        p.context.close()


def unit_state(daemon: Daemon, state: int, reason: int = 0, after: int = 0,
               timeout: float = 5.0) -> float:
    """Wall-clock time of the first brake frame from ``after`` on in ``state`` (reason)."""
    frame = daemon.wait_frame(lambda f: f.is_brake() and f.state == state
                              and (reason == 0 or f.reason == reason), timeout=timeout,
                              after=after)
    return frame.t


def arm(phone: Phone, daemon: Daemon, tap: UdpTap) -> None:
    """A finger in the middle (neutral), RELEASE: the unit is ARMED."""
    n = tap.count()
    phone.down(1, phone.point(0.5, 0.5))
    tap.wait("control", after=n, n=6)  # the unit needs 5 valid packets for a live link
    phone.tap("#release")
    phone.wait_state("ARMED")
    unit_state(daemon, ARMED)


# ------------------------------------------------------------------------------ the tests

def test_the_pages_mac_is_blake2s(browser: Any) -> None:
    """the page's static/blake2s.js (its MAC) gives hashlib's keyed BLAKE2s, at every length
    around the block size."""
    context = browser.new_context()
    try:
        page = context.new_page()
        page.add_script_tag(content=resources.files("estop.remote.touch").joinpath(
            "static", "blake2s.js").read_text())
        key = os.urandom(16)
        for n in (0, 1, 31, 63, 64, 65, 127, 128, 129, 300):
            data = os.urandom(n)
            got = page.evaluate("([k, d]) => bytesToHex(blake2s(hexToBytes(k), hexToBytes(d), 16))",
                                [key.hex(), data.hex()])
            assert got == hashlib.blake2s(data, key=key, digest_size=16).hexdigest(), n
        assert page.evaluate("bytesToHex(blake2s(new Uint8Array(0), new Uint8Array(0), 32))") \
            == hashlib.blake2s(b"").hexdigest()
    finally:
        context.close()


def test_touch_release_drive_second_finger_and_lift(daemon: Daemon, tap: UdpTap,
                                                    remote: TouchRemote, phone: Phone) -> None:
    phone.wait_state("STOPPED", "boot")
    shoot(phone, "stopped-boot")
    # a finger in the middle (not quite at its centre) holds the car ready: neutral packets
    n = tap.count()
    phone.down(1, phone.point(0.53, 0.46))
    tap.wait("control", after=n, n=6)
    steer, gas = control_of(tap.of("control", n)[-1][1], KEY)
    assert (steer, gas) == (0.0, 0.0)
    phone.tap("#release")
    phone.wait_state("ARMED")
    unit_state(daemon, ARMED)
    shoot(phone, "armed-neutral")

    # at the rate: one packet per frame of the page, 50 a second
    frames0, n = phone.page.evaluate("window.estop.framesSent"), tap.count()
    time.sleep(1.0)
    frames = phone.page.evaluate("window.estop.framesSent") - frames0
    got = tap.of("control", n)
    assert len(got) > 10, remote.output() + str(phone.page.evaluate("window.estop.sent"))
    span = got[-1][0] - got[0][0]
    rate = (len(got) - 1) / span
    gaps = sorted(b[0] - a[0] for a, b in zip(got, got[1:], strict=False))
    figure(f"control packets while held: {rate:.1f} per second (rate {RATE_HZ}), gaps median "
           f"{statistics.median(gaps) * 1000:.1f} ms, longest {gaps[-1] * 1000:.1f} ms; "
           f"{len(got)} packets for {frames} frames; load {os.getloadavg()[0]:.1f}")
    # never more packets than frames (no clock of the remote's own), at most a few frames
    # dropped as late (the two at the window's edges may fall either side)
    assert 0.9 * frames - 2 <= len(got) <= frames + 2, (len(got), frames)
    assert 0.8 * RATE_HZ <= rate <= 1.1 * RATE_HZ, rate
    assert gaps[-1] < SLOW_MS / 1000 / 2, gaps[-1]

    # the finger up and right: gas and steering right, from its position
    phone.move(1, phone.point(0.85, 0.2))
    n = tap.count()
    tap.wait("control", after=n, n=3)
    steer, gas = control_of(tap.of("control", n)[-1][1], KEY)
    assert steer > 0.5 and gas > 0.5, (steer, gas)
    phone.move(1, phone.point(0.1, 0.9))  # down and left: brake, steering left
    n = tap.count()
    tap.wait("control", after=n, n=3)
    steer, gas = control_of(tap.of("control", n)[-1][1], KEY)
    assert steer < -0.5 and gas < -0.5, (steer, gas)
    phone.tap("#gear-drive")
    phone.page.wait_for_function("window.estop.last.gear === 'drive'")
    # the device's tilt steers instead, when chosen (the finger still gives the gas)
    phone.page.evaluate("window.dispatchEvent(new DeviceOrientationEvent('deviceorientation', "
                        "{alpha: 0, beta: 10, gamma: 25}))")
    assert phone.page.is_visible("#tilt-box")
    phone.page.evaluate("document.getElementById('tilt').click()")
    n = tap.count()
    tap.wait("control", after=n, n=3)
    steer, gas = control_of(tap.of("control", n)[-1][1], KEY)
    assert abs(steer - (25 / 35 - 0.12) / 0.88) < 0.01 and gas < -0.5, (steer, gas)
    phone.page.evaluate("document.getElementById('tilt').click()")
    phone.move(1, phone.point(0.6, 0.35))
    time.sleep(0.3)
    shoot(phone, "armed-driving")

    # a second finger down and up: still ARMED, no lift, the packets go on
    n, s = tap.count(), len(daemon.frames())
    phone.down(2, phone.point(0.3, 0.7))
    time.sleep(0.1)
    phone.up(2)
    time.sleep(0.3)
    assert not tap.of("lift", n)
    tap.wait("control", after=n, n=15)  # the tap's thread may be behind the page
    assert all(f.state == ARMED for f in daemon.frames()[s:] if f.is_brake())

    # the last finger up: the lift datagrams at once, 10 ms apart; STOPPED lift
    n, s = tap.count(), len(daemon.frames())
    t_up = phone.up(1)
    lifts = tap.wait("lift", after=n, n=3)
    gaps = [b[0] - a[0] for a, b in zip(lifts, lifts[1:], strict=False)]
    assert all(0.009 <= g <= 0.05 for g in gaps), gaps
    t_stop = unit_state(daemon, STOPPED, R_LIFT, after=s)
    figure(f"one lift: touch end -> first lift datagram {(lifts[0][0] - t_up) * 1000:.1f} ms, "
           f"-> STOPPED lift on the bus {(t_stop - t_up) * 1000:.1f} ms; lift gaps "
           f"{[round(g * 1000, 1) for g in gaps]} ms")
    time.sleep(0.1)
    last_lift = tap.of("lift", n)[-1][0]
    assert not [t for t, _ in tap.of("control", n) if t > last_lift]  # nothing after it
    phone.wait_state("STOPPED", "lift")
    shoot(phone, "stopped-lift")
    remote.wait_line("lift (touchend): lift sent x3")
    assert phone.page.evaluate("window.estop.renderErrors + window.estop.badMacs") == 0


def test_lift_latency_distribution(daemon: Daemon, tap: UdpTap, remote: TouchRemote,
                                   phone: Phone) -> None:
    """From the touch's end (the DevTools event sent) to the kernel's receive time of the
    first lift datagram, over many holds; the page's own share (its touchend handler's
    time) beside it. Goal: p99 <= 30 ms on this machine; the check asks only that a lift
    beats the slow time (what makes it worth sending), the goal is a figure."""
    cycles = 60
    total, page_part = [], []
    for i in range(cycles):
        n = tap.count()
        phone.down(1, phone.point(0.5, 0.5))
        tap.wait("control", after=n, n=2)
        t0 = phone.up(1)
        first = tap.wait("lift", after=n)[0][0]
        at = phone.page.evaluate("window.estop.sent.filter((x) => x.t === 'lift').pop().at")
        total.append(first - t0)
        page_part.append(at - t0)
        time.sleep(0.02 + 0.01 * (i % 3))  # not in step with the page's timer
    total.sort()
    page_part.sort()

    def pct(xs: list[float], p: float) -> float:
        return xs[min(len(xs) - 1, int(p * len(xs)))] * 1000

    figure(f"lift latency, touch end -> first lift datagram, {cycles} lifts: p50 "
           f"{pct(total, 0.5):.1f} ms, p90 {pct(total, 0.9):.1f} ms, p99 {pct(total, 0.99):.1f}"
           f" ms, max {total[-1] * 1000:.1f} ms (goal p99 <= 30 ms); of which the browser to "
           f"the page's touchend handler p50 {pct(page_part, 0.5):.1f} ms, p99 "
           f"{pct(page_part, 0.99):.1f} ms; load {os.getloadavg()[0]:.1f}")
    assert total[-1] < SLOW_MS / 1000, total[-1]


def test_page_frozen_is_silence_slowing_at_s_stopped_at_t(
        browser: Any, daemon: Daemon, tap: UdpTap, remote: TouchRemote, phone: Phone) -> None:
    """The page's script paused (DevTools Debugger.pause): no frames, so no packets; the unit
    slows at S and stops at T after the last packet. A second page (another phone, not
    holding) shows the states meanwhile."""
    arm(phone, daemon, tap)
    watcher = open_phone(browser, remote.url)
    try:
        watcher.page.wait_for_function("window.estop.last && window.estop.last.hold === 'other'")
        s = len(daemon.frames())
        n = tap.count()
        phone.cdp.send("Debugger.enable")
        t_freeze = time.time()
        phone.cdp.send("Debugger.pause")
        try:
            t_slow = unit_state(daemon, SLOWING, after=s)
            watcher.wait_state("SLOWING")
            shoot(watcher, "slowing")
            t_stop = unit_state(daemon, STOPPED, R_UDP_TIMEOUT, after=s, timeout=5.0)
            first, last = tap.last_forwarded("control")  # maybe before the pause, under load
            assert not tap.of("lift", n)  # silence: a paused page says nothing
            watcher.wait_state("STOPPED", "udp_timeout")
            remote.wait_line("no fresh frame for 2 periods")
        finally:  # a paused page answers nothing, the test's own clean-up included
            phone.cdp.send("Debugger.resume")
        figure(f"page frozen (script paused): last control packet {(last - t_freeze) * 1000:.1f}"
               f" ms after the pause; SLOWING {(t_slow - last) * 1000:.1f} ms and STOPPED udp "
               f"timeout {(t_stop - last) * 1000:.1f} ms after it (S = {SLOW_MS}, T = "
               f"{TIMEOUT_MS}; the tap's send took {(last - first) * 1000:.1f} ms)")
        assert first - t_freeze < 0.1
        # The packet reached the unit between first and last: a time in there must fit.
        assert (t_slow - first) * 1000 >= SLOW_MS - 5 and (t_slow - last) * 1000 <= SLOW_MS + 100
        assert (t_stop - first) * 1000 >= TIMEOUT_MS - 5
        assert (t_stop - last) * 1000 <= TIMEOUT_MS + 100
        phone.wait_state("STOPPED", "udp_timeout")  # latched, though the finger is still down
        phone.page.wait_for_function("window.estop.last.hold === 'you' && "
                                     "!window.estop.last.stalled")  # fresh frames again
        shoot(phone, "stopped-udp-timeout")
        phone.up(1)
    finally:
        watcher.context.close()


def test_stop_while_driving(daemon: Daemon, tap: UdpTap, remote: TouchRemote,
                            phone: Phone) -> None:
    arm(phone, daemon, tap)
    s, n = len(daemon.frames()), tap.count()
    phone.tap("#stop", finger=5)  # a second finger on STOP; the first still drives
    unit_state(daemon, STOPPED, R_TCP_STOP, after=s)
    tap.wait("stop", after=n)
    phone.wait_state("STOPPED", "tcp_stop")
    phone.page.wait_for_function("document.getElementById('note').textContent.includes('ACK')")
    assert not tap.of("lift", n)  # the STOP finger is not the dead-man's
    shoot(phone, "stopped-tcp-stop")
    remote.wait_line("stop -> ACK")


@pytest.mark.parametrize("how", ["tab closed", "touchcancel", "page hidden"])
def test_the_page_going_lifts(how: str, daemon: Daemon, tap: UdpTap, remote: TouchRemote,
                              phone: Phone) -> None:
    arm(phone, daemon, tap)
    s, n = len(daemon.frames()), tap.count()
    t0 = time.time()
    if how == "tab closed":
        phone.page.close()
    elif how == "touchcancel":
        phone.cancel()
    else:  # the app switcher, the screen locked: the page is hidden
        phone.page.evaluate("Object.defineProperty(document, 'visibilityState', "
                            "{value: 'hidden', configurable: true}); "
                            "document.dispatchEvent(new Event('visibilitychange'))")
    lift = tap.wait("lift", after=n, n=3)[0][0]
    unit_state(daemon, STOPPED, R_LIFT, after=s)
    figure(f"{how}: first lift datagram {(lift - t0) * 1000:.1f} ms after")
    time.sleep(0.1)
    assert not [t for t, _ in tap.of("control", n) if t > lift]


def test_websocket_cut_lifts(browser: Any, daemon: Daemon, tap: UdpTap, remote: TouchRemote
                             ) -> None:
    """The page's connection reset on its way (a relay in front of the remote cuts it):
    the remote lifts at once; the page says it lost the remote and drives no more."""
    port = int(remote.base.rsplit(":", 1)[1].strip("/"))
    relay = TcpCut(port)
    phone = open_phone(browser, f"http://127.0.0.1:{relay.port}/#{remote.fragment}")
    try:
        phone.page.wait_for_function("window.estop.last && window.estop.last.paired")
        arm(phone, daemon, tap)
        s, n = len(daemon.frames()), tap.count()
        t_cut = relay.cut()
        lift = tap.wait("lift", after=n, n=3)[0][0]
        unit_state(daemon, STOPPED, R_LIFT, after=s)
        figure(f"WebSocket cut: first lift datagram {(lift - t_cut) * 1000:.1f} ms after")
        phone.wait_shown("NO REMOTE")
        shoot(phone, "no-remote")
        time.sleep(0.1)
        assert not [t for t, _ in tap.of("control", n) if t > lift]
        remote.wait_line("WebSocket closed")
    finally:
        relay.close()
        phone.context.close()


def test_remote_killed_is_silence(daemon: Daemon, tap: UdpTap, remote: TouchRemote,
                                  phone: Phone) -> None:
    arm(phone, daemon, tap)
    s, n = len(daemon.frames()), tap.count()
    remote.proc.send_signal(signal.SIGKILL)
    remote.proc.wait(10)
    t_kill = time.time()
    t_slow = unit_state(daemon, SLOWING, after=s)
    t_stop = unit_state(daemon, STOPPED, R_UDP_TIMEOUT, after=s)
    got = tap.received(n)
    assert all(t <= t_kill for t, _ in got), "a datagram after the remote was killed"
    assert not tap.of("lift", n)
    _, last = tap.last_forwarded("control")
    figure(f"remote killed: SLOWING {(t_slow - last) * 1000:.1f} ms, STOPPED udp timeout "
           f"{(t_stop - last) * 1000:.1f} ms after its last packet")
    phone.wait_shown("NO REMOTE")


def test_a_page_without_the_token_is_refused(browser: Any, daemon: Daemon, tap: UdpTap,
                                             key_file: Path) -> None:
    """Listening beyond loopback (every address; the test connects over loopback): the
    address comes with a QR code; a page without the token, or with another one, drives
    nothing and releases nothing, and may still stop (anyone may)."""
    remote = start_remote(daemon, tap, key_file, "--listen", "0.0.0.0:0")
    try:
        remote.wait_line("status -> ")  # printed after the QR code
        assert "open to the network" in remote.output()
        assert any("\u2588" in line or "\u2580" in line for line in remote.lines), "no QR code"
        port = remote.base.rsplit(":", 1)[1].strip("/")
        for suffix in ("", "#k=AAAAAAAAAAAAAAAAAAAAAA"):
            phone = open_phone(browser, f"http://127.0.0.1:{port}/{suffix}")
            try:
                phone.wait_shown("NOT PAIRED")
                assert phone.page.evaluate("document.documentElement.scrollWidth <= innerWidth")
                n = tap.count()
                phone.down(1, phone.point(0.5, 0.5))
                phone.tap("#release")
                phone.page.wait_for_function(
                    "document.getElementById('note').textContent.includes('refused')")
                time.sleep(0.3)
                assert not tap.of("control", n)
                phone.up(1)
                if suffix:
                    remote.wait_line("pairing refused")
                else:
                    shoot(phone, "refused")
            finally:
                phone.context.close()
        phone = open_phone(browser, f"http://127.0.0.1:{port}/")
        try:
            phone.wait_shown("NOT PAIRED")
            n = tap.count()
            phone.tap("#stop")
            tap.wait("stop", after=n)
            phone.page.wait_for_function(
                "document.getElementById('note').textContent.includes('STOP: ACK')")
        finally:
            phone.context.close()
    finally:
        remote.stop()


def test_portrait_and_landscape(daemon: Daemon, tap: UdpTap, remote: TouchRemote,
                                phone: Phone) -> None:
    """Both orientations of a phone: STOP, RELEASE, the gears and the drive area on screen,
    the state large; driving goes on across the turn."""
    arm(phone, daemon, tap)
    for name, size in (("portrait", PHONE), ("landscape", {"width": 860, "height": 412})):
        phone.page.set_viewport_size(size)
        time.sleep(0.2)
        for sel in ("#stop", "#release", "#gears", "#drive", "#state"):
            box = phone.area(sel)
            assert box["x"] >= 0 and box["y"] >= 0, (name, sel, box)
            assert box["x"] + box["width"] <= size["width"] + 0.5, (name, sel, box)
            assert box["y"] + box["height"] <= size["height"] + 0.5, (name, sel, box)
        assert phone.page.evaluate("document.documentElement.scrollWidth <= innerWidth && "
                                   "document.documentElement.scrollHeight <= innerHeight")
        stop = phone.area("#stop")
        assert stop["width"] >= 120 and stop["height"] >= 80, (name, stop)
        px = float(phone.page.evaluate(
            "parseFloat(getComputedStyle(document.getElementById('state')).fontSize)"))
        assert px >= 35, (name, px)
        drive = phone.area("#drive")
        assert drive["width"] * drive["height"] >= 0.3 * size["width"] * size["height"], name
        phone.wait_state("ARMED")
        shoot(phone, f"armed-{name}")
    n = tap.count()
    tap.wait("control", after=n, n=5)
    phone.up(1)
