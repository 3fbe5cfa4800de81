#include "estop_crc.h"

uint32_t estop_crc32(const uint8_t *data, size_t len)
{
    /* CRC-32 of each nibble value (reflected form). */
    static const uint32_t crc32_nibble[16] = {
        0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u,
        0x4DB26158u, 0x5005713Cu, 0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu,
        0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu};
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    /*@ loop assigns i, crc;
        loop variant len - i; */
    for (i = 0u; i < len; i++) {
        crc ^= data[i];
        crc = (crc >> 4) ^ crc32_nibble[crc & 0x0Fu];
        crc = (crc >> 4) ^ crc32_nibble[crc & 0x0Fu];
    }
    return crc ^ 0xFFFFFFFFu;
}

/*@ assigns \nothing; */
static uint8_t crc8_byte(uint8_t crc, uint8_t byte)
{
    /* CRC-8 (poly 0x1D) of each high-nibble value. */
    static const uint8_t crc8_nibble[16] = {0x00u, 0x1Du, 0x3Au, 0x27u, 0x74u, 0x69u, 0x4Eu, 0x53u,
                                            0xE8u, 0xF5u, 0xD2u, 0xCFu, 0x9Cu, 0x81u, 0xA6u, 0xBBu};
    uint8_t c = (uint8_t)(crc ^ byte);
    c = (uint8_t)((uint8_t)(c << 4) ^ crc8_nibble[c >> 4]);
    c = (uint8_t)((uint8_t)(c << 4) ^ crc8_nibble[c >> 4]);
    return c;
}

uint8_t estop_crc8_e2e(uint16_t data_id, const uint8_t *payload, size_t len)
{
    uint8_t crc = 0xFFu;
    size_t i;
    crc = crc8_byte(crc, (uint8_t)(data_id & 0xFFu));
    crc = crc8_byte(crc, (uint8_t)(data_id >> 8));
    /*@ loop assigns i, crc;
        loop variant len - i; */
    for (i = 0u; i < len; i++) {
        crc = crc8_byte(crc, payload[i]);
    }
    return (uint8_t)(crc ^ 0xFFu);
}
