"""The kernel's account of the unit's UDP socket, read from /proc/net/udp's text."""

from __future__ import annotations

import socket

from estop.unit.udpsocket import UdpSocket, udp_socket

PROC_NET_UDP = """\
   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout \
inode ref pointer drops
11060: 0100007F:D252 00000000:0000 07 00000000:007FFE80 00:00000000 00000000     0        0 \
201297 2 0000000020bb6bc2 226942
14081: 0100007F:9E1F 0100007F:D252 01 00000000:00000000 00:00000000 00000000     0        0 \
201301 2 00000000afdcb09b 7
"""


def test_the_units_socket_in_the_table() -> None:
    assert udp_socket(0xD252, PROC_NET_UDP) == UdpSocket(0x7FFE80, 226942)
    # the flooder's own connected socket (remote port set) is not the daemon's
    assert udp_socket(0x9E1F, PROC_NET_UDP) is None
    assert udp_socket(5700, "header only\n") is None


def test_a_socket_of_this_process_is_found_in_the_real_table() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        got = udp_socket(port)
        assert got is not None and got.drops == 0
