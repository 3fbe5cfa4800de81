"""The one clause of make prove's contracts that is admitted, not proved (prove/assumed.txt:
mac_value): estop_b2s_mac's 16-byte MAC of a message of 1..64 bytes, a multiple of 4, is the
first 16 bytes of one BLAKE2s compression F (RFC 7693 3.2) of the key state and the message
zero-padded to a block, with byte counter 64 + len and the final-block flag, exactly as
prove/logic.h's MAC_BYTE reads it. F is written out here from the RFC, independent of the C
code; hashlib.blake2s checks this F in turn."""

from __future__ import annotations

import hashlib
import struct

import pytest

from estop.core import ffi, lib

IV = (0x6A09E667, 0xBB67AE85, 0x3C6EF372, 0xA54FF53A,
      0x510E527F, 0x9B05688C, 0x1F83D9AB, 0x5BE0CD19)
SIGMA = ((0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
         (14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3),
         (11, 8, 12, 0, 5, 2, 15, 13, 10, 14, 3, 6, 7, 1, 9, 4),
         (7, 9, 3, 1, 13, 12, 11, 14, 2, 6, 5, 10, 4, 0, 15, 8),
         (9, 0, 5, 7, 2, 4, 10, 15, 14, 1, 11, 12, 6, 8, 3, 13),
         (2, 12, 6, 10, 0, 11, 8, 3, 4, 13, 7, 5, 15, 14, 1, 9),
         (12, 5, 1, 15, 14, 13, 4, 10, 0, 7, 6, 3, 9, 2, 8, 11),
         (13, 11, 7, 14, 12, 1, 3, 9, 5, 0, 15, 4, 8, 6, 2, 10),
         (6, 15, 14, 9, 11, 3, 0, 8, 12, 2, 13, 7, 1, 4, 10, 5),
         (10, 2, 8, 4, 7, 6, 1, 5, 15, 11, 9, 14, 3, 12, 13, 0))
M32 = 0xFFFFFFFF


def rotr(x: int, n: int) -> int:
    return ((x >> n) | (x << (32 - n))) & M32


def compress(h: list[int], m: list[int], t: int, final: bool) -> list[int]:
    """RFC 7693 3.2: F(h, m, t, f), the new chain value h0..h7."""
    v = list(h) + list(IV)
    v[12] ^= t & M32
    v[13] ^= t >> 32
    if final:
        v[14] ^= M32

    def g(a: int, b: int, c: int, d: int, x: int, y: int) -> None:
        v[a] = (v[a] + v[b] + x) & M32
        v[d] = rotr(v[d] ^ v[a], 16)
        v[c] = (v[c] + v[d]) & M32
        v[b] = rotr(v[b] ^ v[c], 12)
        v[a] = (v[a] + v[b] + y) & M32
        v[d] = rotr(v[d] ^ v[a], 8)
        v[c] = (v[c] + v[d]) & M32
        v[b] = rotr(v[b] ^ v[c], 7)

    for r in range(10):
        s = SIGMA[r]
        for i, (a, b, c, d) in enumerate(((0, 4, 8, 12), (1, 5, 9, 13), (2, 6, 10, 14),
                                          (3, 7, 11, 15), (0, 5, 10, 15), (1, 6, 11, 12),
                                          (2, 7, 8, 13), (3, 4, 9, 14))):
            g(a, b, c, d, m[s[2 * i]], m[s[2 * i + 1]])
    return [h[i] ^ v[i] ^ v[i + 8] for i in range(8)]


def mac_byte_model(h: list[int], msg: bytes) -> bytes:
    """prove/logic.h's MAC_BYTE(k, msg, len, i) for i = 0..15."""
    words = list(struct.unpack("<16I", msg.ljust(64, b"\0")))
    out = compress(h, words, 64 + len(msg), True)
    return b"".join(struct.pack("<I", w) for w in out)[:16]


def key_state(key: bytes) -> object:
    k = ffi.new("estop_b2s_key_t *")
    assert lib.estop_b2s_key_init(k, ffi.from_buffer("uint8_t[]", key), len(key), 16) == 0
    return k


def c_mac(k: object, msg: bytes) -> bytes:
    out = ffi.new("uint8_t[]", 16)
    assert lib.estop_b2s_mac(k, ffi.from_buffer("uint8_t[]", msg), len(msg), out) == 0
    return bytes(ffi.buffer(out, 16))


@pytest.mark.parametrize("length", range(4, 65, 4))
def test_the_mac_is_one_compression_of_the_key_state_and_the_block(length: int) -> None:
    for seed in range(8):
        key = hashlib.sha256(b"key%d" % seed).digest()[: 1 + seed * 4]
        msg = hashlib.sha512(b"msg%d-%d" % (seed, length)).digest()[:length]
        k = key_state(key)
        h = list(k.h)
        assert c_mac(k, msg) == mac_byte_model(h, msg)
        # The model's F is BLAKE2s's: with the key block first it gives hashlib's MAC.
        key_block = list(struct.unpack("<16I", key.ljust(64, b"\0")))
        param = list(IV)
        param[0] ^= 0x01010000 ^ (len(key) << 8) ^ 16
        assert compress(param, key_block, 64, False) == h
        assert mac_byte_model(h, msg) == hashlib.blake2s(msg, key=key, digest_size=16).digest()


def test_the_model_tells_another_message_from_this_one() -> None:
    k = key_state(bytes(range(32)))
    h = list(k.h)
    msg = bytes(range(44))
    assert mac_byte_model(h, msg) != mac_byte_model(h, msg[:-1] + b"\x01")
    assert mac_byte_model(h, msg[:32]) != mac_byte_model(h, msg[:32] + bytes(4))
