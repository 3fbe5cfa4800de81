"""Who a remote is to a unit (spec section 5): its key, its remote id among those sharing the
key, the counter it raises with every message and the unit's session as it last learnt it.

One :class:`Identity` goes with a remote to every channel it talks on (the TCP stop channel,
the stop and lift datagrams, the control packets), so that all of them tag with the one key,
carry the one remote id and session and raise the one counter; before, each took them as
loose arguments and the callers kept them in step.

The one counter has a rule of its own with a key (issue 25; docs/REMOTE.md section 4): the
unit refuses a RELEASE that is not above the newest counter it has taken from its remote on
either channel, and it reads its UDP and TCP sockets apart. A control packet made after a
RELEASE (a higher counter) that reaches the unit while the RELEASE still waits in its socket
is read first and makes the RELEASE stale (NAK 4). So from taking a RELEASE's counter until
its reply the identity makes no control packet (:meth:`Identity.control_packet` says None), for
at most :data:`RELEASE_QUIET_S`, so that the dead-man's silence stays short whatever the
unit does.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

from estop.protocol import auth, tcp
from estop.protocol.udp import ControlPacket

__all__ = ["DEFAULT_REMOTE_ID", "RELEASE_QUIET_S", "Identity", "MessageCounter",
           "check_release_quiet"]

DEFAULT_REMOTE_ID = 1  # a remote's id (spec section 5) without a key, unless told otherwise
# The longest a RELEASE in flight holds back the control packets: a 50 Hz remote is then
# silent for at most 70 ms, under the default warn time (100 ms) and far from the timeout.
RELEASE_QUIET_S = 0.05


def check_release_quiet(seconds: float) -> float:
    """``seconds`` if it is a bound for the quiet of a RELEASE in flight (0..1 s; 0: none),
    else ValueError with a one-line message."""
    if not isinstance(seconds, int | float) or not math.isfinite(seconds) \
            or not 0 <= seconds <= 1:
        raise ValueError(f"release quiet must be 0..1 s, got {seconds!r}")
    return float(seconds)


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

    With a key, a RELEASE frame made here starts a quiet: no control packet until the stop
    channel reports its reply (:meth:`answered`), or ``release_quiet_s`` has passed.
    ``on_quiet_end`` (if set) is called, from the stop channel's thread, when the last quiet
    ends by a reply; one that ends by its bound calls nothing (:meth:`quiet_until` said when).
    """

    def __init__(self, key: bytes | None = None, remote_id: int = DEFAULT_REMOTE_ID,
                 counter: MessageCounter | None = None, *,
                 release_quiet_s: float = RELEASE_QUIET_S) -> None:
        self.key = None if key is None else auth.check_key(key)
        self.remote_id = remote_id
        self.counter = counter or MessageCounter()
        self.session = 0
        self.release_quiet_s = check_release_quiet(release_quiet_s)
        self.on_quiet_end: Callable[[], None] | None = None
        # Taking a counter and looking at the quiet happen together under this lock, so no
        # control packet takes a counter above a RELEASE's once the RELEASE has taken it.
        self._lock = threading.Lock()
        self._releases: dict[int, float] = {}  # RELEASE in flight: counter -> end of its quiet

    @property
    def keyed(self) -> bool:
        return self.key is not None

    def request(self, msg_id: int, seq: int) -> auth.AuthRequest:
        """A 48-byte request frame's fields (spec section 5.2), with the next counter; a
        keyed RELEASE starts its quiet."""
        with self._lock:
            counter = self.counter.next()
            if msg_id == tcp.RELEASE and self.keyed and self.release_quiet_s > 0:
                self._releases[counter] = time.monotonic() + self.release_quiet_s
        return auth.AuthRequest(msg_id, seq, self.remote_id, self.session, counter)

    def answered(self, counter: int) -> None:
        """The request made with ``counter`` got its reply, or can get none any more (its
        connection was closed): the unit has read it, or never will. Ends its quiet if it was
        a RELEASE's."""
        with self._lock:
            ended = self._releases.pop(counter, None) is not None and \
                not self._quiet_until(time.monotonic())
        if ended and self.on_quiet_end is not None:
            self.on_quiet_end()

    def quiet_until(self) -> float:
        """While a RELEASE is in flight: when its quiet ends at the latest (on
        ``time.monotonic()``); 0.0 when no control packet is held back."""
        with self._lock:
            return self._quiet_until(time.monotonic())

    def _quiet_until(self, now: float) -> float:
        for counter, end in list(self._releases.items()):
            if end <= now:  # past its bound: the dead-man's silence rules come first
                del self._releases[counter]
        return max(self._releases.values(), default=0.0)

    def request_frame(self, msg_id: int, seq: int) -> bytes:
        """:meth:`request`, encoded and tagged with the key (zero tag without one)."""
        return self.request(msg_id, seq).encode(self.key)

    def control_packet(self, body: ControlPacket) -> bytes | None:
        """The 60-byte authenticated control packet carrying ``body`` (needs the key), with
        the next counter; None while a RELEASE is in flight (nothing is made: send it when
        the quiet ends)."""
        if self.key is None:
            raise ValueError("an authenticated control packet needs a key")
        with self._lock:
            if self._quiet_until(time.monotonic()):
                return None
            counter = self.counter.next()
        return auth.AuthControlPacket(self.remote_id, self.session, counter,
                                      body).encode(self.key)
