"""Protocol version 2 (spec section 5): the authenticated codecs of estop.protocol.auth against
the spec's test vectors and properties, the v2 framing rules of section 2, and key files.

hashlib's BLAKE2s is the reference for every tag (no copy of the codec's own code).
"""

from __future__ import annotations

import hashlib
import os
import stat
import struct
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from estop import cli
from estop.client.keyfile import KeyFileError, load_key_file, write_key_file
from estop.protocol import auth, tcp, udp
from estop.protocol.auth import (
    AuthControlPacket,
    AuthError,
    AuthReply,
    AuthRequest,
    TagMismatch,
)
from estop.protocol.tcp import NakCode, RequestAssembler
from estop.protocol.udp import ControlPacket, Gear, TurnSignal

# ------------------------------------------------------------------ spec 5.4 test vectors

K = bytes(range(32))
N = 0x0123456789ABCDEF
RID = 7
BODY = ControlPacket(0.3, -0.25, Gear.DRIVE, TurnSignal.LEFT, 0)


def h(*lines: str) -> bytes:
    return bytes.fromhex(" ".join(lines))


V_CONTROL = h("45 53 55 32 07 00 00 00 EF CD AB 89 67 45 23 01 01 00 00 00 00 00 00 00",
              "9A 99 99 3E 00 00 80 BE 08 00 00 00 01 00 00 00 00 00 00 00",
              "0C EF FB 40 CD 71 1A F5 A3 87 85 67 B9 28 7C 72")
V_STATUS = h("45 53 51 32 01 00 00 00 01 00 00 00 07 00 00 00 00 00 00 00 00 00 00 00",
             "88 77 66 55 44 33 22 11 E0 5B 65 D7 00 A8 04 C4 65 2A 16 32 A0 EA DD 1E")
V_STATUS_REPLY = h("45 53 52 32 80 00 00 00 01 00 00 00 00 01 00 00 EF CD AB 89 67 45 23 01",
                   "88 77 66 55 44 33 22 11 E0 3C 40 08 C7 26 9C 38 B7 4F 4C 23 9E 56 E7 0D")
V_RELEASE = h("45 53 51 32 02 00 00 00 02 00 00 00 07 00 00 00 EF CD AB 89 67 45 23 01",
              "02 00 00 00 00 00 00 00 15 42 BA 83 A0 CE 93 39 AA 34 55 A8 66 EF 4D E5")
V_STOP = h("45 53 51 32 70 E5 70 E5 03 00 00 00 07 00 00 00 EF CD AB 89 67 45 23 01",
           "03 00 00 00 00 00 00 00 2D 87 7B 42 F3 EA AC D8 BB 0A 03 26 F1 8E D5 2A")

STATUS_REQ = AuthRequest(tcp.STATUS, 1, RID, 0, 0x1122334455667788)
STATUS_REPLY = AuthReply(True, 1, 0, 1, flags=0, nak_code=0, session=N,
                         counter=0x1122334455667788)
REQUEST_VECTORS = [
    (V_STATUS, STATUS_REQ),
    (V_RELEASE, AuthRequest(tcp.RELEASE, 2, RID, N, 2)),
    (V_STOP, AuthRequest(tcp.DEFAULT_STOP_ID, 3, RID, N, 3)),
]


def blake(key: bytes, data: bytes) -> bytes:
    return hashlib.blake2s(data, key=key, digest_size=16).digest()


def test_vectors_are_what_hashlib_says() -> None:
    # the vectors themselves, re-derived from the spec's layout with hashlib and struct only
    assert V_CONTROL[44:] == blake(K, V_CONTROL[:44])
    for frame, _ in REQUEST_VECTORS:
        assert frame[32:] == blake(K, frame[:32])
    assert V_STATUS_REPLY[32:] == blake(K, V_STATUS[32:] + V_STATUS_REPLY[:32])
    assert V_CONTROL[:24] == b"ESU2" + struct.pack("<IQQ", RID, N, 1)


def test_vector_control_packet() -> None:
    pkt = AuthControlPacket(RID, N, 1, BODY)
    assert pkt.encode(K) == V_CONTROL
    got = AuthControlPacket.decode(V_CONTROL, K)
    assert (got.remote_id, got.session, got.counter) == (RID, N, 1)
    assert got.body == udp.decode(V_CONTROL[24:44])
    assert got.body.encode() == BODY.encode()
    assert len(V_CONTROL) == auth.CONTROL_SIZE == 60


@pytest.mark.parametrize(("frame", "req"), REQUEST_VECTORS, ids=["status", "release", "stop"])
def test_vector_requests(frame: bytes, req: AuthRequest) -> None:
    assert req.encode(K) == frame
    assert AuthRequest.decode(frame, K) == req
    assert auth.request_tag(frame) == frame[32:]
    assert len(frame) == auth.REQUEST_SIZE == 48


def test_vector_request_kinds() -> None:
    assert [AuthRequest.decode(f, K).kind() for f, _ in REQUEST_VECTORS] == [
        "status", "release", "stop"]


def test_vector_reply() -> None:
    assert STATUS_REPLY.encode(K, V_STATUS[32:]) == V_STATUS_REPLY
    got = AuthReply.decode(V_STATUS_REPLY, K, auth.request_tag(V_STATUS))
    assert got == STATUS_REPLY
    assert got.reply == tcp.Reply(True, 1, 0, 1, 0, 0)
    assert got.msg_id == tcp.ACK and len(V_STATUS_REPLY) == auth.REPLY_SIZE == 48


def test_stop_datagram_helper_is_the_stop_vector() -> None:
    assert auth.stop_datagram(3, 3, key=K, session=N, remote_id=RID) == V_STOP
    keyless = auth.stop_datagram(1, 1)
    assert keyless == (b"ESQ2" + struct.pack("<IIIQQ", tcp.DEFAULT_STOP_ID, 1, 0, 0, 1)
                       + bytes(16))
    with pytest.raises(ValueError, match="stop ID"):
        auth.stop_datagram(1, 1, stop_id=2)


# ------------------------------------------------------------------------- tag failures

def flips(frame: bytes) -> list[tuple[int, bytes]]:
    out = []
    for bit in range(len(frame) * 8):
        b = bytearray(frame)
        b[bit // 8] ^= 1 << (bit % 8)
        out.append((bit, bytes(b)))
    return out


def test_control_packet_any_bit_flip_is_refused() -> None:
    for bit, bad in flips(V_CONTROL):
        with pytest.raises(TagMismatch if bit >= 32 else AuthError):
            AuthControlPacket.decode(bad, K)


@pytest.mark.parametrize("frame", [f for f, _ in REQUEST_VECTORS], ids=["status", "release",
                                                                        "stop"])
def test_request_any_bit_flip_is_refused(frame: bytes) -> None:
    for bit, bad in flips(frame):
        with pytest.raises(TagMismatch if bit >= 32 else AuthError):
            AuthRequest.decode(bad, K)


def test_reply_any_bit_flip_is_refused() -> None:
    tag = V_STATUS[32:]
    for bit, bad in flips(V_STATUS_REPLY):
        with pytest.raises(TagMismatch if bit >= 32 else AuthError):
            AuthReply.decode(bad, K, tag)
    # ... and a flip in the request's tag it answers
    for _bit, bad_tag in flips(tag):
        with pytest.raises(TagMismatch):
            AuthReply.decode(V_STATUS_REPLY, K, bad_tag)


def test_wrong_key_is_refused_everywhere() -> None:
    other = bytes(range(1, 33))
    with pytest.raises(TagMismatch):
        AuthControlPacket.decode(V_CONTROL, other)
    for frame, _ in REQUEST_VECTORS:
        with pytest.raises(TagMismatch):
            AuthRequest.decode(frame, other)
    with pytest.raises(TagMismatch):
        AuthReply.decode(V_STATUS_REPLY, other, V_STATUS[32:])
    assert isinstance(TagMismatch("x"), tcp.FrameError)  # tools catch every frame error


def test_reply_is_bound_to_its_request() -> None:
    # a genuine reply, checked against another request's tag (a replay): refused
    with pytest.raises(TagMismatch):
        AuthReply.decode(V_STATUS_REPLY, K, V_RELEASE[32:])
    with pytest.raises(ValueError, match="request's tag"):
        AuthReply.decode(V_STATUS_REPLY, K)


def test_keyless_forms_have_zero_tags() -> None:
    assert AuthControlPacket(RID, N, 1, BODY).encode(None) == V_CONTROL[:44] + bytes(16)
    for frame, req in REQUEST_VECTORS:
        assert req.encode(None) == frame[:32] + bytes(16)
    assert STATUS_REPLY.encode(None, V_STATUS[32:]) == V_STATUS_REPLY[:32] + bytes(16)
    assert auth.ZERO_TAG == bytes(16)
    # without a key nothing is verified (a keyless remote cannot): zero or real tags decode
    assert AuthReply.decode(V_STATUS_REPLY[:32] + bytes(16), None) == STATUS_REPLY
    assert AuthReply.decode(V_STATUS_REPLY, None) == STATUS_REPLY
    assert AuthRequest.decode(STATUS_REQ.encode(None), None) == STATUS_REQ
    # with a key, a zero tag is just a wrong tag
    with pytest.raises(TagMismatch):
        AuthReply.decode(V_STATUS_REPLY[:32] + bytes(16), K, V_STATUS[32:])
    with pytest.raises(TagMismatch):
        AuthRequest.decode(V_STOP[:32] + bytes(16), K)


# ------------------------------------------------------------------ malformed and values

def test_lengths_and_magics() -> None:
    for n in (0, 16, 20, 47, 49, 59, 61):
        with pytest.raises(AuthError, match="bytes"):
            AuthControlPacket.decode(bytes(n), K)
    with pytest.raises(AuthError, match="48 bytes"):
        AuthRequest.decode(V_STOP[:47], K)
    with pytest.raises(AuthError, match="48 bytes"):
        AuthReply.decode(V_STATUS_REPLY + b"\x00", K, V_STATUS[32:])
    with pytest.raises(AuthError, match="ESQ2"):
        AuthRequest.decode(V_STATUS_REPLY, K)  # a reply is not a request
    with pytest.raises(AuthError, match="ESR2"):
        AuthReply.decode(V_STATUS, K, V_STATUS[32:])
    with pytest.raises(AuthError, match="ESU2"):
        AuthControlPacket.decode(V_CONTROL[:3] + b"3" + V_CONTROL[4:], None)


def test_reply_fields_are_checked() -> None:
    tag = V_STATUS[32:]
    good = dict(session=N, counter=5)
    for bad, match in [(AuthReply(True, 1, 3, 0, **good), "state"),
                       (AuthReply(True, 1, 0, 1, nak_code=4, **good), "ACK with nak"),
                       (AuthReply(False, 1, 0, 1, nak_code=5, **good), "nak code 5"),
                       (AuthReply(True, 1, 0, 1, session=0, counter=5), "session 0")]:
        with pytest.raises(AuthError, match=match):
            bad.encode(K, tag)
        frame = bad.encode(K, tag, validate=False)
        with pytest.raises(AuthError, match=match):
            AuthReply.decode(frame, K, tag)
        assert AuthReply.decode(frame, K, tag, strict=False) == bad
    signed = b"ESR2" + struct.pack("<IIBBBBQQ", 0x82, 1, 0, 1, 0, 0, N, 1)
    with pytest.raises(AuthError, match="neither ACK"):
        AuthReply.decode(signed + blake(K, tag + signed), K, tag, strict=False)


def test_nak_4_not_authenticated() -> None:
    assert NakCode.NOT_AUTHENTICATED == 4
    assert tcp.NAK_NAMES[4] == "not_authenticated"
    nak = AuthReply(False, 2, 0, 1, nak_code=NakCode.NOT_AUTHENTICATED, session=N, counter=2)
    frame = nak.encode(K, V_RELEASE[32:])
    assert frame[4:16] == h("81 00 00 00 02 00 00 00 00 01 00 04")
    assert AuthReply.decode(frame, K, V_RELEASE[32:]).nak_code == 4
    plain = tcp.Reply(False, 2, 0, 1, 0, NakCode.NOT_AUTHENTICATED)  # plain RELEASE, keyed unit
    assert tcp.Reply.decode(plain.encode()) == plain


def test_field_ranges_on_encode() -> None:
    for bad in (AuthRequest(1, 1, 2**32, 0, 0), AuthRequest(1, -1, 0, 0, 0),
                AuthRequest(1, 1, 0, 2**64, 0), AuthRequest(1, 1, 0, 0, -1)):
        with pytest.raises(ValueError, match="u32|u64"):
            bad.encode(K)
    with pytest.raises(ValueError, match="u64"):
        AuthControlPacket(1, 1, 2**64).encode(K)
    with pytest.raises(udp.InvalidPacket):
        AuthControlPacket(1, 1, 1, ControlPacket(gear=3)).encode(K)
    with pytest.raises(ValueError, match="32 bytes"):
        AuthRequest(1, 1, 1, 1, 1).encode(b"short")
    with pytest.raises(ValueError, match="16 bytes"):
        STATUS_REPLY.encode(K, b"\x00" * 15)


def test_control_body_is_validated_after_the_tag() -> None:
    bad_body = ControlPacket(float("nan"), 0.0, 4)
    frame = AuthControlPacket(RID, N, 9, bad_body).encode(K, validate=False)
    with pytest.raises(udp.InvalidPacket):
        AuthControlPacket.decode(frame, K)
    raw = AuthControlPacket.decode(frame, K, validate=False)
    assert raw.counter == 9 and raw.body.gas_brake != raw.body.gas_brake  # NaN kept
    with pytest.raises(TagMismatch):  # the tag is checked before the body
        AuthControlPacket.decode(frame[:-1] + bytes([frame[-1] ^ 1]), K)


# ---------------------------------------------------------------------- round trips

u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)
keys = st.binary(min_size=32, max_size=32)
axis = st.floats(-1.0, 1.0, width=32)
bodies = st.builds(ControlPacket, axis, axis, st.sampled_from([1, 2, 4, 8]),
                   st.integers(0, 3), st.integers(0, 1))


@given(keys, u32, u64, u64, bodies)
def test_control_roundtrip(key: bytes, rid: int, session: int, counter: int,
                           body: ControlPacket) -> None:
    pkt = AuthControlPacket(rid, session, counter, body)
    data = pkt.encode(key)
    assert len(data) == 60 and data[:4] == b"ESU2"
    assert data[4:24] == struct.pack("<IQQ", rid, session, counter)
    assert data[44:] == blake(key, data[:44])
    assert AuthControlPacket.decode(data, key) == pkt
    assert AuthControlPacket.decode(pkt.encode(None), None) == pkt


@given(keys, u32, u32, u32, u64, u64)
def test_request_roundtrip(key: bytes, msg_id: int, seq: int, rid: int, session: int,
                           counter: int) -> None:
    req = AuthRequest(msg_id, seq, rid, session, counter)
    data = req.encode(key)
    assert data[:32] == b"ESQ2" + struct.pack("<IIIQQ", msg_id, seq, rid, session, counter)
    assert data[32:] == blake(key, data[:32])
    assert AuthRequest.decode(data, key) == req


valid_fields = st.one_of(
    st.tuples(st.just(True), st.just(0), st.integers(1, 4), st.just(0), st.just(0)),
    st.tuples(st.just(True), st.just(1), st.just(0), st.integers(0, 1), st.just(0)),
    st.tuples(st.just(False), st.just(0), st.integers(1, 4), st.just(0), st.integers(1, 4)),
    st.tuples(st.just(False), st.just(1), st.just(0), st.integers(0, 1), st.integers(1, 4)),
)


@given(keys, valid_fields, u32, st.integers(1, 2**64 - 1), u64,
       st.binary(min_size=16, max_size=16))
def test_reply_roundtrip(key: bytes, fields: tuple[bool, int, int, int, int], seq: int,
                         session: int, counter: int, req_tag: bytes) -> None:
    ack, state, reason, flags, nak = fields
    rep = AuthReply(ack, seq, state, reason, flags=flags, nak_code=nak, session=session,
                    counter=counter)
    data = rep.encode(key, req_tag)
    assert data[32:] == blake(key, req_tag + data[:32])
    assert data[16:32] == struct.pack("<QQ", session, counter)
    assert AuthReply.decode(data, key, req_tag) == rep


# ------------------------------------------------------------- stop IDs and stream framing

def test_stop_id_may_not_be_the_request_magic() -> None:
    assert struct.unpack("<I", b"ESQ2")[0] == 0x32515345 == tcp.REQUEST_MAGIC_ID
    for bad in (0, 1, 2, 0x32515345):
        with pytest.raises(ValueError, match="0x32515345"):
            tcp.check_stop_id(bad)
    assert tcp.check_stop_id(0x32515344) == 0x32515344


def test_cli_refuses_the_magic_stop_id(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["stop", "--host", "127.0.0.1", "--stop-id", "0x32515345"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0x32515345" in err


MIXED = [V_STOP, tcp.Request(tcp.STATUS, 9).encode(), V_STATUS, V_RELEASE,
         tcp.Request(tcp.DEFAULT_STOP_ID, 1).encode()]


def test_request_assembler_by_magic_split_everywhere() -> None:
    stream = b"".join(MIXED)
    for cut in range(len(stream) + 1):
        asm = RequestAssembler()
        assert asm.feed(stream[:cut]) + asm.feed(stream[cut:]) == MIXED
        assert asm.pending == 0
    asm = RequestAssembler()
    assert asm.feed(b"ESQ") == [] and asm.pending == 3  # 3 bytes decide nothing yet
    assert asm.feed(b"2" + bytes(43)) == [] and asm.pending == 47
    asm.reset()
    assert asm.pending == 0
    assert RequestAssembler.frame_size(b"ESQ2") == 48
    assert RequestAssembler.frame_size(b"ESR2") == 16  # only requests are 48 on this side
    assert RequestAssembler.frame_size(b"ES") is None


@given(st.lists(st.sampled_from(MIXED), max_size=8), st.lists(st.integers(0, 400),
                                                             max_size=12))
def test_request_assembler_any_split(frames: list[bytes], cuts: list[int]) -> None:
    stream = b"".join(frames)
    points = sorted({min(c, len(stream)) for c in cuts} | {0, len(stream)})
    asm = RequestAssembler()
    got: list[bytes] = []
    for a, b in zip(points, points[1:], strict=False):
        got += asm.feed(stream[a:b])
    assert got == frames and asm.pending == 0


def test_client_reads_48_byte_replies() -> None:
    asm = tcp.FrameAssembler(48)
    assert asm.feed(V_STATUS_REPLY[:20]) == []
    assert asm.feed(V_STATUS_REPLY[20:] + V_STATUS_REPLY[:1]) == [V_STATUS_REPLY]
    assert asm.pending == 1


# ------------------------------------------------------------------------- key files

KEY_HEX = K.hex()


def key_file(tmp_path: Path, content: bytes, mode: int = 0o600) -> Path:
    p = tmp_path / "estop.key"
    p.write_bytes(content)
    p.chmod(mode)
    return p


@pytest.mark.parametrize("content", [
    KEY_HEX.encode(), KEY_HEX.encode() + b"\n", KEY_HEX.upper().encode(),
    KEY_HEX.upper().encode() + b"\n",
], ids=["plain", "newline", "upper", "upper-newline"])
def test_key_file_good(tmp_path: Path, content: bytes) -> None:
    assert load_key_file(key_file(tmp_path, content)) == K
    assert load_key_file(str(key_file(tmp_path, content, 0o400))) == K


@pytest.mark.parametrize(("content", "match"), [
    (KEY_HEX.encode() + b"\n\n", "more than one line"),
    (KEY_HEX[:63].encode(), "found 63"),
    (KEY_HEX[:63].encode() + b"\n", "found 63"),
    (KEY_HEX.encode() + b"0", "found 65"),
    (KEY_HEX[:62].encode() + b"zz", "0x7a 'z'"),
    (KEY_HEX.encode() + b"\r\n", "0x0d"),
    (b" " + KEY_HEX.encode(), "0x20"),
    (KEY_HEX[:32].encode() + b"\n" + KEY_HEX[32:].encode(), "more than one line"),
    (b"", "found 0"),
    (b"0" * 5000, "too long"),
], ids=["two-newlines", "63", "63-newline", "65", "non-hex", "crlf", "space", "split",
        "empty", "huge"])
def test_key_file_malformed(tmp_path: Path, content: bytes, match: str) -> None:
    path = key_file(tmp_path, content)
    with pytest.raises(KeyFileError, match=match) as info:
        load_key_file(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o602, 0o620, 0o660, 0o666, 0o644])
def test_key_file_group_or_others_refused(tmp_path: Path, mode: int) -> None:
    path = key_file(tmp_path, KEY_HEX.encode() + b"\n", mode)
    with pytest.raises(KeyFileError, match=f"mode {mode:04o}") as info:
        load_key_file(path)
    assert "\n" not in str(info.value) and "chmod 600" in str(info.value)


def test_key_file_missing_and_not_regular(tmp_path: Path) -> None:
    with pytest.raises(KeyFileError, match="No such file") as info:
        load_key_file(tmp_path / "absent.key")
    assert "\n" not in str(info.value)
    with pytest.raises(KeyFileError, match="not a regular file"):
        load_key_file(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo, 0o600)
    with pytest.raises(KeyFileError, match="not a regular file"):
        load_key_file(fifo)  # refused without hanging on the open


def test_parse_and_format_key() -> None:
    assert auth.parse_key(auth.format_key(K)) == K
    assert auth.format_key(K) == KEY_HEX.encode() + b"\n"
    with pytest.raises(auth.KeyTextError):
        auth.parse_key(b"00" * 31)


# ------------------------------------------------------------------------- estop keygen

def test_keygen_writes_a_fresh_0600_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    a, b = tmp_path / "a.key", tmp_path / "b.key"
    old = os.umask(0)  # the widest umask: the mode still comes out 0600
    try:
        assert cli.main(["keygen", str(a)]) == 0
    finally:
        os.umask(old)
    assert cli.main(["keygen", str(b)]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 2 and str(a) in out
    for p in (a, b):
        assert stat.S_IMODE(p.stat().st_mode) == 0o600
        text = p.read_bytes()
        assert len(text) == 65 and text.endswith(b"\n")
        assert len(load_key_file(p)) == 32
    assert a.read_bytes() != b.read_bytes()  # fresh randomness each time
    assert a.read_bytes()[:64].decode() not in out  # the key is never printed


def test_keygen_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                     ) -> None:
    path = tmp_path / "k"
    path.write_text("precious\n")
    assert cli.main(["keygen", str(path)]) == 4  # a file error (the exit-code table)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("estop: error: ")
    assert "already exists" in err
    assert path.read_text() == "precious\n"
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "target")  # a dangling link is refused, not followed
    assert cli.main(["keygen", str(link)]) == 4
    assert not (tmp_path / "target").exists()
    capsys.readouterr()


def test_keygen_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                    ) -> None:
    assert cli.main(["keygen", str(tmp_path / "no" / "such" / "dir" / "k")]) == 4
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot create" in err
    assert cli.main(["keygen"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_write_key_file_api(tmp_path: Path) -> None:
    path = tmp_path / "k"
    assert write_key_file(path, K) == K
    assert path.read_bytes() == KEY_HEX.encode() + b"\n"
    with pytest.raises(KeyFileError, match="already exists"):
        write_key_file(path)
