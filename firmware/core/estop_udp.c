/*
 * estop_udp: a UDP datagram's step (PROTOCOL.md sections 1 and 3): whether it is a stop
 * request (the stop ID or LIFT, which anyone may send), a valid control packet of the form the
 * unit expects (plain without a key, authenticated with one: estop_auth.c), or neither; and
 * what a valid packet does to the link and to a SLOWING unit. The entry point estop_udp_rx()
 * runs the three steps of every entry point (estop_core.c).
 */
#include "estop_core.h"

#include "estop_internal.h"

#define FLOAT_ONE_BITS 0x3F800000u  /* IEEE-754 single 1.0f */
#define FLOAT_ABS_MASK 0x7FFFFFFFu
#define FLOAT_SIGN_BIT 0x80000000u
#define CONTROL_BODY_AT 24u        /* 5.1: the control body inside an authenticated packet */
#define CONTROL_IDS_AT 4u          /* 5.1: remote id, session, counter from byte 4 */
#define CONTROL_TAG_AT 44u         /* 5.1: the tag covers bytes 0..43 */

/* A float32 (as raw bits) is finite and within -1.0 .. 1.0. NaN and infinities have a
 * magnitude above 1.0's bit pattern, so one comparison covers all three; no FPU needed. */
static int unit_range_bits(uint32_t bits)
{
    return (bits & FLOAT_ABS_MASK) <= FLOAT_ONE_BITS;
}

/* gas_brake <= 0: any negative value, -0.0 or +0.0. */
static int non_positive_bits(uint32_t bits)
{
    return ((bits & FLOAT_SIGN_BIT) != 0u) || (bits == 0u);
}

/* Section 1: every field of a control body's first 16 bytes in range: the whole body of the
 * 16-byte form. The forms with a horn word use horned_body_valid (a flag here would leave a
 * branch dead in each call WP inlines, which its smoke tests refuse). */
static int body_valid(const uint8_t *b)
{
    uint32_t gear = rd_u32le(&b[8]);
    uint32_t turn = rd_u32le(&b[12]);
    return unit_range_bits(rd_u32le(b)) && unit_range_bits(rd_u32le(&b[4])) &&
           ((gear == 1u) || (gear == 2u) || (gear == 4u) || (gear == 8u)) && (turn <= 3u);
}

/* Section 1: a control body with its horn word (the 20-byte plain packet's and the
 * authenticated packet's): the 16 bytes above in range, and the horn 0 or 1. */
static int horned_body_valid(const uint8_t *b)
{
    return body_valid(b) && (rd_u32le(&b[16]) <= 1u);
}

/* Section 1: a plain control packet (20 bytes, or 16 without the horn) with every field in
 * range. */
static int plain_valid(const uint8_t *d, size_t len)
{
    int ok = 0;
    if (len == ESTOP_UDP_LEN) {
        ok = horned_body_valid(d);
    } else if (len == ESTOP_UDP_LEN_NO_HORN) {
        ok = body_valid(d);
    } else {
        /* another length: not a plain control packet */
    }
    return ok;
}

/* Section 1: valid_body on a unit with a key: the control body of an authenticated control
 * packet, or NULL; plain: the datagram is a valid plain packet (counted as an authentication
 * failure). A function of its own so that valid_body's clauses meet one call past the plain
 * packet's checks, not its three branches (issue 24's forty-fifth round: past them
 * body_keeps_link and body_keeps_state took 16 to 19 s each beside make test's other steps,
 * and one ran out of 90 s in one order of its assertions in four). */
/*@ requires \valid(core) && \valid_read(d + (0 .. len - 1)) &&
        \separated(core, d + (0 .. len - 1));
    requires core->mac.outlen <= 16 && core->cfg.key_len != 0;
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks;
    ensures \result == \null || (\result == d + 24 && len == 60);
    ensures keyed_tagged: \result != \null ==> len == 60 && \at(datagram_keyed(core, d), Pre);
 */
static const uint8_t *keyed_body(estop_core_t *core, const uint8_t *d, size_t len, int plain)
{
    const uint8_t *body = NULL;
    if ((len == ESTOP_UDP_AUTH_LEN) && horned_body_valid(&d[CONTROL_BODY_AT])) {
        if (rd_u32le(d) != ESTOP_MAGIC_CONTROL) {
            estop__unauthenticated(core);
        } else if (estop__authenticate(core, d, CONTROL_TAG_AT, CONTROL_IDS_AT, CHANNEL_UDP) !=
                   0) {
            body = &d[CONTROL_BODY_AT];
        } else {
            /* counted by estop__authenticate: body stays NULL */
        }
    } else if (plain != 0) {
        estop__unauthenticated(core); /* a plain packet: the key holder's are tagged */
    } else {
        /* not a control packet at all: invalid, body stays NULL */
    }
    return body;
}

/* Section 1: the control body of a valid packet of the form the unit expects (plain without
 * a key, authenticated with one), or NULL. d is not NULL. With a key, a control packet whose
 * body is valid but that is not authenticated counts as an authentication failure (the body
 * is checked first: docs/PROTOCOL.md 5). */
/*@ requires \valid(core) && \valid_read(d + (0 .. len - 1)) &&
        \separated(core, d + (0 .. len - 1));
    requires core->mac.outlen <= 16;
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks;
    ensures \result == \null || (\result == d && len >= 16) || (\result == d + 24 && len == 60);
    ensures body_keeps_state: core->state == \old(core->state);
    ensures body_keeps_link: core->last_valid_us == \old(core->last_valid_us);
    ensures body_keeps_link: core->link_fresh == \old(core->link_fresh);
    ensures body_keeps_link: core->last_neutral == \old(core->last_neutral);
    ensures body_keeps_link: core->valid_run == \old(core->valid_run);
    ensures body_keyed: \result != \null && core->cfg.key_len != 0 ==> len == 60 &&
        \at(datagram_keyed(core, d), Pre);
 */
static const uint8_t *valid_body(estop_core_t *core, const uint8_t *d, size_t len)
{
    const uint8_t *body = NULL;
    const int plain = plain_valid(d, len); /* once: each call is another copy for WP */
    if (core->cfg.key_len == 0u) {
        if (plain != 0) {
            body = d;
        } else {
            /* no valid plain packet: body stays NULL */
        }
    } else {
        body = keyed_body(core, d, len, plain);
    }
    return body;
}

/* Section 1: a request frame with the stop ID or LIFT; returns its stop reason, or 0. Anyone may
 * stop, so its tag, session and counter are never looked at. d is not NULL. */
static uint8_t stop_datagram(const estop_core_t *core, const uint8_t *d, size_t len)
{
    uint8_t reason = (uint8_t)ESTOP_REASON_NONE;
    if ((len == ESTOP_REQ_FRAME_LEN) && (rd_u32le(d) == ESTOP_MAGIC_REQUEST)) {
        reason = estop__stop_reason(core, rd_u32le(&d[4]));
    }
    return reason;
}

/* Section 3: a SLOWING unit's way back to ARMED, at its third valid packet in a row (a step of
 * its own: its contract carries the core past the frame's write to out). */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv(core) && times_ok(core);
    requires core->state == 2 && core->last_valid_us == core->now_us && out->n_can <= 3;
    assigns core->counters.rearms, core->state, out->state_changed, out->can[0 .. 2],
            out->n_can, core->brake_counter, core->brake_due_us;
    ENSURES_KEPT(rearm)
    ensures rearm_arms: core->state == 1 && out->state_changed == 1;
    ensures rearm_frames: out->n_can <= 3;
    ensures rearm_keeps_clock: core->now_us == \old(core->now_us) &&
        core->magic == \old(core->magic) && core->link_fresh == \old(core->link_fresh) &&
        core->last_valid_us == \old(core->last_valid_us) &&
        core->cfg.key_len == \old(core->cfg.key_len);
 */
static void rearm(estop_core_t *core, estop_out_t *out)
{
    sat32_inc(&core->counters.rearms);
    core->state = (uint8_t)ESTOP_STATE_ARMED;
    estop__state_changed(core, out);
}

/* Section 3: a valid packet makes the link fresh from now; while SLOWING it counts toward the
 * way back to ARMED. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv(core) && times_ok(core);
    requires \valid_read(body + (0 .. 3)) && \separated(body + (0 .. 3), core, out);
    requires out->n_can <= 3;
    assigns core->gaps[0 .. 31], core->silences, core->gap_known, core->counters.udp_valid,
            core->counters.rearms, core->status_valid, core->valid_run, core->last_valid_us,
            core->link_fresh, core->last_neutral, core->slow_run, core->state,
            out->state_changed, out->can[0 .. 2], out->n_can, core->brake_counter,
            core->brake_due_us;
    ENSURES_KEPT(valid)
    ensures valid_frames: out->n_can <= 3;
    ensures valid_never_leaves_stopped: \old(core->state) == 0 ==> core->state == 0;
    ensures valid_keeps_clock: core->now_us == \old(core->now_us) &&
        core->magic == \old(core->magic);
    ensures valid_keeps_key: core->cfg.key_len == \old(core->cfg.key_len);
    ensures valid_fresh: core->link_fresh == 1 && core->last_valid_us == core->now_us;
    ensures valid_rearms: \old(core->state) == 2 &&
        ESTOP_REARM_PACKETS <= \old(core->slow_run) + 1 <= 255 ==> core->state == 1;
    ensures valid_slowing: \old(core->state) == 2 &&
        \old(core->slow_run) + 1 < ESTOP_REARM_PACKETS ==> core->state == 2;
    ensures valid_keeps_state: \old(core->state) != 2 ==> core->state == \old(core->state);
 */
static void take_valid(estop_core_t *core, const uint8_t *body, estop_out_t *out)
{
    /* The valid_step assertions hand the solvers the slots and the link's age a step at a
     * time: with them CVC4 alone proves every goal of take_valid (28 s idle); without, CVC4
     * took 49 s on valid_inv_3 and ran out of 90 s on valid_times_4 (Z3: 28 s). */
    estop__record_gap(core); /* core->now_us is now_us from here on */
    /*@ assert valid_step: slots_ok(core); */
    sat32_inc(&core->counters.udp_valid);
    core->status_valid = sat8_inc(core->status_valid);
    sat32_inc(&core->valid_run);
    /*@ assert valid_step: slots_ok(core); */
    core->last_valid_us = core->now_us;
    core->link_fresh = 1u;
    core->last_neutral = non_positive_bits(rd_u32le(body)) ? 1u : 0u;
    /*@ assert valid_step: slots_ok(core) && udiff(core->now_us, core->last_valid_us) == 0; */
    if (core->state == ESTOP_STATE_SLOWING) {
        core->slow_run++;
        if (core->slow_run >= ESTOP_REARM_PACKETS) {
            rearm(core, out);
        }
    }
}

estop_err_t estop_udp_rx(estop_core_t *core, const uint8_t *data, size_t len, uint32_t now_us,
                         estop_out_t *out)
{
    estop_err_t err = estop__begin(core, now_us, out);
    /*@ assert begun_stopped: core != \null ==> (\at(core->state, Pre) == 0 ==> core->state == 0); */
    if (err == ESTOP_OK) {
        const uint8_t *body = NULL;
        uint8_t reason = (uint8_t)ESTOP_REASON_NONE;
        /* What stop_datagram reads of data, as the caller passed it: the clock step wrote only
         * core and out. A goal a byte: as one goal CVC4 took 9 s of its 20; as two of four
         * bytes 7 and 4 s; as eight, under a second each (issue 24's fifty-first round). */
        /*@ assert data_kept: data != \null && len == 48 ==> data[0] == \at(data[0], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[1] == \at(data[1], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[2] == \at(data[2], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[3] == \at(data[3], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[4] == \at(data[4], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[5] == \at(data[5], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[6] == \at(data[6], Pre); */
        /*@ assert data_kept: data != \null && len == 48 ==> data[7] == \at(data[7], Pre); */
        /* The core as valid_body finds it (stop_datagram, before it, only reads): the key
         * state and the remote table its rule below reads. */
        /*@ ghost checked: ; */
        if (data != NULL) {
            reason = stop_datagram(core, data, len);
            if (reason == ESTOP_REASON_NONE) {
                body = valid_body(core, data, len);
                /* body_keyed, at the label (handled_keyed below, one branch at a time). */
                /*@ assert keyed_body: body != \null && core->cfg.key_len != 0 ==> len == 60 &&
                        \at(datagram_keyed(core, data), checked); */
            }
        }
        /*@ assert datagram_read: data != \null &&
                \at(datagram_asks_stop(data, len, core->cfg.stop_id), Pre) ==> reason != 0; */
        if (reason != ESTOP_REASON_NONE) {
            sat32_inc(&core->counters.udp_stops);
            /* The clock's stop frame, past the count (core and out apart: the solvers' step). */
            /*@ assert counted_keeps: \at(core->state, Pre) != 0 ==> out->n_can <= 2 &&
                    (core->state != 0 || (1 <= out->n_can && emergency(out, 0, core))); */
            estop__stop(core, reason, out);
            /*@ assert stopped_brakes: \at(core->state, Pre) != 0 ==> emergency_sent(out, core); */
        } else if (body != NULL) {
            take_valid(core, body, out);
        } else {
            sat32_inc(&core->counters.udp_invalid);
            core->status_invalid = sat8_inc(core->status_invalid);
        }
        /* slots_ok past the merge of the three branches, one branch at a time: asserted
         * whole, the solvers must split the merged memory themselves (40 s and more; an
         * assertion inside a branch does not help, Qed drops it there). */
        /*@ assert branch_slots: reason != 0 ==> slots_ok(core); */
        /*@ assert branch_slots: reason == 0 && body != \null ==> slots_ok(core); */
        /*@ assert branch_slots: reason == 0 && body == \null ==> slots_ok(core); */
        /*@ assert branch_keyed: reason != 0 ==>
                core->last_valid_us == \at(core->last_valid_us, Pre) &&
                core->link_fresh == \at(core->link_fresh, checked) &&
                core->last_neutral == \at(core->last_neutral, checked) && core->valid_run == 0; */
        /*@ assert branch_keyed: reason == 0 && body == \null ==>
                core->last_valid_us == \at(core->last_valid_us, Pre) &&
                core->link_fresh == \at(core->link_fresh, checked) &&
                core->last_neutral == \at(core->last_neutral, checked) &&
                core->valid_run == \at(core->valid_run, checked); */
        /*@ assert branch_keyed: reason == 0 && body != \null && core->cfg.key_len != 0 ==>
                data != \null && len == 60 &&
                \at(datagram_keyed(core, data), checked); */
        /* Nothing without the key prolongs motion: on a unit with a key, the link is kept
         * fresh (its last valid packet's time moved, or its freshness, or the latest packet's
         * neutrality changed, or the release count rose past the clock step) only by this
         * call's 60-byte datagram,
         * whose tag is the MAC of its first 44 bytes under the unit's key state, of this
         * session, with a counter above its remote's kept UDP counter, as the core stood when
         * the datagram was checked (valid_body's body_keyed; issue 24's thirty-seventh
         * round). Here, next to branch_keyed, its premises: past the invariant's assertions
         * below, which are hypotheses of every goal after them, it took 12 s and ran out of
         * 90 s in 1 of 4 orders of its problem (issue 24's forty-third round). Still 11 s here
         * as one implication from the four changes, which Qed could not take apart; from each
         * change alone (keyed_change), Qed proves three and both solvers' steps take under a
         * second (issue 24's fifty-first round). */
        /*@ assert keyed_change: core->cfg.key_len != 0 &&
                core->last_valid_us != \at(core->last_valid_us, Pre) ==>
                data != \null && len == 60 && \at(datagram_keyed(core, data), checked); */
        /*@ assert keyed_change: core->cfg.key_len != 0 &&
                core->link_fresh != \at(core->link_fresh, checked) ==>
                data != \null && len == 60 && \at(datagram_keyed(core, data), checked); */
        /*@ assert keyed_change: core->cfg.key_len != 0 &&
                core->last_neutral != \at(core->last_neutral, checked) ==>
                data != \null && len == 60 && \at(datagram_keyed(core, data), checked); */
        /*@ assert keyed_change: core->cfg.key_len != 0 &&
                core->valid_run > \at(core->valid_run, checked) ==>
                data != \null && len == 60 && \at(datagram_keyed(core, data), checked); */
        /*@ assert handled_keyed: core->cfg.key_len != 0 &&
                (core->last_valid_us != \at(core->last_valid_us, Pre) ||
                 core->link_fresh != \at(core->link_fresh, checked) ||
                 core->last_neutral != \at(core->last_neutral, checked) ||
                 core->valid_run > \at(core->valid_run, checked)) ==> data != \null &&
                len == 60 && \at(datagram_keyed(core, data), checked); */
        /*@ assert branch_times: reason != 0 ==> times_ok(core); */
        /*@ assert branch_times: reason == 0 && body != \null ==> times_ok(core); */
        /*@ assert branch_times: reason == 0 && body == \null ==> times_ok(core); */
        /* The invariant and the times, carried past the three branches here so that
         * inv_kept after estop__finish (which writes only out) is Qed's: left to the
         * solvers it timed out at 150 s on a busy machine. */
        /*@ assert handled_inv: cfg_ok(core) && known_ok(core); */
        /*@ assert handled_inv: slots_ok(core); */
        /*@ assert handled_inv: fresh_ok(core); */
        /*@ assert handled_times: times_ok(core); */
        /*@ assert handled_stopped: \at(core->state, Pre) == 0 ==> core->state == 0; */
        /*@ assert handled_now: core->now_us == now_us; */
        /*@ assert handled_magic: core->magic == 0x45535450; */
        /*@ assert handled_stop: reason != 0 ==> core->state == 0; */
        /*@ assert handled_valid: reason == 0 && body != \null ==>
                core->link_fresh != 0 && core->last_valid_us == now_us; */
        /*@ assert handled_brake: reason != 0 && \at(core->state, Pre) != 0 ==>
                emergency_sent(out, core); */
        estop__finish(core, out);
    }
    return err;
}
