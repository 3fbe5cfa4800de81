#include "frame.h"

#include <string.h>

static uint8_t crc8_byte(uint8_t crc, uint8_t b)
{
    unsigned c = (unsigned)(crc ^ b);
    int i;
    for (i = 0; i < 8; i++) {
        c = (c & 0x80u) != 0u ? ((c << 1) ^ 0x1Du) : (c << 1);
    }
    return (uint8_t)(c & 0xFFu);
}

uint8_t frame_crc8(uint16_t data_id, const uint8_t *data)
{
    uint8_t crc = 0xFFu;
    unsigned i;
    crc = crc8_byte(crc, (uint8_t)(data_id & 0xFFu));
    crc = crc8_byte(crc, (uint8_t)(data_id >> 8));
    for (i = 0; i < 7u; i++) {
        crc = crc8_byte(crc, data[i]);
    }
    return (uint8_t)(crc ^ 0xFFu);
}

void frame_next_stopped(const estop_can_frame_t *prev, uint32_t can_id, uint16_t data_id,
                        uint8_t reason, estop_can_frame_t *out)
{
    unsigned counter = 0u;

    if (prev != NULL) {
        counter = ((unsigned)(prev->data[6] & 0x0Fu) + 1u) % FRAME_COUNTER_MOD;
    }
    memset(out, 0, sizeof *out);
    out->id = can_id;
    out->dlc = ESTOP_CAN_DLC;
    out->data[0] = 1u;   /* brake_request: emergency brake */
    out->data[1] = 100u; /* brake_level percent */
    out->data[2] = ESTOP_STATE_STOPPED;
    out->data[3] = reason;
    out->data[4] = 0u;   /* flags: link-degraded only exists while ARMED */
    out->data[5] = 0u;
    out->data[6] = (uint8_t)counter;
    out->data[7] = frame_crc8(data_id, out->data);
}
