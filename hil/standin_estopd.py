"""Stand-in for estopd, used ONLY to self-test the HIL harness (``hil/run --dut-standin``).

It follows spec sections 1-5 (version 3: LIFT by TCP and lift datagram, SLOWING with
``--slow-ms``/``--slow-level``, ``--warn-ms``) and the daemon's log lines (a ``cause`` on every
``state`` line, firmware/estopd/README.md) closely enough for the harness to exercise every
scenario, so the harness can be checked without the real daemon. It is not the product:
test protocols made with it say so in their header. ``--bug NAME`` injects a known defect so
that one can see the harness catch it:

- ``tick``: the udp timeout is only noticed on the 10 ms tick (not at the deadline)
- ``invalid-alive``: invalid UDP packets also keep the link alive
- ``no-fault``: CAN transmit errors are ignored (no fault, no stop)
- ``bad-crc``: every 50th ESTOP_BRAKE frame carries a wrong CRC
- ``no-tag-check``: (with a key) tags are not checked, so forged messages authenticate
- ``no-replay-check``: (with a key) session and counter are not checked, so replays do
- ``no-lift``: LIFT is not known (NAK 1 on TCP, a lift datagram counts as invalid): only the
  silence stops the car after a lift
- ``slow-back-2``: SLOWING ends after 2 valid packets instead of 3

With ``--key-file`` it has a key (spec section 5, codecs of ``estop.protocol.auth``).
"""

from __future__ import annotations

import argparse
import ctypes
import errno
import json
import os
import select
import signal
import socket
import struct
import sys
import time

from estop.client.keyfile import KeyFileError, load_key_file
from estop.protocol import auth, tcp, udp
from estop.protocol.can import BrakeFrame, StatusFrame
from mmsg import Iovec, Mmsghdr  # this folder (run as a script)

PERIOD_US = 10_000
STATUS_PERIOD_US = 100_000
FAULT_AFTER_US = 20_000  # no ESTOP_BRAKE got out for this long: fault
REASONS = ["none", "boot", "tcp_stop", "udp_timeout", "fault", "lift"]
STATES = ["STOPPED", "ARMED", "SLOWING"]
STOPPED, ARMED, SLOWING = 0, 1, 2
SLOW_BACK_PACKETS = 3  # valid packets that end SLOWING (spec section 3)
UDP_RCVBUF = 4 << 20
UDP_ROUND_MAX = 256  # datagrams read per loop round, at most
UDP_ROUND_US = 2_000  # and for at most this long (the batch under way is finished)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # root may exceed net.core.rmem_max


def now_us() -> int:
    return time.monotonic_ns() // 1000


class BatchReceiver:
    """``recvmmsg(2)`` through ctypes (Python's socket module has none): up to ``n`` datagrams
    of up to ``size`` bytes (longer ones cut, as ``recv(size)`` would) in one system call."""

    def __init__(self, sock: socket.socket, n: int = 64, size: int = 64) -> None:
        self.fd = sock.fileno()
        self.n = n
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.libc.recvmmsg.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint,
                                       ctypes.c_int, ctypes.c_void_p]
        self.libc.recvmmsg.restype = ctypes.c_int
        self.bufs = [ctypes.create_string_buffer(size) for _ in range(n)]
        self.iovs = (Iovec * n)()
        self.msgs = (Mmsghdr * n)()
        for i, buf in enumerate(self.bufs):
            self.iovs[i].iov_base = ctypes.cast(buf, ctypes.c_void_p)
            self.iovs[i].iov_len = size
            self.msgs[i].msg_hdr.msg_iov = ctypes.pointer(self.iovs[i])
            self.msgs[i].msg_hdr.msg_iovlen = 1

    def recv(self) -> list[bytes]:
        """The datagrams queued now (at most ``n``); none when the queue is empty."""
        got = self.libc.recvmmsg(self.fd, ctypes.addressof(self.msgs), self.n,
                                 socket.MSG_DONTWAIT, None)
        if got < 0:
            err = ctypes.get_errno()
            if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                return []
            raise OSError(err, os.strerror(err))
        return [self.bufs[i].raw[:self.msgs[i].msg_len] for i in range(got)]


class Daemon:
    def __init__(self, args: argparse.Namespace) -> None:
        self.a = args
        self.bugs = set(args.bug or [])
        self.timeout_us = args.timeout_ms * 1000
        self.slow_us = (args.slow_ms if args.slow_ms is not None else args.timeout_ms) * 1000
        # spec section 3: W defaults to half the slow time, in whole ms
        self.warn_us = (args.warn_ms * 1000 if args.warn_ms is not None
                        else self.slow_us // 2 // 1000 * 1000)
        if not 0 < self.warn_us <= self.slow_us <= self.timeout_us:
            raise ValueError("times must satisfy 0 < warn <= slow <= timeout")
        if not 1 <= args.slow_level <= 99:
            raise ValueError("--slow-level must be 1..99")
        self.slow_level = args.slow_level
        self.state, self.reason = STOPPED, 1
        self.last_valid: int | None = None
        self.valid_run = 0
        self.slow_packets = 0  # valid packets since SLOWING began
        self.neutral = False
        self.ctr_b = self.ctr_s = 0
        self.n_valid = self.n_invalid = self.n_badcrc = self.n_stops = self.n_auth = 0
        self.n_slow = 0
        self.key: bytes | None = load_key_file(args.key_file) if args.key_file else None
        self.session = int.from_bytes(os.urandom(8), "little") or 1
        self.remotes: dict[int, dict[str, int]] = {}  # remote id -> channel -> counter
        self.fail_since: int | None = None
        self.sent_brake = 0
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # as estopd: a receive buffer that absorbs a flood (4 MiB asked, the kernel doubles it)
        try:
            self.udp.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, UDP_RCVBUF)
        except OSError:
            self.udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RCVBUF)
        self.udp.bind((args.bind, args.udp_port))
        self.udp.setblocking(False)
        self.rx = BatchReceiver(self.udp)
        self.lsn = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.lsn.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsn.bind((args.bind, args.tcp_port))
        self.lsn.listen(8)
        self.lsn.setblocking(False)
        self.clients: dict[socket.socket, tuple[tcp.RequestAssembler, str]] = {}
        self.can = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        self.can.bind((args.can,))
        self.can.setblocking(False)
        self.running = True
        t = now_us()
        self.log("start", can=args.can, udp_port=args.udp_port, tcp_port=args.tcp_port,
                 timeout_ms=args.timeout_ms, slow_ms=self.slow_us // 1000,
                 slow_level=self.slow_level, warn_ms=self.warn_us // 1000,
                 auth="key" if self.key else "none", session=f"0x{self.session:016X}",
                 udp_rcvbuf=self.udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        self.next_b = t
        self.next_s = t

    def log(self, event: str, **kv: object) -> None:
        rec = {"t_mono": time.clock_gettime(time.CLOCK_BOOTTIME), "event": event, **kv}
        sys.stderr.write(json.dumps(rec) + "\n")
        sys.stderr.flush()

    # ---- CAN
    def send(self, can_id: int, data: bytes, t: int) -> None:
        try:
            self.can.send(struct.pack("=IB3x8s", can_id, 8, data))
            if can_id == 0x050:  # only brake frames getting out count as mended
                self.fail_since = None
        except OSError as exc:
            name = errno.errorcode.get(exc.errno or 0, str(exc.errno))
            self.log("can_error", errno=name)
            if "no-fault" in self.bugs:
                return
            if self.fail_since is None:
                self.fail_since = t
            elif t - self.fail_since >= FAULT_AFTER_US and self.state != STOPPED:
                self.log("fault", cause="can_tx")
                self.stop(4, t, "-", "fault")

    def send_brake(self, t: int, periodic: bool = False) -> None:
        data = BrakeFrame.for_state(self.state, self.reason, self.flags(t), self.ctr_b,
                                    slow_level=self.slow_level).encode()
        self.sent_brake += 1
        if "bad-crc" in self.bugs and self.sent_brake % 50 == 0:
            data = data[:7] + bytes((data[7] ^ 0x5A,))
        self.ctr_b = (self.ctr_b + 1) % 15
        # periodic: keep the 10 ms grid; a state change restarts it from now (spec 4)
        self.next_b = self.next_b + PERIOD_US if periodic else t + PERIOD_US
        if self.next_b <= t:  # fell behind (stalled): no burst of catch-up frames
            self.next_b = t + PERIOD_US
        self.send(0x050, data, t)

    def send_status(self, t: int) -> None:
        age = 0xFFFF
        if self.last_valid is not None and t - self.last_valid < self.timeout_us:
            age = min((t - self.last_valid) // 1000, 0xFFFE)
        data = StatusFrame(min(self.n_valid, 255), min(self.n_invalid, 255),
                           min(self.n_auth, 255), min(self.n_stops, 15), age,
                           self.ctr_s, min(self.n_slow, 15)).encode()
        self.n_valid = self.n_invalid = self.n_auth = self.n_stops = self.n_slow = 0
        self.ctr_s = (self.ctr_s + 1) % 15
        self.next_s += STATUS_PERIOD_US
        self.send(0x051, data, t)

    # ---- state
    def flags(self, t: int) -> int:
        """Link degraded: ARMED or SLOWING and no valid packet for the warn time."""
        return int(self.state != STOPPED and self.last_valid is not None
                   and t - self.last_valid >= self.warn_us)

    def change(self, state: int, reason: int, t: int, src: str, cause: str) -> None:
        """A state change: logged (with its cause), and a frame at once."""
        self.log("state", **{"from": STATES[self.state], "to": STATES[state],
                             "reason": REASONS[reason], "src": src, "cause": cause})
        self.state, self.reason = state, reason
        self.send_brake(t)

    def stop(self, reason: int, t: int, src: str, cause: str) -> None:
        self.valid_run = 0
        if self.state == STOPPED:
            return
        self.n_stops += 1
        self.change(STOPPED, reason, t, src, cause)

    def slow_down(self, t: int) -> None:
        self.slow_packets = 0
        self.n_slow += 1
        self.change(SLOWING, 0, t, "-", "udp_silence")

    def live(self, t: int) -> bool:
        return (self.last_valid is not None and t - self.last_valid < self.timeout_us
                and self.valid_run >= 5)

    def authenticate(self, signed: bytes, tag: bytes, rid: int, session: int, counter: int,
                     channel: str) -> bool:
        """Spec section 5: tag, session, a place for the remote id, a rising counter."""
        assert self.key is not None
        ok = "no-tag-check" in self.bugs or auth.mac(self.key, signed) == tag
        if ok and "no-replay-check" not in self.bugs:
            seen = self.remotes.get(rid)
            if session != self.session or (seen is None and len(self.remotes) >= 8):
                ok = False
            elif seen is not None and channel in seen and counter <= seen[channel]:
                ok = False
            else:
                self.remotes.setdefault(rid, {})[channel] = counter
        if not ok:
            self.n_auth += 1
        return ok

    def body(self, data: bytes) -> bytes | None:
        """The control body of a valid packet of the form this unit expects, or None."""
        if self.key is None:
            return data if udp.is_valid(data) else None
        if len(data) != auth.CONTROL_SIZE or data[:4] != auth.CONTROL_MAGIC \
                or not udp.is_valid(data[24:44]):
            return None
        rid, session, counter = struct.unpack_from("<IQQ", data, 4)
        return data[24:44] if self.authenticate(data[:44], data[44:], rid, session, counter,
                                                "udp") else None

    def on_udp(self, t: int) -> None:
        # As estopd: datagrams in batches (recvmmsg: a system call costs tens of us under TCG),
        # a bounded number and time per loop round, so that a backlog (a flood into the large
        # receive buffer) never holds up the frames, the deadlines or the stop channel.
        n = 0
        while n < UDP_ROUND_MAX and now_us() - t < UDP_ROUND_US:
            batch = self.rx.recv()
            if not batch:
                return
            n += len(batch)
            for data in batch:
                self.on_datagram(data, t)

    def on_datagram(self, data: bytes, t: int) -> None:
        if len(data) == auth.REQUEST_SIZE and data[:4] == auth.REQUEST_MAGIC:
            msg_id = struct.unpack_from("<I", data, 4)[0]
            # stop and lift datagrams: whatever their tags say
            if msg_id == self.a.stop_id:
                self.stop(2, t, "udp", "stop_datagram")
                return
            if msg_id == tcp.LIFT and "no-lift" not in self.bugs:
                self.stop(5, t, "udp", "lift_datagram")
                return
        body = self.body(data)
        if body is not None or "invalid-alive" in self.bugs:
            self.last_valid = t
            if body is not None:
                self.n_valid += 1
                self.valid_run += 1
                self.neutral = udp.decode(body).is_neutral
                if self.state == SLOWING:
                    self.slow_packets += 1
                    back = 2 if "slow-back-2" in self.bugs else SLOW_BACK_PACKETS
                    if self.slow_packets >= back:
                        self.change(ARMED, 0, t, "udp", "link_back")
        else:
            self.n_invalid += 1

    def reply(self, sock: socket.socket, req: tcp.Request, nak: int, t: int,
              frame: bytes | None = None) -> None:
        flags = self.flags(t)
        if frame is None:
            rep = tcp.Reply(nak == 0, req.seq, self.state, self.reason, flags, nak)
            sock.sendall(rep.encode())
            return
        counter = struct.unpack_from("<Q", frame, 24)[0]
        arep = auth.AuthReply(nak == 0, req.seq, self.state, self.reason, flags=flags,
                              nak_code=nak, session=self.session, counter=counter)
        sock.sendall(arep.encode(self.key, auth.request_tag(frame)))

    def on_client(self, sock: socket.socket, t: int) -> None:
        asm, peer = self.clients[sock]
        try:
            data = sock.recv(4096)
        except OSError:
            data = b""
        if not data:
            self.close(sock)
            return
        for raw in asm.feed(data):
            frame: bytes | None = None
            authed = self.key is None  # a plain RELEASE is authenticated only without a key
            if len(raw) == auth.REQUEST_SIZE:
                frame = raw
                msg_id, seq, rid, session, counter = struct.unpack_from("<IIIQQ", raw, 4)
                req = tcp.Request(msg_id, seq)
                # without a key a request frame's RELEASE gets NAK 4; with one, only a RELEASE
                # is authenticated (STOP and STATUS are honoured whatever the tag says)
                authed = (self.key is not None and req.kind(self.a.stop_id) == "release"
                          and self.authenticate(raw[:32], raw[32:], rid, session, counter,
                                                "tcp"))
            else:
                try:
                    req = tcp.Request.decode(raw)
                except tcp.FrameError:
                    self.n_badcrc += 1
                    self.log("bad_crc", src=peer)
                    self.close(sock)
                    return
            kind = req.kind(self.a.stop_id)
            if kind == "lift" and "no-lift" in self.bugs:
                kind = "unknown"
            if kind == "stop":
                self.stop(2, t, peer, "tcp_stop")
                self.reply(sock, req, 0, t, frame)
            elif kind == "lift":
                self.stop(5, t, peer, "lift")
                self.reply(sock, req, 0, t, frame)
            elif kind == "status":
                self.reply(sock, req, 0, t, frame)
            elif kind == "release":
                if not authed:
                    self.reply(sock, req, 4, t, frame)
                elif self.state != STOPPED:  # while SLOWING as while ARMED
                    self.reply(sock, req, 0, t, frame)
                elif not self.live(t):
                    self.reply(sock, req, 2, t, frame)
                elif not self.neutral:
                    self.reply(sock, req, 3, t, frame)
                else:
                    # a link silent for the slow time arms straight into SLOWING
                    silent = self.last_valid is not None and t - self.last_valid >= self.slow_us
                    if silent:
                        self.slow_packets = 0
                        self.n_slow += 1
                    self.change(SLOWING if silent else ARMED, 0, t, peer, "release")
                    self.reply(sock, req, 0, t, frame)
            else:
                self.reply(sock, req, 1, t, frame)

    def close(self, sock: socket.socket) -> None:
        _, peer = self.clients.pop(sock)
        self.log("client_close", src=peer)
        sock.close()

    def deadline(self) -> int | None:
        """The next silence deadline: the slow time while ARMED (when S < T), the timeout."""
        if self.state == STOPPED or self.last_valid is None:
            return None
        if self.state == ARMED and self.slow_us < self.timeout_us:
            return self.last_valid + self.slow_us
        return self.last_valid + self.timeout_us

    def on_deadline(self, t: int) -> None:
        """Act on the silence deadline that is due at ``t`` (each at its own time)."""
        assert self.last_valid is not None
        if self.state == ARMED and self.slow_us < self.timeout_us:
            self.slow_down(self.last_valid + self.slow_us)
        if self.state != STOPPED and t - self.last_valid >= self.timeout_us:
            self.stop(3, self.last_valid + self.timeout_us, "-", "udp_timeout")

    def run(self) -> None:
        while self.running:
            t = now_us()
            dl = self.deadline()
            if dl is not None and t >= dl and "tick" not in self.bugs:
                self.on_deadline(t)
            if t >= self.next_b:
                if dl is not None and t >= dl and "tick" in self.bugs:
                    self.on_deadline(t)
                if t >= self.next_b:
                    self.send_brake(t, periodic=True)
            if t >= self.next_s:
                self.send_status(t)
            dl = self.deadline()
            due = min(x for x in (self.next_b, self.next_s, dl if "tick" not in self.bugs
                                  else None) if x is not None)
            wait = max(0, due - now_us()) / 1e6
            socks = [self.udp, self.lsn, *self.clients]
            try:
                ready, _, _ = select.select(socks, [], [], wait)
            except InterruptedError:
                continue
            t = now_us()
            for s in ready:
                if s is self.udp:
                    self.on_udp(t)
                elif s is self.lsn:
                    c, addr = self.lsn.accept()
                    peer = f"{addr[0]}:{addr[1]}"
                    self.clients[c] = (tcp.RequestAssembler(), peer)
                    self.log("client_open", src=peer)
                elif s in self.clients:
                    self.on_client(s, t)
        t = now_us()
        self.state = 0
        self.reason = self.reason or 1
        self.send_brake(t)
        self.log("exit", code=0)


def main() -> int:
    p = argparse.ArgumentParser(prog="standin_estopd")
    p.add_argument("--can", required=True)
    p.add_argument("--can-log")
    p.add_argument("--udp-port", type=int, default=5700)
    p.add_argument("--tcp-port", type=int, default=5701)
    p.add_argument("--bind", default="0.0.0.0")
    p.add_argument("--timeout-ms", type=int, default=200)
    p.add_argument("--slow-ms", type=int, help="as estopd (default: the timeout)")
    p.add_argument("--slow-level", type=int, default=30)
    p.add_argument("--warn-ms", type=int, help="as estopd (default: half the slow time)")
    p.add_argument("--stop-id", type=lambda s: int(s, 0), default=tcp.DEFAULT_STOP_ID)
    p.add_argument("--log-json", action="store_true")
    keying = p.add_mutually_exclusive_group(required=True)
    keying.add_argument("--no-auth", action="store_true", help="as estopd: no key")
    keying.add_argument("--key-file", help="as estopd: the unit's key")
    p.add_argument("--bug", action="append", choices=["tick", "invalid-alive", "no-fault",
                                                        "bad-crc", "no-tag-check",
                                                        "no-replay-check", "no-lift",
                                                        "slow-back-2"])
    args = p.parse_args()
    try:
        d = Daemon(args)
    except (KeyFileError, ValueError) as exc:
        p.exit(2 if isinstance(exc, ValueError) else 1, f"standin_estopd: {exc}\n")

    def on_signal(_sig: int, _frm: object) -> None:
        d.running = False

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    d.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
