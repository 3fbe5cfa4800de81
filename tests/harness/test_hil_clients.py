"""The harness's own clients against a real estopd (hil/hilclients.py)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

from daemon_util import Daemon
from hilclients import NEUTRAL, AuthRemote

KEY = bytes(range(32))
RID = 9


def test_the_key_holders_release_is_not_made_stale_by_its_own_keepalive(
        tmp_path: Path, estopd: str) -> None:
    """A RELEASE that waits in the unit's TCP socket while the remote's keepalive goes on: the
    unit reads the control port before the frame, so a control packet made after the RELEASE
    (a higher counter) made it stale, NAK 4 (issue 25 item 2: one counter per remote, a
    RELEASE above the newest on either channel). `make hil`'s keyed rows failed so on a loaded
    machine. The daemon is held (SIGSTOP) for five keepalive periods while the RELEASE waits;
    the remote must make no control packet until its reply."""
    key = tmp_path / "key"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    with Daemon(tmp_path, "--key-file", str(key)) as d:
        assert d.proc is not None
        ar = AuthRemote(d.udp_port, d.tcp_port, KEY, RID)
        try:
            ar.learn_session()
            ar.start(NEUTRAL, period=0.01)
            time.sleep(0.1)  # a live link
            os.kill(d.proc.pid, signal.SIGSTOP)
            got: list[object] = []
            th = threading.Thread(target=lambda: got.append(ar.release()), daemon=True)
            try:
                th.start()
                time.sleep(0.05)  # the RELEASE waits; the keepalive would send five meanwhile
            finally:
                os.kill(d.proc.pid, signal.SIGCONT)
            th.join(timeout=5)
            assert got, "no reply to the RELEASE"
            ex = got[0]
            assert ex.reply.ack and ex.reply.state == 1, ex.reply  # type: ignore[attr-defined]
        finally:
            ar.close()


def test_the_storm_row_counts_the_stop_clients_the_unit_closed() -> None:
    """rows_storm.evicted: the harness's idle stop clients that the unit closed, found
    without reading or sending. Since the harness's StopClient became the package's
    StopChannel (issue 27) it has no ``sock``: the storm row failed with an AttributeError."""
    import socket
    from types import SimpleNamespace

    import rows_storm
    from hilclients import StopClient

    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(8)
        port = srv.getsockname()[1]
        clients = [StopClient(port) for _ in range(3)]
        accepted = [srv.accept()[0] for _ in clients]
        try:
            run = SimpleNamespace(clients=clients)
            assert rows_storm.evicted(run) == 0  # type: ignore[arg-type]
            accepted[0].close()
            accepted[2].close()
            deadline = time.monotonic() + 2.0
            while rows_storm.evicted(run) < 2 and time.monotonic() < deadline:  # type: ignore[arg-type]
                time.sleep(0.01)
            assert rows_storm.evicted(run) == 2  # type: ignore[arg-type]
        finally:
            for c in clients:
                c.close()
            for a in accepted:
                a.close()


def test_a_keepalive_send_held_after_its_stamp_counts_in_the_pause() -> None:
    """A keepalive thread held between its stamp and its send (a loaded guest) sent later than
    stamped: the pause it may have left is from the stamp before one send to the return of the
    next (a local run: the unit timed out with 'no' pause of 150 ms in the stamps)."""
    from hilclients import UdpRemote

    rem = UdpRemote.__new__(UdpRemote)  # no socket: the bookkeeping alone
    rem.keepalive_times = [0.0, 0.02, 0.04, 0.06]
    rem.keepalive_after = [0.001, 0.021, 0.24, 0.061]  # the third send returned 200 ms late
    assert abs(rem.max_gap(0.0, 1.0) - 0.22) < 1e-9  # stamps alone: 0.02
    assert abs(rem.max_gap(0.05, 1.0) - 0.0) < 1e-9  # one packet: no pause in the range
