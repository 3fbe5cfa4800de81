"""The HIL harness's load and its counts: the UDP socket's drops, the status windows, what the
flooder sends, latencies under stalls, the keyed rows and the attack packets."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from hil_util import BOOT

import hilcheck
from estop.protocol.can import StatusFrame
from hilcheck import Frame
from repo import ROOT


def _status(ts: float, valid: int, invalid: int, auth: int, ctr: int) -> Frame:
    return Frame(ts, 0x051, StatusFrame(valid, invalid, auth, 0, 0xFFFF, ctr).encode())


def test_status_windows() -> None:
    frames = [_status(1.0, 0, 0, 0, 0), Frame(1.05, 0x050, BOOT), _status(1.1, 5, 12, 3, 1),
              _status(1.2, 0, 255, 0, 2)]
    ws = hilcheck.status_windows(frames)
    assert [(w.start, w.end, w.valid, w.invalid, w.auth_failures) for w in ws] == [
        (1.0, 1.1, 5, 12, 3), (1.1, 1.2, 0, 255, 0)]
    bad = bytearray(frames[2].data)
    bad[7] ^= 1
    ws2 = hilcheck.status_windows([frames[0], Frame(1.1, 0x051, bytes(bad)), frames[3]])
    assert ws2 == []  # a bad frame loses its window and the one after (unknown start)


def test_sent_between() -> None:
    series = [[10.0, 0], [10.005, 100], [10.010, 200], [10.015, 300]]
    assert hilcheck.sent_between(series, 10.005, 10.010) == (100, 100)
    lo, hi = hilcheck.sent_between(series, 10.002, 10.012)
    assert (lo, hi) == (100, 300)
    assert hilcheck.sent_between(series, 9.0, 11.0) == (300, 300)


def test_flooder_counts_what_it_sends() -> None:
    """flood.py against a real socket on loopback: a burst is exactly N, cycling the kinds."""
    import socket
    import time

    import flood

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    port = rx.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-B", str(ROOT / "hil" / "flood.py"), str(port),
                             "--rate", "2000"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        def ask(line: str) -> dict:
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.write(line + "\n")
            proc.stdin.flush()
            return json.loads(proc.stdout.readline())

        assert json.loads(proc.stdout.readline())["ready"] is True  # unasked, once up
        assert ask("ready?")["ready"] is True
        burst = ask("burst 30")
        assert burst["sent"] == 30 and burst["errors"] == 0
        rx.settimeout(2.0)
        got = [rx.recv(128) for _ in range(30)]
        assert got == (flood.INVALID_PACKETS * 3)[:30]
        proc.stdin.write("flood\n")
        proc.stdin.flush()
        time.sleep(0.3)
        res = ask("stop")
        span = res["t1"] - res["t0"]
        assert 0 < res["sent"] <= 2000 * span + 64  # the rate limit holds (one GSO send over)
        assert res["series"][0][1] == 0 and res["series"][-1][1] == res["sent"]
        # UDP GSO cuts the flood's sends apart: each kind arrives as datagrams of its own, in
        # equal numbers, and every one that was counted as sent arrives (no drops here)
        assert res["gso"] is True and res["errors"] == 0
        rx.settimeout(0.5)
        flooded = [rx.recv(128) for _ in range(res["sent"])]
        kinds = {p: flooded.count(p) for p in flood.INVALID_PACKETS}
        assert sum(kinds.values()) == res["sent"]
        assert max(kinds.values()) - min(kinds.values()) <= 8
        with pytest.raises(TimeoutError):
            rx.recv(128)
        assert "error" in ask("bogus")
    finally:
        proc.stdin.write("quit\n")
        proc.stdin.close()
        proc.wait(timeout=10)
        rx.close()


def test_judge_latencies_counts_stalled_samples_as_upper_bounds() -> None:
    jl = hilcheck.judge_latencies
    # all within the limits, stalls or not: met (a stall can only delay)
    v = jl([1.0, 2.0, 4.0, 11.0], [True, True, True, True], 5.0, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    # a slow daemon fails on its clean samples
    v = jl([7.0, 8.0, 9.0, 30.0], [False, False, False, True], 5.0, 25.0, "x")
    assert v.fails == ["x: median > 5.0 ms (waits for the 10 ms tick?)"]
    assert v.inconclusive is None
    # the median over the limit only with stalled samples in it, too few clean ones: undecided
    v = jl([1.0, 8.0, 8.0, 9.0], [False, True, True, True], 5.0, 25.0, "x")
    assert v.inconclusive is not None and v.fails[0].startswith("x: median not judged")
    # enough clean samples decide, the stalled ones aside
    v = jl([1.0, 1.5, 2.0, 8.0, 9.0, 9.5], [False] * 3 + [True] * 3, 5.0, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    # over the max without a stall: a failure; with one: not judged if most samples stalled
    assert jl([1.0, 26.0], [False, False], None, 25.0, "x").fails == ["x: 26.0 ms > 25.0 ms"]
    v = jl([1.0, 26.0, 2.0], [True, True, False], None, 25.0, "x")
    assert v.inconclusive is not None and v.fails[0].startswith("x: max not judged")
    v = jl([1.0, 26.0, 2.0], [False, True, False], None, 25.0, "x")
    assert v.fails == [] and v.inconclusive is None
    assert jl([], [], 5.0, 25.0, "x") == hilcheck.Verdict([])


def test_keyed_rows_run_last() -> None:
    import scenarios

    ids = [sid for sid, *_ in scenarios.SCENARIOS]
    keyed = [i for i, sid in enumerate(ids) if sid in scenarios.KEYED]
    assert len(keyed) == len(scenarios.KEYED) == 4
    assert keyed == list(range(len(ids) - 4, len(ids)))
    assert scenarios.KEYED <= scenarios.RETRYABLE


def test_attack_packets_are_made_without_the_key() -> None:
    from types import SimpleNamespace

    import rows_keyed
    from estop.protocol import auth, udp
    from hilclients import NEUTRAL

    key = bytes(range(32))
    remote = SimpleNamespace(remote_id=7, session=0x0123456789ABCDEF, udp_counter=41)
    genuine = [auth.AuthControlPacket(7, remote.session, c, udp.decode(NEUTRAL))
               .encode(key) for c in (40, 41)]
    pkts = rows_keyed.attack_packets(remote, key, genuine)  # type: ignore[arg-type]
    assert [k for k, _ in pkts] == ["plain", "wrong_key", "replay"] * 2
    for kind, data in pkts:
        if kind == "plain":
            assert data == NEUTRAL and udp.is_valid(data)
        elif kind == "replay":
            assert data in genuine
        else:
            # the right session and remote id, a counter above the remote's, a wrong tag
            with pytest.raises(auth.TagMismatch):
                auth.AuthControlPacket.decode(data, key)
            p = auth.AuthControlPacket.decode(data, None)
            assert p.session == remote.session and p.remote_id == 7 and p.counter > 41
