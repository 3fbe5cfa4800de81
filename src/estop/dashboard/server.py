"""The web side of ``estop dashboard`` (aiohttp): the page and its assets from the package
(``estop/dashboard/static``: no CDN, the car has no internet), and one server-sent-events
stream of the model's snapshots.

Cheap by design: the snapshot is built and encoded once per push for every client. A state
change (a new timeline entry, or the 50 ms silence rule) is pushed at once, at most every
50 ms; anything else (counters, period, status fields) at most every 200 ms, which is also
the heartbeat the page watches (500 ms without one: it says it lost its feed). So a page
gets at most 20 updates a second, however fast the frames come. A client that does not read
holds up only itself: it keeps the latest snapshot, never a queue.

There is no way to release or drive the car here. With a stop action (``--allow-stop``) the
page gets a STOP button: ``POST /stop`` with the header ``X-Estop-Stop: 1`` (a page of
another site cannot send it without the server's consent) presses the stop button of
``estop stop`` (datagram plus TCP, retried until the deadline).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from collections.abc import Callable

from aiohttp import web

from estop.dashboard.model import DashboardModel
from estop.web import StaticPages, serve

__all__ = ["MIN_INTERVAL", "REGULAR_INTERVAL", "DashboardServer", "ServerThread",
           "stop_action_for"]

MIN_INTERVAL = 0.05  # s between two pushes: at most 20 updates a second
REGULAR_INTERVAL = 0.2  # s: counters and the heartbeat
_STATIC = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css"}

StopAction = Callable[[], str]  # presses stop, returns the outcome in one line (blocking)


class _Client:
    """One page's stream: only the latest snapshot waits to be written."""

    def __init__(self) -> None:
        self.latest: bytes | None = None
        self.ready = asyncio.Event()
        self.sent = 0

    def put(self, data: bytes) -> None:
        self.latest = data
        self.ready.set()


class DashboardServer:
    """Serves ``model`` on ``host:port`` (port 0: a free one; :attr:`port` after
    :meth:`start`). Feed the model through :meth:`can_line`, :meth:`log_line`,
    :meth:`frame` and :meth:`note`, on the server's loop: they wake the pusher."""

    def __init__(self, model: DashboardModel, host: str, port: int, *,
                 stop_action: StopAction | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.model = model
        self.host = host
        self.port = port
        self.stop_action = stop_action
        self.clock = clock
        self.clients: set[_Client] = set()
        self.pushes = 0  # snapshots built and sent (to every client)
        self._urgent = asyncio.Event()
        self._runner: web.AppRunner | None = None
        self._pusher: asyncio.Task[None] | None = None
        self._stopping = asyncio.Event()
        self._pages = StaticPages("estop.dashboard", _STATIC, {"Cache-Control": "no-cache"})

    # ------------------------------------------------------------------ feeding the model

    def _take(self, take: Callable[[], None]) -> None:
        """Give the model one input; a change it shows at once wakes the pusher. Whatever
        goes wrong inside is said on the page: a feed never stops on one bad input."""
        changes = self.model.changes
        try:
            take()
        except Exception as exc:  # the feed must go on
            self.model.note(f"internal error on an input: {type(exc).__name__}: {exc}"[:200])
        if self.model.changes != changes:
            self._urgent.set()

    def can_line(self, line: str, arrived: float) -> None:
        self._take(lambda: self.model.can_line(line, arrived))

    def frame(self, t: float, can_id: int, data: bytes) -> None:
        self._take(lambda: self.model.frame(t, can_id, data, self.clock()))

    def log_line(self, line: str, arrived: float) -> None:
        self._take(lambda: self.model.log_line(line, arrived))

    def note(self, text: str) -> None:
        self.model.note(text)
        self._urgent.set()

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        app = web.Application()
        self._pages.add_routes(app)
        app.router.add_get("/events", self._events)
        app.router.add_post("/stop", self._stop)
        self._runner, self.port = await serve(app, self.host, self.port)
        self._pusher = asyncio.get_running_loop().create_task(self._push())

    async def close(self) -> None:
        self._stopping.set()
        if self._pusher is not None:
            self._pusher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pusher
        for client in self.clients:
            client.ready.set()  # wake the streams so they end
        if self._runner is not None:
            await self._runner.cleanup()

    # ------------------------------------------------------------------ pushing

    def encode(self) -> bytes:
        snap = self.model.snapshot(self.clock())
        snap["allow_stop"] = self.stop_action is not None
        try:
            body = json.dumps(snap, separators=(",", ":"), allow_nan=False)
        except ValueError:  # a figure that is not finite: the page could not parse it
            snap["link"] = {"edges_us": [], "counts": [], "error": "a figure is not finite"}
            body = json.dumps(snap, separators=(",", ":"))
        return b"data: " + body.encode() + b"\n\n"

    async def _push(self) -> None:
        """Push when the page must change at once (a new timeline entry, the 50 ms rule
        turning the state to NO SIGNAL) or when 200 ms passed since the last push; never
        two pushes within 50 ms."""
        loop = asyncio.get_running_loop()
        last_push = loop.time()
        had_signal = False
        while True:
            wait = last_push + REGULAR_INTERVAL - loop.time()
            deadline = self.model.deadline(self.clock())
            if deadline is not None:  # the 50 ms rule turns the state without any input
                wait = min(wait, deadline - self.clock() + 0.001)
            if wait > 0:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._urgent.wait(), wait)
            signal = self.model.signal(self.clock())
            due = (self._urgent.is_set() or (had_signal and not signal)
                   or loop.time() - last_push >= REGULAR_INTERVAL)
            had_signal = signal
            if not due:
                continue  # a deadline that a newer frame moved on
            self._urgent.clear()
            if self.clients:
                data = self.encode()
                self.pushes += 1
                for client in self.clients:
                    client.put(data)
            last_push = loop.time()
            await asyncio.sleep(MIN_INTERVAL)

    # ------------------------------------------------------------------ handlers

    async def _events(self, request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})
        await resp.prepare(request)
        client = _Client()
        client.put(self.encode())
        self.clients.add(client)
        try:
            while not self._stopping.is_set():
                await client.ready.wait()
                client.ready.clear()
                data, client.latest = client.latest, None
                if data is None:
                    continue
                await resp.write(data)
                client.sent += 1
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self.clients.discard(client)
        return resp

    async def _stop(self, request: web.Request) -> web.Response:
        action = self.stop_action
        if action is None:
            raise web.HTTPForbidden(text="this dashboard was started without --allow-stop")
        if request.headers.get("X-Estop-Stop") != "1":
            raise web.HTTPForbidden(text="missing X-Estop-Stop header")
        line = await asyncio.get_running_loop().run_in_executor(None, action)
        self.model.note(f"STOP pressed on the page: {line}")
        self._urgent.set()
        return web.json_response({"outcome": line})


def stop_action_for(host: str, tcp_port: int, udp_port: int, *, key: bytes | None,
                    remote_id: int, stop_id: int, timeout: float,
                    deadline: float) -> StopAction:
    """The stop button of ``estop stop`` (:func:`estop.client.oneshot.stop_once`), as a callable."""
    from estop.client.oneshot import stop_once

    def press() -> str:
        outcome = stop_once(host, tcp_port, udp_port, stop_id=stop_id, timeout=timeout,
                            deadline=deadline, key=key, remote_id=remote_id)
        return outcome.line() if outcome.reply is not None else outcome.summary()

    return press



class ServerThread:
    """The server on a thread of its own, for a program that is not asyncio (``estop demo
    --dashboard``): :meth:`can_line` from any thread."""

    def __init__(self, host: str, port: int) -> None:
        self._loop = asyncio.new_event_loop()
        self.server = DashboardServer(DashboardModel(), host, port)
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="dashboard", daemon=True)

    def start(self, wait_s: float = 10.0) -> str:
        """Start serving; return the page's address (raises OSError if it cannot listen)."""
        self._thread.start()
        if not self._started.wait(wait_s):
            raise OSError("the dashboard did not start")
        if self._error is not None:
            raise self._error
        host = self.server.host
        return f"http://{f'[{host}]' if ':' in host else host}:{self.server.port}/"

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self.server.start())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._started.set()
            return
        self._started.set()
        self._loop.run_forever()
        self._loop.run_until_complete(self.server.close())
        self._loop.close()

    def can_line(self, line: str) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is closing
            self._loop.call_soon_threadsafe(self.server.can_line, line, time.time())

    def log_line(self, line: str) -> None:
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self.server.log_line, line, time.time())

    def close(self) -> None:
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=5)
