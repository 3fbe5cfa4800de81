"""The admitted clause crc_value (prove/assumed.txt): the core's estop_crc32 over a plain
frame's first 12 bytes is CRC-32 (zlib's, PROTOCOL.md section 2) of those bytes. Through the
core: a plain frame is answered exactly when its bytes 12..15 are that CRC; any other value
closes the connection unanswered."""

from __future__ import annotations

import random
import struct

from core_util import Unit
from estop.protocol.crc import crc32

REQUEST_MAGIC = b"ESQ2"


def _answer(frame: bytes) -> tuple[bool, bool]:
    """(answered, closed) for one frame sent to a fresh unit."""
    steps = Unit().send(frame)
    return any(s.reply is not None for s in steps), any(s.close for s in steps)


def test_a_plain_frame_is_answered_exactly_when_its_crc_is_crc32() -> None:
    rng = random.Random(24)
    for _ in range(200):
        body = bytes(rng.randrange(256) for _ in range(12))
        if body[:4] == REQUEST_MAGIC:
            continue
        good = crc32(body)
        assert _answer(body + struct.pack("<I", good)) == (True, False)
        wrong = good ^ rng.randrange(1, 1 << 32)
        assert _answer(body + struct.pack("<I", wrong)) == (False, True)
