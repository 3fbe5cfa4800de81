"""estop.web: the site both pages share (the dashboard, the touch remote)."""

from __future__ import annotations

import asyncio
import urllib.error
import urllib.request

from aiohttp import web

from estop.web import StaticPages, serve

_TYPES = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css"}


def _get(url: str) -> tuple[int, dict[str, str], bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return resp.status, dict(resp.headers), resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), b""


def test_a_site_on_port_0_learns_its_port_and_serves_only_its_files() -> None:
    async def run() -> list[tuple[int, dict[str, str], bytes]]:
        app = web.Application()
        StaticPages("estop.dashboard", _TYPES, {"X-Frame-Options": "DENY"}).add_routes(app)
        runner, port = await serve(app, "127.0.0.1", 0)
        try:
            assert port > 0
            base = f"http://127.0.0.1:{port}"
            urls = [base + "/", base + "/static/app.js", base + "/static/../pyproject.toml",
                    base + "/static/model.py", base + "/etc/passwd"]
            return [await asyncio.to_thread(_get, u) for u in urls]
        finally:
            await runner.cleanup()

    index, app_js, dotdot, source, other = asyncio.run(run())
    assert index[0] == 200 and index[1]["Content-Type"].startswith("text/html")
    assert b"<html" in index[2].lower() and index[1]["X-Frame-Options"] == "DENY"
    assert app_js[0] == 200 and app_js[1]["Content-Type"].startswith("text/javascript")
    assert [dotdot[0], source[0], other[0]] == [404, 404, 404]
