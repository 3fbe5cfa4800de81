"""CRCs used on the wire: CRC-8 SAE J1850 (CAN frames) and CRC-32 (TCP frames)."""

from __future__ import annotations

import zlib

__all__ = ["CRC8_INIT", "CRC8_POLY", "CRC8_XOROUT", "crc8_j1850", "crc32", "e2e_crc8"]

CRC8_POLY = 0x1D
CRC8_INIT = 0xFF
CRC8_XOROUT = 0xFF


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()


def crc8_j1850(data: bytes | bytearray | memoryview, init: int = CRC8_INIT) -> int:
    """CRC-8 SAE J1850: poly 0x1D, MSB first, register starts at ``init``, final xor 0xFF.

    ``crc8_j1850(b"123456789") == 0x4B`` (the catalogue check value).
    """
    if not 0 <= init <= 0xFF:
        raise ValueError(f"crc8 init must be 0..255, got {init}")
    crc = init
    for byte in bytes(data):
        crc = _TABLE[crc ^ byte]
    return crc ^ CRC8_XOROUT


def e2e_crc8(data_id: int, payload: bytes | bytearray | memoryview) -> int:
    """CRC of an AUTOSAR E2E profile 1 style frame: data ID low byte, high byte, then payload.

    For ESTOP_BRAKE / ESTOP_STATUS the payload is bytes 0..6 and the result goes to byte 7.
    """
    if not 0 <= data_id <= 0xFFFF:
        raise ValueError(f"data ID must be 0..0xFFFF, got {data_id:#x}")
    return crc8_j1850(bytes((data_id & 0xFF, data_id >> 8)) + bytes(payload))


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32 exactly as :func:`zlib.crc32` (IEEE 802.3, reflected, init/xorout 0xFFFFFFFF)."""
    return zlib.crc32(bytes(data)) & 0xFFFFFFFF
