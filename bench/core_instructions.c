/*
 * Drives the core with N valid UDP packets and N TCP STATUS frames, and computes N BLAKE2s
 * tags of a 44-byte message (the authenticated control packet of PROTOCOL.md 5.1) from a
 * precomputed key state, so that callgrind can count the instructions of estop_udp_rx,
 * estop_tcp_rx and estop_b2s_mac (run by core_instructions.py).
 */
#include <stdio.h>
#include <stdlib.h>

#include "estop_blake2s.h"
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
    uint8_t key[ESTOP_B2S_KEY_MAX];
    uint8_t auth[44] = {0x45u, 0x53u, 0x55u, 0x32u}; /* "ESU2", then zeros */
    uint8_t tag[16] = {0};
    estop_b2s_key_t mac_key;
    uint32_t n = (argc > 1) ? (uint32_t)strtoul(argv[1], NULL, 10) : 10000u;
    uint32_t t = 0u;
    uint32_t i;
    size_t consumed = 0u;

    estop_config_default(&cfg);
    if (estop_init(&core, &cfg, t) != ESTOP_OK) {
        return 1;
    }
    for (i = 0u; i < sizeof key; i++) {
        key[i] = (uint8_t)i;
    }
    if (estop_b2s_key_init(&mac_key, key, sizeof key, sizeof tag) != 0) {
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
        put_u32(auth + 16, i); /* the counter field */
        (void)estop_b2s_mac(&mac_key, auth, sizeof auth, tag);
    }
    printf("%u %u %02x\n", (unsigned)n, (unsigned)core.counters.udp_valid, (unsigned)tag[0]);
    return 0;
}
