"""The aiohttp site both pages use (the dashboard, the touch remote): started without
aiohttp's signal handlers or access log, closed quickly, on the port asked for (0: the kernel
picks one, and the caller learns which)."""

from __future__ import annotations

from importlib import resources

from aiohttp import web

__all__ = ["StaticPages", "serve"]


async def serve(app: web.Application, host: str, port: int) -> tuple[web.AppRunner, int]:
    """Serve ``app`` on ``host:port``; return its runner (``cleanup()`` ends it) and the port
    it listens on."""
    runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=0.5)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    # aiohttp has no public accessor for the bound socket; port 0 needs it
    server = getattr(site, "_server", None)
    sockets = getattr(server, "sockets", None) or []
    if sockets:
        port = int(sockets[0].getsockname()[1])
    return runner, port


class StaticPages:
    """A page's files, read once from ``package``'s ``static`` folder: ``/`` is index.html,
    ``/static/NAME`` the others; any other name is 404 (nothing else on disk is served)."""

    def __init__(self, package: str, types: dict[str, str], headers: dict[str, str]) -> None:
        self._types = dict(types)
        self._headers = dict(headers)
        self._files = {name: resources.files(package).joinpath("static", name).read_bytes()
                       for name in self._types}

    def add_routes(self, app: web.Application) -> None:
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)

    async def _index(self, request: web.Request) -> web.Response:
        return self._file("index.html")

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in self._types:
            raise web.HTTPNotFound()
        return self._file(name)

    def _file(self, name: str) -> web.Response:
        return web.Response(body=self._files[name], content_type=self._types[name],
                            headers=self._headers)
