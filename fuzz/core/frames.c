/*
 * The shadow's TCP framing (the first 4 bytes decide the form, as PROTOCOL.md 2 says), and
 * the checks of one CAN frame and of one reply.
 */
#include <string.h>

#include "estop_blake2s.h"
#include "harness.h"

/* The shadow's TCP framing: appends the call's consumed bytes; notes a completed frame. */
void fz_shadow_tcp(shadow_slot_t *s, call_t *c, int closed_by_core)
{
    size_t i;
    for (i = 0; i < c->consumed; i++) {
        size_t want;
        s->buf[s->fill++] = c->data[i];
        want = (s->fill >= 4u && fz_get32(s->buf) == ESTOP_MAGIC_REQUEST)
                   ? ESTOP_REQ_FRAME_LEN
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
    return fz_crc32_bitwise(f, 12u) == fz_get32(f + 12);
}

int fz_request_tag_ok(const world_t *w, const uint8_t *f)
{
    uint8_t tag[ESTOP_TAG_LEN];
    if (!w->has_key) {
        return 0;
    }
    CHECK(estop_blake2s(tag, ESTOP_TAG_LEN, w->key, ESTOP_KEY_LEN, f, 32u) == 0, "blake2s");
    return memcmp(tag, f + 32, ESTOP_TAG_LEN) == 0;
}

/* The msg_id of a completed frame, and whether the unit may act on it at all. */
uint32_t fz_frame_msg(const call_t *c, int *good)
{
    if (c->frame_len == ESTOP_REQ_FRAME_LEN) {
        *good = 1; /* any tag: STOP and STATUS work regardless */
        return fz_get32(c->frame + 4);
    }
    *good = plain_crc_ok(c->frame);
    return fz_get32(c->frame);
}

void fz_check_frame(world_t *w, const estop_can_frame_t *f, uint64_t t)
{
    const estop_config_t *cfg = &w->cfg;
    CHECK(f->dlc == ESTOP_CAN_DLC, "frame: dlc 8");
    CHECK((f->data[6] & 0xF0u) == 0u && (f->data[6] & 0x0Fu) < 15u, "frame: counter 0..14");
    if (f->id == cfg->brake_can_id) {
        CHECK(f->data[7] == fz_crc8_e2e(cfg->brake_data_id, f->data), "brake frame: crc");
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
        CHECK(f->data[7] == fz_crc8_e2e(cfg->status_data_id, f->data), "status frame: crc");
        CHECK(w->status_counter < 0 || f->data[6] == w->status_counter, "status frame: counter");
        w->status_counter = (f->data[6] + 1) % 15;
        w->last_status_t = t;
    }
}

void fz_check_reply(const world_t *w, const estop_out_t *out, const call_t *c)
{
    int good;
    uint32_t msg = fz_frame_msg(c, &good);
    const uint8_t *r = out->reply;
    CHECK(c->frame_done && good, "reply without a complete good frame");
    CHECK(out->reply_len == c->frame_len, "reply: form follows the request's");
    if (out->reply_len == ESTOP_TCP_FRAME_LEN) {
        CHECK(fz_crc32_bitwise(r, 12u) == fz_get32(r + 12), "plain reply: crc");
        CHECK(fz_get32(r + 4) == fz_get32(c->frame + 4), "plain reply: seq");
    } else {
        uint8_t m[ESTOP_TAG_LEN + 32u];
        uint8_t tag[ESTOP_TAG_LEN];
        CHECK(fz_get32(r) == ESTOP_MAGIC_REPLY, "reply frame: magic");
        CHECK(fz_get32(r + 8) == fz_get32(c->frame + 8), "reply frame: seq");
        CHECK(fz_get64(r + 16) == SESSION, "reply frame: session");
        CHECK(fz_get64(r + 24) == fz_get64(c->frame + 24), "reply frame: counter echo");
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
        uint32_t ack = fz_get32(r);
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

