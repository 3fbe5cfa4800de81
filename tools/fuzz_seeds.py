"""Writes the seed corpora of the fuzz targets (fuzz/fuzz_core.c, fuzz/fuzz_parsers.c).

The core's seeds are programs in the harness's input language (see fuzz/fuzz_core.c) built
around the byte vectors of docs/PROTOCOL.md: every hex example is read from the document
itself, then sent as a datagram and as TCP bytes to a unit with and without the key of 5.4,
and two whole scenarios (drive, RELEASE, STOP) arm and stop a unit each way. The parsers'
seeds are a valid key file and typical command lines.
Usage: python tools/fuzz_seeds.py OUTDIR   (writes OUTDIR/core/ and OUTDIR/parsers/)
"""

from __future__ import annotations

import hashlib
import re
import struct
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEX_LINE = re.compile(r"^`((?:[0-9A-F]{2} )+[0-9A-F]{2})`$")

# Opcodes of fuzz_core.c (the op byte is taken modulo 16).
OP_TICK_NEXT, OP_UDP_RAW, OP_OPEN, OP_TCP_RAW = 1, 2, 6, 8
OP_REQUEST, OP_FAULT, OP_DRIVE = 10, 11, 14
KEY_FLAG, SHORT_TIMES_FLAG, TWO_STAGE_FLAG = 1, 2, 4
SOON = 100  # time selector: most of the way to the core's next call time


def spec_path() -> Path:
    """The project's own protocol document: it carries every example of the shared contract
    (tests/docs/test_docs.py checks that), and unlike ../shared it is always in the checkout."""
    return ROOT / "docs" / "PROTOCOL.md"


def spec_vectors(text: str) -> list[bytes]:
    """Every hex example of the spec; an example split over consecutive lines is one vector."""
    vectors: list[bytes] = []
    current = b""
    for line in text.splitlines():
        match = HEX_LINE.match(line.strip())
        if match:
            current += bytes.fromhex(match.group(1))
            continue
        if current:
            vectors.append(current)
            current = b""
        # inline examples: "Example ...: `70 E5 ...`"
        for inline in re.findall(r"`((?:[0-9A-F]{2} ){7,}[0-9A-F]{2})`", line):
            vectors.append(bytes.fromhex(inline))
    if current:
        vectors.append(current)
    return vectors


def header(flags: int, start: int = 0) -> bytes:
    return bytes([flags]) + struct.pack("<I", start)


def udp_raw(data: bytes) -> bytes:
    return bytes([OP_UDP_RAW, SOON, len(data)]) + data


def tcp_raw(data: bytes, slot: int = 0) -> bytes:
    return bytes([OP_TCP_RAW, slot, SOON, 0, len(data)]) + data


def open_slot(slot: int = 0) -> bytes:
    return bytes([OP_OPEN, slot, SOON])


def drive(n: int = 5, neutral: bool = True, gap_sel: int = 90) -> bytes:
    return bytes([OP_DRIVE, n, 0 if neutral else 1, gap_sel])


def release_request(remote: int = 3) -> bytes:
    """An authenticated RELEASE made by the harness (pick_msg 0, fields right)."""
    return bytes([OP_REQUEST, 0, 0, 0, remote, 9, SOON])


def core_seeds(vectors: list[bytes]) -> dict[str, bytes]:
    seeds: dict[str, bytes] = {}
    for flags, name in ((0, "nokey"), (KEY_FLAG, "key")):
        for i, v in enumerate(vectors):
            if len(v) > 255:
                continue
            seeds[f"{name}-vector{i:02d}-udp"] = header(flags) + udp_raw(v)
            seeds[f"{name}-vector{i:02d}-tcp"] = header(flags) + open_slot() + tcp_raw(v)
    by_len = {len(v): v for v in vectors}
    plain_stop = next(v for v in vectors if len(v) == 16 and v[:4] == bytes.fromhex("70E570E5"))
    plain_release = next(v for v in vectors if len(v) == 16 and v[:4] == b"\x02\0\0\0")
    requests = [v for v in vectors if len(v) == 48 and v[:4] == b"ESQ2"]
    # No key: drive, plain RELEASE (arms), plain STOP, ticks, the 16-byte packet form.
    seeds["scenario-nokey"] = (header(0, 0xFFFFF000) + open_slot() + drive()
                               + tcp_raw(plain_release) + bytes([OP_TICK_NEXT, 8])
                               + tcp_raw(plain_stop) + drive(5) + tcp_raw(plain_release)
                               + bytes([OP_TICK_NEXT, 31]) + bytes([OP_FAULT, SOON]))
    # Key: the spec's control packet, its STATUS, drive, the spec's RELEASE (counter 2 of
    # remote 7: accepted), the stop datagram, the spec's STOP over TCP.
    control = by_len.get(60, b"")
    seeds["scenario-key"] = (header(KEY_FLAG) + udp_raw(control) + open_slot()
                             + b"".join(tcp_raw(r) for r in requests[:1]) + drive()
                             + b"".join(tcp_raw(r) for r in requests[1:2])
                             + bytes([OP_TICK_NEXT, 4]) + udp_raw(requests[-1])
                             + drive() + release_request() + tcp_raw(requests[-1]))
    # Short times: timeout, warn time and periods all reached within the input.
    short = header(KEY_FLAG | SHORT_TIMES_FLAG) + struct.pack("<HHHH", 200, 500, 10, 700) + b"\x02"
    seeds["scenario-key-short"] = (short + open_slot() + drive(3) + release_request()
                                   + bytes([OP_TICK_NEXT, 31, OP_TICK_NEXT, 31]))
    # Two stages (version 3): the slow time a third of the timeout, slow level 30.
    two_stage = (header(KEY_FLAG | SHORT_TIMES_FLAG | TWO_STAGE_FLAG)
                 + struct.pack("<HHHH", 200, 500, 10, 700) + b"\x02"
                 + struct.pack("<H", 600) + bytes([29]))
    seeds["scenario-key-two-stage"] = (two_stage + open_slot() + drive(3) + release_request()
                                       + bytes([OP_TICK_NEXT, 31]) + drive(3)
                                       + bytes([OP_TICK_NEXT, 31, OP_TICK_NEXT, 31]))
    return seeds


def parser_seeds() -> dict[str, bytes]:
    key = hashlib.sha256(b"estop fuzz seed").hexdigest().encode()
    lines = [
        [b"--no-auth"],
        [b"--key-file", b"/etc/estop/key", b"--can", b"vcan0", b"--can-log", b"-"],
        [b"--no-auth", b"--udp-port", b"0", b"--tcp-port", b"5701", b"--bind", b"127.0.0.1"],
        [b"--no-auth", b"--timeout-ms", b"200", b"--warn-ms", b"100", b"--stop-id",
         b"0xE570E570", b"--rt-prio", b"10", b"--mlock", b"--log-json"],
        [b"--no-auth", b"--timeout-ms=60000", b"--stop-id=3"],
        [b"--no-auth", b"extra"],
        [b"--help"],
    ]
    # keyfile: selector 0, the error buffer's size, the contents
    seeds = {"keyfile-ok": b"\x00\x80" + key + b"\n", "keyfile-short": b"\x00\x40" + key[:10]}
    # ACL: selector 2, the daemon's uid, the error buffer's size, the attribute: systemd's
    # credential (user::r--, user:61234:r--, group::---, mask::r--, other::---), and one
    # that lets user 1000 read
    uid = struct.pack("<I", 61234)
    entries = [(1, 4, 0xFFFFFFFF), (2, 4, 61234), (4, 0, 0xFFFFFFFF), (0x10, 4, 0xFFFFFFFF),
               (0x20, 0, 0xFFFFFFFF)]
    acl = struct.pack("<I", 2) + b"".join(struct.pack("<HHI", *e) for e in entries)
    seeds["acl-credential"] = b"\x02" + uid + b"\x80" + acl
    seeds["acl-other-user"] = b"\x02" + uid + b"\x80" + acl + struct.pack("<HHI", 2, 4, 1000)
    for i, argv in enumerate(lines):
        seeds[f"opts-{i}"] = b"\x01" + b"\x00".join(argv)
    return seeds


def main(outdir: str) -> int:
    vectors = spec_vectors(spec_path().read_text())
    if len(vectors) < 10:
        raise SystemExit(f"fuzz_seeds: error: only {len(vectors)} vectors found in the spec")
    out = Path(outdir)
    for target, seeds in (("core", core_seeds(vectors)), ("parsers", parser_seeds())):
        folder = out / target
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in seeds.items():
            (folder / name).write_bytes(data)
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: fuzz_seeds.py OUTDIR")
    sys.exit(main(sys.argv[1]))
