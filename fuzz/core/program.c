/*
 * The input program of fuzz_core.c: bytes read one field at a time (zeros once it runs out),
 * control bodies, tags, session and counter fields and request frames made from them.
 */
#include <string.h>

#include "estop_blake2s.h"
#include "harness.h"

uint8_t fz_in_u8(input_t *in)
{
    uint8_t v = 0;
    if (in->n > 0u) {
        v = in->p[0];
        in->p++;
        in->n--;
    }
    return v;
}

uint16_t fz_in_u16(input_t *in)
{
    uint16_t lo = fz_in_u8(in);
    return (uint16_t)(lo | (uint16_t)(fz_in_u8(in) << 8));
}

uint32_t fz_in_u32(input_t *in)
{
    uint32_t lo = fz_in_u16(in);
    return lo | ((uint32_t)fz_in_u16(in) << 16);
}

uint64_t fz_in_u64(input_t *in)
{
    uint64_t lo = fz_in_u32(in);
    return lo | ((uint64_t)fz_in_u32(in) << 32);
}

/* A control body from 4 input bytes: mostly valid values, some out of range. */
void fz_make_body(input_t *in, uint8_t body[20])
{
    static const uint32_t gas[8] = {0x00000000u, 0x80000000u, 0x3F800000u, 0xBF800000u,
                                    0x3E99999Au, 0xBE800000u, 0x3F800001u, 0x7FC00000u};
    static const uint32_t gear[5] = {1u, 2u, 4u, 8u, 3u};
    uint8_t a = fz_in_u8(in);
    uint8_t b = fz_in_u8(in);
    fz_put32(body, gas[a & 7u]);
    fz_put32(body + 4, gas[(a >> 3) & 7u]);
    fz_put32(body + 8, gear[(b & 7u) % 5u]);
    fz_put32(body + 12, (uint32_t)((b >> 3) & 3u) + ((b & 0x80u) ? 4u : 0u));
    fz_put32(body + 16, (uint32_t)((b >> 5) & 1u) + ((b & 0x40u) && (a & 0x80u) ? 2u : 0u));
}

void fz_tag(const world_t *w, uint8_t *msg, size_t covered, int corrupt)
{
    /* With the spec's key even on a unit without one (then the form is wrong anyway). */
    static const uint8_t spec_key[ESTOP_KEY_LEN] = {
        0,  1,  2,  3,  4,  5,  6,  7,  8,  9,  10, 11, 12, 13, 14, 15,
        16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31};
    CHECK(estop_blake2s(msg + covered, ESTOP_TAG_LEN, w->has_key ? w->key : spec_key,
                        ESTOP_KEY_LEN, msg, covered) == 0,
          "blake2s");
    if (corrupt) {
        msg[covered + (corrupt & 15)] ^= 0x01u;
    }
}

/* Session and counter fields chosen by a selector byte: mostly right, sometimes not. */
void fz_auth_fields(world_t *w, input_t *in, uint8_t *session_at, uint8_t *counter_at,
                    uint32_t remote, int channel, uint8_t sel)
{
    uint64_t *next = &w->counter[remote % 10u][0]; /* one for both channels */
    (void)channel;
    fz_put64(session_at, (sel & 0x10u) ? fz_in_u64(in) : SESSION);
    switch (sel & 3u) {
    case 0:
    case 1:
        fz_put64(counter_at, ++*next);
        break;
    case 2:
        fz_put64(counter_at, *next); /* a replay of the latest */
        break;
    default:
        fz_put64(counter_at, fz_in_u64(in));
        break;
    }
}

void fz_make_request(world_t *w, input_t *in, uint8_t f[ESTOP_REQ_FRAME_LEN], uint32_t msg_id)
{
    uint8_t sel = fz_in_u8(in);
    uint32_t remote = (uint32_t)(fz_in_u8(in) % 10u);
    memset(f, 0, ESTOP_REQ_FRAME_LEN);
    fz_put32(f, ESTOP_MAGIC_REQUEST);
    fz_put32(f + 4, msg_id);
    fz_put32(f + 8, fz_in_u8(in));
    fz_put32(f + 12, remote);
    fz_auth_fields(w, in, f + 16, f + 24, remote, 1, sel);
    fz_tag(w, f, 32u, (sel & 0x20u) ? (sel >> 6) + 1 : 0);
}

uint32_t fz_pick_msg(const world_t *w, input_t *in)
{
    uint8_t s = fz_in_u8(in);
    switch (s & 3u) {
    case 0:
        return ESTOP_MSG_RELEASE;
    case 1:
        return ESTOP_MSG_STATUS;
    case 2:
        return w->cfg.stop_id;
    default:
        return fz_in_u32(in);
    }
}

uint64_t fz_later(const world_t *w, uint32_t dt)
{
    return w->t + dt;
}

/* The host's usual time: at most the core's next call time, sometimes a little late. */
uint64_t fz_host_time(const world_t *w, input_t *in)
{
    uint8_t s = fz_in_u8(in);
    uint32_t until = w->next_call - (uint32_t)w->t;
    if (s < 200u) {
        return w->t + (uint64_t)((uint32_t)s * until / 200u);
    }
    return w->t + until + (uint32_t)(s - 200u) * 97u;
}


/* Keeps a copy of an authenticated control packet for a later replay (a ring of REC_MAX). */
void fz_record(world_t *w, const uint8_t p[ESTOP_UDP_AUTH_LEN])
{
    memcpy(w->rec[w->n_rec % REC_MAX], p, ESTOP_UDP_AUTH_LEN);
    w->n_rec++;
}
