"""``estop remote --touch``'s WebSocket without a browser: a hostile or broken page (no token,
a wrong one, replays, garbage, a second page, too many pages) against the real command and a
real estopd with a key; what reaches the unit is seen at a UDP tap in front of it."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from daemon_util import Daemon
from estop.client.keyfile import write_key_file
from estop.remote.touch.server import MAX_PAGES
from estop.remote.touch.wire import decode_token, new_nonce, new_token, parse, seal
from touch_util import TouchRemote, UdpTap

KEY = bytes(range(32))
pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]


@pytest.fixture
def setup(tmp_path: Path, estopd: str) -> Iterator[tuple[Daemon, UdpTap, TouchRemote]]:
    key = tmp_path / "key"
    write_key_file(str(key), KEY)
    with Daemon(tmp_path, "--key-file", str(key)) as daemon:
        tap = UdpTap(daemon.udp_port)
        remote = TouchRemote("--host", "127.0.0.1", "--udp-port", str(tap.port), "--tcp-port",
                             str(daemon.tcp_port), "--key-file", str(key), "--listen",
                             "127.0.0.1:0")
        try:
            yield daemon, tap, remote
        finally:
            remote.stop()
            tap.close()


class Page:
    """A page's side of the WebSocket, in Python."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse, token: bytes | None) -> None:
        self.ws = ws
        self.token = token
        self.server_nonce = b""
        self.nonce = new_nonce()
        self.n = 0
        self.n_in = 0
        self.got: list[Any] = []

    async def hello(self) -> None:
        msg = parse(await self.ws.receive_str(timeout=5), None, None)
        assert msg.kind == "hello"
        self.server_nonce = bytes.fromhex(msg.fields["nonce"])

    async def send(self, msg: dict[str, Any], *, n: int | None = None) -> None:
        if self.token is None:
            await self.ws.send_str(seal(msg))
            return
        self.n = self.n + 1 if n is None else n
        await self.ws.send_str(seal({**msg, "n": self.n}, self.token, self.server_nonce))

    async def pair(self) -> None:
        await self.hello()
        await self.send({"t": "pair", "nonce": self.nonce.hex()})
        await self.expect("paired")

    async def expect(self, kind: str, timeout: float = 5.0) -> Any:
        """The next message of ``kind`` (others are kept in ``got``); each must verify once
        paired."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            assert left > 0, f"no {kind} message: {self.got}"
            text = await self.ws.receive_str(timeout=left)
            msg = parse(text, self.token, self.nonce)
            assert msg.authentic or text.startswith("- ")
            if msg.authentic:  # the server's counter rises in the order the page reads
                assert msg.fields["n"] > self.n_in, (msg, self.n_in)
                self.n_in = msg.fields["n"]
            self.got.append(msg)
            if msg.kind == kind:
                return msg

    async def held(self, steer: float = 0.0, gas: float = 0.0) -> None:
        await self.send({"t": "held", "at": time.monotonic() * 1000, "steer": steer,
                         "gas": gas})

    async def hold_for(self, seconds: float, period: float = 0.02) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            await self.held()
            await asyncio.sleep(period)


def token_of(remote: TouchRemote) -> bytes:
    return decode_token(remote.fragment.removeprefix("k="))


async def connect(session: aiohttp.ClientSession, remote: TouchRemote, token: bytes | None
                  ) -> Page:
    ws = await session.ws_connect(remote.base + "ws")
    return Page(ws, token)


def run(coro: Any) -> Any:
    return asyncio.run(asyncio.wait_for(coro, 30))


def test_a_page_without_the_token_drives_nothing_and_may_stop(
        setup: tuple[Daemon, UdpTap, TouchRemote]) -> None:
    daemon, tap, remote = setup

    async def go() -> None:
        async with aiohttp.ClientSession() as s:
            plain = await connect(s, remote, None)
            await plain.hello()
            await plain.hold_for(0.2)
            refused = await plain.expect("refused")
            assert refused.fields["what"] == "held"
            await plain.send({"t": "release"})
            await plain.send({"t": "gear", "gear": "drive"})
            wrong = await connect(s, remote, new_token())
            await wrong.hello()
            await wrong.send({"t": "pair", "nonce": wrong.nonce.hex()})
            assert (await wrong.expect("refused")).fields["what"] == "pair"
            await wrong.hold_for(0.2)
            assert not tap.of("control")
            n = tap.count()
            await plain.send({"t": "stop"})  # anyone may stop
            reply = await plain.expect("reply")
            assert reply.fields["what"] == "stop" and reply.fields["ok"]
            # sent before the TCP request, but the tap's thread may record it after the reply
            # has come back (a fresh-machine run: none recorded yet when the reply was read)
            tap.wait("stop", after=n)
    run(go())
    remote.wait_line("pairing refused")
    assert "gear drive" not in remote.output()


def test_replays_and_garbage_close_the_socket_and_lift(
        setup: tuple[Daemon, UdpTap, TouchRemote]) -> None:
    daemon, tap, remote = setup

    async def go() -> None:
        async with aiohttp.ClientSession() as s:
            for bad in ("replay", "garbage", "binary", "bad field"):
                page = await connect(s, remote, token_of(remote))
                await page.pair()
                await page.hold_for(0.15)
                n = tap.count()
                if bad == "replay":
                    await page.send({"t": "held", "at": 1.0, "steer": 0, "gas": 0}, n=page.n)
                elif bad == "garbage":
                    await page.ws.send_str("not a message")
                elif bad == "binary":
                    await page.ws.send_bytes(b"\x00" * 8)
                else:
                    await page.send({"t": "held", "at": 1.0, "steer": 2, "gas": 0})
                msg = await page.ws.receive(timeout=5)
                while msg.type == aiohttp.WSMsgType.TEXT:
                    msg = await page.ws.receive(timeout=5)
                assert msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED), bad
                tap.wait("lift", after=n, n=3)
                await page.ws.close()
    run(go())


def test_one_page_drives_a_second_only_watches(setup: tuple[Daemon, UdpTap, TouchRemote]
                                               ) -> None:
    daemon, tap, remote = setup

    async def go() -> None:
        async with aiohttp.ClientSession() as s:
            first = await connect(s, remote, token_of(remote))
            second = await connect(s, remote, token_of(remote))
            await first.pair()
            await second.pair()
            await first.held()
            n = tap.count()
            await asyncio.gather(first.hold_for(0.5), second.hold_for(0.5))
            sent = len(tap.of("control", n))
            assert 15 <= sent <= 27, sent  # one page's frames, 50 a second, not two pages'
            state = await second.expect("state")
            while state.fields["hold"] != "other":
                state = await second.expect("state")
            await second.send({"t": "lift", "why": "touchend"})  # not its hold
            await asyncio.sleep(0.1)
            assert not tap.of("lift", n)
            await first.send({"t": "lift", "why": "touchend"})
            tap.wait("lift", after=n, n=3)
    run(go())


def test_page_limit_assets_and_their_headers(setup: tuple[Daemon, UdpTap, TouchRemote]
                                             ) -> None:
    daemon, tap, remote = setup

    async def go() -> None:
        async with aiohttp.ClientSession() as s:
            async with s.get(remote.base) as r:
                assert r.status == 200 and "drive area" in await r.text()
                assert r.headers["X-Frame-Options"] == "DENY"
                assert "frame-ancestors 'none'" in r.headers["Content-Security-Policy"]
            for name in ("app.js", "style.css", "blake2s.js"):
                async with s.get(remote.base + "static/" + name) as r:
                    assert r.status == 200, name
            async with s.get(remote.base + "static/../touch.py") as r:
                assert r.status == 404
            # a crowd of pages that never pair cannot keep the driver's page out: the oldest
            # unpaired one makes room; paired pages are never pushed out (a ninth: 503)
            crowd = [await s.ws_connect(remote.base + "ws") for _ in range(MAX_PAGES)]
            driver = await connect(s, remote, token_of(remote))
            await driver.pair()
            assert (await crowd[0].receive(timeout=5)).type in (
                aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
            paired = [driver]
            for _ in range(MAX_PAGES - 1):
                page = await connect(s, remote, token_of(remote))
                await page.pair()
                paired.append(page)
            with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
                await s.ws_connect(remote.base + "ws")
            assert exc.value.status == 503
            n = tap.count()
            await driver.hold_for(0.2)  # the driver drives all along
            tap.wait("control", after=n, n=5)  # the tap's thread may be behind (as above)
            # STOP flooded: one press at a time, the presses meanwhile answered with its outcome
            for _ in range(20):
                await driver.send({"t": "stop"})
            reply = await driver.expect("reply")
            assert reply.fields["what"] == "stop" and reply.fields["ok"]
            for ws in crowd:
                await ws.close()
            for page in paired:
                await page.ws.close()
    run(go())
    time.sleep(1.0)  # any press still queued would be done and said by now
    presses = remote.output().count("STOP pressed")
    assert presses == 20 and remote.output().count("stop -> ") < presses / 2, remote.output()


def test_command_line_errors(setup: tuple[Daemon, UdpTap, TouchRemote],
                             capsys: pytest.CaptureFixture[str]) -> None:
    """Same vocabulary and exit codes as every command: usage 2, unreachable 3."""
    from estop.cli import main
    from net_util import unused_tcp_port

    daemon, tap, remote = setup
    unit = ["--host", "127.0.0.1", "--udp-port", str(daemon.udp_port)]
    assert main(["remote", *unit, "--listen", "127.0.0.1:0", "--script", "wait 0"]) == 2
    assert main(["remote", *unit, "--touch", "--gamepad"]) == 2
    assert main(["remote", *unit, "--touch", "--listen", "nowhere"]) == 2
    assert main(["remote", *unit, "--touch", "--listen", "127.0.0.1:70000"]) == 2
    assert main(["remote", *unit, "--tcp-port", str(unused_tcp_port()), "--touch",
                 "--reply-timeout-ms", "200"]) == 3
    taken = remote.base.rsplit(":", 1)[1].strip("/")
    assert main(["remote", *unit, "--tcp-port", str(daemon.tcp_port), "--touch", "--listen",
                 f"127.0.0.1:{taken}"]) == 3
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 6 and all(line.startswith("estop: error: ") for line in errors)
    assert "cannot listen on 127.0.0.1:" in errors[-1]
