"""The HIL harness's clients of the daemon: the remote (UDP control packets, a keepalive
thread), the TCP stop channel's clients (plain and 48-byte frames), and the key holder's remote.
"""

from __future__ import annotations

import bisect
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass

from estop.client.channel import StopChannel, StopChannelError
from estop.protocol import auth, tcp, udp
from hilrig import RigError

NEUTRAL = udp.ControlPacket(0.0, 0.0, udp.Gear.NEUTRAL).encode()
DRIVE_GAS = udp.ControlPacket(0.3, -0.25, udp.Gear.DRIVE, udp.TurnSignal.LEFT).encode()


class UdpRemote:
    """Control packets to the daemon; a keepalive thread sends one every ``period`` s."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.lock = threading.Lock()
        self.last_send: float | None = None  # wall time taken just before the last sendto
        self.keepalive_times: list[float] = []
        # ... and when each send returned: a thread held between its stamp and its send (a
        # loaded guest) sent later than stamped, and a pause seen only in the stamps before
        # the sends was up to that much longer (max_gap takes the longest it may have been).
        self.keepalive_after: list[float] = []
        self.sent = 0
        self.errors = 0

    def packet(self, body: bytes) -> bytes:
        """The datagram that carries the control body ``body`` (here: the body itself)."""
        return body

    def sent_since(self, t: float) -> int:
        """Keepalive packets sent at or after wall time ``t`` (the list is in time order and
        long: a binary search, as this is polled)."""
        return len(self.keepalive_times) - bisect.bisect_left(self.keepalive_times, t)

    def nth_since(self, t: float, n: int) -> float | None:
        """The send time of the ``n``-th keepalive packet (1: the first) at or after ``t``."""
        i = bisect.bisect_left(self.keepalive_times, t) + n - 1
        return self.keepalive_times[i] if i < len(self.keepalive_times) else None

    def send(self, data: bytes) -> float:
        t = time.time()
        try:
            self.sock.send(data)
        except OSError:  # ECONNREFUSED from an earlier datagram while the daemon was down
            self.errors += 1
        self.sent += 1
        return t

    def start(self, data: bytes = NEUTRAL, period: float = 0.02) -> None:
        self.stop()
        self._stop.clear()

        def run() -> None:
            nxt = time.monotonic()
            while not self._stop.is_set():
                self.last_send = self.send(self.packet(data))
                self.keepalive_times.append(self.last_send)
                self.keepalive_after.append(time.time())
                nxt += period
                self._stop.wait(max(0.0, nxt - time.monotonic()))

        self._thread = threading.Thread(target=run, name="udp-keepalive", daemon=True)
        self._thread.start()

    def stop(self) -> float | None:
        """Stop the keepalive; returns the time of the last packet it sent."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2)
            if self._thread.is_alive():
                raise RigError("UDP keepalive thread did not stop")
            self._thread = None
        return self.last_send

    def max_gap(self, t0: float, t1: float) -> float:
        """Longest pause between keepalive packets sent in ``[t0, t1]`` (seconds): from the
        stamp before one send to the return of the next, the longest the pause may have been."""
        i = bisect.bisect_left(self.keepalive_times, t0)
        j = bisect.bisect_right(self.keepalive_times, t1)
        before, after = self.keepalive_times[i:j], self.keepalive_after[i:j]
        return max((b - a for a, b in zip(before, after[1:], strict=False)), default=0.0)

    def close(self) -> None:
        self.stop()
        self.sock.close()


@dataclass(frozen=True, slots=True)
class Exchange:
    reply: tcp.Reply
    t_send: float  # just before sendall
    t_reply: float  # when the complete reply was read
    auth: auth.AuthReply | None = None  # a 48-byte reply (to a 48-byte request)
    tag_ok: bool | None = None  # its tag verified under the unit's key, for this request
    frame: bytes = b""  # the request as sent


def read_reply(sock: socket.socket, asm: tcp.FrameAssembler, timeout: float,
               what: str) -> tuple[bytes, float]:
    """Reads exactly one reply frame (``asm`` knows its size) within ``timeout`` s: the frame
    and the time it was whole. ``what`` names the request in the errors."""
    end = time.monotonic() + timeout
    while True:
        left = end - time.monotonic()
        if left <= 0:
            raise RigError(f"no reply to {what} within {timeout} s")
        sock.settimeout(left)
        data = sock.recv(128)
        if not data:
            raise RigError(f"connection closed instead of a reply to {what}")
        frames = asm.feed(data)
        if frames:
            t1 = time.time()
            if len(frames) > 1 or asm.pending:
                raise RigError("more than one reply frame to one request")
            return frames[0], t1


class StopClient:
    """One TCP connection of the stop channel: the package's client
    (:class:`estop.client.channel.StopChannel`, plain 16-byte frames), each exchange timed.
    :meth:`request_frame` probes the 48-byte form on a connection of its own."""

    def __init__(self, port: int, timeout: float = 2.0) -> None:
        self.port = port
        self.timeout = timeout
        self.channel = StopChannel("127.0.0.1", port, timeout=timeout)
        self.channel.connect()
        self._framed: socket.socket | None = None
        self.seq = 0

    def request(self, msg_id: int) -> Exchange:
        try:
            seq, t0 = self.channel.send(msg_id)
            rep = self.channel.receive(seq)
        except StopChannelError as exc:
            raise RigError(f"msg_id {msg_id:#x}: {exc}") from None
        return Exchange(rep, t0, time.time())

    def stop(self, stop_id: int = tcp.DEFAULT_STOP_ID) -> Exchange:
        return self.request(stop_id)

    def lift(self) -> Exchange:
        return self.request(tcp.LIFT)

    def request_frame(self, msg_id: int, remote_id: int = 0, counter: int = 1) -> Exchange:
        """A 48-byte request frame (spec section 5.2, tag 16 zero bytes, session 0) and its
        48-byte reply: ``tag_ok`` says whether the reply has the zero tag of a unit without a
        key and echoes the seq and counter."""
        if self._framed is None:
            self._framed = socket.create_connection(("127.0.0.1", self.port),
                                                    timeout=self.timeout)
            self._framed.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.seq += 1
        frame = auth.AuthRequest(msg_id, self.seq, remote_id, 0, counter).encode(None)
        t0 = time.time()
        self._framed.sendall(frame)
        raw, t1 = read_reply(self._framed, tcp.FrameAssembler(auth.REPLY_SIZE), self.timeout,
                             "a request frame")
        try:
            rep = auth.AuthReply.decode(raw, None)
        except tcp.FrameError as exc:
            raise RigError(f"bad reply frame {raw.hex(' ')}: {exc}") from exc
        ok = raw[32:] == bytes(16) and rep.seq == self.seq and rep.counter == counter
        return Exchange(rep.reply, t0, t1, rep, ok, frame)

    def status(self) -> Exchange:
        return self.request(tcp.STATUS)

    def release(self) -> Exchange:
        return self.request(tcp.RELEASE)

    def peer_closed(self) -> bool:
        """Whether the unit has closed this connection (EOF or reset), seen without reading a
        byte (MSG_PEEK) or sending one, so that an idle client stays idle."""
        sock = self.channel._sock  # the package's channel keeps its socket to itself
        if sock is None:
            return True
        # select first: on a socket with a timeout, recv waits out the timeout on EAGAIN
        if not select.select([sock], [], [], 0)[0]:
            return False
        try:
            return sock.recv(16, socket.MSG_DONTWAIT | socket.MSG_PEEK) == b""
        except OSError:
            return True

    def close(self) -> None:
        self.channel.close()
        if self._framed is not None:
            self._framed.close()
            self._framed = None


class AuthClient:
    """One TCP connection that speaks 48-byte request and reply frames (spec section 5).

    Requests carry ``remote_id``, the session this client believes in and a counter it raises
    with every request; they are tagged with ``key`` (None: 16 zero bytes). Every reply is
    checked against ``unit_key`` (the key the unit holds, known to the harness) and the
    request's own tag: ``tag_ok`` says whether it verified. A genuine reply teaches the
    client the unit's session. ``sent`` records every request frame as sent (for replays).
    """

    def __init__(self, port: int, key: bytes | None, unit_key: bytes, remote_id: int,
                 timeout: float = 2.0) -> None:
        self.port = port
        self.key = key
        self.unit_key = unit_key
        self.remote_id = remote_id
        self.session = 0
        self.counter = 0
        self.seq = 0
        self.timeout = timeout
        self.sent: list[bytes] = []
        self.sock: socket.socket | None = None
        self.connect()

    def connect(self) -> None:
        self.close()
        self.sock = socket.create_connection(("127.0.0.1", self.port), timeout=self.timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def frame(self, msg_id: int, counter: int | None = None) -> bytes:
        """A new request frame (raising the counter unless ``counter`` is given)."""
        self.seq += 1
        if counter is None:
            self.counter += 1
            counter = self.counter
        return auth.AuthRequest(msg_id, self.seq, self.remote_id, self.session,
                                counter).encode(self.key)

    def exchange(self, frame: bytes) -> Exchange:
        """Send one 48-byte request frame as it is and read its 48-byte reply."""
        assert self.sock is not None
        seq = struct.unpack_from("<I", frame, 8)[0]
        t0 = time.time()
        self.sock.sendall(frame)
        self.sent.append(frame)
        raw, t1 = read_reply(self.sock, tcp.FrameAssembler(auth.REPLY_SIZE), self.timeout,
                             "a request frame")
        tag = auth.request_tag(frame)
        try:
            rep = auth.AuthReply.decode(raw, self.unit_key, tag)
            ok = True
        except auth.TagMismatch:
            rep = auth.AuthReply.decode(raw, None)
            ok = False
        except tcp.FrameError as exc:
            raise RigError(f"bad reply frame {raw.hex(' ')}: {exc}") from exc
        if rep.seq != seq:
            raise RigError(f"reply seq {rep.seq}, request seq {seq}")
        if ok:
            self.session = rep.session
        return Exchange(rep.reply, t0, t1, rep, ok, frame)

    def request(self, msg_id: int, counter: int | None = None) -> Exchange:
        return self.exchange(self.frame(msg_id, counter))

    def status(self) -> Exchange:
        return self.request(tcp.STATUS)

    def release(self) -> Exchange:
        return self.request(tcp.RELEASE)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class AuthRemote(UdpRemote):
    """The key holder's remote: authenticated 60-byte control packets with a rising counter
    (its keepalive thread wraps every body), and an :class:`AuthClient` on the stop channel.
    It learns the unit's session with a STATUS request frame (session 0) and records every
    control packet it sent, with its time, so that an attacker's replay can be staged."""

    def __init__(self, udp_port: int, tcp_port: int, key: bytes, remote_id: int) -> None:
        super().__init__(udp_port)
        self.key = key
        self.remote_id = remote_id
        self.udp_counter = 0
        self.recorded: list[tuple[float, bytes]] = []
        self.tcp = AuthClient(tcp_port, key, key, remote_id)

    @property
    def session(self) -> int:
        return self.tcp.session

    def learn_session(self) -> Exchange:
        """(Re)connect and ask STATUS with session 0, as a remote does after a restart."""
        self.tcp.connect()
        self.tcp.session = 0
        ex = self.tcp.status()
        if not ex.tag_ok:
            raise RigError("the reply to STATUS does not verify under the key")
        return ex

    def packet(self, body: bytes) -> bytes:
        with self.lock:
            # one counter for all the remote's messages (PROTOCOL.md 5): a RELEASE must be
            # above the newest control packet (issue 25)
            self.tcp.counter += 1
            self.udp_counter = self.tcp.counter
            pkt = auth.AuthControlPacket(self.remote_id, self.session, self.udp_counter,
                                         udp.decode(body)).encode(self.key)
            self.recorded.append((time.time(), pkt))
        return pkt

    def release(self) -> Exchange:
        # No control packet is made between the RELEASE and its reply: the unit reads the
        # control port before each stop-channel frame, so one made later (a higher counter)
        # that came while the RELEASE waited would make it stale (NAK 4, a RELEASE must be
        # above the remote's newest counter on either channel, issue 25 item 2).
        with self.lock:
            return self.tcp.release()

    def close(self) -> None:
        super().close()
        self.tcp.close()


def wrong_key(key: bytes) -> bytes:
    """A key that is not ``key`` (every byte changed)."""
    return bytes(b ^ 0x5A for b in key)


def connect_retry(port: int, timeout: float) -> StopClient:
    end = time.monotonic() + timeout
    while True:
        try:
            return StopClient(port)
        except OSError as exc:
            if time.monotonic() >= end:
                raise RigError(f"cannot connect to the stop channel on port {port}: {exc}") \
                    from exc
            time.sleep(0.02)
