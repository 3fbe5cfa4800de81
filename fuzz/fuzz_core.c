/*
 * libFuzzer target of the firmware core (issue 9).
 *
 * The input is a small program: a configuration header, then operations with times (UDP
 * datagrams raw or well-formed, TCP bytes per slot, opens, closes, ticks, faults, time jumps
 * forwards and backwards, with or without a key). The harness plays the host exactly as
 * estop_core.h asks (frames sent, slots closed on request, TCP bytes fed until consumed) and,
 * after every call into the core, checks the safety invariants against its own shadow record,
 * kept with its own code (bitwise CRCs, its own TCP framing, its own clock in 64 bits):
 *   - never ARMED without an accepted RELEASE (the right form, an ACK, a good CRC or tag, a
 *     live link of enough valid packets since the latest stop, a neutral latest packet);
 *   - never ARMED past the slow time, never ARMED or SLOWING past the timeout (from the
 *     latest valid packet); SLOWING only from ARMED, and left for ARMED only after 3 valid
 *     packets since it began;
 *   - ESTOP_BRAKE and ESTOP_STATUS never later than their period, every frame's CRC, alive
 *     counter and content right, the latest brake frame telling the state after the call;
 *   - next_call_us never in the past and never after a due frame or the deadline;
 *   - replies of the right form (CRC, magic, session, echoed counter, tag);
 *   - every TCP call makes progress (the host would spin otherwise);
 * and AddressSanitizer sees every buffer at its exact size, so any read or write out of
 * bounds aborts. Any violation aborts with a message naming the invariant.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "estop_blake2s.h"
#include "estop_core.h"

#define SESSION 0x0123456789ABCDEFull /* PROTOCOL.md 5.4, so the spec's tagged vectors pass */
#define SLOTS_TRIED (ESTOP_MAX_SLOTS + 1u) /* one index past the end: ESTOP_ERR_SLOT */
#define MAX_OPS 128u

#define CHECK(cond, what)                                                                      \
    do {                                                                                       \
        if (!(cond)) {                                                                         \
            fprintf(stderr, "invariant broken: %s (%s:%d)\n", what, __FILE__, __LINE__);       \
            abort();                                                                           \
        }                                                                                      \
    } while (0)

/* ---- reading the input ----------------------------------------------------------------- */

typedef struct {
    const uint8_t *p;
    size_t n;
} input_t;

static uint8_t in_u8(input_t *in)
{
    uint8_t v = 0;
    if (in->n > 0u) {
        v = in->p[0];
        in->p++;
        in->n--;
    }
    return v;
}

static uint16_t in_u16(input_t *in)
{
    uint16_t lo = in_u8(in);
    return (uint16_t)(lo | (uint16_t)(in_u8(in) << 8));
}

static uint32_t in_u32(input_t *in)
{
    uint32_t lo = in_u16(in);
    return lo | ((uint32_t)in_u16(in) << 16);
}

static uint64_t in_u64(input_t *in)
{
    uint64_t lo = in_u32(in);
    return lo | ((uint64_t)in_u32(in) << 32);
}

/* ---- independent codecs (bitwise, not the core's table code) ---------------------------- */

static uint32_t crc32_bitwise(const uint8_t *d, size_t n)
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

static uint8_t crc8_e2e(uint16_t data_id, const uint8_t *d)
{
    uint8_t crc = 0xFFu;
    crc = crc8_step(crc, (uint8_t)(data_id & 0xFFu));
    crc = crc8_step(crc, (uint8_t)(data_id >> 8));
    for (int i = 0; i < 7; i++) {
        crc = crc8_step(crc, d[i]);
    }
    return (uint8_t)(crc ^ 0xFFu);
}

static uint32_t get32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

static uint64_t get64(const uint8_t *p)
{
    return (uint64_t)get32(p) | ((uint64_t)get32(p + 4) << 32);
}

static void put32(uint8_t *p, uint32_t v)
{
    for (int i = 0; i < 4; i++) {
        p[i] = (uint8_t)(v >> (8 * i));
    }
}

static void put64(uint8_t *p, uint64_t v)
{
    put32(p, (uint32_t)v);
    put32(p + 4, (uint32_t)(v >> 32));
}

/* ---- the harness's world ---------------------------------------------------------------- */

typedef struct {
    int open;
    size_t fill;
    uint8_t buf[ESTOP_REQ_FRAME_LEN];
} shadow_slot_t;

typedef struct {
    estop_core_t core;
    estop_config_t cfg;
    uint8_t key[ESTOP_KEY_LEN];
    int has_key;
    uint64_t t;              /* the host's clock in 64 bits: the core sees its low 32 */
    uint32_t next_call;
    int booted;              /* the first call (the boot frames) has been made */
    /* shadow of the link */
    int have_valid;
    uint64_t last_valid_t;
    int last_neutral;
    uint32_t run;            /* valid packets since boot, the latest stop request, silence */
    uint32_t slow_run;       /* valid packets since SLOWING began */
    int link_dead;           /* silent for the timeout since the latest valid packet */
    /* shadow of the frames */
    uint64_t last_brake_t;
    uint64_t last_status_t;
    int brake_counter;       /* next expected alive counter, -1 before the first frame */
    int status_counter;
    shadow_slot_t slots[SLOTS_TRIED];
    uint64_t counter[10][2]; /* per remote id, per channel: what the harness sends next */
    estop_counters_t prev;   /* counters before the call */
    uint8_t prev_state;
} world_t;

/* What the harness knows about the input of one call. */
typedef struct {
    int kind;                /* 0 clock only, 1 udp, 2 tcp bytes, 3 fault, 4 open/close */
    const uint8_t *data;
    size_t len;
    size_t consumed;
    int frame_done;          /* the shadow completed a frame with this call's bytes */
    uint8_t frame[ESTOP_REQ_FRAME_LEN];
    size_t frame_len;
    int slot_closed_call;    /* tcp_rx on a closed slot */
} call_t;

static int neutral_bits(uint32_t bits)
{
    return ((bits & 0x80000000u) != 0u) || (bits == 0u);
}

/* The shadow's TCP framing: appends the call's consumed bytes; notes a completed frame. */
static void shadow_tcp(shadow_slot_t *s, call_t *c, int closed_by_core)
{
    size_t i;
    for (i = 0; i < c->consumed; i++) {
        size_t want;
        s->buf[s->fill++] = c->data[i];
        want = (s->fill >= 4u && get32(s->buf) == ESTOP_MAGIC_REQUEST) ? ESTOP_REQ_FRAME_LEN
                                                                        : ESTOP_TCP_FRAME_LEN;
        if (s->fill == want) {
            memcpy(c->frame, s->buf, want);
            c->frame_len = want;
            c->frame_done = 1;
            s->fill = 0;
            i++;
            break;
        }
    }
    /* The core takes at most one frame; only a bad plain frame drops the rest of the bytes. */
    if (!closed_by_core) {
        CHECK(i == c->consumed, "tcp: consumed bytes past the end of a frame");
    }
}

static int plain_crc_ok(const uint8_t *f)
{
    return crc32_bitwise(f, 12u) == get32(f + 12);
}

static int request_tag_ok(const world_t *w, const uint8_t *f)
{
    uint8_t tag[ESTOP_TAG_LEN];
    if (!w->has_key) {
        return 0;
    }
    CHECK(estop_blake2s(tag, ESTOP_TAG_LEN, w->key, ESTOP_KEY_LEN, f, 32u) == 0, "blake2s");
    return memcmp(tag, f + 32, ESTOP_TAG_LEN) == 0;
}

/* The msg_id of a completed frame, and whether the unit may act on it at all. */
static uint32_t frame_msg(const call_t *c, int *good)
{
    if (c->frame_len == ESTOP_REQ_FRAME_LEN) {
        *good = 1; /* any tag: STOP and STATUS work regardless */
        return get32(c->frame + 4);
    }
    *good = plain_crc_ok(c->frame);
    return get32(c->frame);
}

static void check_frame(world_t *w, const estop_can_frame_t *f, uint64_t t)
{
    const estop_config_t *cfg = &w->cfg;
    CHECK(f->dlc == ESTOP_CAN_DLC, "frame: dlc 8");
    CHECK((f->data[6] & 0xF0u) == 0u && (f->data[6] & 0x0Fu) < 15u, "frame: counter 0..14");
    if (f->id == cfg->brake_can_id) {
        CHECK(f->data[7] == crc8_e2e(cfg->brake_data_id, f->data), "brake frame: crc");
        CHECK(w->brake_counter < 0 || f->data[6] == w->brake_counter, "brake frame: counter");
        w->brake_counter = (f->data[6] + 1) % 15;
        CHECK(f->data[2] <= 2u && f->data[3] < ESTOP_REASON_COUNT, "brake: state/reason");
        if (f->data[2] == ESTOP_STATE_STOPPED) {
            CHECK(f->data[0] == 1u && f->data[1] == 100u, "brake: emergency while STOPPED");
        } else if (f->data[2] == ESTOP_STATE_SLOWING) {
            CHECK(f->data[0] == 2u && f->data[1] == cfg->slow_level, "brake: slow level");
        } else {
            CHECK(f->data[0] == 0u && f->data[1] == 0u, "brake: released while ARMED");
        }
        CHECK((f->data[2] != ESTOP_STATE_STOPPED) == (f->data[3] == ESTOP_REASON_NONE),
              "brake: reason none exactly while ARMED or SLOWING");
        CHECK(f->data[4] <= 1u && (f->data[4] == 0u || f->data[2] != ESTOP_STATE_STOPPED),
              "brake: flags");
        CHECK(f->data[5] == 0u, "brake: byte 5");
        w->last_brake_t = t;
    } else {
        CHECK(f->id == cfg->status_can_id, "frame: unknown CAN id");
        CHECK(f->data[7] == crc8_e2e(cfg->status_data_id, f->data), "status frame: crc");
        CHECK(w->status_counter < 0 || f->data[6] == w->status_counter, "status frame: counter");
        w->status_counter = (f->data[6] + 1) % 15;
        w->last_status_t = t;
    }
}

static void check_reply(const world_t *w, const estop_out_t *out, const call_t *c)
{
    int good;
    uint32_t msg = frame_msg(c, &good);
    const uint8_t *r = out->reply;
    CHECK(c->frame_done && good, "reply without a complete good frame");
    CHECK(out->reply_len == c->frame_len, "reply: form follows the request's");
    if (out->reply_len == ESTOP_TCP_FRAME_LEN) {
        CHECK(crc32_bitwise(r, 12u) == get32(r + 12), "plain reply: crc");
        CHECK(get32(r + 4) == get32(c->frame + 4), "plain reply: seq");
    } else {
        uint8_t m[ESTOP_TAG_LEN + 32u];
        uint8_t tag[ESTOP_TAG_LEN];
        CHECK(get32(r) == ESTOP_MAGIC_REPLY, "reply frame: magic");
        CHECK(get32(r + 8) == get32(c->frame + 8), "reply frame: seq");
        CHECK(get64(r + 16) == SESSION, "reply frame: session");
        CHECK(get64(r + 24) == get64(c->frame + 24), "reply frame: counter echo");
        memset(tag, 0, sizeof tag);
        if (w->has_key) {
            memcpy(m, c->frame + 32, ESTOP_TAG_LEN);
            memcpy(m + ESTOP_TAG_LEN, r, 32u);
            CHECK(estop_blake2s(tag, ESTOP_TAG_LEN, w->key, ESTOP_KEY_LEN, m, sizeof m) == 0,
                  "blake2s");
        }
        CHECK(memcmp(tag, r + 32, ESTOP_TAG_LEN) == 0, "reply frame: tag");
        r += 4;
    }
    {
        uint32_t ack = get32(r);
        uint8_t nak = r[11];
        CHECK(ack == (nak == 0u ? ESTOP_MSG_ACK : ESTOP_MSG_NAK), "reply: ACK iff nak 0");
        CHECK(nak <= ESTOP_NAK_NOT_AUTHENTICATED, "reply: nak code");
        CHECK(r[8] == out->state && r[9] == out->reason && r[10] == out->flags,
              "reply: state, reason, flags after the call");
        if (msg == w->cfg.stop_id || msg == ESTOP_MSG_LIFT) {
            CHECK(nak == 0u && r[8] == ESTOP_STATE_STOPPED, "reply: STOP acknowledged, STOPPED");
        } else if (msg != ESTOP_MSG_RELEASE && msg != ESTOP_MSG_STATUS) {
            CHECK(nak == ESTOP_NAK_UNKNOWN_ID, "reply: unknown id NAK 1");
        } else if (msg == ESTOP_MSG_RELEASE && !w->has_key) {
            CHECK(nak != 0u || c->frame_len == ESTOP_TCP_FRAME_LEN,
                  "reply: request-frame RELEASE without a key NAK 4");
        } else if (msg == ESTOP_MSG_RELEASE && c->frame_len == ESTOP_TCP_FRAME_LEN) {
            CHECK(nak == ESTOP_NAK_NOT_AUTHENTICATED, "reply: plain RELEASE with a key NAK 4");
        }
    }
}

/* Everything checked after one call. err is the call's result. */
static void after_call(world_t *w, estop_err_t err, const estop_out_t *out, call_t *c,
                       uint64_t t_new)
{
    const estop_config_t *cfg = &w->cfg;
    estop_status_t st;
    uint64_t t_old = w->t;
    int backwards = t_new < t_old;
    uint32_t d;
    int brakes = 0;
    int stop_request = 0;

    if (err == ESTOP_ERR_SLOT) {
        return; /* refused before the clock: the core saw nothing, out is not filled */
    }
    CHECK(err == ESTOP_OK || (err == ESTOP_ERR_SLOT_CLOSED && c->slot_closed_call),
          "unexpected error");
    w->t = t_new;
    CHECK(estop_get_status(&w->core, &st) == ESTOP_OK, "status read-out");
    CHECK(out->n_can <= ESTOP_OUT_MAX_CAN, "at most 3 frames");
    CHECK(out->state == st.state && out->reason == st.reason, "out tells the state");

    /* The link as the unit must see it at this call's time, before the input. */
    if (backwards) {
        w->link_dead = 1;
        w->run = 0;
    } else if (w->have_valid && !w->link_dead && t_new >= w->last_valid_t + cfg->timeout_us) {
        w->link_dead = 1;
        w->run = 0;
    }

    /* Frames: a due brake (or status) frame is in this call's output. */
    {
        /* (A clock gone backwards is judged by next_call_us below.) */
        int brake_due = !w->booted ||
                        (!backwards && t_new >= w->last_brake_t + cfg->brake_period_us);
        int status_due = !w->booted ||
                         (!backwards && t_new >= w->last_status_t + cfg->status_period_us);
        int status_seen = 0;
        const estop_can_frame_t *last_brake = NULL;
        for (uint8_t i = 0; i < out->n_can; i++) {
            check_frame(w, &out->can[i], t_new);
            if (out->can[i].id == cfg->brake_can_id) {
                brakes++;
                last_brake = &out->can[i];
            } else {
                status_seen = 1;
            }
        }
        CHECK(!brake_due || brakes > 0, "ESTOP_BRAKE later than its period");
        CHECK(!status_due || status_seen, "ESTOP_STATUS later than its period");
        if (last_brake != NULL) {
            CHECK(last_brake->data[2] == out->state && last_brake->data[3] == out->reason,
                  "the latest brake frame tells the state after the call");
        }
        CHECK(!out->state_changed || brakes > 0, "a state change sends ESTOP_BRAKE at once");
        w->booted = 1;
    }

    /* SLOWING only from ARMED (or by a RELEASE of a link already silent for the slow time,
     * checked with the other releases below), and only once the link was silent for the slow
     * time (the input comes after the clock, so the time of this call decides). */
    if (st.state == ESTOP_STATE_SLOWING && w->prev_state != ESTOP_STATE_SLOWING) {
        CHECK(t_new >= w->last_valid_t + cfg->slow_us, "SLOWING before the slow time");
        CHECK(cfg->slow_us < cfg->timeout_us, "SLOWING with the slow time = the timeout");
        CHECK(st.counters.slowdowns == w->prev.slowdowns + 1u, "slow-down counted");
        w->slow_run = 0;
    }

    /* The input. */
    if (c->kind == 1 && st.counters.udp_valid != w->prev.udp_valid) {
        const uint8_t *body = c->len == ESTOP_UDP_AUTH_LEN ? c->data + 24 : c->data;
        CHECK(st.counters.udp_valid == w->prev.udp_valid + 1u, "one valid packet a datagram");
        CHECK(c->len == (w->has_key ? ESTOP_UDP_AUTH_LEN : ESTOP_UDP_LEN) ||
                  (!w->has_key && c->len == ESTOP_UDP_LEN_NO_HORN),
              "valid packet of the wrong form");
        w->have_valid = 1;
        w->last_valid_t = t_new;
        w->link_dead = 0;
        w->last_neutral = neutral_bits(get32(body));
        if (w->run < 0xFFFFFFFFu) {
            w->run++;
        }
        if (w->prev_state == ESTOP_STATE_SLOWING || st.state == ESTOP_STATE_SLOWING) {
            w->slow_run++;
        }
    }
    if (c->kind == 1 && st.counters.udp_stops != w->prev.udp_stops) {
        stop_request = 1;
    }
    if (c->kind == 3) {
        stop_request = 1;
        CHECK(st.counters.faults > w->prev.faults, "fault counted");
    }
    if (c->kind == 2 && !c->slot_closed_call) {
        int good = 0;
        uint32_t msg = 0;
        if (c->frame_done) {
            msg = frame_msg(c, &good);
        }
        CHECK(c->len == 0u || c->consumed > 0u, "tcp: no progress on an open slot");
        CHECK(out->close_slot == (c->frame_done && !good), "tcp: close exactly on a bad crc");
        CHECK(out->has_reply == (c->frame_done && good), "tcp: one reply a good frame");
        if (out->has_reply) {
            check_reply(w, out, c);
        }
        if (c->frame_done && good && (msg == cfg->stop_id || msg == ESTOP_MSG_LIFT)) {
            stop_request = 1;
        }
    } else {
        CHECK(!out->has_reply && !out->close_slot, "reply or close without TCP bytes");
    }
    if (stop_request) {
        w->run = 0;
        CHECK(st.state == ESTOP_STATE_STOPPED, "a stop request leaves the unit STOPPED");
    }
    if (backwards) {
        CHECK(st.state == ESTOP_STATE_STOPPED, "a clock going backwards stops the unit");
    }

    /* SLOWING -> ARMED: only a valid packet, the third since SLOWING began. */
    if (st.state == ESTOP_STATE_ARMED && w->prev_state == ESTOP_STATE_SLOWING) {
        CHECK(c->kind == 1 && st.counters.udp_valid == w->prev.udp_valid + 1u,
              "SLOWING left for ARMED without a valid packet");
        CHECK(w->slow_run == 3u, "SLOWING left for ARMED before 3 valid packets");
        CHECK(st.counters.rearms == w->prev.rearms + 1u, "way back to ARMED counted");
    }
    /* Never ARMED (or SLOWING) without an accepted RELEASE. */
    if (st.state != ESTOP_STATE_STOPPED && w->prev_state == ESTOP_STATE_STOPPED) {
        int good = 0;
        uint32_t msg;
        CHECK(c->kind == 2 && c->frame_done && out->has_reply, "ARMED without a RELEASE frame");
        msg = frame_msg(c, &good);
        CHECK(good && msg == ESTOP_MSG_RELEASE, "ARMED by a frame that is no RELEASE");
        if (w->has_key) {
            CHECK(c->frame_len == ESTOP_REQ_FRAME_LEN && request_tag_ok(w, c->frame) &&
                      get64(c->frame + 16) == SESSION,
                  "ARMED by a RELEASE not made with the key");
        } else {
            CHECK(c->frame_len == ESTOP_TCP_FRAME_LEN, "ARMED by a request frame without a key");
        }
        CHECK(w->have_valid && !w->link_dead && w->run >= cfg->release_packets,
              "ARMED without a live link");
        CHECK(w->last_neutral, "ARMED with a latest packet that is not neutral");
        CHECK(st.counters.releases_accepted == w->prev.releases_accepted + 1u,
              "release counted");
    }
    /* Never ARMED past the slow time, never moving past the timeout. */
    if (st.state != ESTOP_STATE_STOPPED) {
        CHECK(w->have_valid && !w->link_dead && t_new < w->last_valid_t + cfg->timeout_us,
              "ARMED or SLOWING past the deadline");
        CHECK(st.state == ESTOP_STATE_SLOWING || t_new < w->last_valid_t + cfg->slow_us,
              "ARMED past the slow time");
        CHECK(st.reason == ESTOP_REASON_NONE, "ARMED or SLOWING with a reason");
    } else {
        CHECK(st.reason != ESTOP_REASON_NONE, "STOPPED without a reason");
    }
    CHECK(st.link_live == (uint8_t)(w->have_valid && !w->link_dead &&
                                    w->run >= cfg->release_packets),
          "link_live read-out");

    /* next_call_us: in the future, no later than the next due brake frame and the deadline. */
    d = out->next_call_us - (uint32_t)t_new;
    CHECK(d > 0u, "next_call_us in the past (or now)");
    CHECK(d <= cfg->brake_period_us, "next_call_us beyond a brake period");
    CHECK(t_new + d <= w->last_brake_t + cfg->brake_period_us || backwards,
          "next_call_us after the next brake frame is due");
    CHECK(t_new + d <= w->last_status_t + cfg->status_period_us || backwards,
          "next_call_us after the next status frame is due");
    if (st.state == ESTOP_STATE_ARMED) {
        CHECK(t_new + d <= w->last_valid_t + cfg->slow_us, "next_call_us after the slow time");
    } else if (st.state == ESTOP_STATE_SLOWING) {
        CHECK(t_new + d <= w->last_valid_t + cfg->timeout_us, "next_call_us after the deadline");
    }
    w->next_call = out->next_call_us;
    w->prev = st.counters;
    w->prev_state = st.state;
}

/* ---- operations ----------------------------------------------------------------------- */

static void do_tick(world_t *w, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    after_call(w, estop_tick(&w->core, (uint32_t)t, &out), &out, &c, t);
}

static void do_udp(world_t *w, const uint8_t *bytes, size_t len, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    /* An exact-size heap copy: the sanitizer sees a read past len. */
    uint8_t *copy = malloc(len > 0u ? len : 1u);
    const uint8_t *arg = NULL;
    if (copy == NULL) {
        abort();
    }
    if (len > 0u) {
        memcpy(copy, bytes, len);
        arg = copy;
    }
    c.kind = 1;
    c.data = arg;
    c.len = len;
    after_call(w, estop_udp_rx(&w->core, arg, len, (uint32_t)t, &out), &out, &c, t);
    free(copy);
}

static void do_slot(world_t *w, uint32_t slot, int open, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    estop_err_t err = open ? estop_tcp_open(&w->core, slot, (uint32_t)t, &out)
                           : estop_tcp_close(&w->core, slot, (uint32_t)t, &out);
    c.kind = 4;
    CHECK((slot < ESTOP_MAX_SLOTS) == (err != ESTOP_ERR_SLOT), "slot range");
    after_call(w, err, &out, &c, t);
    if (err == ESTOP_OK) {
        w->slots[slot].open = open;
        w->slots[slot].fill = 0;
    }
}

/* The host's loop for TCP bytes: feed the rest until all is consumed or the slot closes. */
static void do_tcp(world_t *w, uint32_t slot, const uint8_t *bytes, size_t len, uint64_t t,
                   uint64_t step)
{
    size_t at = 0;
    int calls = 0;
    do {
        estop_out_t out;
        call_t c = {0};
        size_t rest = len - at;
        size_t consumed = 0;
        uint8_t *copy = malloc(rest > 0u ? rest : 1u);
        estop_err_t err;
        if (copy == NULL) {
            abort();
        }
        if (rest > 0u) {
            memcpy(copy, bytes + at, rest);
        }
        c.kind = 2;
        c.data = copy;
        c.len = rest;
        c.slot_closed_call = slot < ESTOP_MAX_SLOTS && !w->slots[slot].open;
        err = estop_tcp_rx(&w->core, slot, rest > 0u ? copy : NULL, rest, &consumed, (uint32_t)t,
                           &out);
        CHECK(consumed <= rest, "tcp: consumed more than given");
        CHECK((slot < ESTOP_MAX_SLOTS) == (err != ESTOP_ERR_SLOT), "slot range");
        c.consumed = consumed;
        if (err == ESTOP_OK) {
            shadow_tcp(&w->slots[slot], &c, out.close_slot);
        } else {
            CHECK(consumed == 0u, "tcp: consumed bytes on an error");
        }
        after_call(w, err, &out, &c, t);
        free(copy);
        if (err != ESTOP_OK) {
            break;
        }
        at += consumed;
        if (out.close_slot) {
            CHECK(at == len, "tcp: a closed stream is dropped whole");
            CHECK(w->core.slots[slot].open == 0u, "tcp: slot marked closed");
            do_slot(w, slot, 0, t);
            break;
        }
        t += step; /* the rest may come a little later */
        calls++;
    } while (at < len && calls < 64);
}

/* A control body from 4 input bytes: mostly valid values, some out of range. */
static void make_body(input_t *in, uint8_t body[20])
{
    static const uint32_t gas[8] = {0x00000000u, 0x80000000u, 0x3F800000u, 0xBF800000u,
                                    0x3E99999Au, 0xBE800000u, 0x3F800001u, 0x7FC00000u};
    static const uint32_t gear[5] = {1u, 2u, 4u, 8u, 3u};
    uint8_t a = in_u8(in);
    uint8_t b = in_u8(in);
    put32(body, gas[a & 7u]);
    put32(body + 4, gas[(a >> 3) & 7u]);
    put32(body + 8, gear[(b & 7u) % 5u]);
    put32(body + 12, (uint32_t)((b >> 3) & 3u) + ((b & 0x80u) ? 4u : 0u));
    put32(body + 16, (uint32_t)((b >> 5) & 1u) + ((b & 0x40u) && (a & 0x80u) ? 2u : 0u));
}

static void tag(const world_t *w, uint8_t *msg, size_t covered, int corrupt)
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
static void auth_fields(world_t *w, input_t *in, uint8_t *session_at, uint8_t *counter_at,
                        uint32_t remote, int channel, uint8_t sel)
{
    uint64_t *next = &w->counter[remote % 10u][channel];
    put64(session_at, (sel & 0x10u) ? in_u64(in) : SESSION);
    switch (sel & 3u) {
    case 0:
    case 1:
        put64(counter_at, ++*next);
        break;
    case 2:
        put64(counter_at, *next); /* a replay of the latest */
        break;
    default:
        put64(counter_at, in_u64(in));
        break;
    }
}

static void make_request(world_t *w, input_t *in, uint8_t f[ESTOP_REQ_FRAME_LEN], uint32_t msg_id)
{
    uint8_t sel = in_u8(in);
    uint32_t remote = (uint32_t)(in_u8(in) % 10u);
    memset(f, 0, ESTOP_REQ_FRAME_LEN);
    put32(f, ESTOP_MAGIC_REQUEST);
    put32(f + 4, msg_id);
    put32(f + 8, in_u8(in));
    put32(f + 12, remote);
    auth_fields(w, in, f + 16, f + 24, remote, 1, sel);
    tag(w, f, 32u, (sel & 0x20u) ? (sel >> 6) + 1 : 0);
}

static uint32_t pick_msg(const world_t *w, input_t *in)
{
    uint8_t s = in_u8(in);
    switch (s & 3u) {
    case 0:
        return ESTOP_MSG_RELEASE;
    case 1:
        return ESTOP_MSG_STATUS;
    case 2:
        return w->cfg.stop_id;
    default:
        return in_u32(in);
    }
}

static uint64_t later(const world_t *w, uint32_t dt)
{
    return w->t + dt;
}

/* The host's usual time: at most the core's next call time, sometimes a little late. */
static uint64_t host_time(const world_t *w, input_t *in)
{
    uint8_t s = in_u8(in);
    uint32_t until = w->next_call - (uint32_t)w->t;
    if (s < 200u) {
        return w->t + (uint64_t)((uint32_t)s * until / 200u);
    }
    return w->t + until + (uint32_t)(s - 200u) * 97u;
}

static void setup(world_t *w, input_t *in)
{
    uint8_t flags = in_u8(in);
    uint32_t start = in_u32(in);
    estop_config_default(&w->cfg);
    w->cfg.session = SESSION;
    w->has_key = (flags & 1u) != 0u;
    if (w->has_key) {
        for (uint32_t i = 0; i < ESTOP_KEY_LEN; i++) {
            w->key[i] = (uint8_t)i;
        }
        w->cfg.key_len = (uint8_t)ESTOP_KEY_LEN;
        memcpy(w->cfg.key, w->key, ESTOP_KEY_LEN);
    }
    if (flags & 2u) {
        /* Short times, so the timeouts, the warn time and the periods are all reached. */
        uint32_t to = 1000u + (uint32_t)in_u16(in) * 8u;
        uint32_t bp = 1000u + (uint32_t)in_u16(in) % 24001u;
        uint32_t sp = 10000u + (uint32_t)in_u16(in) * 15u;
        uint16_t warn = in_u16(in);
        w->cfg.timeout_us = to;
        w->cfg.release_packets = 1u + in_u8(in) % 8u;
        /* Flag 4, a two-stage stop (protocol version 3): the slow time anywhere up to the
         * timeout, any slow level. Without it S = T (version 2). */
        w->cfg.slow_us = to;
        if (flags & 4u) {
            w->cfg.slow_us = 1u + (uint32_t)in_u16(in) % to;
            w->cfg.slow_level = (uint8_t)(1u + in_u8(in) % 99u);
        }
        w->cfg.warn_us = 1u + (uint32_t)warn % w->cfg.slow_us;
        w->cfg.brake_period_us = bp;
        w->cfg.status_period_us = sp < bp ? bp : sp;
    }
    CHECK(estop_config_check(&w->cfg) == ESTOP_OK, "harness config");
    CHECK(estop_init(&w->core, &w->cfg, start) == ESTOP_OK, "init");
    w->cfg.key_len = 0u; /* the harness keeps its key in w->key; cfg is only compared */
    memset(w->cfg.key, 0, sizeof w->cfg.key);
    w->t = (uint64_t)start;
    w->next_call = start;
    w->brake_counter = 0;
    w->status_counter = 0;
    w->prev = (estop_counters_t){0};
    w->prev.stops[ESTOP_REASON_BOOT] = 1u;
    w->prev_state = ESTOP_STATE_STOPPED;
    /* Calling at init time sends the boot frames (the host contract). */
    do_tick(w, w->t);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static world_t w;
    input_t in = {data, size};
    uint32_t ops = 0;
    memset(&w, 0, sizeof w);
    setup(&w, &in);
    while (in.n > 0u && ops < MAX_OPS) {
        uint8_t op = in_u8(&in);
        ops++;
        switch (op % 16u) {
        case 0: /* tick at a host's time */
            do_tick(&w, host_time(&w, &in));
            break;
        case 1: /* tick exactly at next_call_us, several times */
        {
            uint8_t n = (uint8_t)(1u + in_u8(&in) % 8u);
            for (uint8_t i = 0; i < n; i++) {
                do_tick(&w, w.t + (uint32_t)(w.next_call - (uint32_t)w.t));
            }
            break;
        }
        case 2: /* a raw datagram */
        {
            uint64_t t = host_time(&w, &in);
            size_t len = in_u8(&in);
            if (len > in.n) {
                len = in.n;
            }
            do_udp(&w, in.p, len, t);
            in.p += len;
            in.n -= len;
            break;
        }
        case 3: /* a plain control packet, 20 or 16 bytes */
        {
            uint8_t body[20];
            uint8_t s = in_u8(&in);
            make_body(&in, body);
            do_udp(&w, body, (s & 1u) ? ESTOP_UDP_LEN_NO_HORN : ESTOP_UDP_LEN, host_time(&w, &in));
            break;
        }
        case 4: /* an authenticated control packet */
        {
            uint8_t p[ESTOP_UDP_AUTH_LEN];
            uint8_t sel = in_u8(&in);
            uint32_t remote = (uint32_t)(in_u8(&in) % 10u);
            put32(p, ESTOP_MAGIC_CONTROL);
            put32(p + 4, remote);
            auth_fields(&w, &in, p + 8, p + 16, remote, 0, sel);
            make_body(&in, p + 24);
            tag(&w, p, 44u, (sel & 0x20u) ? (sel >> 6) + 1 : 0);
            do_udp(&w, p, sizeof p, host_time(&w, &in));
            break;
        }
        case 5: /* a stop datagram (any tag) */
        {
            uint8_t f[ESTOP_REQ_FRAME_LEN];
            make_request(&w, &in, f, (in_u8(&in) & 1u) ? w.cfg.stop_id : pick_msg(&w, &in));
            do_udp(&w, f, sizeof f, host_time(&w, &in));
            break;
        }
        case 6:
        case 7: /* open (6) or close (7) a slot */
        {
            uint32_t slot = in_u8(&in) % SLOTS_TRIED;
            do_slot(&w, slot, op % 16u == 6u, host_time(&w, &in));
            break;
        }
        case 8: /* raw TCP bytes */
        {
            uint32_t slot = in_u8(&in) % SLOTS_TRIED;
            uint64_t t = host_time(&w, &in);
            uint8_t step = in_u8(&in);
            size_t len = in_u8(&in);
            if (len > in.n) {
                len = in.n;
            }
            do_tcp(&w, slot, in.p, len, t, step);
            in.p += len;
            in.n -= len;
            break;
        }
        case 9: /* a plain frame, right CRC or not, in pieces */
        {
            uint8_t f[ESTOP_TCP_FRAME_LEN];
            uint32_t slot = in_u8(&in) % SLOTS_TRIED;
            uint8_t s = in_u8(&in);
            put32(f, pick_msg(&w, &in));
            put32(f + 4, in_u8(&in));
            put32(f + 8, 0u);
            put32(f + 12, crc32_bitwise(f, 12u) ^ ((s & 0x80u) ? 1u : 0u));
            do_tcp(&w, slot, f, 1u + (s & 15u), host_time(&w, &in), 100u);
            if ((s & 15u) < 15u) {
                do_tcp(&w, slot, f + 1u + (s & 15u), 15u - (s & 15u), w.t + 100u, 0u);
            }
            break;
        }
        case 10: /* a request frame */
        {
            uint8_t f[ESTOP_REQ_FRAME_LEN];
            uint32_t slot = in_u8(&in) % SLOTS_TRIED;
            make_request(&w, &in, f, pick_msg(&w, &in));
            do_tcp(&w, slot, f, sizeof f, host_time(&w, &in), 0u);
            break;
        }
        case 11:
        {
            estop_out_t out;
            call_t c = {0};
            uint64_t t = host_time(&w, &in);
            c.kind = 3;
            after_call(&w, estop_fault(&w.core, (uint32_t)t, &out), &out, &c, t);
            break;
        }
        case 12: /* a jump forwards, up to the longest step the contract allows */
            do_tick(&w, later(&w, in_u32(&in) & ESTOP_MAX_STEP_US));
            break;
        case 13: /* the clock goes backwards */
        {
            uint32_t back = 1u + in_u32(&in) % 0x7FFFFFFFu;
            do_tick(&w, w.t >= back ? w.t - back : w.t + 0x100000000ull - back);
            break;
        }
        case 14: /* drive: n good packets, neutral or not, at a gap (ticking as a host does) */
        {
            uint8_t n = in_u8(&in) % 8u;
            uint8_t s = in_u8(&in);
            uint32_t gap = 1000u + (uint32_t)in_u8(&in) * 100u;
            for (uint8_t i = 0; i < n; i++) {
                uint64_t due = w.t + gap;
                uint8_t p[ESTOP_UDP_AUTH_LEN];
                while (w.t + (uint32_t)(w.next_call - (uint32_t)w.t) < due) {
                    do_tick(&w, w.t + (uint32_t)(w.next_call - (uint32_t)w.t));
                }
                memset(p, 0, sizeof p);
                put32(p + 8, 4u);
                if (s & 1u) {
                    put32(p, 0x3E800000u); /* gas 0.25: not neutral */
                }
                if (w.has_key) {
                    memmove(p + 24, p, 20u);
                    put32(p, ESTOP_MAGIC_CONTROL);
                    put32(p + 4, 3u);
                    put64(p + 8, SESSION);
                    put64(p + 16, ++w.counter[3][0]);
                    tag(&w, p, 44u, 0);
                    do_udp(&w, p, ESTOP_UDP_AUTH_LEN, due);
                } else {
                    do_udp(&w, p, ESTOP_UDP_LEN, due);
                }
            }
            break;
        }
        default: /* a NULL datagram and an empty TCP read */
        {
            uint32_t slot;
            do_udp(&w, NULL, 0u, host_time(&w, &in));
            slot = in_u8(&in) % SLOTS_TRIED;
            do_tcp(&w, slot, NULL, 0u, w.t, 0u);
        }
            break;
        }
    }
    return 0;
}
