/*
 * The harness's own codecs, written apart from the core's: bitwise CRC-32 and CRC-8 E2E,
 * little-endian fields.
 */
#include "harness.h"

uint32_t fz_crc32_bitwise(const uint8_t *d, size_t n)
{
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        crc ^= d[i];
        for (int b = 0; b < 8; b++) {
            crc = (crc & 1u) ? (crc >> 1) ^ 0xEDB88320u : crc >> 1;
        }
    }
    return crc ^ 0xFFFFFFFFu;
}

static uint8_t crc8_step(uint8_t crc, uint8_t byte)
{
    crc ^= byte;
    for (int b = 0; b < 8; b++) {
        crc = (uint8_t)((crc & 0x80u) ? (uint8_t)(crc << 1) ^ 0x1Du : (uint8_t)(crc << 1));
    }
    return crc;
}

uint8_t fz_crc8_e2e(uint16_t data_id, const uint8_t *d)
{
    uint8_t crc = 0xFFu;
    crc = crc8_step(crc, (uint8_t)(data_id & 0xFFu));
    crc = crc8_step(crc, (uint8_t)(data_id >> 8));
    for (int i = 0; i < 7; i++) {
        crc = crc8_step(crc, d[i]);
    }
    return (uint8_t)(crc ^ 0xFFu);
}

uint32_t fz_get32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

uint64_t fz_get64(const uint8_t *p)
{
    return (uint64_t)fz_get32(p) | ((uint64_t)fz_get32(p + 4) << 32);
}

void fz_put32(uint8_t *p, uint32_t v)
{
    for (int i = 0; i < 4; i++) {
        p[i] = (uint8_t)(v >> (8 * i));
    }
}

void fz_put64(uint8_t *p, uint64_t v)
{
    fz_put32(p, (uint32_t)v);
    fz_put32(p + 4, (uint32_t)(v >> 32));
}

