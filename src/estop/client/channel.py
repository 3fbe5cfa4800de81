"""Client side of the TCP stop channel, the project's one request/reply client: one
connection, requests answered by reply frames (plain, or keyed and verified, under the
remote's :class:`~estop.client.identity.Identity`), and how a reply reads.

Used by ``estop stop|lift|release|status`` (one request per connection), by
:class:`estop.client.sender.Remote` (one connection kept open, as the tablet does), by the
stop button (:mod:`estop.client.button`) and by the loopback link of the demo and the
benchmarks (:mod:`estop.unit.looplink`).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator

from estop.client.identity import Identity
from estop.protocol import auth, tcp
from estop.protocol.can import flag_names, reason_name, state_name
from estop.protocol.tcp import FrameAssembler, Reply, Request

__all__ = [
    "ConnectionClosed",
    "ReplyNotAuthentic",
    "StopChannel",
    "StopChannelError",
    "format_reply",
    "nak_hint",
    "reply_dict",
]

class StopChannelError(OSError):
    """Connecting, sending or receiving failed, or the reply was malformed. One-line ``str``."""


class ConnectionClosed(StopChannelError):
    """The unit closed the connection before replying."""


class ReplyNotAuthentic(StopChannelError):
    """A reply whose tag does not verify under the key: forged, replayed, or from a unit with
    another key (or none). Nothing in it may be believed."""


def format_reply(reply: Reply) -> str:
    """``ACK seq=1 state=STOPPED reason=tcp_stop flags=0x00`` (+ `` nak=<name>`` for a NAK)."""
    flags = f"flags={reply.flags:#04x}"
    names = flag_names(reply.flags)
    if names:
        flags += "(" + ",".join(names) + ")"
    text = (f"{'ACK' if reply.ack else 'NAK'} seq={reply.seq} state={state_name(reply.state)} "
            f"reason={reason_name(reply.reason)} {flags}")
    if not reply.ack:
        text += f" nak={tcp.NAK_NAMES.get(reply.nak_code, str(reply.nak_code))}"
    return text


def nak_hint(reply: Reply, keyed: bool, remote_id: int, *, same_session: bool = True
             ) -> str | None:
    """Why the unit said NAK not_authenticated, where the client can tell (spec section 5);
    None for any other reply. With a key, the reply verified (else it raised): the unit has
    this key, and the request carried its session, so it refused the counter (kept higher for
    this remote id: another remote uses the same id) or had no place left for the id."""
    if reply.ack or reply.nak_code != tcp.NakCode.NOT_AUTHENTICATED:
        return None
    if not keyed:
        return "the unit has a key: give --key-file (or ESTOP_KEY_FILE, or key_file in the config)"
    if not same_session:
        return "the unit has a new session (it restarted since the last reply): ask again"
    return (f"the unit has this key and this session, so it refused remote id {remote_id}'s "
            f"counter as a replay: another remote uses remote id {remote_id} with the same "
            f"key (give each remote its own --remote-id), or 8 remote ids are in use already")


def reply_dict(reply: Reply) -> dict[str, object]:
    """The reply as plain JSON-able values (names alongside the numbers)."""
    return {
        "reply": "ACK" if reply.ack else "NAK",
        "seq": reply.seq,
        "state": state_name(reply.state),
        "state_code": reply.state,
        "reason": reason_name(reply.reason),
        "reason_code": reply.reason,
        "flags": reply.flags,
        "link_degraded": bool(reply.flags & 1),
        "nak_code": reply.nak_code,
        "nak": tcp.NAK_NAMES.get(reply.nak_code, str(reply.nak_code)),
    }


class StopChannel:
    """A TCP connection to the unit's stop port. Thread-safe; reconnects lazily after errors.

    ``request()`` sends one frame and waits (at most ``timeout`` seconds) for the reply that
    echoes its seq. Any failure closes the connection and raises :class:`StopChannelError`.

    Plain 16-byte frames, or, with a keyed ``identity`` (or ``framed=True`` without a key:
    zero tags), the 48-byte request frames of spec section 5.2, answered by 48-byte replies.
    With a key each reply must verify against its request (else :class:`ReplyNotAuthentic`)
    and echo its seq and counter; every reply teaches the identity's session, which later
    requests (and the remote's other messages) carry. The identity's counter is the remote's
    one counter; the channel tells the identity when a request is answered or can be no
    more, which ends a RELEASE's quiet (:class:`~estop.client.identity.Identity`).
    """

    def __init__(self, host: str, port: int = tcp.DEFAULT_PORT, *, timeout: float = 2.0,
                 stop_id: int = tcp.DEFAULT_STOP_ID, first_seq: int = 1,
                 identity: Identity | None = None, framed: bool | None = None) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        self.stop_id = tcp.check_stop_id(stop_id)
        self.identity = identity or Identity()
        self.framed = self.identity.keyed if framed is None else framed
        if self.identity.keyed and not self.framed:
            raise ValueError("with a key, requests must be 48-byte frames")
        self.sent_session = 0  # the session the latest request carried
        self._seq = first_seq & 0xFFFFFFFF
        self._sock: socket.socket | None = None
        self._asm = FrameAssembler(auth.REPLY_SIZE if self.framed else tcp.FRAME_SIZE)
        self._lock = threading.Lock()
        # requests sent and not answered yet: seq -> (frame, the framed request or None)
        self._pending: dict[int, tuple[bytes, auth.AuthRequest | None]] = {}

    @property
    def session(self) -> int:
        """The unit's session as last seen in a reply (0: not known yet)."""
        return self.identity.session

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> None:
        with self._lock:
            self._connect(self.timeout)

    def _connect(self, timeout: float) -> socket.socket:
        if self._sock is not None:
            return self._sock
        try:
            sock = socket.create_connection((self.host, self.port), timeout=timeout)
        except TimeoutError:
            raise StopChannelError(f"connecting to {self.host}:{self.port} timed out after "
                                   f"{timeout:g} s") from None
        except OSError as exc:
            raise StopChannelError(f"cannot connect to {self.host}:{self.port}: "
                                   f"{exc.strerror or exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._asm.reset()
        return sock

    def close(self) -> None:
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._asm.reset()
        pending = [req for _frame, req in self._pending.values() if req is not None]
        self._pending.clear()  # no reply comes on a closed connection
        for req in pending:
            self.identity.answered(req.counter)  # a RELEASE's quiet ends with it

    def __enter__(self) -> StopChannel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_seq(self) -> int:
        with self._lock:
            return self._seq

    def take_seq(self) -> int:
        """The next seq of this channel's own counter, used up (for a request sent later with
        an explicit seq)."""
        with self._lock:
            seq = self._seq
            self._seq = (seq + 1) & 0xFFFFFFFF
            return seq

    def nak_hint(self, reply: Reply) -> str | None:
        """:func:`nak_hint` for the latest reply of this channel."""
        return nak_hint(reply, self.identity.keyed, self.identity.remote_id,
                        same_session=self.sent_session == self.session)

    def stop(self, seq: int | None = None) -> Reply:
        return self.request(self.stop_id, seq)

    def release(self, seq: int | None = None) -> Reply:
        return self.request(tcp.RELEASE, seq)

    def status(self, seq: int | None = None) -> Reply:
        return self.request(tcp.STATUS, seq)

    def request(self, msg_id: int, seq: int | None = None, *,
                timeout: float | None = None) -> Reply:
        """Send ``Request(msg_id, seq)`` (seq: the next of this channel's own counter) and
        wait for its reply, at most ``timeout`` seconds (default: the channel's)."""
        with self._lock:
            wait = self.timeout if timeout is None else timeout
            seq, _t = self._send(msg_id, seq, wait)
            return self._receive(seq, wait, skip_others=False)

    def send(self, msg_id: int, seq: int | None = None) -> tuple[int, float]:
        """Send a request without waiting: (its seq, ``time.time()`` just before sending).
        :meth:`receive` collects the reply (the benchmarks time the two apart)."""
        with self._lock:
            return self._send(msg_id, seq, self.timeout)

    def receive(self, seq: int, *, timeout: float | None = None) -> Reply:
        """The reply to the request sent with ``seq``; replies to other requests sent before it
        are read and dropped."""
        with self._lock:
            return self._receive(seq, self.timeout if timeout is None else timeout,
                                 skip_others=True)

    def _send(self, msg_id: int, seq: int | None, wait: float) -> tuple[int, float]:
        if seq is None:
            seq = self._seq
        self._seq = (seq + 1) & 0xFFFFFFFF
        if self.framed:
            self.sent_session = self.session
            req = self.identity.request(msg_id, seq)
            frame = req.encode(self.identity.key)
            self._pending[seq] = (frame, req)
        else:
            frame = Request(msg_id, seq).encode()
            self._pending[seq] = (frame, None)
        with self._failures(wait):
            sock = self._connect(wait)
            t = time.time()
            sock.sendall(frame)
        return seq, t

    def _receive(self, seq: int, wait: float, *, skip_others: bool) -> Reply:
        with self._failures(wait):
            if self._sock is None:
                raise StopChannelError(f"connection to {self.host}:{self.port} lost before "
                                       f"the reply to seq {seq}")
            return self._await_reply(self._sock, seq, wait, skip_others)

    @contextlib.contextmanager
    def _failures(self, wait: float) -> Iterator[None]:
        """Any failure closes the connection and is one :class:`StopChannelError`."""
        try:
            yield
        except StopChannelError:
            self._close()
            raise
        except TimeoutError:
            self._close()
            raise StopChannelError(f"no reply from {self.host}:{self.port} within "
                                   f"{wait:g} s") from None
        except OSError as exc:
            self._close()
            raise StopChannelError(f"connection to {self.host}:{self.port} failed: "
                                   f"{exc.strerror or exc}") from None

    def _await_reply(self, sock: socket.socket, seq: int, timeout: float,
                     skip_others: bool) -> Reply:
        deadline = time.monotonic() + timeout
        while True:
            for raw in self._asm.feed(b""):  # a reply already read with an earlier one
                reply = self._decode(raw, seq, skip_others)
                if reply is not None:
                    return reply
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            sock.settimeout(left)
            chunk = sock.recv(4096)
            if not chunk:
                raise ConnectionClosed(f"{self.host}:{self.port} closed the connection "
                                       f"before replying")
            for raw in self._asm.feed(chunk):
                reply = self._decode(raw, seq, skip_others)
                if reply is not None:
                    return reply

    def _decode(self, raw: bytes, seq: int, skip_others: bool) -> Reply | None:
        """The reply in ``raw`` if it answers ``seq``; None for a reply to another request of
        ours when ``skip_others``; else :class:`StopChannelError`. A framed reply is verified
        against the request it names."""
        if self.framed:
            got = int.from_bytes(raw[8:12], "little")
            frame, sent = self._pending.pop(got, (b"", None))
            if sent is None:
                raise StopChannelError(f"a reply to seq {got}, which was never asked")
            self.identity.answered(sent.counter)  # the unit has read it (a RELEASE's quiet)
            reply = self._decode_framed(raw, frame, sent)
            ours = True
        else:
            reply = self._decode_plain(raw)
            ours = self._pending.pop(reply.seq, None) is not None
        if reply.seq == seq:
            return reply
        if skip_others and ours:
            return None
        raise StopChannelError(f"reply seq {reply.seq} does not match request seq {seq}")

    def _decode_plain(self, raw: bytes) -> Reply:
        try:
            return Reply.decode(raw)
        except tcp.FrameError as exc:
            raise StopChannelError(f"bad reply from {self.host}:{self.port}: {exc}") from None

    def _decode_framed(self, raw: bytes, frame: bytes, sent: auth.AuthRequest) -> Reply:
        try:
            got = auth.AuthReply.decode(raw, self.identity.key, auth.request_tag(frame))
        except auth.TagMismatch:
            raise ReplyNotAuthentic(
                f"reply from {self.host}:{self.port} does NOT verify under the key (forged, "
                f"replayed, or a unit with another key or none): ignored") from None
        except tcp.FrameError as exc:
            raise StopChannelError(f"bad reply from {self.host}:{self.port}: {exc}") from None
        if got.counter != sent.counter:
            raise StopChannelError(f"reply counter {got.counter} does not match request "
                                   f"counter {sent.counter}")
        self.identity.session = got.session
        return got.reply
