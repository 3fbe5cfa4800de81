/*
 * estop_tcp: TCP connection slots, frame reassembly and replies (PROTOCOL.md sections 2 and
 * 5.2-5.3). Bytes arrive for a slot in pieces; each whole frame is handled once (a plain
 * 16-byte frame or a 48-byte request frame) and answered with one reply.
 */
#include "estop_core.h"

#include "estop_crc.h"
#include "estop_internal.h"

#define PLAIN_FRAME_LEN ESTOP_TCP_FRAME_LEN
#define MAGIC_LEN 4u               /* the first bytes of a frame decide its form */
#define REQUEST_IDS_AT 12u         /* 5.2: remote id, session, counter from byte 12 */
#define REQUEST_TAG_AT 32u         /* 5.2: the tag covers bytes 0..31 */

static estop_err_t check_slot(const estop_core_t *core, uint32_t slot)
{
    estop_err_t err = ESTOP_OK;
    if (core == NULL) {
        err = ESTOP_ERR_NULL_ARG;
    } else if (slot >= ESTOP_MAX_SLOTS) {
        err = ESTOP_ERR_SLOT;
    } else {
        /* a slot in range: err stays ESTOP_OK */
    }
    return err;
}

/* Opening and closing a slot both start it empty; only the open mark differs. */
static estop_err_t set_slot(estop_core_t *core, uint32_t slot, uint8_t open, uint32_t now_us,
                            estop_out_t *out)
{
    estop_err_t err = check_slot(core, slot);
    if (err == ESTOP_OK) {
        err = estop__begin(core, now_us, out);
    }
    if (err == ESTOP_OK) {
        core->slots[slot].open = open;
        core->slots[slot].fill = 0u;
        estop__finish(core, out);
    }
    return err;
}

estop_err_t estop_tcp_open(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out)
{
    return set_slot(core, slot, 1u, now_us, out);
}

estop_err_t estop_tcp_close(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out)
{
    return set_slot(core, slot, 0u, now_us, out);
}

/* The reply fields shared by both forms: ACK/NAK, seq, state, reason, flags, nak code. */
static void reply_head(const estop_core_t *core, uint8_t *r, uint32_t seq, uint8_t nak_code)
{
    wr_u32le(r, (nak_code == ESTOP_NAK_NONE) ? ESTOP_MSG_ACK : ESTOP_MSG_NAK);
    wr_u32le(&r[4], seq);
    r[8] = core->state;
    r[9] = core->reason;
    r[10] = estop__current_flags(core);
    r[11] = nak_code;
}

/* Section 2: the 16-byte reply to a plain frame. */
static void reply_plain(const estop_core_t *core, uint32_t seq, uint8_t nak_code, estop_out_t *out)
{
    reply_head(core, out->reply, seq, nak_code);
    wr_u32le(&out->reply[12], estop_crc32(out->reply, 12u));
    out->reply_len = (uint8_t)ESTOP_TCP_FRAME_LEN;
    out->has_reply = 1u;
}

/* Section 5.3: the 48-byte reply to a request frame, tagged over the request's tag and the
 * reply's first 32 bytes (zero tag without a key, or when the MAC cannot be made). */
/*@ requires \valid_read(core) && \valid(out) && \valid_read(req + (0 .. 47));
    requires \separated(out, core, req + (0 .. 47));
    assigns out->reply[0 .. 47], out->reply_len, out->has_reply;
    ensures out->has_reply == 1 && out->reply[15] == nak_code;
 */
static void reply_request(const estop_core_t *core, const uint8_t *req, uint8_t nak_code,
                          estop_out_t *out)
{
    uint8_t *r = out->reply;
    wr_u32le(r, ESTOP_MAGIC_REPLY);
    reply_head(core, &r[4], rd_u32le(&req[8]), nak_code);
    wr_u64le(&r[16], core->cfg.session);
    wr_u64le(&r[24], rd_u64le(&req[24]));
    if (core->cfg.key_len != 0u) {
        uint8_t m[ESTOP_TAG_LEN + REQUEST_TAG_AT];
        copy_bytes(m, &req[REQUEST_TAG_AT], ESTOP_TAG_LEN);
        copy_bytes(&m[ESTOP_TAG_LEN], r, REQUEST_TAG_AT);
        if (estop_b2s_mac(&core->mac, m, sizeof m, &r[REQUEST_TAG_AT]) != 0) {
            zero_bytes(&r[REQUEST_TAG_AT], ESTOP_TAG_LEN); /* no tag rather than a stale one */
        }
    } else {
        zero_bytes(&r[REQUEST_TAG_AT], ESTOP_TAG_LEN);
    }
    out->reply_len = (uint8_t)ESTOP_REPLY_MAX;
    out->has_reply = 1u;
}

/* Section 2: one whole 16-byte plain frame. A plain RELEASE is authenticated only on a unit
 * without a key. */
static void handle_plain(estop_core_t *core, estop_slot_t *slot, estop_out_t *out)
{
    const uint8_t *f = slot->buf;
    if (estop_crc32(f, 12u) != rd_u32le(&f[12])) {
        /* The stream has lost framing: nothing after this can be trusted. */
        sat32_inc(&core->counters.tcp_bad_crc);
        slot->open = 0u;
        out->close_slot = 1u;
    } else {
        const uint32_t msg_id = rd_u32le(f);
        uint8_t nak;
        if ((msg_id == ESTOP_MSG_RELEASE) && (core->cfg.key_len != 0u)) {
            estop__unauthenticated(core); /* the key holder's RELEASE is a request frame */
        }
        nak = estop__handle_msg(core, msg_id, core->cfg.key_len == 0u, out);
        reply_plain(core, rd_u32le(&f[4]), nak, out);
    }
}

/* Section 5.2: one whole 48-byte request frame. Only a RELEASE needs authentication; a STOP or
 * LIFT is honoured and a STATUS answered whatever the tag says. */
static void handle_request(estop_core_t *core, const estop_slot_t *slot, estop_out_t *out)
{
    const uint8_t *f = slot->buf;
    uint32_t msg_id = rd_u32le(&f[4]);
    int authenticated = 0;
    uint8_t nak;
    if ((msg_id == ESTOP_MSG_RELEASE) && (core->cfg.key_len != 0u)) {
        authenticated =
            estop__authenticate(core, f, REQUEST_TAG_AT, REQUEST_IDS_AT, CHANNEL_TCP);
    }
    nak = estop__handle_msg(core, msg_id, authenticated, out);
    reply_request(core, f, nak, out);
}

/* A frame's length, known once its first 4 bytes are in. */
static uint32_t frame_len(const estop_slot_t *s)
{
    return ((s->fill >= MAGIC_LEN) && (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST))
               ? ESTOP_REQ_FRAME_LEN
               : PLAIN_FRAME_LEN;
}

estop_err_t estop_tcp_rx(estop_core_t *core, uint32_t slot, const uint8_t *data, size_t len,
                         size_t *consumed, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = check_slot(core, slot);
    if ((err == ESTOP_OK) && ((consumed == NULL) || ((data == NULL) && (len > 0u)))) {
        err = ESTOP_ERR_NULL_ARG;
    }
    if (err == ESTOP_OK) {
        *consumed = 0u;
        err = estop__begin(core, now_us, out);
    }
    if ((err == ESTOP_OK) && (core->slots[slot].open == 0u)) {
        err = ESTOP_ERR_SLOT_CLOSED;
        estop__finish(core, out);
    }
    if (err == ESTOP_OK) {
        estop_slot_t *s = &core->slots[slot];
        size_t take = 0u;
        uint32_t need;
        /* Up to one whole frame: first its 4 magic bytes, which decide its length, then the
         * rest of it. Each loop bounds both indexes itself (fill below the frame's length,
         * at most 48; take below len). */
        /*@ loop invariant 0 <= take <= len && s->fill <= 47;
            loop assigns take, s->fill, s->buf[0 .. 47];
            loop variant len - take;
         */
        while ((take < len) && (s->fill < MAGIC_LEN)) {
            s->buf[s->fill] = data[take];
            s->fill++;
            take++;
        }
        need = frame_len(s);
        /*@ loop invariant 0 <= take <= len && s->fill <= need;
            loop assigns take, s->fill, s->buf[0 .. 47];
            loop variant len - take;
         */
        while ((take < len) && (s->fill < need)) {
            s->buf[s->fill] = data[take];
            s->fill++;
            take++;
        }
        *consumed = take;
        if (s->fill == need) {
            s->fill = 0u;
            if (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST) {
                handle_request(core, s, out);
            } else {
                handle_plain(core, s, out);
            }
            if (out->close_slot != 0u) {
                *consumed = len; /* the rest of a broken stream is dropped */
            }
        }
        estop__finish(core, out);
    }
    return err;
}
