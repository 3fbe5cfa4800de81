/*
 * Drives two cores, one without a key and one with the key of PROTOCOL.md 5.4, with N calls of
 * every kind, each through its own small wrapper so that callgrind (core_instructions.py,
 * --toggle-collect=<wrapper>) counts one kind of input at a time:
 *   plain_udp      a valid 20-byte control packet, unit without a key
 *   auth_udp       a valid 60-byte authenticated control packet, unit with a key
 *   plain_tcp      a 16-byte STATUS frame
 *   request_tcp    a 48-byte STATUS request frame (the reply is tagged)
 *   release_tcp    an authenticated 48-byte RELEASE while ARMED (tag checked, reply tagged)
 *   tick           a tick every 20 ms (two ESTOP_BRAKE frames due, a STATUS every fifth)
 *   mac44          one BLAKE2s tag of 44 bytes from the precomputed key state
 * The authenticated packets carry rising counters; their tags are made with the core's own
 * BLAKE2s (tested against hashlib elsewhere), so every one of them is valid.
 */
#include <stdio.h>
#include <stdlib.h>

#include "estop_blake2s.h"
#include "estop_core.h"
#include "estop_crc.h"

/* External and never inlined or cloned: callgrind finds them by these names. */
#define NOINLINE __attribute__((noinline, noclone))

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static void put_u64(uint8_t *p, uint64_t v)
{
    put_u32(p, (uint32_t)v);
    put_u32(p + 4, (uint32_t)(v >> 32));
}

NOINLINE void plain_udp(estop_core_t *c, const uint8_t *p, uint32_t t, estop_out_t *o)
{
    (void)estop_udp_rx(c, p, ESTOP_UDP_LEN, t, o);
}

NOINLINE void auth_udp(estop_core_t *c, const uint8_t *p, uint32_t t, estop_out_t *o)
{
    (void)estop_udp_rx(c, p, ESTOP_UDP_AUTH_LEN, t, o);
}

NOINLINE void plain_tcp(estop_core_t *c, const uint8_t *f, uint32_t t, estop_out_t *o)
{
    size_t used;
    (void)estop_tcp_rx(c, 0u, f, ESTOP_TCP_FRAME_LEN, &used, t, o);
}

NOINLINE void request_tcp(estop_core_t *c, const uint8_t *f, uint32_t t, estop_out_t *o)
{
    size_t used;
    (void)estop_tcp_rx(c, 0u, f, ESTOP_REQ_FRAME_LEN, &used, t, o);
}

NOINLINE void release_tcp(estop_core_t *c, const uint8_t *f, uint32_t t, estop_out_t *o)
{
    size_t used;
    (void)estop_tcp_rx(c, 1u, f, ESTOP_REQ_FRAME_LEN, &used, t, o);
}

NOINLINE void tick(estop_core_t *c, uint32_t t, estop_out_t *o)
{
    (void)estop_tick(c, t, o);
}

NOINLINE void mac44(const estop_b2s_key_t *k, const uint8_t *m, uint8_t *tag)
{
    (void)estop_b2s_mac(k, m, 44u, tag);
}

/* A tagged 60-byte control packet (5.1), neutral, with counter ctr. */
static void make_control(const estop_b2s_key_t *k, uint8_t *p, uint64_t session, uint64_t ctr)
{
    uint32_t i;
    for (i = 0u; i < ESTOP_UDP_AUTH_LEN; i++) {
        p[i] = 0u;
    }
    put_u32(p, ESTOP_MAGIC_CONTROL);
    put_u32(p + 4, 7u);
    put_u64(p + 8, session);
    put_u64(p + 16, ctr);
    put_u32(p + 24 + 8, 4u); /* gear neutral */
    (void)estop_b2s_mac(k, p, 44u, p + 44);
}

/* A tagged 48-byte request frame (5.2). */
static void make_request(const estop_b2s_key_t *k, uint8_t *f, uint32_t msg, uint64_t session,
                         uint64_t ctr)
{
    put_u32(f, ESTOP_MAGIC_REQUEST);
    put_u32(f + 4, msg);
    put_u32(f + 8, (uint32_t)ctr);
    put_u32(f + 12, 7u);
    put_u64(f + 16, session);
    put_u64(f + 24, ctr);
    (void)estop_b2s_mac(k, f, 32u, f + 32);
}

int main(int argc, char **argv)
{
    static estop_core_t plain;
    static estop_core_t keyed;
    estop_config_t cfg;
    estop_out_t out;
    estop_b2s_key_t mac_key;
    uint8_t pkt[ESTOP_UDP_LEN] = {0};
    uint8_t apkt[ESTOP_UDP_AUTH_LEN];
    uint8_t frame[ESTOP_TCP_FRAME_LEN] = {0};
    uint8_t req[ESTOP_REQ_FRAME_LEN];
    uint8_t rel[ESTOP_REQ_FRAME_LEN];
    uint8_t tag[16];
    uint32_t n = (argc > 1) ? (uint32_t)strtoul(argv[1], NULL, 10) : 10000u;
    uint64_t session = 0x0123456789ABCDEFu;
    uint32_t t = 0u;
    uint32_t i;
    uint64_t ctr = 0u; /* the remote's one counter, for both channels (PROTOCOL.md 5) */
    size_t used;

    estop_config_default(&cfg);
    cfg.session = session;
    if (estop_init(&plain, &cfg, t) != ESTOP_OK) {
        return 1;
    }
    cfg.key_len = (uint8_t)ESTOP_KEY_LEN;
    for (i = 0u; i < ESTOP_KEY_LEN; i++) {
        cfg.key[i] = (uint8_t)i;
    }
    if (estop_init(&keyed, &cfg, t) != ESTOP_OK ||
        estop_b2s_key_init(&mac_key, cfg.key, ESTOP_KEY_LEN, 16u) != 0) {
        return 1;
    }
    put_u32(pkt + 8, 4u); /* neutral gear, everything else 0: a valid, neutral packet */
    put_u32(frame, ESTOP_MSG_STATUS);
    put_u32(frame + 12, estop_crc32(frame, 12u));
    (void)estop_tcp_open(&plain, 0u, t, &out);
    (void)estop_tcp_open(&keyed, 0u, t, &out);
    (void)estop_tcp_open(&keyed, 1u, t, &out);
    /* Arm the keyed unit, so the RELEASEs measured are the authenticated "already ARMED" path. */
    for (i = 1u; i <= 5u; i++) {
        t += 20000u;
        make_control(&mac_key, apkt, session, ++ctr);
        (void)estop_udp_rx(&keyed, apkt, sizeof apkt, t, &out);
    }
    make_request(&mac_key, rel, ESTOP_MSG_RELEASE, session, ++ctr);
    (void)estop_tcp_rx(&keyed, 1u, rel, sizeof rel, &used, t, &out);
    if (out.state != ESTOP_STATE_ARMED) {
        return 2;
    }
    for (i = 0u; i < n; i++) {
        t += 20000u; /* 50 Hz, as the remote sends */
        tick(&plain, t, &out);
        plain_udp(&plain, pkt, t, &out);
        plain_tcp(&plain, frame, t, &out);
        (void)estop_tick(&keyed, t, &out); /* frames due go here, not into the rows below */
        make_control(&mac_key, apkt, session, ++ctr);
        auth_udp(&keyed, apkt, t, &out);
        make_request(&mac_key, req, ESTOP_MSG_STATUS, session, ++ctr);
        request_tcp(&keyed, req, t, &out);
        make_request(&mac_key, rel, ESTOP_MSG_RELEASE, session, ++ctr);
        release_tcp(&keyed, rel, t, &out);
        mac44(&mac_key, apkt, tag);
    }
    if (keyed.counters.udp_valid != n + 5u || keyed.state != ESTOP_STATE_ARMED ||
        plain.counters.udp_valid != n) {
        return 3; /* a measured input was not the valid one it claims to be */
    }
    printf("%u %u %02x\n", (unsigned)n, (unsigned)keyed.counters.udp_valid, (unsigned)tag[0]);
    return 0;
}
