"""The touch remote's lift latency as a distribution, beside a peer and the timer floor.

``estop remote --touch`` serving Debian's chromium (headless, Playwright, a phone's viewport
with touch), a finger put down and lifted through the DevTools protocol, many times. Measured:
from the moment the touchEnd event is sent to the kernel's receive time (SO_TIMESTAMPNS) of
the first lift datagram at a UDP socket standing in for the unit's control port (the unit's
TCP port is a real estopd, for the remote's STATUS). Beside it, in the same run:

- a **peer**: the least any page-plus-remote can do over the same two hops, a bare page whose
  touchend sends one WebSocket message to a bare aiohttp server that sends one datagram;
- the machine's **timer floor** (bench/latency_machine.timer_floor: sleep wake-up latency).

Goal (issue 28): p99 <= 30 ms. Output: printed, and bench/out/touch_lift.json. Usage:
bench/touch_lift.py [--lifts 200]. Not part of `make test` (figures, not a timed test);
tests/browser/test_touch_browser.py checks the behaviour and prints a short distribution.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the bench's modules beside this script
    sys.path.insert(0, str(HERE))

from estop.unit.daemon import Daemon, find_estopd  # noqa: E402
from latency_machine import timer_floor  # noqa: E402

OUT = HERE / "out"
GOAL_P99_MS = 30.0
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
LIFT_ID = 3

PEER_PAGE = """<!doctype html><meta name=viewport content="width=device-width">
<div id=d style="position:fixed;inset:0;touch-action:none"></div><script>
const ws = new WebSocket("ws://" + location.host + "/ws"); let down = 0;
const d = document.getElementById("d");
d.addEventListener("touchstart", (e) => { e.preventDefault(); down += e.changedTouches.length; },
  {passive: false});
d.addEventListener("touchend", (e) => { e.preventDefault(); down -= e.changedTouches.length;
  if (!down) ws.send("lift"); }, {passive: false});
</script>"""


class Sink:
    """UDP on loopback: the kernel's receive time of each datagram that is a lift (or any,
    for the peer)."""

    def __init__(self, only_lifts: bool) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = int(self.sock.getsockname()[1])
        self.only_lifts = only_lifts
        self.stamps: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, anc, _, _ = self.sock.recvmsg(256, socket.CMSG_SPACE(16))
            except TimeoutError:
                continue
            if self.only_lifts and not (len(data) == 48
                                        and struct.unpack_from("<I", data, 4)[0] == LIFT_ID):
                continue
            stamp = time.time()
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = struct.unpack("qq", raw[:16])
                    stamp = sec + nsec / 1e9
            self.stamps.append(stamp)

    def first_after(self, n: int, timeout: float = 2.0) -> float:
        deadline = time.monotonic() + timeout
        while len(self.stamps) <= n:
            if time.monotonic() > deadline:
                raise RuntimeError("no datagram")
            time.sleep(0.001)
        return self.stamps[n]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def peer_server(sink_port: int) -> tuple[threading.Thread, asyncio.AbstractEventLoop, int]:
    """The bare two-hop peer: a page and a WebSocket whose message sends one datagram."""
    from aiohttp import WSMsgType, web

    loop = asyncio.new_event_loop()
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ready = threading.Event()
    port: list[int] = []

    async def page(request: web.Request) -> web.Response:
        return web.Response(text=PEER_PAGE, content_type="text/html")

    async def ws_handler(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        async for msg in ws:
            if msg.type == WSMsgType.TEXT:
                out.sendto(b"lift", ("127.0.0.1", sink_port))
        return ws

    async def start() -> None:
        app = web.Application()
        app.router.add_get("/", page)
        app.router.add_get("/ws", ws_handler)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port.append(site._server.sockets[0].getsockname()[1])  # type: ignore[union-attr]

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(start())
        ready.set()
        loop.run_forever()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    ready.wait(10)
    return th, loop, port[0]


def lifts(browser: Any, url: str, sink: Sink, n: int, ready_js: str,
          parts: dict[str, list[float]] | None = None) -> list[float]:
    """n holds and lifts of one finger on the page at ``url``; ms from touchEnd sent to the
    first datagram at the sink. With ``parts``, the touch page's own account of each lift
    (window.estop.sent): ``browser`` from the DevTools event to its touchend handler, of which
    ``queued`` waiting for the page's thread, ``page`` the handler's work to the WebSocket
    send, ``remote`` the rest (the WebSocket hop and the remote to the datagram)."""
    ctx = browser.new_context(viewport={"width": 412, "height": 860}, is_mobile=True,
                              has_touch=True, bypass_csp=True)
    page = ctx.new_page()
    page.goto(url)
    page.wait_for_function(ready_js, timeout=10_000)
    cdp = ctx.new_cdp_session(page)
    out = []
    point = [{"x": 206, "y": 400, "id": 1}]
    for i in range(n):
        cdp.send("Input.dispatchTouchEvent", {"type": "touchStart", "touchPoints": point})
        time.sleep(0.05 + 0.01 * (i % 3))  # a few frames, not in step with the page's timer
        seen = len(sink.stamps)
        t0 = time.time()
        cdp.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": []})
        first = sink.first_after(seen)
        out.append((first - t0) * 1000)
        if parts is not None:
            e = page.evaluate("window.estop.sent.filter((x) => x.t === 'lift').pop()")
            parts.setdefault("browser", []).append((e["at"] - t0) * 1000)
            parts.setdefault("queued", []).append(e["queued"] or 0.0)
            parts.setdefault("page", []).append((e["sent"] - e["at"]) * 1000)
            parts.setdefault("remote", []).append((first - e["sent"]) * 1000)
        time.sleep(0.03)
    ctx.close()
    return out


def summary(ms: list[float]) -> dict[str, float]:
    xs = sorted(ms)

    def pct(p: float) -> float:
        return xs[min(len(xs) - 1, int(p * len(xs)))]

    return {"n": len(xs), "p50": pct(0.5), "p90": pct(0.9), "p99": pct(0.99), "max": xs[-1]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lifts", type=int, default=200)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    estopd = find_estopd()
    if chromium is None or estopd is None:
        print("needs Debian's chromium (scripts/ensure-debs browser) and estopd (make setup)")
        return 5
    load0 = os.getloadavg()[0]
    parts: dict[str, list[float]] = {}
    remote_sink, peer_sink = Sink(only_lifts=True), Sink(only_lifts=False)
    with Daemon([estopd]) as unit:
        remote = subprocess.Popen(
            [sys.executable, "-m", "estop", "remote", "--touch", "--host", "127.0.0.1",
             "--udp-port", str(remote_sink.port), "--tcp-port", str(unit.tcp_port),
             "--listen", "127.0.0.1:0"], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True)
        try:
            assert remote.stdout is not None
            url = ""
            for line in remote.stdout:
                m = re.search(r"open (http://\S+)", line)
                if m:
                    url = m[1]
                    break
            threading.Thread(target=lambda: [None for _ in remote.stdout or []],
                             daemon=True).start()
            _, loop, peer_port = peer_server(peer_sink.port)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                             args=["--no-sandbox"])
                try:
                    ours = lifts(browser, url, remote_sink, args.lifts,
                                 "window.estop && window.estop.last && window.estop.last.paired",
                                 parts)
                    peer = lifts(browser, f"http://127.0.0.1:{peer_port}/", peer_sink,
                                 args.lifts, "true")
                finally:
                    browser.close()
            loop.call_soon_threadsafe(loop.stop)
        finally:
            remote.terminate()
            remote.wait(10)
    floor = timer_floor(1000, 0.001)
    result = {"lifts": args.lifts, "load": [load0, os.getloadavg()[0]],
              "estop_remote_touch_ms": summary(ours), "peer_ms": summary(peer),
              "timer_floor_ms": summary(floor), "goal_p99_ms": GOAL_P99_MS,
              "touch_parts_ms": {k: summary(v) for k, v in parts.items()}}
    o, p, f = result["estop_remote_touch_ms"], result["peer_ms"], result["timer_floor_ms"]
    print(f"touch end -> first lift datagram over {args.lifts} lifts (load {load0:.1f}):")
    for name, s in (("estop remote --touch", o), ("bare page + WebSocket peer", p),
                    ("timer floor (1 ms sleeps)", f)):
        print(f"  {name:28} p50 {s['p50']:6.2f}  p90 {s['p90']:6.2f}  p99 {s['p99']:6.2f}  "
              f"max {s['max']:6.2f} ms")
    for name, v in parts.items():
        s = summary(v)
        print(f"    of which {name:18} p50 {s['p50']:6.2f}  p90 {s['p90']:6.2f}  p99 "
              f"{s['p99']:6.2f}  max {s['max']:6.2f} ms")
    print(f"  ratio to the peer: p50 {o['p50'] / p['p50']:.2f}, p99 {o['p99'] / p['p99']:.2f}")
    met = o["p99"] <= GOAL_P99_MS
    print(f"  goal p99 <= {GOAL_P99_MS:g} ms: {'met' if met else 'NOT met'}")
    OUT.mkdir(exist_ok=True)
    (OUT / "touch_lift.json").write_text(json.dumps(result, indent=1))
    remote_sink.close()
    peer_sink.close()
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
