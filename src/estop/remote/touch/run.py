"""``estop remote --touch``: the remote serves a touch page, and any phone, tablet or touch
laptop with a browser drives with a real dead-man (a finger on the page).

The process is the remote: it holds the key, the counter and the stop channel
(:class:`~estop.client.sender.Remote`, not paced: one control packet per fresh frame from the
page); the page (``static/`` beside this module, served by :mod:`estop.remote.touch.server`)
never sees the key. It listens on 127.0.0.1:8081 unless ``--listen ADDR:PORT`` says
otherwise: another address serves the network, an explicit choice. Either way the page pairs
with a token drawn at each start; the address printed first carries it in its fragment
(``#k=...``, which a browser never sends), and beyond loopback a QR code of it is printed too,
for the tablet's camera. A page without the token sees the state and may press STOP, nothing
else.

The run ends on Ctrl-C, SIGTERM or SIGHUP (a hold still on ends with its lift, as every run
of ``estop remote``); exit code 3 when the unit cannot be reached at the start (with a key,
its session must be learnt) or the address cannot be listened on, 5 without the extra.
"""

from __future__ import annotations

import asyncio
import io
import signal
from collections.abc import Callable

from estop.client.channel import StopChannel, StopChannelError, format_reply
from estop.client.sender import Remote
from estop.errors import ConnectionFailure
from estop.extras import require_extra
from estop.remote.touch import DEFAULT_LISTEN
from estop.remote.touch.wire import encode_token, new_token

__all__ = ["DEFAULT_LISTEN", "LOOPBACK", "page_url", "qr_text", "run_touch"]

LOOPBACK = ("127.0.0.1", "localhost", "::1")
Log = Callable[[str], None]


def page_url(host: str, port: int, token: bytes) -> str:
    """The address to open: the token in the fragment, which the browser keeps to itself."""
    if host in ("0.0.0.0", "::", ""):
        host = _outward_address() or host
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/#k={encode_token(token)}"


def _outward_address() -> str | None:
    """This machine's address towards the network (for a page served on every address), read
    from the route a UDP socket would take; no packet is sent."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: only the route is looked up
            return str(s.getsockname()[0])
        except OSError:
            return None


def qr_text(url: str) -> str:
    """``url`` as a QR code in the terminal (half blocks), for a tablet's camera."""
    require_extra("touch", "segno")
    import segno

    buf = io.StringIO()
    segno.make(url, error="m").terminal(out=buf, compact=True)
    return buf.getvalue()


def _interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def run_touch(remote: Remote, host: str, port: int, *, log: Log, say: Log, warn: Log) -> int:
    """Serve the page on ``host:port`` and drive ``remote`` from it until Ctrl-C, SIGTERM or
    SIGHUP (the caller lifts a hold still on and closes the remote). ``say`` prints what
    must be seen (the address, the QR code), ``warn`` a warning, ``log`` the events."""
    require_extra("touch", "aiohttp")
    listen = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    try:
        first = remote.status()  # the unit is there, and its session is known before a hold
    except StopChannelError as exc:
        raise ConnectionFailure(f"status (to reach the unit and learn its session): "
                                f"{exc}") from None
    stop_channel = StopChannel(remote.addr[0], remote.channel.port,
                               timeout=remote.channel.timeout, stop_id=remote.channel.stop_id,
                               identity=remote.identity)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _interrupt)
    try:
        asyncio.run(_serve(remote, stop_channel, host, port, listen,
                           f"status -> {format_reply(first)}", log, say, warn))
    except KeyboardInterrupt:
        pass
    finally:
        stop_channel.close()
    return 0


async def _serve(remote: Remote, stop_channel: StopChannel, host: str, port: int, listen: str,
                 first: str, log: Log, say: Log, warn: Log) -> None:
    from estop.remote.touch.server import TouchServer  # aiohttp: imported once it is known

    token = new_token()
    server = TouchServer(remote, host, port, token, stop_channel=stop_channel, log=log)
    try:
        try:
            await server.start()
        except OSError as exc:
            raise ConnectionFailure(f"cannot listen on {listen}: {exc.strerror or exc}") \
                from None
        url = page_url(host, server.port, token)
        say(f"estop remote --touch: open {url}")
        if host in LOOPBACK:
            say("  (this machine only, the default; --listen ADDR:PORT serves a tablet)")
        else:
            warn(f"estop remote --touch: the page is open to the network on {host} "
                 "(--listen); it drives only with the pairing token in its address")
            say(qr_text(url))
        log(first)
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            loop.add_signal_handler(sig, done.set)
        try:
            await done.wait()
        finally:
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                loop.remove_signal_handler(sig)
    finally:
        await server.close()
