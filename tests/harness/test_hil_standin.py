"""The HIL harness's stand-in and storm (hil/standin_estopd.py, hil/storm.py, rows_storm) and
its UDP tap (hil/hilload.py), on loopback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from repo import ROOT


def test_standin_reads_datagrams_in_batches() -> None:
    """The stand-in's recvmmsg (ctypes): in order, at most n a call, long ones cut at 64."""
    import socket
    import time

    import standin_estopd

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.bind(("127.0.0.1", 0))
        rx.setblocking(False)
        batch = standin_estopd.BatchReceiver(rx, n=8)
        assert batch.recv() == []
        tx.connect(rx.getsockname())
        sent = [b"", b"a" * 19, b"b" * 20, b"c" * 100] + [bytes([i]) * 5 for i in range(10)]
        for m in sent:
            tx.send(m)
        got: list[bytes] = []
        end = time.monotonic() + 2.0
        while len(got) < len(sent) and time.monotonic() < end:
            more = batch.recv()
            assert len(more) <= 8
            got += more
        assert got == [m[:64] for m in sent]
    finally:
        rx.close()
        tx.close()


def test_storm_holds_every_place_and_closes_an_idle_client() -> None:
    """storm.py against a loopback server that keeps 8 connections and closes the one quiet
    longest (as the unit does, docs/PROTOCOL.md section 2): its busy connections get their
    replies, a client that connected first and stays idle is closed, and it counts what it
    did."""
    import selectors
    import socket
    import threading
    import time

    from estop.protocol import tcp

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(64)
    srv.setblocking(False)
    port = srv.getsockname()[1]
    done = threading.Event()

    def serve() -> None:  # the unit's rule for making room, and a reply per request
        sel = selectors.DefaultSelector()
        sel.register(srv, selectors.EVENT_READ)
        quiet: dict[socket.socket, float] = {}
        while not done.is_set():
            for key, _ in sel.select(0.01):
                if key.fileobj is not srv and key.fileobj not in quiet:
                    continue  # closed earlier in this round to make room: its event is stale
                if key.fileobj is srv:
                    conn, _addr = srv.accept()
                    if len(quiet) >= 8:
                        victim = min(quiet, key=quiet.__getitem__)
                        sel.unregister(victim)
                        del quiet[victim]
                        victim.close()
                    conn.setblocking(False)
                    quiet[conn] = time.monotonic()
                    sel.register(conn, selectors.EVENT_READ)
                    continue
                conn = key.fileobj  # type: ignore[assignment]
                try:
                    data = conn.recv(4096)
                except OSError:
                    data = b""
                if not data:
                    sel.unregister(conn)
                    quiet.pop(conn, None)
                    conn.close()
                    continue
                quiet[conn] = time.monotonic()
                try:
                    conn.send(bytes(tcp.FRAME_SIZE) * (len(data) // tcp.FRAME_SIZE))
                except OSError:
                    pass
        for c in quiet:
            c.close()

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    idle = socket.create_connection(("127.0.0.1", port))
    proc = subprocess.Popen([sys.executable, "-B", str(ROOT / "hil" / "storm.py"), str(port)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        assert json.loads(proc.stdout.readline())["ready"] is True
        proc.stdin.write("storm\n")
        proc.stdin.flush()
        busy = json.loads(proc.stdout.readline())
        assert busy["busy"] is True
        time.sleep(0.3)
        idle.settimeout(2.0)
        assert idle.recv(16) == b""  # the idle client was the quietest: closed
        proc.stdin.write("stop\n")
        proc.stdin.flush()
        res = json.loads(proc.stdout.readline())
        assert res["connects"] > 0 and res["refused"] == 0
        assert res["status_sent"] > 0 and 0 < res["replies"] <= res["status_sent"]
        assert res["busy_closed_by_unit"] > 0  # every new connect closes someone
    finally:
        proc.stdin.write("quit\n")
        proc.stdin.close()
        proc.wait(timeout=10)
        done.set()
        server.join(timeout=2)
        idle.close()
        srv.close()


def test_sched_text_and_the_stop_datagram_the_storm_row_looks_for() -> None:
    import os

    import hildaemon
    import rows_storm
    from estop.protocol import auth, tcp

    me = hildaemon.threads_sched(os.getpid())
    assert me and me[0].tid == os.getpid()  # the main thread first
    assert hildaemon.sched_text(me).startswith(f"loop {me[0].policy}")
    fifo = hildaemon.ThreadSched(1, "estopd", "FIFO", 50, True)
    out = hildaemon.ThreadSched(2, "estopd-out", "OTHER", 0, False)
    assert hildaemon.sched_text([fifo, out, out]) == \
        "loop FIFO 50 reset-on-fork; 2 other threads OTHER"
    assert hildaemon.sched_text([]).startswith("unknown")
    assert rows_storm.is_stop_datagram(auth.stop_datagram(1, 1))
    assert not rows_storm.is_stop_datagram(auth.stop_datagram(1, 1, stop_id=0x12345678))
    assert not rows_storm.is_stop_datagram(tcp.Request(tcp.DEFAULT_STOP_ID, 1).encode())


def test_udp_tap_times_only_the_datagrams_asked_for() -> None:
    """hilload.UdpTap (a packet socket on lo, root only): the kernel's time of each datagram of
    the size asked for to the port asked for; the others (a keepalive's 20-byte packets, in
    thousands) never reach its queue."""
    import socket
    import time

    from estop.protocol import auth
    from hilload import UdpTap

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    port = rx.getsockname()[1]
    try:
        tap = UdpTap(port, auth.REQUEST_SIZE)
    except PermissionError:
        rx.close()
        pytest.skip("a packet socket needs root")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(3000):
            tx.sendto(bytes(20), ("127.0.0.1", port))
        t0 = time.time()
        tx.sendto(auth.stop_datagram(1, 1), ("127.0.0.1", port))
        t1 = time.time()
        tx.sendto(bytes(auth.REQUEST_SIZE), ("127.0.0.1", port + 1 if port < 65535 else 1))
        got = tap.read()
        assert [p for _, p in got][:1] == [auth.stop_datagram(1, 1)]
        assert all(p == auth.stop_datagram(1, 1) for _, p in got)  # sent, maybe received too
        assert t0 - 1e-3 <= got[0][0] <= t1 + 1e-3
    finally:
        tap.close()
        tx.close()
        rx.close()
