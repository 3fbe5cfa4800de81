"""``estop remote --touch``: a touch page as the remote's dead-man. :mod:`~.run` serves it
and prints its address; :mod:`~.server` is the web side (the page's WebSocket driving the
:class:`~estop.client.sender.Remote`); :mod:`~.hold` the dead-man across the page's hop
(which frames make a packet); :mod:`~.wire` the messages and their pairing MACs; ``static/``
the page itself (HTML, CSS, JavaScript, no CDN)."""

__all__ = ["DEFAULT_LISTEN"]

# Where the page is served unless --listen says otherwise: this machine only. Here, not in
# run, so that estop remote's parser names it without loading the page's server (asyncio).
DEFAULT_LISTEN = "127.0.0.1:8081"
