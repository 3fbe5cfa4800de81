/*
 * estop_core: the emergency-stop state machine. See estop_core.h for the host contract and
 * PROTOCOL.md sections 1-4 for the rules implemented here.
 *
 * Every entry point runs the same three steps:
 *   1. estop__begin(): advance the clock (timeout stop, link ageing), send what is due;
 *   2. the input itself (a datagram, a TCP frame, a fault...);
 *   3. estop__finish(): state read-out and the next call time.
 * So a late input can never undo a stop that its own timestamp already implies.
 *
 * This file: the core's start (estop_init), a RELEASE's step (arm, release), what a TCP
 * frame's message asks for, faults and the status read-out. The clock step, the CAN frames and
 * the stop and slow-down they carry are in estop_clock.c, a UDP datagram's step in
 * estop_udp.c, authentication in estop_auth.c, TCP framing and replies in estop_tcp.c, the
 * link statistics in estop_link.c (estop_internal.h); the configuration's defaults and check
 * and the names of the codes in estop_config.c.
 */
#include "estop_core.h"

#include "estop_internal.h"


/* Field by field: the host's struct padding is never read (a byte copy of the whole struct
 * read it, indeterminate in a host's stack variable), and the key is not kept: every tag
 * starts from the state after the key block. */
static void copy_config(estop_config_t *dst, const estop_config_t *src)
{
    dst->timeout_us = src->timeout_us;
    dst->slow_us = src->slow_us;
    dst->warn_us = src->warn_us;
    dst->stop_id = src->stop_id;
    dst->brake_can_id = src->brake_can_id;
    dst->status_can_id = src->status_can_id;
    dst->brake_data_id = src->brake_data_id;
    dst->status_data_id = src->status_data_id;
    dst->release_packets = src->release_packets;
    dst->brake_period_us = src->brake_period_us;
    dst->status_period_us = src->status_period_us;
    dst->session = src->session;
    dst->tag_window_us = src->tag_window_us;
    dst->slow_level = src->slow_level;
    dst->tag_checks = src->tag_checks;
    dst->key_len = src->key_len;
}

/* Every byte of the core to 0, padding and MAC state included: magic 0 (unusable until
 * estop_init accepts the configuration), no slot holding bytes, no MAC key state. WP cannot
 * follow a struct written through a byte pointer, so this contract is admitted
 * (prove/assumed.txt names the test that fails were it false); estop_init is proved from it. */
/*@ requires \valid(core);
    assigns *core;
    admit ensures core_wiped: core->magic == 0 && core->mac.outlen == 0 &&
        core->link_fresh == 0 && core->valid_run == 0 &&
        \forall integer i; 0 <= i < 8 ==> core->slots[i].fill == 0;
 */
static void wipe_core(estop_core_t *core)
{
    zero_bytes((uint8_t *)core, sizeof(*core));
}

estop_err_t estop_init(estop_core_t *core, const estop_config_t *cfg, uint32_t now_us)
{
    estop_err_t err = ESTOP_ERR_NULL_ARG;
    if (core != NULL) {
        wipe_core(core);
        err = estop_config_check(cfg);
        if (err == ESTOP_OK) {
            copy_config(&core->cfg, cfg); /* core->cfg.key stays zero */
            /*@ assert init_step: cfg_ok(core) && slots_ok(core) && core->link_fresh == 0 &&
                    core->mac.outlen == 0; */
            if (cfg->key_len == ESTOP_KEY_LEN) {
                /* (a key of valid length cannot fail here) */
                (void)estop_b2s_key_init(&core->mac, cfg->key, ESTOP_KEY_LEN, ESTOP_TAG_LEN);
            }
            /*@ assert init_step: cfg_ok(core) && slots_ok(core) && core->link_fresh == 0 &&
                    core->mac.outlen == (cfg->key_len == ESTOP_KEY_LEN ? ESTOP_TAG_LEN : 0); */
            core->now_us = now_us;
            core->state = (uint8_t)ESTOP_STATE_STOPPED;
            core->reason = (uint8_t)ESTOP_REASON_BOOT;
            core->counters.stops[ESTOP_REASON_BOOT] = 1u;
            core->brake_due_us = now_us; /* the boot frames are due at once */
            core->status_due_us = now_us;
            core->tag_window_us = now_us; /* the first tag-check window starts at boot */
            core->tag_window_open = 1u;
            core->magic = CORE_MAGIC;
        }
    }
    return err;
}

/* The link check of a RELEASE. begin() has already aged the link, so a fresh link is younger
 * than the timeout. */
static int link_live(const estop_core_t *core)
{
    return (core->link_fresh != 0u) && (core->valid_run >= core->cfg.release_packets);
}

/* An accepted RELEASE. The link is younger than the timeout but may be older than the slow
 * time (S < T): then the slow-down is already due, and the unit goes straight to SLOWING, so
 * that no frame ever releases the brake for a link that has been silent for S. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv_base(core);
    requires core->link_fresh != 0 && out->n_can <= 3;
    assigns core->state, core->reason, core->slow_run, core->counters.slowdowns,
            core->status_slowdowns, out->state_changed, out->can[0 .. 2], out->n_can,
            core->brake_counter, core->brake_due_us;
    ensures inv_base(core) && core->state != 0 && out->state_changed == 1 &&
        out->n_can <= 3;
    ensures arm_clears_reason: core->reason == 0;
    ENSURES_SLOTS_KEPT(arm)
    ensures arm_slows: core->state == 1 ==>
        udiff(core->now_us, core->last_valid_us) < core->cfg.slow_us;
    ensures core->brake_due_us == (uint32_t)(core->now_us + core->cfg.brake_period_us);
    ensures brake_due_ok(core);
    ensures \old(out->n_can) < 3 ==> out->n_can == \old(out->n_can) + 1 &&
        out->can[\old(out->n_can)].id == core->cfg.brake_can_id &&
        out->can[\old(out->n_can)].data[2] == core->state &&
        brake_ok(out, \old(out->n_can), core->cfg.slow_level);
    ensures \old(out->n_can) >= 3 ==> out->n_can == \old(out->n_can);
 */
static void arm(estop_core_t *core, estop_out_t *out)
{
    core->state = (uint8_t)ESTOP_STATE_ARMED;
    core->reason = (uint8_t)ESTOP_REASON_NONE;
    if (estop__link_age(core) >= core->cfg.slow_us) {
        estop__enter_slowing(core);
    }
    estop__state_changed(core, out);
}

/* The reason a stop request of this msg_id stops the unit with: a STOP or a LIFT; 0 (none) for
 * any other msg_id. */
uint8_t estop__stop_reason(const estop_core_t *core, uint32_t msg_id)
{
    uint8_t reason = (uint8_t)ESTOP_REASON_NONE;
    if (msg_id == core->cfg.stop_id) {
        reason = (uint8_t)ESTOP_REASON_TCP_STOP;
    } else if (msg_id == ESTOP_MSG_LIFT) {
        reason = (uint8_t)ESTOP_REASON_LIFT;
    } else {
        /* not a stop request */
    }
    return reason;
}

/* ---- what a TCP request asks for (its framing and reply: estop_tcp.c) --------------------- */

/* Section 3: a RELEASE that is authenticated (or needs no authentication) still needs a live
 * link and a neutral latest packet. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv(core) && times_ok(core);
    requires out->n_can <= 3;
    assigns core->state, core->reason, core->slow_run, core->counters.slowdowns,
            core->counters.releases_accepted, core->counters.releases_refused,
            core->status_slowdowns, out->state_changed, out->can[0 .. 2], out->n_can,
            core->brake_counter, core->brake_due_us;
    ENSURES_KEPT(rel)
    ensures rel_frames: out->n_can <= 3;
    ensures rel_only_authenticated: \old(core->state) == 0 && core->state != 0 ==>
        authenticated != 0 && \result == 0;
    ensures rel_only_live_neutral: \old(core->state) == 0 && core->state != 0 ==>
        core->last_neutral != 0 && core->link_fresh != 0 &&
        core->valid_run >= core->cfg.release_packets;
    ensures rel_acked: \result == 0 ==> core->state != 0;
    ENSURES_SLOTS_KEPT(rel)
    ensures rel_refused_keeps: \result != 0 ==> core->state == \old(core->state);
    ensures \result <= 4;
 */
static uint8_t release(estop_core_t *core, int authenticated, estop_out_t *out)
{
    uint8_t nak = (uint8_t)ESTOP_NAK_NONE;
    if (!authenticated) {
        nak = (uint8_t)ESTOP_NAK_NOT_AUTHENTICATED;
    } else if (core->state == ESTOP_STATE_STOPPED) {
        if (!link_live(core)) {
            nak = (uint8_t)ESTOP_NAK_NO_LIVE_LINK;
        } else if (core->last_neutral == 0u) {
            nak = (uint8_t)ESTOP_NAK_NOT_NEUTRAL;
        } else {
            arm(core, out);
            /* Counted here, not from out->state_changed: the clock may have changed the state
             * earlier in the same call (ARMED -> SLOWING), and an acknowledgement is not a
             * release. */
            sat32_inc(&core->counters.releases_accepted);
        }
    } else {
        nak = (uint8_t)ESTOP_NAK_NONE; /* ARMED or SLOWING: acknowledged, nothing changes */
    }
    if (nak != ESTOP_NAK_NONE) {
        sat32_inc(&core->counters.releases_refused);
    }
    return nak;
}

/* What a good frame of either form asks for; returns the NAK code of its reply. */
uint8_t estop__handle_msg(estop_core_t *core, uint32_t msg_id, int release_authenticated,
                          estop_out_t *out)
{
    uint8_t nak = (uint8_t)ESTOP_NAK_NONE;
    const uint8_t reason = estop__stop_reason(core, msg_id);
    sat32_inc(&core->counters.tcp_frames);
    if (reason != ESTOP_REASON_NONE) {
        estop__stop(core, reason, out);
    } else if (msg_id == ESTOP_MSG_RELEASE) {
        nak = release(core, release_authenticated, out);
    } else if (msg_id != ESTOP_MSG_STATUS) {
        sat32_inc(&core->counters.tcp_unknown_id);
        nak = (uint8_t)ESTOP_NAK_UNKNOWN_ID;
    } else {
        /* STATUS: answered with ACK, changes nothing */
    }
    /* slots_ok past the merge, one branch at a time (as estop_tcp_rx's framed_slots): left to
     * the solvers, msg_inv_3 took 13 s in one make prove and ran out of 90 s asked alone, and
     * of 90 s in 1 of 4 orders of its problem (issue 24's forty-third round); 0.2 s. */
    /*@ assert msg_slots: reason != 0 ==> slots_ok(core); */
    /*@ assert msg_slots: reason == 0 && msg_id == ESTOP_MSG_RELEASE ==> slots_ok(core); */
    /*@ assert msg_slots: reason == 0 && msg_id != ESTOP_MSG_RELEASE ==> slots_ok(core); */
    return nak;
}

estop_err_t estop_fault(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = estop__begin(core, now_us, out);
    if (err == ESTOP_OK) {
        sat32_inc(&core->counters.faults);
        estop__stop(core, (uint8_t)ESTOP_REASON_FAULT, out);
        estop__finish(core, out);
    }
    return err;
}

estop_err_t estop_get_status(const estop_core_t *core, estop_status_t *status)
{
    estop_err_t err = ESTOP_OK;
    if ((core == NULL) || (status == NULL)) {
        err = ESTOP_ERR_NULL_ARG;
    } else if (core->magic != CORE_MAGIC) {
        err = ESTOP_ERR_NOT_INIT;
    } else {
        status->state = core->state;
        status->reason = core->reason;
        status->flags = estop__current_flags(core);
        status->link_live = link_live(core) ? 1u : 0u;
        status->valid_run = core->valid_run;
        status->link_age_us = (core->link_fresh != 0u) ? estop__link_age(core) : 0xFFFFFFFFu;
        copy_bytes((uint8_t *)&status->counters, (const uint8_t *)&core->counters,
                   sizeof(core->counters));
    }
    return err;
}
