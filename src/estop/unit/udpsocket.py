"""The kernel's account of the unit's UDP control socket (``/proc/net/udp`` of this network
namespace): the bytes waiting in its receive queue and the datagrams it dropped for want of
room. The benchmarks, the HIL harness and the tests read a flood's cost from it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = ["PROC_NET_UDP", "UdpSocket", "udp_socket"]

PROC_NET_UDP = Path("/proc/net/udp")


@dataclass(frozen=True, slots=True)
class UdpSocket:
    rx_queue: int  # bytes of the receive buffer in use
    drops: int  # datagrams dropped since the socket was made


def udp_socket(port: int, table: str | None = None) -> UdpSocket | None:
    """The unconnected UDP socket bound to ``port`` (a connected one, a sender's, is not a
    unit's), from ``table`` (the text of /proc/net/udp; read now when None); None when there
    is no such socket or the table cannot be read."""
    if table is None:
        try:
            table = PROC_NET_UDP.read_text()
        except OSError:
            return None
    for line in table.splitlines()[1:]:
        f = line.split()
        if len(f) < 13 or ":" not in f[1] or ":" not in f[4]:
            continue
        try:
            lport = int(f[1].rsplit(":", 1)[1], 16)
            rport = int(f[2].rsplit(":", 1)[1], 16)
            rxq = int(f[4].split(":")[1], 16)
            drops = int(f[-1])
        except ValueError:
            continue
        if lport == port and rport == 0:
            return UdpSocket(rxq, drops)
    return None
