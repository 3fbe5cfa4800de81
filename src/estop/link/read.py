"""The inputs of ``estop link``: a file of arrival times or a pcap of the control port, and the
choice between them and estopd's ``--log-json`` log (read by :mod:`estop.link.histogram`), each read
into gap cells (:mod:`estop.link.gaps`). Bad input is a :class:`LinkInputError`: one line,
exit 2."""

from __future__ import annotations

import math
import os
import re
import struct
from typing import Any

import numpy as np

from estop.link.gaps import F64, Gaps, LinkInputError, gaps_from_histogram, gaps_from_times
from estop.link.histogram import open_text, read_histogram_log

__all__ = ["detect_format", "load", "read_pcap_times", "read_times"]

CONTROL_LENGTHS = frozenset({20, 16, 60})
_JOURNAL_LINE = re.compile(rb"^.*?\S\[\d+\]: ")  # `... estopd[812]: message`


def read_times(path: str) -> F64:
    """Arrival times, one float in seconds per line (blank lines and # comments skipped)."""
    with open_text(path) as f:
        try:
            text = f.read()
        except UnicodeDecodeError:
            raise LinkInputError(f"{path}: not a text file of times") from None
    if "#" not in text:  # fast path; any doubt goes to the line-by-line reader for its message
        tokens = text.split()
        if len(tokens) == sum(1 for line in text.splitlines() if line.strip()):
            try:
                t = np.asarray(tokens, dtype=np.float64)
            except ValueError:
                t = None
            if t is not None and np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0):
                return t
    return _read_times_slow(path, text)


def _read_times_slow(path: str, text: str) -> F64:
    values: list[float] = []
    prev = -math.inf
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            v = float(line)
        except ValueError:
            raise LinkInputError(f"{path}:{no}: not a time in seconds: {line[:40]!r}") from None
        if not math.isfinite(v):
            raise LinkInputError(f"{path}:{no}: not a finite time: {line[:40]!r}")
        if v < prev:
            raise LinkInputError(f"{path}:{no}: time goes backwards ({v:g} after {prev:g})")
        prev = v
        values.append(v)
    return np.asarray(values, dtype=np.float64)


def read_pcap_times(path: str, udp_port: int = 5700) -> tuple[F64, int]:
    """Arrival times of the UDP datagrams to ``udp_port`` that have a control packet's length
    (20, 16 or 60 bytes), from a pcap or pcapng file; also the number of other datagrams to
    that port (stop datagrams, bad lengths). IPv4 and IPv6 over Ethernet, Linux cooked (v1,
    v2), loopback and raw IP."""
    import dpkt

    try:
        f = open(path, "rb")
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None
    times: list[float] = []
    other = 0
    with f:
        try:
            reader = dpkt.pcap.UniversalReader(f)
        except (ValueError, dpkt.Error):
            raise LinkInputError(f"{path}: not a pcap or pcapng capture") from None
        decode = _link_decoder(int(reader.datalink()), path)
        try:
            for ts, buf in reader:
                try:
                    ip = decode(buf)
                except (dpkt.Error, IndexError, ValueError, struct.error):
                    continue
                if not isinstance(ip, (dpkt.ip.IP, dpkt.ip6.IP6)):
                    continue
                udp = ip.data
                if not isinstance(udp, dpkt.udp.UDP) or udp.dport != udp_port:
                    continue
                if int(udp.ulen) - 8 in CONTROL_LENGTHS:
                    times.append(float(ts))
                else:
                    other += 1
        except (dpkt.Error, ValueError, struct.error) as exc:
            raise LinkInputError(f"{path}: capture cut short or damaged ({exc})") from None
    t = np.sort(np.asarray(times, dtype=np.float64))
    return t, other


def _link_decoder(linktype: int, path: str) -> Any:
    import dpkt

    def raw_ip(buf: bytes) -> Any:
        version = buf[0] >> 4 if buf else 0
        if version == 4:
            return dpkt.ip.IP(buf)
        if version == 6:
            return dpkt.ip6.IP6(buf)
        return None

    def data_of(cls: Any) -> Any:
        return lambda buf: cls(buf).data

    decoders: dict[int, Any] = {
        1: data_of(dpkt.ethernet.Ethernet),  # DLT_EN10MB
        0: data_of(dpkt.loopback.Loopback),  # DLT_NULL
        108: data_of(dpkt.loopback.Loopback),  # DLT_LOOP
        113: data_of(dpkt.sll.SLL),  # DLT_LINUX_SLL
        276: data_of(dpkt.sll2.SLL2),  # DLT_LINUX_SLL2
        101: raw_ip, 12: raw_ip, 14: raw_ip, 228: raw_ip, 229: raw_ip,  # raw IP forms
    }
    if linktype not in decoders:
        raise LinkInputError(f"{path}: link type {linktype} not supported (Ethernet, Linux "
                             "cooked, loopback or raw IP captures are)")
    return decoders[linktype]


def detect_format(path: str) -> str:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as exc:
        raise LinkInputError(f"cannot open {path}: {exc.strerror}") from None
    if head[:4] in (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1",
                    b"\xa1\xb2\x3c\x4d", b"\x0a\x0d\x0d\x0a"):
        return "pcap"
    lines = [s for s in (line.strip() for line in head.splitlines())
             if s and not s.startswith(b"#") and not s.startswith(b"-- ")]
    if not lines:
        raise LinkInputError(f"{path}: empty file")
    if any(s.startswith(b"{") or _JOURNAL_LINE.match(s) for s in lines):
        return "log"  # estopd's JSON (also among systemd's lines: -o cat), -o json, plain
    return "times"


def load(path: str, fmt: str, rate_hz: float, max_gap: float, udp_port: int) -> Gaps:
    """Read one input file into gap cells."""
    kind = detect_format(path) if fmt == "auto" else fmt
    name = os.path.basename(path)
    if kind == "log":
        return gaps_from_histogram(read_histogram_log(path), rate_hz, max_gap,
                                   f"estopd log {name}")
    if kind == "pcap":
        t, other = read_pcap_times(path, udp_port)
        if t.size < 2:
            raise LinkInputError(f"{path}: fewer than 2 control packets to UDP port {udp_port}")
        g = gaps_from_times(t, rate_hz, max_gap, f"capture {name}")
        g.extra["other_datagrams"] = other
        return g
    return gaps_from_times(read_times(path), rate_hz, max_gap, f"arrival times {name}")


