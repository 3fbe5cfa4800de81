"""BLAKE2s of the firmware core (firmware/core/estop_blake2s.c) through the cffi module:
RFC 7693 vectors, hashlib.blake2s as the independent reference, the tags of PROTOCOL.md 5.4,
the constant-time comparison and the argument checks."""

from __future__ import annotations

import hashlib
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estop.core import ffi, lib

KEY_MAX = lib.ESTOP_B2S_KEY_MAX
OUT_MAX = lib.ESTOP_B2S_OUT_MAX
SPEC_KEY = bytes(range(32))  # PROTOCOL.md 5.4: K = 00 01 02 ... 1F
TAG_LEN = 16


def ptr(data: bytes | None) -> Any:
    return ffi.NULL if data is None else ffi.from_buffer("uint8_t[]", data)


def c_blake2s(msg: bytes, key: bytes | None = None, outlen: int = 32) -> bytes:
    out = ffi.new("uint8_t[]", OUT_MAX)
    keylen = 0 if key is None else len(key)
    assert lib.estop_blake2s(out, outlen, ptr(key), keylen, ptr(msg), len(msg)) == 0
    return bytes(ffi.buffer(out, outlen))


def c_key(key: bytes, outlen: int = TAG_LEN) -> Any:
    k = ffi.new("estop_b2s_key_t *")
    assert lib.estop_b2s_key_init(k, ptr(key), len(key), outlen) == 0
    return k


def c_mac(k: Any, msg: bytes) -> bytes:
    out = ffi.new("uint8_t[]", OUT_MAX)
    assert lib.estop_b2s_mac(k, ptr(msg), len(msg), out) == 0
    return bytes(ffi.buffer(out, k.outlen))


def ref(msg: bytes, key: bytes = b"", outlen: int = 32) -> bytes:
    return hashlib.blake2s(msg, key=key, digest_size=outlen).digest()


def rfc_seq(length: int, seed: int) -> bytes:
    """RFC 7693 Appendix E: the self-test's deterministic input (a Fibonacci generator)."""
    a = (0xDEAD4BAD * seed) & 0xFFFFFFFF
    b = 1
    out = bytearray()
    for _ in range(length):
        t = (a + b) & 0xFFFFFFFF
        a, b = b, t
        out.append(t >> 24)
    return bytes(out)


# -- RFC 7693 ---------------------------------------------------------------------------------
def test_rfc7693_appendix_b_abc() -> None:
    # Appendix B: BLAKE2s-256("abc"), the digest printed in the RFC.
    expected = bytes.fromhex("508C5E8C327C14E2E1A72BA34EEB452F37458B209ED63A294D999B4C86675982")
    assert c_blake2s(b"abc") == expected


SELFTEST_GRAND_HASH = bytes.fromhex(
    "6A411F08CE25ADCDFB02ABA641451CEC53C598B24F4FC787FBDC88797F4C1DFE")


def selftest_digests(hash_fn: Any) -> bytes:
    """The 48 digests that RFC 7693 Appendix E feeds into its grand hash, in order."""
    hashes = bytearray()
    for outlen in (16, 20, 28, 32):
        for inlen in (0, 3, 64, 65, 255, 1024):
            data = rfc_seq(inlen, inlen)
            hashes += hash_fn(data, None, outlen)
            hashes += hash_fn(data, rfc_seq(outlen, outlen), outlen)
    return bytes(hashes)


def test_rfc7693_appendix_e_selftest() -> None:
    digests = selftest_digests(lambda m, k, n: c_blake2s(m, k, n))
    assert c_blake2s(digests) == SELFTEST_GRAND_HASH  # 1152 bytes: 18 blocks in one call


def test_rfc7693_selftest_generator_matches_hashlib() -> None:
    # The same procedure with hashlib reaches the RFC's value: the generator above is right.
    digests = selftest_digests(lambda m, k, n: ref(m, k or b"", n))
    assert ref(digests) == SELFTEST_GRAND_HASH


# -- against hashlib --------------------------------------------------------------------------
@pytest.mark.parametrize("length", range(201))
def test_every_length_up_to_200(length: int) -> None:
    msg = rfc_seq(length, length + 1)
    key = rfc_seq(length % KEY_MAX + 1, 7 * length + 3)
    outlen = (length * 7) % OUT_MAX + 1
    assert c_blake2s(msg) == ref(msg)
    assert c_blake2s(msg, outlen=outlen) == ref(msg, outlen=outlen)
    assert c_blake2s(msg, key, outlen) == ref(msg, key, outlen)
    assert c_blake2s(msg, SPEC_KEY, TAG_LEN) == ref(msg, SPEC_KEY, TAG_LEN)
    if length > 0:
        assert c_mac(c_key(key, outlen), msg) == ref(msg, key, outlen)
        assert c_mac(c_key(SPEC_KEY), msg) == ref(msg, SPEC_KEY, TAG_LEN)


@settings(max_examples=400, deadline=None)
@given(key=st.binary(min_size=1, max_size=KEY_MAX), msg=st.binary(max_size=200),
       outlen=st.integers(1, OUT_MAX))
def test_keyed_matches_hashlib(key: bytes, msg: bytes, outlen: int) -> None:
    expected = ref(msg, key, outlen)
    assert c_blake2s(msg, key, outlen) == expected
    if msg:
        assert c_mac(c_key(key, outlen), msg) == expected


@settings(max_examples=200, deadline=None)
@given(msg=st.binary(max_size=200), outlen=st.integers(1, OUT_MAX))
def test_unkeyed_matches_hashlib(msg: bytes, outlen: int) -> None:
    assert c_blake2s(msg, None, outlen) == ref(msg, outlen=outlen)


@settings(max_examples=50, deadline=None)
@given(key=st.binary(min_size=1, max_size=KEY_MAX), msg=st.binary(min_size=1, max_size=2000))
def test_long_messages_match_hashlib(key: bytes, msg: bytes) -> None:
    assert c_blake2s(msg, key) == ref(msg, key)
    assert c_mac(c_key(key, 32), msg) == ref(msg, key)


def test_empty_key_buffer_is_unkeyed() -> None:
    # keylen 0 with a pointer (not NULL) is the unkeyed hash too.
    assert c_blake2s(b"abc", b"") == ref(b"abc")
    assert c_blake2s(b"", b"") == ref(b"")


def test_one_key_state_serves_many_messages() -> None:
    k = c_key(SPEC_KEY)
    before = bytes(ffi.buffer(k))
    messages = [rfc_seq(n, n) for n in (44, 32, 48, 1, 64, 65, 44)]
    for msg in messages:
        assert c_mac(k, msg) == ref(msg, SPEC_KEY, TAG_LEN)
    assert bytes(ffi.buffer(k)) == before
    assert k.outlen == TAG_LEN


def test_key_state_is_the_state_after_the_key_block() -> None:
    # Same key, other digest length: another state (the length is in the parameter block).
    k16, k32 = c_key(SPEC_KEY, 16), c_key(SPEC_KEY, 32)
    assert list(k16.h) != list(k32.h)
    assert c_mac(k32, b"x") == ref(b"x", SPEC_KEY, 32)


# -- PROTOCOL.md 5.4 --------------------------------------------------------------------------
UDP_AUTH = bytes.fromhex(
    "45 53 55 32 07 00 00 00 EF CD AB 89 67 45 23 01 01 00 00 00 00 00 00 00"
    "9A 99 99 3E 00 00 80 BE 08 00 00 00 01 00 00 00 00 00 00 00"
    "0C EF FB 40 CD 71 1A F5 A3 87 85 67 B9 28 7C 72")
STATUS_REQ = bytes.fromhex(
    "45 53 51 32 01 00 00 00 01 00 00 00 07 00 00 00 00 00 00 00 00 00 00 00"
    "88 77 66 55 44 33 22 11 E0 5B 65 D7 00 A8 04 C4 65 2A 16 32 A0 EA DD 1E")
STATUS_REPLY = bytes.fromhex(
    "45 53 52 32 80 00 00 00 01 00 00 00 00 01 00 00 EF CD AB 89 67 45 23 01"
    "88 77 66 55 44 33 22 11 E0 3C 40 08 C7 26 9C 38 B7 4F 4C 23 9E 56 E7 0D")
RELEASE_REQ = bytes.fromhex(
    "45 53 51 32 02 00 00 00 02 00 00 00 07 00 00 00 EF CD AB 89 67 45 23 01"
    "02 00 00 00 00 00 00 00 15 42 BA 83 A0 CE 93 39 AA 34 55 A8 66 EF 4D E5")
STOP_REQ = bytes.fromhex(
    "45 53 51 32 70 E5 70 E5 03 00 00 00 07 00 00 00 EF CD AB 89 67 45 23 01"
    "03 00 00 00 00 00 00 00 2D 87 7B 42 F3 EA AC D8 BB 0A 03 26 F1 8E D5 2A")

# (name, MAC input, tag printed in the spec)
SPEC_TAGS = [
    ("udp control packet", UDP_AUTH[:44], UDP_AUTH[44:]),
    ("status request", STATUS_REQ[:32], STATUS_REQ[32:]),
    ("status reply", STATUS_REQ[32:] + STATUS_REPLY[:32], STATUS_REPLY[32:]),
    ("release request", RELEASE_REQ[:32], RELEASE_REQ[32:]),
    ("stop request", STOP_REQ[:32], STOP_REQ[32:]),
]


@pytest.mark.parametrize(("name", "msg", "tag"), SPEC_TAGS, ids=[t[0] for t in SPEC_TAGS])
def test_spec_tags(name: str, msg: bytes, tag: bytes) -> None:
    assert len(msg) in (44, 32, 48) and len(tag) == TAG_LEN
    assert c_mac(c_key(SPEC_KEY), msg) == tag
    assert c_blake2s(msg, SPEC_KEY, TAG_LEN) == tag
    assert lib.estop_ct_equal(ptr(c_mac(c_key(SPEC_KEY), msg)), ptr(tag), TAG_LEN) == 1


def test_spec_tags_need_the_key() -> None:
    other = bytes(range(1, 33))
    for _, msg, tag in SPEC_TAGS:
        assert c_mac(c_key(other), msg) != tag


# -- constant-time comparison -----------------------------------------------------------------
def ct_equal(a: bytes | None, b: bytes | None, n: int) -> int:
    return int(lib.estop_ct_equal(ptr(a), ptr(b), n))


def test_ct_equal_equal() -> None:
    tag = STATUS_REQ[32:]
    assert ct_equal(tag, bytes(tag), TAG_LEN) == 1
    assert ct_equal(bytes(256), bytes(256), 256) == 1


@pytest.mark.parametrize("where", [0, 7, TAG_LEN - 1], ids=["first", "middle", "last"])
def test_ct_equal_one_byte_differs(where: int) -> None:
    tag = STATUS_REQ[32:]
    for bit in range(8):
        other = bytearray(tag)
        other[where] ^= 1 << bit
        assert ct_equal(tag, bytes(other), TAG_LEN) == 0
    other = bytearray(tag)
    other[where] ^= 0xFF
    assert ct_equal(tag, bytes(other), TAG_LEN) == 0
    # Only the first n bytes count.
    assert ct_equal(tag, bytes(other), where) == 1


def test_ct_equal_every_position_and_difference() -> None:
    a = bytes(range(TAG_LEN))
    for where in range(TAG_LEN):
        for diff in range(1, 256):
            other = bytearray(a)
            other[where] ^= diff
            assert ct_equal(a, bytes(other), TAG_LEN) == 0


def test_ct_equal_n_zero() -> None:
    assert ct_equal(b"\x01", b"\x02", 0) == 1
    assert ct_equal(None, None, 0) == 1
    assert ct_equal(b"\x01", None, 0) == 1


def test_ct_equal_null_with_length_differs() -> None:
    assert ct_equal(None, bytes(4), 4) == 0
    assert ct_equal(bytes(4), None, 4) == 0
    assert ct_equal(None, None, 4) == 0


# -- argument checks --------------------------------------------------------------------------
def fresh_out() -> Any:
    return ffi.new("uint8_t[]", [0xAA] * OUT_MAX)


def untouched(out: Any) -> bool:
    return bytes(out) == b"\xAA" * OUT_MAX


@pytest.mark.parametrize(("keylen", "outlen"), [(0, 16), (33, 16), (32, 0), (32, 33), (1, 0)])
def test_key_init_rejects_lengths(keylen: int, outlen: int) -> None:
    k = ffi.new("estop_b2s_key_t *")
    assert lib.estop_b2s_key_init(k, ptr(bytes(40)), keylen, outlen) == -1
    assert bytes(ffi.buffer(k)) == bytes(ffi.sizeof("estop_b2s_key_t"))


def test_key_init_rejects_null() -> None:
    k = ffi.new("estop_b2s_key_t *")
    assert lib.estop_b2s_key_init(ffi.NULL, ptr(SPEC_KEY), 32, 16) == -1
    assert lib.estop_b2s_key_init(k, ffi.NULL, 32, 16) == -1
    assert k.outlen == 0


def test_key_init_accepts_the_limits() -> None:
    for keylen, outlen in ((1, 1), (32, 32), (1, 32), (32, 1)):
        key = SPEC_KEY[:keylen]
        assert c_mac(c_key(key, outlen), b"m") == ref(b"m", key, outlen)


def test_mac_rejects_bad_arguments() -> None:
    k = c_key(SPEC_KEY)
    msg = ptr(b"message")
    out = fresh_out()
    assert lib.estop_b2s_mac(ffi.NULL, msg, 7, out) == -1
    assert lib.estop_b2s_mac(k, ffi.NULL, 7, out) == -1
    assert lib.estop_b2s_mac(k, msg, 7, ffi.NULL) == -1
    # The empty message: the key block would have been the final block (see the header).
    assert lib.estop_b2s_mac(k, msg, 0, out) == -1
    assert untouched(out)
    assert lib.estop_b2s_mac(k, msg, 7, out) == 0
    assert bytes(out)[:TAG_LEN] == ref(b"message", SPEC_KEY, TAG_LEN)
    assert bytes(out)[TAG_LEN:] == b"\xAA" * (OUT_MAX - TAG_LEN)  # exactly outlen bytes


@pytest.mark.parametrize("outlen", [0, 33, 255])
def test_mac_rejects_a_key_state_with_a_bad_length(outlen: int) -> None:
    # An uninitialised (zeroed) or damaged state is refused rather than used.
    k = c_key(SPEC_KEY)
    k.outlen = outlen
    out = fresh_out()
    assert lib.estop_b2s_mac(k, ptr(b"m"), 1, out) == -1
    assert untouched(out)


@pytest.mark.parametrize(("outlen", "key", "keylen", "msg", "length"), [
    (0, None, 0, b"abc", 3),
    (33, None, 0, b"abc", 3),
    (16, bytes(40), 33, b"abc", 3),
    (16, None, 16, b"abc", 3),
    (16, SPEC_KEY, 32, None, 3),
])
def test_blake2s_rejects_bad_arguments(outlen: int, key: bytes | None, keylen: int,
                                       msg: bytes | None, length: int) -> None:
    out = fresh_out()
    assert lib.estop_blake2s(out, outlen, ptr(key), keylen, ptr(msg), length) == -1
    assert untouched(out)


def test_blake2s_rejects_null_output() -> None:
    assert lib.estop_blake2s(ffi.NULL, 16, ptr(SPEC_KEY), 32, ptr(b"abc"), 3) == -1


def test_blake2s_null_message_of_length_zero() -> None:
    out = fresh_out()
    assert lib.estop_blake2s(out, 32, ffi.NULL, 0, ffi.NULL, 0) == 0
    assert bytes(out) == ref(b"")
    assert lib.estop_blake2s(out, 16, ptr(SPEC_KEY), 32, ffi.NULL, 0) == 0
    assert bytes(out)[:16] == ref(b"", SPEC_KEY, 16)
