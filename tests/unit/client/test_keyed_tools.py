"""The tools with a key (``--key-file``, spec section 5) against a small keyed unit on loopback.

The unit here checks and makes tags with hashlib and struct directly (not with
estop.protocol.auth), so the tools' use of the codecs is checked independently: their packets
and requests must verify, and replies that do not verify must be refused loudly.
"""

from __future__ import annotations

import hashlib
import hmac
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from cli_util import run_cli
from estop.client.channel import ReplyNotAuthentic
from estop.client.sender import Remote
from estop.protocol import tcp, udp
from estop.protocol.udp import Gear
from net_util import LOCAL, FakeUnitPorts, chunks, connections, datagrams, wait_until

pytestmark = pytest.mark.timeout(60)

K = bytes(range(100, 132))
N = 0x1122334455667788  # the unit's session


def blake(data: bytes, key: bytes = K) -> bytes:
    return hashlib.blake2s(data, key=key, digest_size=16).digest()


@dataclass
class KeyedUnit(FakeUnitPorts):
    """UDP and TCP ports of a unit with key K and session N. ``mode``: ``normal``, ``forge``
    (reply tags are wrong), ``keyless`` (reply tags are zero, as from a unit without a key).
    It keeps what it authenticated: ``packets`` (60-byte control packets, decoded fields),
    ``stop_datagrams`` and ``lift_datagrams`` (tag and session right, session, counter; a lift
    datagram also its seq), ``requests`` (msg_id, authenticated, session, frame length)."""

    mode: str = "normal"
    packets: list[tuple[int, int, int, bytes]] = field(default_factory=list)
    rejected: int = 0
    stop_datagrams: list[tuple[bool, int, int]] = field(default_factory=list)
    lift_datagrams: list[tuple[bool, int, int, int]] = field(default_factory=list)
    requests: list[tuple[int, bool, int, int]] = field(default_factory=list)
    state: int = 0
    reason: int = 1

    def __post_init__(self) -> None:
        self.high: dict[tuple[int, str], int] = {}
        self._open_ports(0.02)

    def _authentic(self, signed: bytes, tag: bytes, rid: int, session: int, counter: int,
                   channel: str) -> bool:
        if not hmac.compare_digest(blake(signed), tag) or session != N:
            return False
        if counter <= self.high.get((rid, channel), 0):
            return False
        self.high[(rid, channel)] = counter
        return True

    def _udp_loop(self) -> None:
        for data in datagrams(self.udp, self._stop):
            if len(data) == 60 and data[:4] == b"ESU2":
                rid, session, counter = struct.unpack("<IQQ", data[4:24])
                if self._authentic(data[:44], data[44:], rid, session, counter, "udp") and \
                        udp.is_valid(data[24:44]):
                    self.packets.append((rid, session, counter, data[24:44]))
                else:
                    self.rejected += 1
            elif len(data) == 48 and data[:4] == b"ESQ2":
                msg_id, seq, rid, session, counter = struct.unpack("<IIIQQ", data[4:32])
                ok = hmac.compare_digest(blake(data[:32]), data[32:]) and session == N
                if msg_id == tcp.DEFAULT_STOP_ID:  # anyone may stop
                    self.stop_datagrams.append((ok, session, counter))
                    self.state, self.reason = 0, 2 if self.state == 1 else self.reason
                elif msg_id == 3:  # LIFT: a stop request too, reason lift
                    self.lift_datagrams.append((ok, session, counter, seq))
                    self.state, self.reason = 0, 5 if self.state == 1 else self.reason
            else:
                self.rejected += 1

    def _tcp_loop(self) -> None:
        for conn in connections(self.tcp, self._stop):
            th = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            self._threads.append(th)
            th.start()

    def _serve(self, conn: socket.socket) -> None:
        asm = tcp.RequestAssembler()
        with conn:
            for chunk in chunks(conn, self._stop, 0.02):
                for frame in asm.feed(chunk):
                    conn.sendall(self._answer(frame))

    def _answer(self, frame: bytes) -> bytes:
        if len(frame) == 16:
            req = tcp.Request.decode(frame)
            self.requests.append((req.msg_id, False, 0, 16))
            ack, nak = self._decide(req.msg_id, authenticated=False)
            return tcp.Reply(ack, req.seq, self.state, self.reason, 0, nak).encode()
        msg_id, seq, rid, session, counter = struct.unpack("<IIIQQ", frame[4:32])
        ok = self._authentic(frame[:32], frame[32:], rid, session, counter, "tcp")
        self.requests.append((msg_id, ok, session, 48))
        ack, nak = self._decide(msg_id, authenticated=ok)
        body = b"ESR2" + struct.pack("<IIBBBBQQ", 0x80 if ack else 0x81, seq, self.state,
                                     self.reason, 0, nak, N, counter)
        if self.mode == "keyless":
            return body + bytes(16)
        tag = blake(frame[32:] + body)
        if self.mode == "forge":
            tag = bytes(b ^ 0x55 for b in tag)
        return body + tag

    def _decide(self, msg_id: int, authenticated: bool) -> tuple[bool, int]:
        if msg_id in (tcp.DEFAULT_STOP_ID, tcp.LIFT):  # stop requests: never refused
            if self.state == 1:
                self.state, self.reason = 0, 2 if msg_id == tcp.DEFAULT_STOP_ID else 5
            return True, 0
        if msg_id == tcp.STATUS:
            return True, 0
        if msg_id == tcp.RELEASE:
            if not authenticated:
                return False, 4
            self.state, self.reason = 1, 0
            return True, 0
        return False, 1


@pytest.fixture
def unit() -> Iterator[KeyedUnit]:
    u = KeyedUnit()
    yield u
    u.close()


@pytest.fixture
def key_path(tmp_path: Path) -> str:
    p = tmp_path / "estop.key"
    p.write_text(K.hex() + "\n")
    p.chmod(0o600)
    return str(p)


# ------------------------------------------------------------------------ one-shot tools

def test_status_with_a_key(unit: KeyedUnit, key_path: str, capsys) -> None:
    code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", str(unit.tcp_port),
                             "--key-file", key_path)
    assert (code, err) == (0, "")
    assert out.strip() == "ACK seq=1 state=STOPPED reason=boot flags=0x00"
    # a 48-byte request with session 0: a right tag, not authenticated (session unknown yet)
    assert unit.requests == [(tcp.STATUS, False, 0, 48)]


def test_the_key_file_may_come_from_the_environment(unit: KeyedUnit, key_path: str, capsys,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ESTOP_KEY_FILE", key_path)
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(unit.tcp_port))
    assert code == 0
    assert out.strip().startswith("ACK seq=1 state=ARMED")
    assert unit.requests == [(tcp.STATUS, False, 0, 48), (tcp.RELEASE, True, N, 48)]


def test_key_file_option_wins_over_the_environment(unit: KeyedUnit, key_path: str, capsys,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   tmp_path: Path) -> None:
    monkeypatch.setenv("ESTOP_KEY_FILE", str(tmp_path / "missing.key"))
    code, out, _ = run_cli(capsys, "status", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--key-file", key_path)
    assert code == 0, out


def test_a_bad_key_file_in_the_environment_is_one_line_naming_it(capsys,
                                                                 monkeypatch: pytest.MonkeyPatch,
                                                                 tmp_path: Path) -> None:
    monkeypatch.setenv("ESTOP_KEY_FILE", str(tmp_path / "missing.key"))
    code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", "9")
    assert code == 4 and out == ""  # a file error (the exit-code table), naming its source
    assert len(err.strip().splitlines()) == 1 and "ESTOP_KEY_FILE" in err, err


def test_release_with_a_key_learns_the_session_first(unit: KeyedUnit, key_path: str,
                                                     capsys) -> None:
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--key-file", key_path, "--seq", "5")
    assert code == 0
    assert out.strip() == "ACK seq=5 state=ARMED reason=none flags=0x00"
    assert unit.requests == [(tcp.STATUS, False, 0, 48), (tcp.RELEASE, True, N, 48)]


def test_release_without_a_key_is_nak_4(unit: KeyedUnit, capsys) -> None:
    code, out, _ = run_cli(capsys, "release", "--host", LOCAL, "--port", str(unit.tcp_port))
    assert code == 1
    assert out.strip().endswith("nak=not_authenticated")


@pytest.mark.parametrize("mode", ["forge", "keyless"])
def test_replies_that_do_not_verify_are_refused_loudly(mode: str, key_path: str,
                                                       capsys) -> None:
    u = KeyedUnit(mode=mode)
    try:
        code, out, err = run_cli(capsys, "status", "--host", LOCAL, "--port", str(u.tcp_port),
                                 "--key-file", key_path)
    finally:
        u.close()
    assert code == 3 and out == ""
    lines = err.splitlines()
    assert len(lines) == 1 and "does NOT verify under the key" in lines[0]


def test_stop_with_a_key(unit: KeyedUnit, key_path: str, capsys) -> None:
    code, out, _ = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(unit.tcp_port),
                           "--udp-port", str(unit.udp_port), "--key-file", key_path,
                           "--remote-id", "9")
    assert code == 0 and out.strip().endswith("(after 1 attempt)")
    assert unit.requests == [(tcp.DEFAULT_STOP_ID, False, 0, 48)]
    wait_until(lambda: bool(unit.stop_datagrams))
    assert len(unit.stop_datagrams) == 1
    ok, session, _ = unit.stop_datagrams[0]
    assert session == 0 and not ok  # the session is not known yet: a stop all the same


def test_lift_with_a_key(unit: KeyedUnit, key_path: str, capsys) -> None:
    code, out, _ = run_cli(capsys, "lift", "--host", LOCAL, "--tcp-port", str(unit.tcp_port),
                           "--udp-port", str(unit.udp_port), "--key-file", key_path,
                           "--remote-id", "9", "--seq", "4")
    assert code == 0 and out.strip() == ("ACK seq=4 state=STOPPED reason=boot flags=0x00 "
                                         "(lift sent x3)")
    # a 48-byte LIFT (its tag right, but not authenticated: the session is not known, and a
    # LIFT needs none), after the three lift datagrams, tagged, with rising counters
    assert unit.requests == [(tcp.LIFT, False, 0, 48)]
    wait_until(lambda: len(unit.lift_datagrams) >= 3)
    assert [(ok, session, seq) for ok, session, _, seq in unit.lift_datagrams] == [
        (False, 0, 4)] * 3
    counters = [c for _, _, c, _ in unit.lift_datagrams]
    assert counters == sorted(counters) and len(set(counters)) == 3


def test_forged_ack_to_a_stop_is_not_believed(key_path: str, capsys) -> None:
    u = KeyedUnit(mode="forge")
    try:
        code, _, err = run_cli(capsys, "stop", "--host", LOCAL, "--port", str(u.tcp_port),
                               "--udp-port", str(u.udp_port), "--key-file", key_path,
                               "--stop-deadline", "0.3")
    finally:
        u.close()
    assert code == 3
    assert "no ACK within 0.3 s" in err and "does NOT verify" in err and err.count("\n") == 1


@pytest.mark.parametrize("argv", [
    ["status", "--host", LOCAL],
    ["remote", "--host", LOCAL, "--script", "hold 0.1"],
])
def test_bad_key_file_is_a_file_error(argv: list[str], tmp_path: Path, capsys) -> None:
    p = tmp_path / "k"
    p.write_text(K.hex() + "\n")
    p.chmod(0o644)
    code, out, err = run_cli(capsys, *argv, "--key-file", str(p))
    assert code == 4 and out == ""
    assert err.count("\n") == 1 and "--key-file: key file" in err and "mode 0644" in err


def test_legacy_and_key_do_not_mix(key_path: str, capsys) -> None:
    code, _, err = run_cli(capsys, "remote", "--host", LOCAL, "--legacy", "--key-file",
                           key_path, "--script", "hold 0.1")
    assert code == 2 and "--legacy" in err and err.count("\n") == 1


# ------------------------------------------------------------------------------ the remote

def test_remote_with_a_key_end_to_end(unit: KeyedUnit, key_path: str, capsys) -> None:
    code, out, _ = run_cli(capsys, "remote", "--host", LOCAL, "--udp-port", str(unit.udp_port),
                           "--tcp-port", str(unit.tcp_port), "--key-file", key_path,
                           "--remote-id", "7", "--rate", "100", "--script",
                           "hold 0.2; release; expect ack armed; drive 0.3 0.1; stop; "
                           "expect ack stopped tcp_stop; lift")
    assert code == 0, out
    # hold learned the session with a STATUS; the RELEASE was authenticated
    assert unit.requests[:2] == [(tcp.STATUS, False, 0, 48), (tcp.RELEASE, True, N, 48)]
    assert unit.requests[2] == (tcp.DEFAULT_STOP_ID, True, N, 48)
    wait_until(lambda: len(unit.packets) >= 5 and bool(unit.stop_datagrams))
    assert len(unit.packets) >= 5 and unit.rejected == 0  # every packet verified
    assert {(rid, session) for rid, session, _, _ in unit.packets} == {(7, N)}
    counters = [c for _, _, c, _ in unit.packets]
    assert counters == sorted(counters) and len(set(counters)) == len(counters)
    bodies = {udp.decode(b) for _, _, _, b in unit.packets}
    assert udp.ControlPacket() in bodies
    assert any(b.gear == Gear.DRIVE and b.gas_brake > 0.29 for b in bodies)
    assert unit.stop_datagrams == [(True, N, unit.stop_datagrams[0][2])]  # authenticated
    # the lift at the end: three lift datagrams with the key, the session and the remote's
    # counter (above every control packet's), one seq
    assert "lift: lift sent x3" in out
    wait_until(lambda: len(unit.lift_datagrams) >= 3)
    assert len(unit.lift_datagrams) == 3
    assert {(ok, session) for ok, session, _, _ in unit.lift_datagrams} == {(True, N)}
    assert len({seq for *_, seq in unit.lift_datagrams}) == 1
    lift_counters = [c for _, _, c, _ in unit.lift_datagrams]
    assert lift_counters == sorted(lift_counters) and lift_counters[0] > max(counters)


def test_remote_api_refuses_a_forged_reply(key_path: str) -> None:
    u = KeyedUnit(mode="forge")
    try:
        with Remote(LOCAL, u.udp_port, u.tcp_port, key=K) as r:
            with pytest.raises(ReplyNotAuthentic):
                r.status()
            with pytest.raises(ReplyNotAuthentic):
                r.hold()  # it cannot learn the session: it does not start sending
            assert not r.held and r.channel.session == 0
        time.sleep(0.1)
        assert u.packets == [] and u.rejected == 0
    finally:
        u.close()
