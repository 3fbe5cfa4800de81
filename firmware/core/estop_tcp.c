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
        /*@ assert slot_set: slots_ok(core); */
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
/*@ requires \valid_read(core) && \valid(out) && \separated(out, core);
    assigns out->reply[0 .. 15], out->reply_len, out->has_reply;
    ensures out->has_reply == 1 && out->reply[11] == nak_code;
    ENSURES_REPLY_KEEPS(plain_reply)
    ENSURES_HEADS_KEPT(plain_reply)
 */
static void reply_plain(const estop_core_t *core, uint32_t seq, uint8_t nak_code, estop_out_t *out)
{
    reply_head(core, out->reply, seq, nak_code);
    wr_u32le(&out->reply[12], estop_crc32(out->reply, 12u));
    out->reply_len = (uint8_t)ESTOP_TCP_FRAME_LEN;
    out->has_reply = 1u;
}

/* Section 5.3: the last 24 bytes of a reply r to the request frame in slot k: the request's
 * counter as it came, then the tag over the request's tag and r's first 32 bytes (zero
 * without a key, or when the MAC cannot be made: no tag rather than a stale one). The key
 * state's digest length (at most 16: the invariant's) is estop_b2s_mac's precondition. The
 * slot's bytes are read here alone: under Typed, the validity of a range of the slot in the
 * context of reply_request's goals ran its keeps of the invariant out of their time (issue
 * 24's thirty-sixth round). */
/*@ requires \valid_read(core) && k < 8 && \valid(r + (0 .. 47));
    requires \separated(r + (0 .. 47), core);
    requires core->mac.outlen <= 16;
    assigns r[24 .. 47];
 */
static void reply_tail(const estop_core_t *core, uint32_t k, uint8_t *r)
{
    const uint8_t *req = core->slots[k].buf;
    copy_bytes(&r[24], &req[24], 8u); /* the request's counter, as it came */
    if (core->cfg.key_len != 0u) {
        uint8_t m[ESTOP_TAG_LEN + REQUEST_TAG_AT];
        copy_bytes(m, &req[REQUEST_TAG_AT], ESTOP_TAG_LEN);
        copy_bytes(&m[ESTOP_TAG_LEN], r, REQUEST_TAG_AT);
        if (estop_b2s_mac(&core->mac, m, sizeof m, &r[REQUEST_TAG_AT]) != 0) {
            zero_bytes(&r[REQUEST_TAG_AT], ESTOP_TAG_LEN);
        }
    } else {
        zero_bytes(&r[REQUEST_TAG_AT], ESTOP_TAG_LEN);
    }
}

/* Section 5.3: the first 24 bytes of a reply r to the request frame in slot k: the reply's
 * magic, the fields shared with the plain reply, the session. A function of
 * its own, as reply_tail: reply_request's keeps past its writes one range at a time. */
/*@ requires \valid_read(core) && k < 8 && \valid(r + (0 .. 47));
    requires \separated(r + (0 .. 47), core);
    assigns r[0 .. 23];
    ensures r[15] == nak_code;
 */
static void reply_front(const estop_core_t *core, uint32_t k, uint8_t nak_code, uint8_t *r)
{
    wr_u32le(r, ESTOP_MAGIC_REPLY);
    reply_head(core, &r[4], rd_u32le(&core->slots[k].buf[8]), nak_code);
    wr_u64le(&r[16], core->cfg.session);
}

/* Section 5.3: the 48-byte reply to the request frame in slot k. Its tag made by a function of its own: under Typed, what the reply keeps of the core and of out's frames was not found
 * past the merge of the tag's branches (issue 24's thirty-first round). The slot by its index,
 * here and in reply_tail, not a pointer to its bytes: under Typed, a caller that passed the
 * pointer had its frame's 48 bytes' validity in the context of every goal past the call, and
 * its rules over slot k ran out of their time (issue 24's thirty-fifth and thirty-sixth
 * rounds). */
/*@ requires \valid_read(core) && \valid(out) && \separated(out, core) && k < 8;
    requires core->mac.outlen <= 16;
    assigns out->reply[0 .. 47], out->reply_len, out->has_reply;
    ensures out->has_reply == 1 && out->reply[15] == nak_code;
    ENSURES_REPLY_KEEPS(request_reply)
    ENSURES_SLOT_KEPT(request_reply)
    ENSURES_WORD_KEPT(request_reply, 4)
    ensures request_reply_fills_kept: \forall integer j; a_slot(j) ==>
        core->slots[j].fill == \old(core->slots[j].fill);
 */
static void reply_request(const estop_core_t *core, uint32_t k, uint8_t nak_code,
                          estop_out_t *out)
{
    uint8_t *r = out->reply;
    reply_front(core, k, nak_code, r);
    reply_tail(core, k, r);
    out->reply_len = (uint8_t)ESTOP_REPLY_MAX;
    out->has_reply = 1u;
}

/* Section 2: the step of a plain frame's message msg_id. A plain RELEASE is authenticated
 * only on a unit without a key. A function of its own, apart from the reply: its rules in the
 * context of the step alone (under Typed, in one function with the reply they ran out of 60 s
 * once the callees stated what they keep: issue 24's thirty-first round). */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires out->n_can <= 3;
    assigns core->counters, core->status_auth_failed, core->valid_run, core->state,
            core->reason, core->slow_run, core->status_stops, core->status_slowdowns,
            core->brake_counter, core->brake_due_us, out->can[0 .. 2], out->n_can,
            out->state_changed;
    ENSURES_KEPT(plain_step)
    ENSURES_HEADS_KEPT(plain_step)
    ensures plain_step_frames: out->n_can <= 3;
    ensures plain_step_release: \old(core->state) == 0 && core->state != 0 ==>
        msg_id == ESTOP_MSG_RELEASE && core->cfg.key_len == 0 && \result == 0;
    ENSURES_STEP_STOPS(plain_step_stops, stop_asked(msg_id, \old(core->cfg.stop_id)))
    ENSURES_STOP_BRAKES_AT(plain_step_brakes)
 */
static uint8_t plain_step(estop_core_t *core, uint32_t msg_id, estop_out_t *out)
{
    if ((msg_id == ESTOP_MSG_RELEASE) && (core->cfg.key_len != 0u)) {
        estop__unauthenticated(core); /* the key holder's RELEASE is a request frame */
    }
    return estop__handle_msg(core, msg_id, core->cfg.key_len == 0u, out);
}

/* Section 2: one whole 16-byte plain frame with a good CRC, in slot k: its step, then its
 * reply. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires k < 8 && out->n_can <= 3;
    assigns core->counters, core->status_auth_failed, core->valid_run, core->state,
            core->reason, core->slow_run, core->status_stops, core->status_slowdowns,
            core->brake_counter, core->brake_due_us, out->can[0 .. 2], out->n_can,
            out->state_changed, out->reply[0 .. 47], out->reply_len, out->has_reply;
    ENSURES_KEPT(plain)
    ENSURES_SLOT_KEPT(plain)
    ENSURES_WORD_KEPT(plain, 0)
    ensures plain_frames: out->n_can <= 3;
    ensures plain_release: \old(core->state) == 0 && core->state != 0 ==>
        out->has_reply == 1 && core->cfg.key_len == 0 && out->reply[11] == 0 &&
        \old(rd_u32le_l(&core->slots[k].buf[0])) == ESTOP_MSG_RELEASE;
    ENSURES_STOPS(plain_stops,
                  stop_asked(\old(rd_u32le_l(&core->slots[k].buf[0])), \old(core->cfg.stop_id)),
                  11)
    ENSURES_STOP_BRAKES_AT(plain_stop_brakes)
 */
static void handle_plain(estop_core_t *core, uint32_t k, estop_out_t *out)
{
    const uint8_t *f = core->slots[k].buf;
    const uint32_t msg_id = rd_u32le(f);
    const uint32_t seq = rd_u32le(&f[4]);
    const uint8_t nak = plain_step(core, msg_id, out);
    reply_plain(core, seq, nak, out);
}

/* A slot's word (rd_u32le_l, a function of the whole byte memory under Typed) as the value of
 * its four bytes, at the state of the call: a caller that calls it before and after steps that
 * keep those bytes has the word kept. */
/*@ ghost
  /@ requires \valid_read(c) && k < 8 && at <= 44;
     assigns \nothing;
     ensures word_is_bytes: rd_u32le_l(&c->slots[k].buf[at]) == u32le_v(&c->slots[k].buf[at]);
   @/
  void word_at(const estop_core_t *c, uint32_t k, uint32_t at) { }
 */

/* Section 5.2: the verdict on the request frame in slot k, of message msg_id: AUTH_NOT_ASKED
 * unless it is a RELEASE on a unit with a key (estop__auth_verdict). Writes nothing: the
 * authentication's writes to the core come after the message's step (commit_request). Under
 * Typed, a step past those writes (the remote table, a range of the core) had 4 of its 42
 * rules run out of 60 s: WP's simplifier read through the range on the hypotheses' side and
 * dropped them, and the solvers did not find the range apart from the slots (issue 24's
 * thirty-fifth round). Past the step, the simplifier reads through it on the goal's side. */
/*@ requires \valid(core) && core->magic == 0x45535450 && inv(core);
    requires k < 8 && msg_id == rd_u32le_l(&core->slots[k].buf[4]);
    assigns \nothing;
    ensures release_verdict_range: \result <= 6;
    ensures release_verdict_tag: \result == 0 ==> msg_id == ESTOP_MSG_RELEASE &&
        core->cfg.key_len != 0 && tag_made(core, &core->slots[k].buf[0], 32);
    ensures release_verdict_fresh: \result == 0 ==> request_fresh(core, core->slots[k].buf);
 */
static uint32_t release_verdict(estop_core_t *core, uint32_t k, uint32_t msg_id)
{
    uint32_t verdict = AUTH_NOT_ASKED;
    if ((msg_id == ESTOP_MSG_RELEASE) && (core->cfg.key_len != 0u)) {
        verdict = estop__auth_verdict(core, core->slots[k].buf, REQUEST_TAG_AT, REQUEST_IDS_AT,
                                      CHANNEL_TCP);
    }
    return verdict;
}

/* Section 5.2: what the verdict on the request frame in slot k leaves in the core (the remote
 * id and counter at REQUEST_IDS_AT, read here). stopped: the unit was STOPPED before the
 * frame's step. A function of its own, always called (AUTH_NOT_ASKED writes nothing): under
 * Typed, a call under a branch merged with the branch that skips it, and every rule past the
 * merge ran out of its time (issue 24's thirty-fifth round). */
/*@ requires \valid(core) && \valid_read(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires k < 8;
    assigns core->remotes[0 .. 7], core->counters, core->status_auth_failed,
            core->tag_window_us, core->tag_window_open, core->newcomer_checks;
    ENSURES_KEPT(request_commit)
    ENSURES_SLOT_KEPT(request_commit)
    ENSURES_WORD_KEPT(request_commit, 4)
    ensures request_commit_state: core->state == \old(core->state);
    ensures request_commit_fills: \forall integer j; a_slot(j) ==>
        core->slots[j].fill == \old(core->slots[j].fill);
    ensures request_commit_out: out->n_can == \old(out->n_can) && frames_kept(Pre, Post, out, 3);
 */
static void commit_request(estop_core_t *core, uint32_t k, uint32_t verdict, int stopped,
                           const estop_out_t *out)
{
    (void)out; /* named by the contract: the frames the step left in out are kept */
    const uint8_t *f = core->slots[k].buf;
    /* request_commit_words from the bytes kept, as in request_step (10 to 12 s; 0.4 s). */
    /*@ ghost word_at(core, k, 4); */
    estop__auth_commit(core, rd_u32le(&f[REQUEST_IDS_AT]), rd_u64le(&f[REQUEST_IDS_AT + 12u]),
                       CHANNEL_TCP, verdict, stopped);
    /*@ ghost word_at(core, k, 4); */
}

/* Section 5.2: a request frame's message step (estop__handle_msg), with only what
 * request_step reads of it: under Typed, request_step's keeps of the slots past
 * estop__handle_msg's own clauses ran out of 60 s, in the context of all of them. out's frames
 * first in its assigns (WP's writes are in the list's order, the first the outermost), so that
 * the fields' writes lie under that range's (issue 24's thirty-sixth round). */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires out->n_can <= 3;
    assigns out->can[0 .. 2], core->counters, core->valid_run, core->state, core->reason,
            core->slow_run, core->status_stops, core->status_slowdowns, core->brake_counter,
            core->brake_due_us, out->n_can, out->state_changed;
    ENSURES_KEPT(msg_step)
    ENSURES_HEADS_KEPT(msg_step)
    ensures msg_step_frames: out->n_can <= 3;
    ensures msg_step_release: \old(core->state) == 0 && core->state != 0 ==>
        msg_id == ESTOP_MSG_RELEASE && authenticated != 0 && \result == 0;
    ENSURES_STEP_STOPS(msg_step_stops,
                       stop_asked(msg_id, \old(core->cfg.stop_id)) && msg_id != ESTOP_MSG_RELEASE)
    ENSURES_STOP_BRAKES_AT(msg_step_brakes)
 */
static uint8_t msg_step(estop_core_t *core, uint32_t msg_id, int authenticated, estop_out_t *out)
{
    const uint8_t nak = estop__handle_msg(core, msg_id, authenticated, out);
    /* Every slot's first bytes, named (from estop__handle_msg's clause over slot and byte). */
    /*@ assert stepped_heads: \forall integer j; 0 <= j < 8 ==> head_kept(Pre, Here, core, j); */
    return nak;
}

/* Section 5.2: the step of a request frame's message msg_id (its ID, in slot k). Only a
 * RELEASE needs authentication, and only on a unit with a key; a STOP or LIFT is honoured and
 * a STATUS answered whatever the tag says. The verdict first, then the message's step, then
 * the verdict's writes. A function of its own, apart from the reply, as plain_step. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires k < 8 && out->n_can <= 3 && msg_id == rd_u32le_l(&core->slots[k].buf[4]);
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks, core->valid_run,
            core->state, core->reason, core->slow_run, core->status_stops, core->status_slowdowns,
            core->brake_counter, core->brake_due_us, out->can[0 .. 2], out->n_can,
            out->state_changed;
    ENSURES_KEPT(request_step)
    ENSURES_SLOT_KEPT(request_step)
    ENSURES_WORD_KEPT(request_step, 4)
    ensures request_step_fills_kept: \forall integer j; a_slot(j) ==>
        core->slots[j].fill == \old(core->slots[j].fill);
    ensures request_step_frames: out->n_can <= 3;
    ensures request_step_release: \old(core->state) == 0 && core->state != 0 ==>
        msg_id == ESTOP_MSG_RELEASE && core->cfg.key_len != 0 && \result == 0 &&
        \at(tag_made(core, &core->slots[k].buf[0], 32), Pre);
    ensures request_step_fresh: \old(core->state) == 0 && core->state != 0 ==>
        \at(request_fresh(core, core->slots[k].buf), Pre);
    ENSURES_STEP_STOPS(request_step_stops,
                       stop_asked(msg_id, \old(core->cfg.stop_id)) && msg_id != ESTOP_MSG_RELEASE)
    ENSURES_STOP_BRAKES_AT(request_step_brakes)
 */
static uint8_t request_step(estop_core_t *core, uint32_t k, uint32_t msg_id, estop_out_t *out)
{
    const uint32_t verdict = release_verdict(core, k, msg_id);
    uint8_t nak;
    /* The message ID's word as its bytes' value before the steps and after them (word_at), so
     * that request_step_words follows from the bytes kept: left to the solvers it took 38 to
     * 47 s in make prove's runs, failed its 90 s alone and under another allocator; 0.15 s. */
    /*@ ghost word_at(core, k, 4); */
    commit_request(core, k, verdict, (core->state == ESTOP_STATE_STOPPED) ? 1 : 0, out);
    nak = msg_step(core, msg_id, (verdict == AUTH_OK) ? 1 : 0, out);
    /* The fills past both calls, a_slot named in the goal, where commit_request's clause
     * (request_commit_fills) is found from it. */
    /*@ assert stepped_fills: \forall integer j; 0 <= j < 8 ==>
            a_slot(j) && core->slots[j].fill == \at(core->slots[j].fill, Pre); */
    /* After stepped_fills, not before: right after msg_step, its hypotheses made that
     * assertion run out of 90 s. */
    /*@ ghost word_at(core, k, 4); */
    return nak;
}

/* Section 5.2: one whole 48-byte request frame, in slot k: its step, then its reply. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires k < 8 && out->n_can <= 3;
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks, core->valid_run,
            core->state, core->reason, core->slow_run, core->status_stops, core->status_slowdowns,
            core->brake_counter, core->brake_due_us, out->can[0 .. 2], out->n_can,
            out->state_changed, out->reply[0 .. 47], out->reply_len, out->has_reply;
    ENSURES_KEPT(request)
    ENSURES_SLOT_KEPT(request)
    ENSURES_WORD_KEPT(request, 0)
    ENSURES_WORD_KEPT(request, 4)
    ensures request_frames: out->n_can <= 3;
    ensures request_release: \old(core->state) == 0 && core->state != 0 ==>
        out->has_reply == 1 && core->cfg.key_len != 0 && out->reply[15] == 0 &&
        rd_u32le_l(&core->slots[k].buf[4]) == ESTOP_MSG_RELEASE &&
        \at(core->mac.outlen == 16 && tag_ok(&core->mac, core->slots[k].buf, 32), Pre);
    ensures request_release_fresh: \old(core->state) == 0 && core->state != 0 ==>
        \at(request_fresh(core, core->slots[k].buf), Pre);
    ENSURES_STOPS(request_stops, request_asks_stop(core->slots[k].buf, \old(core->cfg.stop_id)),
                  15)
    ENSURES_STOP_BRAKES_AT(request_stop_brakes)
 */
static void handle_request(estop_core_t *core, uint32_t k, estop_out_t *out)
{
    const uint32_t msg_id = rd_u32le(&core->slots[k].buf[4]);
    const uint8_t nak = request_step(core, k, msg_id, out);
    reply_request(core, k, nak, out);
    /* The fills past both calls, as in request_step (stepped_fills). */
    /*@ assert replied_fills: \forall integer j; 0 <= j < 8 ==>
            a_slot(j) && core->slots[j].fill == \at(core->slots[j].fill, Pre); */
}

/* A frame's length, known once its first 4 bytes are in. */
static uint32_t frame_len(const estop_slot_t *s)
{
    return ((s->fill >= MAGIC_LEN) && (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST))
               ? ESTOP_REQ_FRAME_LEN
               : PLAIN_FRAME_LEN;
}

/* Appends bytes to a slot, up to one whole frame: first its 4 magic bytes, which decide its
 * length, then the rest of it. Each loop bounds both indexes itself (fill below the frame's
 * length, at most 48; take below len). Returns 1, with the slot empty again and the frame in
 * its buffer, when the frame is whole; *took is how many bytes it took. A slot holding part
 * of a frame that this call does not complete takes every byte of the call (take_rest), so
 * no whole frame is left behind in the call's bytes. */
/*@ requires \valid(s) && \valid(took) && s->fill < 48 && \valid_read(data + (0 .. len - 1));
    requires \separated(s, took, data + (0 .. len - 1));
    assigns s->fill, s->buf[0 .. 47], *took;
    TAKE_ENSURES(take, s)
 */
static int take_frame(estop_slot_t *s, const uint8_t *data, size_t len, size_t *took)
{
    size_t take = 0u;
    uint32_t need;
    int whole = 0;
    /*@ loop invariant 0 <= take <= len && s->fill <= 47;
        loop invariant fill_took: s->fill == \at(s->fill, Pre) + take;
        loop invariant kept: \forall integer i; 0 <= i < \at(s->fill, Pre) ==>
            s->buf[i] == \at(s->buf[i], Pre);
        loop invariant copied: \forall integer i; 0 <= i < take ==>
            s->buf[\at(s->fill, Pre) + i] == data[i];
        loop invariant head: \at(s->fill, Pre) >= 4 ==> take == 0;
        loop invariant head_only: \at(s->fill, Pre) < 4 ==> s->fill <= 4;
        loop assigns take, s->fill, s->buf[0 .. 47];
        loop variant len - take;
     */
    while ((take < len) && (s->fill < MAGIC_LEN)) {
        s->buf[s->fill] = data[take];
        s->fill++;
        take++;
    }
    need = frame_len(s);
    /* A frame's first 4 bytes, already in before the call, are as they were: its length too
     * (the solvers do not find this through the logic function on their own). */
    /*@ assert head_kept: \at(s->fill, Pre) >= 4 ==>
            s->buf[0] == \at(s->buf[0], Pre) && s->buf[1] == \at(s->buf[1], Pre) &&
            s->buf[2] == \at(s->buf[2], Pre) && s->buf[3] == \at(s->buf[3], Pre); */
    /*@ assert head_need: \at(s->fill, Pre) >= 4 ==> slot_need(s) == \at(slot_need(s), Pre); */
    /*@ loop invariant 0 <= take <= len && need <= 48 && (s->fill <= 47 || s->fill == need);
        loop invariant fill_took: s->fill == \at(s->fill, Pre) + take;
        loop invariant kept: \forall integer i; 0 <= i < \at(s->fill, Pre) ==>
            s->buf[i] == \at(s->buf[i], Pre);
        loop invariant copied: \forall integer i; 0 <= i < take ==>
            s->buf[\at(s->fill, Pre) + i] == data[i];
        loop invariant headed: take < len ==> s->fill >= 4;
        loop invariant need_form: s->fill >= 4 ==> need == slot_need(s);
        loop invariant partial: \at(slot_partial(s), Pre) ==> s->fill < 4 || s->fill <= need;
        loop assigns take, s->fill, s->buf[0 .. 47];
        loop variant len - take;
     */
    while ((take < len) && (s->fill < need)) {
        s->buf[s->fill] = data[take];
        s->fill++;
        take++;
    }
    if (s->fill == need) {
        s->fill = 0u;
        whole = 1;
    }
    *took = take;
    return whole;
}

/* take_frame on slot k, with what estop_tcp_rx's assertions read of the core and of out stated
 * kept. Past take_frame's writes to the slot's 48 bytes, in the entry point's whole context,
 * the solvers had to tell each byte they read of the core and of out from those 48 (taken_stop
 * 23 s alone on the idle machine, the six taken_* assertions 50 CPU-s; 4 with the bytes left
 * out of take_frame's assigns: issue 24's forty-sixth round). Here the context is
 * take_frame's contract alone. out is read by the contract only. */
/*@ requires \valid(core) && \valid_read(out) && \separated(core, out) && k < 8;
    requires \valid(took) && \separated(took, core, out);
    requires core->slots[k].fill < 48 && \valid_read(data + (0 .. len - 1));
    requires \separated(&core->slots[k], took, data + (0 .. len - 1));
    assigns core->slots[k].fill, core->slots[k].buf[0 .. 47], *took;
    TAKE_ENSURES(fill, &core->slots[k])
    ENSURES_REPLY_KEEPS(fill)
    ensures fill_keeps: core->reason == \old(core->reason) &&
        core->link_fresh == \old(core->link_fresh) && core->magic == \old(core->magic) &&
        core->now_us == \old(core->now_us) && out->has_reply == \old(out->has_reply);
 */
static int fill_slot(estop_core_t *core, uint32_t k, const uint8_t *data, size_t len,
                     size_t *took, const estop_out_t *out)
{
    (void)out; /* the contract's */
    return take_frame(&core->slots[k], data, len, took);
}

/* One whole frame in slot k, of either form. Returns 1 when the stream has lost framing (a
 * plain frame with a bad CRC): nothing after it can be trusted, and the slot is closed. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    requires core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires k < 8 && out->n_can <= 3;
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks, core->valid_run,
            core->state, core->reason, core->slow_run, core->status_stops, core->status_slowdowns,
            core->brake_counter, core->brake_due_us, core->slots[k].open, out->can[0 .. 2],
            out->n_can, out->state_changed, out->reply[0 .. 47], out->reply_len,
            out->has_reply, out->close_slot;
    ensures frame_inv: core->magic == 0x45535450;
    ensures frame_keeps: core->now_us == \old(core->now_us) &&
        core->cfg.stop_id == \old(core->cfg.stop_id) &&
        core->cfg.brake_can_id == \old(core->cfg.brake_can_id) &&
        core->cfg.brake_period_us == \old(core->cfg.brake_period_us);
    ENSURES_KEPT(frame)
    ensures frame_out: out->n_can <= 3;
    ensures frame_release: \old(core->state) == 0 && core->state != 0 ==>
        out->has_reply == 1 && core->slots[k].fill == \old(core->slots[k].fill) &&
        ((core->cfg.key_len == 0 && out->reply[11] == 0 &&
          rd_u32le_l(&core->slots[k].buf[0]) == ESTOP_MSG_RELEASE &&
          \at(plain_crc_ok(core->slots[k].buf), Pre)) ||
         (core->cfg.key_len != 0 && out->reply[15] == 0 &&
          rd_u32le_l(&core->slots[k].buf[0]) == ESTOP_MAGIC_REQUEST &&
          rd_u32le_l(&core->slots[k].buf[4]) == ESTOP_MSG_RELEASE &&
          \at(core->mac.outlen == 16 && tag_ok(&core->mac, core->slots[k].buf, 32), Pre)));
    ensures frame_release_fresh: \old(core->state) == 0 && core->state != 0 &&
        core->cfg.key_len != 0 ==> \at(request_fresh(core, core->slots[k].buf), Pre);
    ENSURES_STOPS(frame_stops, \old(out->has_reply) == 0 && out->has_reply == 1 &&
                  request_asks_stop(core->slots[k].buf, \old(core->cfg.stop_id)), 15)
    ENSURES_STOPS(frame_stops, \old(out->has_reply) == 0 && out->has_reply == 1 &&
                  plain_asks_stop(core->slots[k].buf, \old(core->cfg.stop_id)), 11)
    ENSURES_STOP_BRAKES(frame_stop_brakes)
 */
static int handle_frame(estop_core_t *core, uint32_t k, estop_out_t *out)
{
    const uint8_t *f = core->slots[k].buf;
    int broken = 0;
    if (rd_u32le(f) == ESTOP_MAGIC_REQUEST) {
        handle_request(core, k, out);
    } else if (estop_crc32(f, 12u) == rd_u32le(&f[12])) {
        handle_plain(core, k, out);
    } else {
        sat32_inc(&core->counters.tcp_bad_crc);
        core->slots[k].open = 0u;
        out->close_slot = 1u;
        broken = 1;
    }
    return broken;
}

/* estop__finish past a frame of slot k, with what the release rule reads of the reply and of
 * the slot stated kept. Asked of the solvers in estop_tcp_rx's context (its path's every
 * assertion a hypothesis), even one byte kept across estop__finish took 11 s and the reply's
 * flag ran out of 90 s; leaves_stopped_only_by_release (19 s in one make prove) ran out of 90
 * s and of the retry's 300 s in another (issue 24's forty-third round, the CI run of
 * fcfba03). Here the context is this contract alone. core is not const: estop__finish
 * requires \valid(core), which Eva found invalid through a pointer to const. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && k < 8;
    FINISH_CONTRACT
    ensures frame_finish_keeps: out->has_reply == \old(out->has_reply) &&
        out->reply[11] == \old(out->reply[11]) && out->reply[15] == \old(out->reply[15]) &&
        core->slots[k].fill == \old(core->slots[k].fill) &&
        core->cfg.key_len == \old(core->cfg.key_len);
    ensures frame_finish_words:
        rd_u32le_l(&core->slots[k].buf[0]) == \old(rd_u32le_l(&core->slots[k].buf[0])) &&
        rd_u32le_l(&core->slots[k].buf[4]) == \old(rd_u32le_l(&core->slots[k].buf[4]));
 */
static void finish_frame(estop_core_t *core, uint32_t k, estop_out_t *out)
{
    (void)k; /* the slot of the contract and the ghost calls */
    /*@ ghost word_at(core, k, 0); */
    /*@ ghost word_at(core, k, 4); */
    estop__finish(core, out);
    /*@ ghost word_at(core, k, 0); */
    /*@ ghost word_at(core, k, 4); */
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
        /* Refused only for a slot closed when the call came (estop__begin keeps the flags). */
        /*@ assert closed_at_call: \at(core->slots[slot].open, Pre) == 0; */
        estop__finish(core, out);
    }
    if (err == ESTOP_OK) {
        size_t take = 0u;
        const int whole = fill_slot(core, slot, data, len, &take, out);
        /*@ ghost uint8_t taken_state = core->state; */
        /*@ assert taken_inv: cfg_ok(core) && core->magic == 0x45535450; */
        /*@ assert taken_inv: known_ok(core); */
        /*@ assert taken_inv: fresh_ok(core); */
        /*@ assert taken_inv: slots_ok(core); */
        /*@ assert taken_times: times_ok(core); */
        /*@ assert taken_state: \at(core->state, Pre) == 0 ==> core->state == 0; */
        /*@ assert taken_now: core->now_us == now_us; */
        /*@ assert taken_whole: whole != 0 ==> core->slots[slot].fill == 0; */
        /*@ assert taken_out: out->has_reply == 0 && out->n_can <= 2; */
        /*@ assert taken_stop: \at(core->state, Pre) != 0 && core->state == 0 ==>
                1 <= out->n_can && emergency(out, 0, core); */
        /* The state the frame is handled in: handle_frame states the tag's rule there, so no
         * goal reads the frame's 48 bytes and the key through the handling's writes (past
         * them, handled_release ran out of 150 s with both solvers). */
        /*@ ghost framed: ; */
        if ((whole != 0) && (handle_frame(core, slot, out) != 0)) {
            take = len; /* the rest of a broken stream is dropped */
        }
        /* slots_ok past the merge, one branch at a time: asserted whole, the solvers split
         * the merged memory themselves (40 s, into the 150-s retry on a busy machine). */
        /*@ assert framed_slots: whole != 0 ==> slots_ok(core); */
        /*@ assert framed_slots: whole == 0 ==> slots_ok(core); */
        /*@ assert handled_inv: cfg_ok(core) && core->magic == 0x45535450; */
        /*@ assert handled_inv: known_ok(core); */
        /*@ assert handled_inv: fresh_ok(core); */
        /*@ assert handled_inv: slots_ok(core); */
        /*@ assert handled_times: times_ok(core); */
        /*@ assert handled_release: \at(core->state, Pre) == 0 && core->state != 0 ==>
                out->has_reply == 1 && core->slots[slot].fill == 0 &&
                ((core->cfg.key_len == 0 && out->reply[11] == 0 &&
                  rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MSG_RELEASE &&
                  \at(plain_crc_ok(core->slots[slot].buf), framed)) ||
                 (core->cfg.key_len != 0 && out->reply[15] == 0 &&
                  rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MAGIC_REQUEST &&
                  rd_u32le_l(&core->slots[slot].buf[4]) == ESTOP_MSG_RELEASE &&
                  \at(core->mac.outlen == 16 &&
                      tag_ok(&core->mac, core->slots[slot].buf, 32), framed))); */
        /*@ assert handled_release_fresh: \at(core->state, Pre) == 0 && core->state != 0 &&
                core->cfg.key_len != 0 ==> \at(request_fresh(core, core->slots[slot].buf), framed); */
        *consumed = take;
        /* The stop rules of a TCP frame for this entry point, here before estop__finish (which
         * writes neither the state, the frames nor the reply): a whole frame this call
         * answered that asks a stop leaves the unit STOPPED with the ACK, and a unit moving
         * at the call's start with an emergency frame, the clock's first or this frame's last.
         * As ensures clauses past estop__finish they took CVC4 25 to 55 s each under Caveat,
         * one failed at 150 s (docs/PROOF.md). */
        /*@ assert handled_stop: out->has_reply == 1 &&
                request_asks_stop(core->slots[slot].buf, core->cfg.stop_id) ==>
                core->state == 0 && out->reply[15] == 0; */
        /*@ assert handled_stop: out->has_reply == 1 &&
                plain_asks_stop(core->slots[slot].buf, core->cfg.stop_id) ==>
                core->state == 0 && out->reply[11] == 0; */
        /*@ assert handled_clock_brake: out->has_reply == 1 && taken_state == 0 &&
                \at(core->state, Pre) != 0 &&
                (request_asks_stop(core->slots[slot].buf, core->cfg.stop_id) ||
                 plain_asks_stop(core->slots[slot].buf, core->cfg.stop_id)) ==>
                1 <= out->n_can && emergency(out, 0, core); */
        /*@ assert handled_stop_brake: taken_state != 0 && core->state == 0 ==>
                1 <= out->n_can && emergency(out, out->n_can - 1, core); */
        /*@ assert handled_now: core->now_us == now_us; */
        /* estop__finish with what the release rule reads stated kept (finish_frame), and the
         * rule past it here, at the end of this branch: leaves_stopped_only_by_release then
         * reads it from this assertion alone (about 3 s in every order of its problem). */
        finish_frame(core, slot, out);
        /*@ assert finished_release: \at(core->state, Pre) == 0 && core->state != 0 ==>
                out->has_reply == 1 && core->slots[slot].fill == 0 &&
                ((core->cfg.key_len == 0 && out->reply[11] == 0 &&
                  rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MSG_RELEASE) ||
                 (core->cfg.key_len != 0 && out->reply[15] == 0 &&
                  rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MAGIC_REQUEST &&
                  rd_u32le_l(&core->slots[slot].buf[4]) == ESTOP_MSG_RELEASE)); */
    }
    return err;
}
