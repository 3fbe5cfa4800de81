"""Who a remote is to a unit (spec section 5): its key, its remote id among those sharing the
key, the counter it raises with every message and the unit's session as it last learnt it.

One :class:`Identity` goes with a remote to every channel it talks on (the TCP stop channel,
the stop and lift datagrams, the control packets), so that all of them tag with the one key,
carry the one remote id and session and raise the one counter; before, each took them as
loose arguments and the callers kept them in step.
"""

from __future__ import annotations

import threading
import time

from estop.protocol import auth
from estop.protocol.udp import ControlPacket

__all__ = ["DEFAULT_REMOTE_ID", "Identity", "MessageCounter"]

DEFAULT_REMOTE_ID = 1  # a remote's id (spec section 5) without a key, unless told otherwise


class MessageCounter:
    """The u64 counter a remote raises with every message (spec section 5). It starts at the
    wall clock in microseconds, so a remote started again continues above the counters it
    used before. Thread-safe."""

    def __init__(self, start: int | None = None) -> None:
        self._last = (time.time_ns() // 1000 if start is None else start) - 1
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            self._last = (self._last + 1) & 0xFFFFFFFFFFFFFFFF
            return self._last

    @property
    def last(self) -> int:
        """The counter most recently handed out."""
        with self._lock:
            return self._last


class Identity:
    """A remote's keyed identity. ``key`` None: the plain forms (and 48-byte frames with zero
    tags where a frame is asked for). ``session`` is the unit's session as last seen in a
    verified reply (0: not known yet); the stop channel writes it, every message carries it.
    """

    def __init__(self, key: bytes | None = None, remote_id: int = DEFAULT_REMOTE_ID,
                 counter: MessageCounter | None = None) -> None:
        self.key = None if key is None else auth.check_key(key)
        self.remote_id = remote_id
        self.counter = counter or MessageCounter()
        self.session = 0

    @property
    def keyed(self) -> bool:
        return self.key is not None

    def request(self, msg_id: int, seq: int) -> auth.AuthRequest:
        """A 48-byte request frame's fields (spec section 5.2), with the next counter."""
        return auth.AuthRequest(msg_id, seq, self.remote_id, self.session, self.counter.next())

    def request_frame(self, msg_id: int, seq: int) -> bytes:
        """:meth:`request`, encoded and tagged with the key (zero tag without one)."""
        return self.request(msg_id, seq).encode(self.key)

    def control_packet(self, body: ControlPacket) -> bytes:
        """The 60-byte authenticated control packet carrying ``body`` (needs the key)."""
        if self.key is None:
            raise ValueError("an authenticated control packet needs a key")
        return auth.AuthControlPacket(self.remote_id, self.session, self.counter.next(),
                                      body).encode(self.key)
