"""UDP flooder of the HIL harness: invalid control packets at a high rate, from a process of
its own so that the harness's threads (bus monitor, clients) are not starved of the GIL.

    python flood.py PORT [--rate PPS] [--batch N]

Sends to 127.0.0.1:PORT with ``sendmmsg(2)`` (through ctypes: one system call sends a batch,
so the rate is the kernel's, not the interpreter's), cycling through :data:`INVALID_PACKETS`.
The flood uses UDP GSO (``UDP_SEGMENT``): the datagrams of one length go down the stack as one
send and are cut apart before they reach the daemon's socket, where each is a datagram of its
own, queued, counted and, when the queue is full, dropped one by one. Under TCG the kernel's
path per datagram is what limits a flood: GSO walks it once per send (a plain sendmmsg flood
reached 14000/s in an otherwise idle VM, and 2000-4000/s beside the harness on a busy host).
Once up (socket open), it writes ``{"ready": true, "t": ...}``. Then commands, one per line on
standard input; every answer is one JSON line on standard output:

- ``ready?``: ``{"ready": true, ...}`` again;
- ``burst N``: exactly N packets as fast as possible;
  answer ``{"sent": N, "t0": ..., "t1": ..., "errors": ...}``;
- ``flood``: packets until the next command line (``stop``), at ``--rate`` packets/s
  (0: as fast as it can); answer as for ``burst`` plus ``"series"``: ``[t, sent so far]``
  about every 5 ms, so the harness can tell how many went out in any interval;
- ``quit``: exit.

Times are wall-clock seconds (CLOCK_REALTIME), as the harness's and SocketCAN's. "Sent" counts
the datagrams the kernel accepted (sendmmsg's return value); a datagram the receiving socket
has no room for is dropped there and shows in ``/proc/net/udp`` (drops), not here.
"""

from __future__ import annotations

import argparse
import ctypes
import errno
import math
import socket
import struct
import sys
import time

from estop.protocol import udp
from helperio import Lines, answer, serve  # this folder (run as a script)
from mmsg import Iovec, Mmsghdr

NEUTRAL = udp.ControlPacket(0.0, 0.0, udp.Gear.NEUTRAL).encode()

# Twelve kinds of invalid control packets (spec section 1): wrong lengths, NaN/inf, values out
# of range, unknown codes, a 16-byte body with a bad gear, one byte too many.
INVALID_PACKETS: list[bytes] = [
    b"",
    bytes(19),
    bytes(21),
    struct.pack("<ffiii", math.nan, 0.0, 4, 0, 0),
    struct.pack("<ffiii", 0.0, math.inf, 4, 0, 0),
    struct.pack("<ffiii", 1.5, 0.0, 4, 0, 0),
    struct.pack("<ffiii", 0.0, 0.0, 3, 0, 0),
    struct.pack("<ffiii", 0.0, 0.0, 4, 4, 0),
    struct.pack("<ffiii", 0.0, 0.0, 4, 0, 2),
    struct.pack("<ffii", 0.0, 0.0, 0, 0),
    struct.pack("<ffiii", -1.0000001, 0.0, 4, 0, 0),
    NEUTRAL + b"\x00",
]

SERIES_EVERY_S = 0.005


SOL_UDP = 17
UDP_SEGMENT = 103  # linux/udp.h: the size of each datagram a send is cut into (UDP GSO)
GSO_MAX_SEGMENTS = 64  # UDP_MAX_SEGMENTS of the kernels in use


class _GsoCmsg(ctypes.Structure):
    """struct cmsghdr with a u16 UDP_SEGMENT payload, padded to CMSG_SPACE(2) (24 bytes)."""

    _fields_ = [("cmsg_len", ctypes.c_size_t), ("cmsg_level", ctypes.c_int),
                ("cmsg_type", ctypes.c_int), ("gso_size", ctypes.c_uint16),
                ("_pad", ctypes.c_uint8 * 6)]


def plain_messages(packets: list[bytes]) -> list[tuple[bytes, int, int]]:
    """One message per datagram: (payload, datagrams, gso size 0)."""
    return [(p, 1, 0) for p in packets]


def gso_messages(packets: list[bytes], copies: int) -> list[tuple[bytes, int, int]]:
    """One round of ``copies`` datagrams of every kind, as few messages as UDP GSO allows: the
    kinds of one length go in one send the kernel cuts into datagrams of that length (each
    arrives at the receiver as a datagram of its own). Zero-length ones cannot be cut out of a
    send: they go one message each."""
    by_len: dict[int, list[bytes]] = {}
    for p in packets:
        by_len.setdefault(len(p), []).append(p)
    out: list[tuple[bytes, int, int]] = []
    for length, kinds in sorted(by_len.items()):
        if length == 0:
            out += [(b"", 1, 0)] * (copies * len(kinds))
            continue
        per_msg = max(1, GSO_MAX_SEGMENTS // len(kinds))  # whole turns of the kinds
        left = copies
        while left:
            n = min(per_msg, left)
            out.append((b"".join(kinds) * n, n * len(kinds), length))
            left -= n
    return out


class Ring:
    """Prepared messages for ``sendmmsg`` on a connected UDP socket, sent in turn."""

    def __init__(self, fd: int, messages: list[tuple[bytes, int, int]], libc: ctypes.CDLL,
                 repeat: int = 1) -> None:
        self.fd = fd
        self.libc = libc
        msgs = messages * repeat
        self.size = len(msgs)
        self.segs = [m[1] for m in msgs]
        self._keep: list[object] = []
        self._msgs = (Mmsghdr * self.size)()
        for i, (payload, segs, gso) in enumerate(msgs):
            buf = ctypes.create_string_buffer(payload, max(1, len(payload)))
            iov = Iovec(ctypes.cast(buf, ctypes.c_void_p), len(payload))
            self._keep += [buf, iov]
            self._msgs[i].msg_hdr.msg_iov = ctypes.pointer(iov)
            self._msgs[i].msg_hdr.msg_iovlen = 1
            if gso and segs > 1:
                cm = _GsoCmsg(ctypes.sizeof(ctypes.c_size_t) + 2 * ctypes.sizeof(ctypes.c_int)
                              + 2, SOL_UDP, UDP_SEGMENT, gso)
                self._keep.append(cm)
                self._msgs[i].msg_hdr.msg_control = ctypes.cast(ctypes.pointer(cm),
                                                                ctypes.c_void_p)
                self._msgs[i].msg_hdr.msg_controllen = ctypes.sizeof(cm)
        self._base = ctypes.addressof(self._msgs)
        self._step = ctypes.sizeof(Mmsghdr)
        self.pos = 0

    def send(self, want: int) -> tuple[int, int]:
        """Messages from the current one on, as many as make up to ``want`` datagrams (at
        least one message, at most to the end of the ring), in one system call. Returns
        (datagrams sent, errno or 0)."""
        k, n = 0, 0
        while self.pos + k < self.size and (k == 0 or n + self.segs[self.pos + k] <= want):
            n += self.segs[self.pos + k]
            k += 1
        got = self.libc.sendmmsg(self.fd, self._base + self.pos * self._step, k, 0)
        if got < 0:
            return 0, ctypes.get_errno()
        sent = sum(self.segs[self.pos:self.pos + got])
        self.pos = (self.pos + got) % self.size
        return sent, 0


class Sender:
    """The flooder's socket, with a plain ring (one datagram per message: exact bursts) and a
    UDP GSO ring for the flood (falls back to the plain one where GSO does not work)."""

    def __init__(self, port: int, batch: int, packets: list[bytes], gso: bool = True) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        libc = ctypes.CDLL(None, use_errno=True)
        libc.sendmmsg.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int]
        libc.sendmmsg.restype = ctypes.c_int
        fd = self.sock.fileno()
        self.batch = batch
        self.plain = Ring(fd, plain_messages(packets), libc,
                          repeat=max(1, math.ceil(batch / len(packets))))
        self.gso: Ring | None = Ring(fd, gso_messages(packets, 8), libc, repeat=4) \
            if gso else None
        self.sent = 0
        self.errors = 0
        self.last_errno = 0

    def send(self, want: int, flood: bool = False) -> int:
        """Up to ``want`` datagrams (at least one message) in one system call; how many went."""
        ring = self.gso if flood and self.gso is not None else self.plain
        got, err = ring.send(want)
        if ring is self.gso and err in (errno.EINVAL, errno.EIO, errno.ENOPROTOOPT,
                                        errno.EOPNOTSUPP):
            self.gso = None  # this kernel or interface cannot: plain datagrams from now on
        if err:
            self.errors += 1  # ECONNREFUSED after an ICMP error, ENOBUFS: counted, not fatal
            self.last_errno = err
        self.sent += got
        return got


def burst(s: Sender, n: int) -> dict[str, object]:
    start, err0 = s.sent, s.errors
    t0 = time.time()
    while s.sent - start < n and s.errors - err0 < 1000:
        s.send(n - (s.sent - start))
    return {"sent": s.sent - start, "t0": t0, "t1": time.time(), "errors": s.errors - err0}


def flood(s: Sender, rate: float, batch: int, lines: Lines) -> dict[str, object]:
    start, err0 = s.sent, s.errors
    t0 = time.time()
    series: list[list[float]] = [[t0, 0]]
    next_mark = t0 + SERIES_EVERY_S
    while True:
        now = time.time()
        n = batch
        if rate > 0:
            due = int(rate * (now - t0)) - (s.sent - start)
            if due <= 0:
                time.sleep(min(0.0005, -due / rate + 1e-5))
                n = 0
            else:
                n = min(batch, due)
        if n:
            s.send(n, flood=True)
        if now >= next_mark:
            series.append([now, s.sent - start])
            next_mark = now + SERIES_EVERY_S
            if lines.waiting():
                break
    t1 = time.time()
    series.append([t1, s.sent - start])
    return {"sent": s.sent - start, "t0": t0, "t1": t1, "errors": s.errors - err0,
            "errno": errno.errorcode.get(s.last_errno, s.last_errno) if s.last_errno else None,
            "gso": s.gso is not None, "series": series}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("port", type=int)
    p.add_argument("--rate", type=float, default=0.0, help="packets/s while flooding (0: max)")
    p.add_argument("--batch", type=int, default=256, help="packets per sendmmsg call (at most)")
    p.add_argument("--no-gso", action="store_true", help="one datagram per message")
    args = p.parse_args(argv)
    s = Sender(args.port, args.batch, INVALID_PACKETS, gso=not args.no_gso)

    def do_burst(words: list[str], _lines: Lines) -> None:
        if len(words) != 1:
            raise ValueError("burst takes a number")
        answer(burst(s, int(words[0])))

    def do_flood(_words: list[str], lines: Lines) -> None:
        res = flood(s, args.rate, args.batch, lines)
        lines.readline()  # the line that ended the flood ("stop")
        answer(res)

    return serve({"burst": do_burst, "flood": do_flood})


if __name__ == "__main__":
    sys.exit(main())
