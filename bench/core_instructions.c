/*
 * Drives the core with N valid UDP packets and N TCP STATUS frames so that callgrind can count
 * the instructions of estop_udp_rx and estop_tcp_rx (run by core_instructions.py).
 */
#include <stdio.h>
#include <stdlib.h>

#include "estop_core.h"
#include "estop_crc.h"

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

int main(int argc, char **argv)
{
    estop_core_t core;
    estop_config_t cfg;
    estop_out_t out;
    uint8_t pkt[ESTOP_UDP_LEN] = {0};
    uint8_t frame[ESTOP_TCP_FRAME_LEN] = {0};
    uint32_t n = (argc > 1) ? (uint32_t)strtoul(argv[1], NULL, 10) : 10000u;
    uint32_t t = 0u;
    uint32_t i;
    size_t consumed = 0u;

    estop_config_default(&cfg);
    if (estop_init(&core, &cfg, t) != ESTOP_OK) {
        return 1;
    }
    put_u32(pkt + 8, 4u); /* neutral gear, everything else 0: a valid, neutral packet */
    put_u32(frame, ESTOP_MSG_STATUS);
    put_u32(frame + 12, estop_crc32(frame, 12u));
    (void)estop_tcp_open(&core, 0u, t, &out);
    for (i = 0u; i < n; i++) {
        t += 20000u; /* 50 Hz, as the remote sends */
        (void)estop_tick(&core, t, &out);
        (void)estop_udp_rx(&core, pkt, sizeof pkt, t, &out);
        (void)estop_tcp_rx(&core, 0u, frame, sizeof frame, &consumed, t, &out);
    }
    printf("%u %u\n", (unsigned)n, (unsigned)core.counters.udp_valid);
    return 0;
}
