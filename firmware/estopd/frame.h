/* ESTOP_BRAKE frame layout (PROTOCOL.md 4), for the one frame the daemon builds itself:
 * the last brake frame on shutdown when the core has no frame due. */
#ifndef ESTOPD_FRAME_H
#define ESTOPD_FRAME_H

#include <stdint.h>

#include "estop_core.h"

#define FRAME_COUNTER_MOD 15u /* alive counter runs 0..14 */

/* CRC-8 SAE J1850 over data id low byte, high byte, then bytes 0..6 of data. */
uint8_t frame_crc8(uint16_t data_id, const uint8_t *data);
/* Fills out with a STOPPED brake frame (brake_request 1, level 100) that follows prev in
 * the alive-counter sequence (counter 0 when prev is NULL). */
void frame_next_stopped(const estop_can_frame_t *prev, uint32_t can_id, uint16_t data_id,
                        uint8_t reason, estop_can_frame_t *out);

#endif
