/*
 * CRCs of the wire contract: CRC-32 as zlib.crc32 (TCP frames) and CRC-8 SAE J1850 in the
 * AUTOSAR E2E profile 1 arrangement (CAN frames). Nibble tables: 80 bytes of constant data
 * instead of 1 KiB, about half the work of a bitwise loop.
 */
#ifndef ESTOP_CRC_H
#define ESTOP_CRC_H

#include <stddef.h>
#include <stdint.h>

/* CRC-32 (reflected poly 0xEDB88320, init and final xor 0xFFFFFFFF), equal to zlib.crc32. */
uint32_t estop_crc32(const uint8_t *data, size_t len);

/* CRC-8 SAE J1850 (poly 0x1D, init 0xFF, final xor 0xFF) over the data ID's low byte, its high
 * byte, then payload[0 .. len-1]. */
uint8_t estop_crc8_e2e(uint16_t data_id, const uint8_t *payload, size_t len);

#endif /* ESTOP_CRC_H */
