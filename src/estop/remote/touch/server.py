"""The web side of ``estop remote --touch`` (aiohttp): the page and its assets from the package
(``estop/remote/touch/static``: no CDN), and one WebSocket per page
(:mod:`estop.remote.touch.wire`).

The server is the remote's second hop. It holds the :class:`~estop.client.sender.Remote` (the
key, the counter, the stop channel): the page never sees the key. From the page:

- ``held`` frames: one control packet for each fresh one (:mod:`estop.remote.touch.hold`), sent from
  the event loop at once (the remote is not paced: the page's clock is the packet clock);
- ``lift`` (the last finger left, touchcancel, the page hidden or left): the lift datagrams at
  once, the first before the handler returns; the same when the holding page's socket closes;
- ``stop``: the stop button of ``estop stop`` (datagram and TCP, retried until the deadline)
  on a stop channel of its own, so a slow STATUS never delays it; any page may stop;
- ``release``, ``gear``: a paired page only.

To the page: the unit's state from STATUS replies (polled every :data:`POLL_S`), whether a
hold is on and whose, the round trip to the unit, the packets sent and lost and the frames
that came late; each page's own round trip is the page's to measure (``ping``/``pong``).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from aiohttp import WSMsgType, web

from estop.client.button import press_stop
from estop.client.channel import StopChannel, StopChannelError
from estop.client.sender import Remote
from estop.protocol.can import FLAG_LINK_DEGRADED, reason_name, state_name
from estop.protocol.udp import Gear, InvalidPacket
from estop.remote import actions
from estop.remote.touch.hold import DeadMan, Verdict
from estop.remote.touch.wire import (
    Message,
    WireError,
    counter,
    new_nonce,
    parse,
    parse_held,
    seal,
)
from estop.web import StaticPages, serve

__all__ = ["MAX_PAGES", "POLL_S", "TouchServer"]

POLL_S = 0.1  # STATUS every 100 ms: the state on the page is at most that old (plus the trip)
PUSH_S = 0.25  # the state goes to the pages at least this often, at once when it changes
MAX_PAGES = 8  # pages at once; a ninth pushes out the oldest unpaired one, else 503
_STATIC = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css",
           "blake2s.js": "text/javascript"}
_HEADERS = {"Cache-Control": "no-store", "X-Frame-Options": "DENY",
            "Referrer-Policy": "no-referrer",
            "Content-Security-Policy": "default-src 'self'; connect-src 'self'; "
                                       "frame-ancestors 'none'"}
_GEARS = {g.name.lower(): g for g in (Gear.PARK, Gear.REVERSE, Gear.NEUTRAL, Gear.DRIVE)}
Log = Callable[[str], None]


@dataclass
class _Page:
    """One WebSocket: its nonces, its counters, whether it proved the token."""

    id: int
    ws: web.WebSocketResponse
    addr: str
    nonce: bytes = field(default_factory=new_nonce)  # the server's: the page MACs with it
    page_nonce: bytes | None = None  # the page's: the server MACs with it, once paired
    n_in: int = 0
    n_out: int = 0
    # what waits to be written: (message, whether it is MACed); counters and MACs are put on
    # as each is written, so the page sees the counters rise in the order it reads them
    latest: tuple[dict[str, Any], bool] | None = None  # the newest state, not yet written
    replies: list[tuple[dict[str, Any], bool]] = field(default_factory=list)
    wake: asyncio.Event = field(default_factory=asyncio.Event)

    @property
    def paired(self) -> bool:
        return self.page_nonce is not None


@dataclass
class _Unit:
    """The unit as the STATUS replies show it."""

    state: str = "UNKNOWN"
    reason: str = ""
    flags: int = 0
    error: str = ""
    at: float = 0.0  # monotonic time of the latest reply (or error)
    rtt_ms: float | None = None


class TouchServer:
    """Serves the touch page on ``host:port`` (port 0: a free one; :attr:`port` after
    :meth:`start`) and drives ``remote`` from it. ``token`` is the pairing token; ``log``
    gets one line per event worth telling (a hold, a lift, a stall, a press)."""

    def __init__(self, remote: Remote, host: str, port: int, token: bytes, *,
                 stop_channel: StopChannel, log: Log) -> None:
        self.remote = remote
        self.host = host
        self.port = port
        self.token = token
        self.stop_channel = stop_channel
        self.log = log
        self.deadman = DeadMan(1.0 / remote.rate_hz)
        self.unit = _Unit()
        self.pages: dict[int, _Page] = {}
        self.lift_reasons: list[str] = []
        self._ids = itertools.count(1)
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._changed = asyncio.Event()
        self._poll_now = asyncio.Event()
        self._stop_waiters: list[_Page] | None = None  # pages waiting for the press in flight
        # TCP off the loop: STATUS and RELEASE share the remote's channel (its session), one
        # at a time; the stop button has its own channel and thread, so it never waits
        self._tcp = ThreadPoolExecutor(1, thread_name_prefix="touch-tcp")
        self._stop = ThreadPoolExecutor(1, thread_name_prefix="touch-stop")
        self._pages = StaticPages("estop.remote.touch", _STATIC, _HEADERS)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        app = web.Application()
        self._pages.add_routes(app)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/favicon.ico", self._no_icon)
        self._runner, self.port = await serve(app, self.host, self.port)
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._poll()), loop.create_task(self._watch())]

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self.deadman.holder is not None:
            self._end_hold(self.deadman.holder, "the remote is closing")
        for page in list(self.pages.values()):
            with contextlib.suppress(Exception):
                await page.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
        self._tcp.shutdown(wait=False, cancel_futures=True)
        self._stop.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------ the dead-man

    def _held(self, page: _Page, fields: dict[str, Any]) -> None:
        frame = parse_held(fields)
        was_stalled = self.deadman.is_stalled
        verdict = self.deadman.frame(page.id, frame.at_ms, time.monotonic())
        if verdict is not Verdict.SEND:
            return
        if was_stalled:
            self._changed.set()
        remote = self.remote
        try:
            remote.set_control(steering=frame.steer, gas_brake=frame.gas)
        except InvalidPacket as exc:  # cannot happen with parse_held's ranges; never fatal
            self.log(f"page {page.id}: control ignored: {exc}")
            return
        if not remote.held:
            if remote.identity.keyed and not remote.identity.session:
                self.deadman.end(page.id)  # no session yet: a packet would keep nothing alive
                return
            remote.hold()  # the session is known: no network here
            self.log(f"page {page.id}: finger down: sending control packets")
            self._changed.set()
        remote.pulse()

    def _end_hold(self, page_id: int, why: str) -> None:
        if not self.deadman.end(page_id):
            return
        n = actions.lift(self.remote)  # the first lift datagram is out when this returns
        self.lift_reasons.append(why)
        self.log(f"page {page_id}: {why}: lift sent x{n}" if n else f"page {page_id}: {why}")
        self._changed.set()

    async def _watch(self) -> None:
        """Says when a hold stalls (no fresh frame for two periods): nothing is sent then.
        A loaded phone misses a period now and then: one line a second at most, counting."""
        said_at, unsaid = -1e9, 0
        while True:
            await asyncio.sleep(self.deadman.period / 2)
            now = time.monotonic()
            if self.deadman.stalled(now):
                self._changed.set()
                unsaid += 1
            if unsaid and now - said_at >= 1.0:
                more = f" ({unsaid} stalls since the last line)" if unsaid > 1 else ""
                self.log(f"page {self.deadman.holder}: no fresh frame for 2 periods: no "
                         f"control packets (the unit slows at S, stops at T){more}")
                said_at, unsaid = now, 0

    # ------------------------------------------------------------------ the unit

    async def _poll(self) -> None:
        loop = asyncio.get_running_loop()
        last_push = 0.0
        while True:
            t0 = time.monotonic()
            unit = self.unit
            before = (unit.state, unit.reason, unit.error)
            try:
                reply = await loop.run_in_executor(self._tcp, self.remote.status)
                unit.state = state_name(reply.state)
                unit.reason = reason_name(reply.reason) if reply.reason else ""
                unit.flags = reply.flags
                unit.error = ""
                unit.rtt_ms = (time.monotonic() - t0) * 1000.0
            except StopChannelError as exc:
                unit.state, unit.reason, unit.error = "UNREACHABLE", "", str(exc)
                unit.rtt_ms = None
            unit.at = time.monotonic()
            if (unit.state, unit.reason, unit.error) != before:
                self._changed.set()
            if self._changed.is_set() or unit.at - last_push >= PUSH_S:
                self._changed.clear()
                self._push_state()
                last_push = unit.at
            wait = POLL_S if not unit.error else 0.5
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._poll_now.wait(), wait)
            self._poll_now.clear()

    def _state_for(self, page: _Page) -> dict[str, Any]:
        unit, stats, hold = self.unit, self.remote.stats, self.deadman
        holder = hold.holder
        return {"t": "state", "state": unit.state, "reason": unit.reason,
                "degraded": bool(unit.flags & FLAG_LINK_DEGRADED), "error": unit.error,
                "unit_rtt_ms": None if unit.rtt_ms is None else round(unit.rtt_ms, 1),
                "gear": Gear(self.remote.control.gear).name.lower(),
                "hold": "none" if holder is None else "you" if holder == page.id else "other",
                "stalled": hold.is_stalled, "paired": page.paired,
                "sent": stats.sent, "lost": stats.lost + stats.send_errors,
                "late": hold.stats.late}

    def _push_state(self) -> None:
        for page in self.pages.values():
            self._set_state(page)

    def _set_state(self, page: _Page) -> None:
        page.latest = (self._state_for(page), page.paired)
        page.wake.set()

    # ------------------------------------------------------------------ pages

    def _seal(self, page: _Page, msg: dict[str, Any], authenticated: bool) -> str:
        if not authenticated:
            return seal(msg)
        page.n_out += 1
        return seal({**msg, "n": page.n_out}, self.token, page.page_nonce)

    def _reply(self, page: _Page, msg: dict[str, Any]) -> None:
        if len(page.replies) < 16:  # a page that does not read keeps only a few
            page.replies.append((msg, page.paired))
            page.wake.set()

    async def _writer(self, page: _Page) -> None:
        """Writes a page's replies and its latest state; a page that does not read holds up
        only this task, and keeps the newest state, never a queue of them."""
        while not page.ws.closed:
            await page.wake.wait()
            page.wake.clear()
            out, page.replies = page.replies, []
            if page.latest is not None:
                out.append(page.latest)
                page.latest = None
            for msg, authenticated in out:
                await page.ws.send_str(self._seal(page, msg, authenticated))

    async def _no_icon(self, request: web.Request) -> web.Response:
        return web.Response(status=204, headers=_HEADERS)

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if len(self.pages) >= MAX_PAGES:
            # room for a newcomer: the oldest page that never paired goes (else a few sockets
            # opened by anyone would keep the driver's page out)
            unpaired = [p for p in self.pages.values() if not p.paired]
            if not unpaired:
                raise web.HTTPServiceUnavailable(text=f"{MAX_PAGES} paired pages already")
            oldest = min(unpaired, key=lambda p: p.id)
            self.log(f"page {oldest.id} ({oldest.addr}): closed to make room (never paired)")
            del self.pages[oldest.id]
            self._spawn(oldest.ws.close())  # its handler ends when the close is done
        # the heartbeat finds a page whose network went away without a word (its socket
        # half-open): closed, and a hold on it ends with a lift
        ws = web.WebSocketResponse(heartbeat=1.0, max_msg_size=4096, timeout=2.0)
        await ws.prepare(request)
        page = _Page(next(self._ids), ws, request.remote or "?")
        self.pages[page.id] = page
        writer = asyncio.get_running_loop().create_task(self._writer(page))
        why = "its socket closed"
        try:
            await ws.send_str(seal({"t": "hello", "nonce": page.nonce.hex(),
                                    "period_ms": round(self.deadman.period * 1000, 3),
                                    "page": page.id}))
            self._set_state(page)
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    why = "it sent a binary frame"
                    break
                try:
                    self._handle(page, parse(msg.data, self.token, page.nonce))
                except WireError as exc:
                    self.log(f"page {page.id}: bad message ({exc}): closed")
                    why = f"bad message ({exc})"
                    break
        finally:
            self._end_hold(page.id, f"WebSocket closed ({why})")
            self.deadman.forget(page.id)
            self.pages.pop(page.id, None)
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await writer
            await ws.close()
            self.log(f"page {page.id} gone ({why})")
        return ws

    def _handle(self, page: _Page, msg: Message) -> None:
        kind, fields = msg.kind, msg.fields
        if msg.authentic:
            n = counter(fields)
            if n <= page.n_in:
                raise WireError(f"counter {n} not above {page.n_in} (a replay)")
            page.n_in = n
        if kind == "stop":  # anyone may stop, paired or not
            self._press_stop(page)
            return
        if kind == "ping":
            self._reply(page, {"t": "pong", "id": fields.get("id")})
            return
        if kind == "pair":
            self._pair(page, msg)
            return
        if not (msg.authentic and page.paired):
            if kind == "lift":
                return  # a lift of a page that could not hold changes nothing
            self._reply(page, {"t": "refused", "what": kind,
                               "why": "not paired: open the address with its pairing token"})
            return
        if kind == "held":
            self._held(page, fields)
        elif kind == "lift":
            why = fields.get("why")
            self._end_hold(page.id, f"lift ({why if isinstance(why, str) else '?'})"[:80])
        elif kind == "release":
            self._request(page, "release")
        elif kind == "gear":
            self._gear(page, fields.get("gear"))
        else:
            raise WireError(f"unknown type {kind[:20]!r}")

    def _pair(self, page: _Page, msg: Message) -> None:
        nonce = msg.fields.get("nonce")
        if page.paired:
            raise WireError("paired already")
        if not msg.authentic or not isinstance(nonce, str) or len(nonce) != 32:
            self.log(f"page {page.id} ({page.addr}): pairing refused (a wrong token)")
            self._reply(page, {"t": "refused", "what": "pair",
                               "why": "wrong pairing token"})
            return
        try:
            page.page_nonce = bytes.fromhex(nonce)
        except ValueError:
            raise WireError("nonce: not hex") from None
        self.log(f"page {page.id} ({page.addr}): paired")
        self._reply(page, {"t": "paired"})
        self._set_state(page)

    def _gear(self, page: _Page, name: object) -> None:
        gear = _GEARS.get(name) if isinstance(name, str) else None
        if gear is None:
            raise WireError(f"gear: {str(name)[:20]!r} is not one of {', '.join(_GEARS)}")
        self.remote.set_control(gear=gear)
        self.log(f"page {page.id}: gear {name}")
        self._changed.set()
        self._push_state()

    # ------------------------------------------------------------------ requests

    def _request(self, page: _Page, what: str) -> None:
        """RELEASE (or STATUS) as every front-end does it (:mod:`estop.remote.actions`), off
        the loop, on the remote's channel; the reply's line goes to the page."""
        async def run() -> None:
            loop = asyncio.get_running_loop()
            try:
                done = await loop.run_in_executor(self._tcp, actions.request, self.remote, what)
                line, ok = done.line.partition(" -> ")[2], done.reply is not None and \
                    done.reply.ack
                hint = self.remote.channel.nak_hint(done.reply) if done.reply else None
                if hint:
                    line += f" ({hint})"
            except StopChannelError as exc:
                line, ok = f"error: {exc}", False
            self.log(f"page {page.id}: {what} -> {line}")
            self._reply(page, {"t": "reply", "what": what, "ok": ok, "line": line})
            self._poll_now.set()

        self._spawn(run())

    def _press_stop(self, page: _Page) -> None:
        """One press at a time: STOP pressed again (on any page) while a press is still
        trying is answered with that press's outcome, so a page that floods STOP queues
        nothing behind it."""
        self.log(f"page {page.id}: STOP pressed")
        if self._stop_waiters is not None:
            self._stop_waiters.append(page)
            return
        self._stop_waiters = [page]

        def press() -> tuple[bool, str]:
            outcome = press_stop(self.stop_channel, deadline=self.remote.stop_deadline,
                                 datagram=self.remote.datagram)
            return outcome.acked, outcome.line()

        async def run() -> None:
            try:
                ok, line = await asyncio.get_running_loop().run_in_executor(self._stop, press)
            finally:
                waiters, self._stop_waiters = self._stop_waiters or [], None
            self.log(f"stop -> {line}")
            for waiter in {w.id: w for w in waiters}.values():
                self._reply(waiter, {"t": "reply", "what": "stop", "ok": ok, "line": line})
            self._poll_now.set()

        self._spawn(run())

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.append(task)
        task.add_done_callback(self._done)

    def _done(self, task: asyncio.Task[Any]) -> None:
        """A task's end; one that failed is said (a bug), never swallowed."""
        if task in self._tasks:
            self._tasks.remove(task)
        if not task.cancelled() and task.exception() is not None:
            exc = task.exception()
            self.log(f"internal error (a bug, please report it): {type(exc).__name__}: {exc}")
