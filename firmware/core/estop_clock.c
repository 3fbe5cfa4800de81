/*
 * estop_clock: the clock step of every entry point, the CAN frames and the state changes
 * they carry (PROTOCOL.md sections 3 and 4). estop__begin() advances the clock to the call's
 * time (the timeout stop, the slow-down, the link's ageing) and sends the frames that are due;
 * estop__finish() fills the state read-out and the next call time; estop_tick() is the two
 * alone. A state change sends its ESTOP_BRAKE frame at once (estop__state_changed); a stop
 * (estop__stop) and the slow-down (estop__enter_slowing) are here because the clock makes
 * them too. estop_core.c and estop_udp.c call into this file, never the other way.
 */
#include "estop_core.h"

#include "estop_crc.h"
#include "estop_internal.h"

#define COUNTER_MODULO 15u        /* alive counter runs 0..14; 15 is never sent */
#define LINK_AGE_NONE_MS 0xFFFFu

uint32_t estop__link_age(const estop_core_t *core)
{
    return (uint32_t)(core->now_us - core->last_valid_us);
}

/* ARMED or SLOWING: the brake is not latched and the watchdog runs. */
static int moving(const estop_core_t *core)
{
    return core->state != ESTOP_STATE_STOPPED;
}

uint8_t estop__current_flags(const estop_core_t *core)
{
    uint8_t flags = 0u;
    if ((moving(core) != 0) && (estop__link_age(core) >= core->cfg.warn_us)) {
        flags = (uint8_t)ESTOP_FLAG_LINK_DEGRADED;
    }
    return flags;
}

/* Every stop request restarts the release count; only the first one sets the reason. Its
 * contract stays beside its code, although estop_core.c and estop_udp.c call it too: Eva reads
 * no contract of prove/contracts.h, and without this one the driver's rule_fault_stops went
 * unshown.
 * stop_brakes is stated once per path (a moving unit; a stopped one whose brake frame came
 * first): as one clause the solvers paid for the merge of both (9.9 s, against 5.6 and 0.1). */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv_base(core);
    requires 1 <= reason <= 5 && out->n_can <= 3;
    assigns core->valid_run, core->state, core->reason, core->counters.stops[0 .. 5],
            core->status_stops, out->state_changed, out->can[0 .. 2], out->n_can,
            core->brake_counter, core->brake_due_us;
    ensures inv_base(core) && core->state == 0 && out->n_can <= 3;
    ensures stop_restarts_release_count: core->valid_run == 0;
    ENSURES_SLOTS_KEPT(stop)
    ensures stop_keeps: frames_kept(Pre, Post, out, \old(out->n_can));
    ensures stop_times: \at(times_ok(core), Pre) ==> times_ok(core);
    ensures stop_keeps_clock: core->now_us == \old(core->now_us) &&
        core->cfg.brake_can_id == \old(core->cfg.brake_can_id) && core->magic == \old(core->magic);
    ensures stop_keeps_link: core->last_valid_us == \old(core->last_valid_us) &&
        core->link_fresh == \old(core->link_fresh) && core->last_neutral == \old(core->last_neutral);
    ensures stop_brakes: \old(out->n_can) <= 2 && \old(core->state) != 0 ==>
        emergency_sent(out, core);
    ensures stop_brakes_stopped: \old(out->n_can) <= 2 && \old(core->state) == 0 &&
        1 <= \old(out->n_can) && \at(emergency(out, 0, core), Pre) ==>
        emergency_sent(out, core);
    behavior moving:
      assumes core->state != 0;
      ensures out->state_changed == 1 && core->reason == reason;
      ensures core->brake_due_us == (uint32_t)(core->now_us + core->cfg.brake_period_us);
      ensures brake_due_ok(core);
      ensures \old(out->n_can) < 3 ==> out->n_can == \old(out->n_can) + 1 &&
          out->can[\old(out->n_can)].id == core->cfg.brake_can_id &&
          out->can[\old(out->n_can)].data[2] == 0 &&
          brake_ok(out, \old(out->n_can), core->cfg.slow_level);
      ensures \old(out->n_can) >= 3 ==> out->n_can == \old(out->n_can);
    behavior stopped:
      assumes core->state == 0;
      ensures out->n_can == \old(out->n_can) && out->state_changed == \old(out->state_changed);
      ensures core->brake_due_us == \old(core->brake_due_us) && core->reason == \old(core->reason);
      ensures \at(brake_due_ok(core), Pre) ==> brake_due_ok(core);
    complete behaviors; disjoint behaviors;
 */
void estop__stop(estop_core_t *core, uint8_t reason, estop_out_t *out)
{
    core->valid_run = 0u;
    if (moving(core) != 0) {
        core->state = (uint8_t)ESTOP_STATE_STOPPED;
        core->reason = reason;
        sat32_inc(&core->counters.stops[reason]);
        core->status_stops = sat4_inc(core->status_stops);
        estop__state_changed(core, out);
    }
}

/* SLOWING at the slow time: a controlled stop that the link's return ends. The caller sends
 * the state change. */
void estop__enter_slowing(estop_core_t *core)
{
    core->state = (uint8_t)ESTOP_STATE_SLOWING;
    core->slow_run = 0u;
    sat32_inc(&core->counters.slowdowns);
    core->status_slowdowns = sat4_inc(core->status_slowdowns);
}

/*@ requires \valid(out) && \valid(counter) && \valid_read(payload + (0 .. 5));
    requires \separated(out, counter, payload + (0 .. 5));
    assigns out->can[0 .. 2], out->n_can, *counter;
    ensures push_keeps: frames_kept(Pre, Post, out, \old(out->n_can));
    behavior room:
      assumes out->n_can < 3;
      ensures out->n_can == \old(out->n_can) + 1;
      ensures out->can[\old(out->n_can)].id == id;
      ensures \forall integer i; 0 <= i < 6 ==>
          out->can[\old(out->n_can)].data[i] == \old(payload[i]);
    behavior full:
      assumes out->n_can >= 3;
      ensures out->n_can == \old(out->n_can);
    complete behaviors; disjoint behaviors;
 */
static void push_frame(estop_out_t *out, uint32_t id, uint16_t data_id, const uint8_t *payload,
                       uint8_t *counter)
{
    /* Callers never exceed ESTOP_OUT_MAX_CAN (see the header); the guard keeps that true. */
    /*@ split out->n_can; */ /* Eva: one state per frame slot, so each write is exact */
    if (out->n_can < ESTOP_OUT_MAX_CAN) {
        estop_can_frame_t *f = &out->can[out->n_can];
        uint8_t i;
        f->id = id;
        f->dlc = (uint8_t)ESTOP_CAN_DLC;
        /*@ loop invariant 0 <= i <= 6;
            loop invariant \forall integer k; 0 <= k < i ==> f->data[k] == payload[k];
            loop assigns i, f->data[0 .. 5];
            loop variant 6 - i;
         */
        for (i = 0u; i < 6u; i++) {
            f->data[i] = payload[i];
        }
        f->data[6] = (uint8_t)(*counter & 0x0Fu);
        f->data[7] = estop_crc8_e2e(data_id, f->data, 7u);
        *counter = (uint8_t)((*counter + 1u) % COUNTER_MODULO);
        out->n_can++;
    }
}

/*@ requires \valid(core) && \valid(out) && \separated(core, out) && core->state <= 2;
    assigns out->can[0 .. 2], out->n_can, core->brake_counter;
    ensures brake_frame_matches_state: \old(out->n_can) < 3 ==>
        out->n_can == \old(out->n_can) + 1 &&
        out->can[\old(out->n_can)].id == core->cfg.brake_can_id &&
        out->can[\old(out->n_can)].data[2] == core->state &&
        brake_ok(out, \old(out->n_can), core->cfg.slow_level);
    ensures \old(out->n_can) >= 3 ==> out->n_can == \old(out->n_can);
    ensures brake_keeps: frames_kept(Pre, Post, out, \old(out->n_can));
    ENSURES_SLOTS_KEPT(brake)
 */
static void send_brake(estop_core_t *core, estop_out_t *out)
{
    uint8_t p[6];
    if (core->state == ESTOP_STATE_ARMED) {
        p[0] = (uint8_t)ESTOP_BRAKE_RELEASE;
        p[1] = 0u;
    } else if (core->state == ESTOP_STATE_SLOWING) {
        p[0] = (uint8_t)ESTOP_BRAKE_CONTROLLED;
        p[1] = core->cfg.slow_level;
    } else {
        p[0] = (uint8_t)ESTOP_BRAKE_EMERGENCY; /* STOPPED, and any state it does not know */
        p[1] = (uint8_t)ESTOP_BRAKE_LEVEL_FULL;
    }
    p[2] = core->state;
    p[3] = core->reason;
    p[4] = estop__current_flags(core);
    p[5] = 0u;
    push_frame(out, core->cfg.brake_can_id, core->cfg.brake_data_id, p, &core->brake_counter);
}

static void send_status(estop_core_t *core, estop_out_t *out)
{
    uint8_t p[6];
    uint32_t age_ms = LINK_AGE_NONE_MS;
    if (core->link_fresh != 0u) {
        age_ms = estop__link_age(core) / 1000u; /* below the 60 s timeout limit, so fits in 16 bits */
    }
    p[0] = core->status_valid;
    p[1] = core->status_invalid;
    p[2] = core->status_auth_failed;
    p[3] = (uint8_t)(core->status_stops | (uint8_t)(core->status_slowdowns << 4));
    p[4] = (uint8_t)(age_ms & 0xFFu);
    p[5] = (uint8_t)((age_ms >> 8) & 0xFFu);
    push_frame(out, core->cfg.status_can_id, core->cfg.status_data_id, p, &core->status_counter);
    core->status_valid = 0u;
    core->status_invalid = 0u;
    core->status_auth_failed = 0u;
    core->status_stops = 0u;
    core->status_slowdowns = 0u;
}

/* A state change sends ESTOP_BRAKE at once and restarts its period from there. */
void estop__state_changed(estop_core_t *core, estop_out_t *out)
{
    out->state_changed = 1u;
    send_brake(core, out);
    core->brake_due_us = core->now_us + core->cfg.brake_period_us;
}

/* A link that has been silent for the timeout is no longer fresh (latched: a wrapped tick can
 * never make it young again), and a RELEASE then needs its packets from after the silence. An
 * old link's gap is aged by every step: a step may be too long to measure, and the next one
 * could wrap the age back to a short one. */
/*@ requires \valid(core) && cfg_ok(core);
    assigns core->link_fresh, core->valid_run, core->gaps[0 .. 31], core->silences,
            core->gap_known;
    ensures link_young: core->link_fresh != 0 ==>
        udiff(core->now_us, core->last_valid_us) < core->cfg.timeout_us;
    ensures link_latched: core->link_fresh != 0 ==> \old(core->link_fresh) != 0;
    ensures link_run: core->valid_run == 0 || core->valid_run == \old(core->valid_run);
 */
static void age_link(estop_core_t *core, uint32_t step)
{
    if (core->link_fresh == 0u) {
        estop__age_gap(core, step); /* a fresh link is younger than 60 s: nothing to age */
    } else if (estop__link_age(core) >= core->cfg.timeout_us) {
        core->link_fresh = 0u;
        core->valid_run = 0u;
        estop__age_gap(core, step);
    } else {
        /* a fresh link: its age is measured from last_valid_us */
    }
}

/* The clock's verdict on the state, once the link is aged: a moving unit whose link went stale
 * stops for reason, an ARMED one whose link is past the slow time slows, any other stays. A
 * function of its own so that advance_clock's clauses meet one call and its contract, not three
 * branches: past the branches, six of them took 10 to 25 s each of the solvers (issue 24's
 * forty-fifth round). The fields it does not assign (the clock, the link, the configuration)
 * are kept by its assigns. */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv_base(core);
    requires link_ok(core) && (reason == 3 || reason == 4);
    requires out->n_can == 0 && out->state_changed == 0;
    assigns core->valid_run, core->state, core->reason, core->counters.stops[0 .. 5],
            core->counters.slowdowns, core->slow_run, core->status_stops,
            core->status_slowdowns, core->brake_counter, core->brake_due_us,
            out->can[0 .. 2], out->n_can, out->state_changed;
    ENSURES_INV(verdict)
    ensures verdict_frame: out->n_can == out->state_changed && out->state_changed <= 1;
    ensures verdict_changed: out->state_changed != 0 <==> core->state != \old(core->state);
    ensures verdict_stays_stopped: \old(core->state) == 0 ==> core->state == 0;
    ensures verdict_run: core->valid_run == 0 || core->valid_run == \old(core->valid_run);
    ensures verdict_stop: \old(core->state) != 0 && core->state == 0 ==>
        out->n_can == 1 && emergency(out, 0, core) && core->reason == reason &&
        core->link_fresh == 0;
    ensures verdict_armed: core->state == 1 ==>
        udiff(core->now_us, core->last_valid_us) < core->cfg.slow_us;
    ensures verdict_due: out->state_changed != 0 ==>
        udiff(core->brake_due_us, core->now_us) == core->cfg.brake_period_us;
 */
static void clock_verdict(estop_core_t *core, uint8_t reason, estop_out_t *out)
{
    /* The state itself rather than moving(): Eva then keeps the test and the stop together
     * (through the call it split the states apart and lost that a moving unit is stopped). */
    if ((core->state != ESTOP_STATE_STOPPED) && (core->link_fresh == 0u)) {
        estop__stop(core, reason, out);
    } else if ((core->state == ESTOP_STATE_ARMED) && (estop__link_age(core) >= core->cfg.slow_us)) {
        estop__enter_slowing(core); /* ARMED implies a fresh link, so the age is meaningful */
        estop__state_changed(core, out);
    } else {
        /* nothing is due: the state stays */
    }
}

/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv(core);
    requires out->n_can == 0 && out->state_changed == 0;
    assigns core->now_us, core->link_fresh, core->valid_run, core->counters.faults,
            core->counters.stops[0 .. 5], core->counters.slowdowns, core->state, core->reason,
            core->slow_run, core->status_stops, core->status_slowdowns, core->gaps[0 .. 31],
            core->silences, core->gap_known, core->brake_counter, core->brake_due_us,
            out->can[0 .. 2], out->n_can, out->state_changed, out->changed_by_clock,
            out->clock_state, out->clock_reason;
    ENSURES_INV(clock)
    ensures clock_now: core->now_us == now_us && out->n_can <= 1;
    ensures clock_link: core->link_fresh != 0 ==>
        udiff(core->now_us, core->last_valid_us) < core->cfg.timeout_us;
    ensures clock_armed: core->state == 1 ==>
        udiff(core->now_us, core->last_valid_us) < core->cfg.slow_us;
    ensures clock_brake_due: out->state_changed != 0 ==>
        udiff(core->brake_due_us, core->now_us) == core->cfg.brake_period_us;
    ensures never_leaves_stopped: \old(core->state) == 0 ==> core->state == 0;
    ensures clock_frame: out->n_can == out->state_changed && out->state_changed <= 1;
    ensures clock_stop_frame: \old(core->state) != 0 && core->state == 0 ==>
        out->n_can == 1 && emergency(out, 0, core);
    ensures clock_backwards_stops: udiff(now_us, \old(core->now_us)) > ESTOP_MAX_STEP_US ==>
        core->state == 0 && core->link_fresh == 0 && core->valid_run == 0;
    ensures clock_stop_reason: \old(core->state) != 0 && core->state == 0 ==>
        core->reason == (udiff(now_us, \old(core->now_us)) > ESTOP_MAX_STEP_US ? 4 : 3);
    ensures clock_reported: out->clock_state == core->state &&
        out->clock_reason == core->reason && out->changed_by_clock == out->state_changed;
    ensures clock_stop_cause: \old(core->state) != 0 && core->state == 0 ==>
        core->link_fresh == 0;
    ensures clock_changed: out->state_changed != 0 <==> core->state != \old(core->state);
 */
static void advance_clock(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    const uint32_t step = (uint32_t)(now_us - core->now_us);
    uint8_t reason = (uint8_t)ESTOP_REASON_UDP_TIMEOUT;
    core->now_us = now_us;
    if (step > ESTOP_MAX_STEP_US) {
        /* The tick went backwards: the unit can no longer trust any age it computes. */
        core->link_fresh = 0u;
        core->valid_run = 0u; /* on a STOPPED unit too: a RELEASE needs packets from after it */
        sat32_inc(&core->counters.faults);
        reason = (uint8_t)ESTOP_REASON_FAULT;
    }
    age_link(core, step);
    clock_verdict(core, reason, out);
    out->changed_by_clock = out->state_changed; /* every change so far came from the clock */
    out->clock_state = core->state;
    out->clock_reason = core->reason;
}

/* A frame is due unless its due time lies in (now, now + period]. So a due time that has been
 * reached is due, and so is one that lies further ahead than a period: that only happens when
 * the tick went backwards, and the period must hold whatever the clock does. */
static int frame_due(uint32_t now, uint32_t due, uint32_t period)
{
    return ((uint32_t)(due - now) - 1u) >= period;
}

/* Next due time on a fixed grid; a caller that fell a whole period behind, or whose clock went
 * backwards, restarts the grid from now. */
static uint32_t next_due(uint32_t due, uint32_t period, uint32_t now)
{
    uint32_t next = due + period;
    if (frame_due(now, next, period) != 0) {
        next = now + period;
    }
    return next;
}

/* due_keeps_core and due_keeps_out: what estop__begin's clauses read past this call, as plain
 * equalities (past the assigns alone, its assertion took 48 s; a clause over out->can[0] here
 * made due_inv slow instead). */
/*@ requires \valid(core) && \valid(out) && \separated(core, out) && inv(core);
    requires out->n_can <= 1;
    assigns out->can[0 .. 2], out->n_can, core->brake_counter, core->status_counter,
            core->brake_due_us, core->status_due_us, core->status_valid, core->status_invalid,
            core->status_auth_failed, core->status_stops, core->status_slowdowns;
    ensures due_brake: 1 <= udiff(core->brake_due_us, core->now_us) <= core->cfg.brake_period_us;
    ensures due_status:
        1 <= udiff(core->status_due_us, core->now_us) <= core->cfg.status_period_us;
    ensures due_frames: \old(out->n_can) <= out->n_can <= \old(out->n_can) + 2;
    ensures due_room: \at(udiff(core->brake_due_us, core->now_us), Pre) ==
        core->cfg.brake_period_us ==> out->n_can <= \old(out->n_can) + 1;
    ensures due_keeps: frames_kept(Pre, Post, out, \old(out->n_can));
    ENSURES_INV(due)
    ensures due_keeps_slots: \forall integer k; 0 <= k < 8 ==>
        core->slots[k].open == \old(core->slots[k].open);
    ensures due_keeps_core: core->magic == \old(core->magic) &&
        core->link_fresh == \old(core->link_fresh) &&
        core->cfg.brake_can_id == \old(core->cfg.brake_can_id) &&
        core->state == \old(core->state) &&
        core->reason == \old(core->reason) && core->now_us == \old(core->now_us) &&
        core->last_valid_us == \old(core->last_valid_us) &&
        core->cfg.timeout_us == \old(core->cfg.timeout_us) &&
        core->cfg.slow_us == \old(core->cfg.slow_us) &&
        core->cfg.stop_id == \old(core->cfg.stop_id);
    ensures due_keeps_period: core->cfg.brake_period_us == \old(core->cfg.brake_period_us);
    ensures due_keeps_out: out->has_reply == \old(out->has_reply) &&
        out->close_slot == \old(out->close_slot) &&
        out->state_changed == \old(out->state_changed) &&
        out->changed_by_clock == \old(out->changed_by_clock) &&
        out->clock_state == \old(out->clock_state) &&
        out->clock_reason == \old(out->clock_reason);
 */
static void send_due_frames(estop_core_t *core, estop_out_t *out)
{
    if (frame_due(core->now_us, core->brake_due_us, core->cfg.brake_period_us) != 0) {
        send_brake(core, out);
        core->brake_due_us = next_due(core->brake_due_us, core->cfg.brake_period_us, core->now_us);
    }
    if (frame_due(core->now_us, core->status_due_us, core->cfg.status_period_us) != 0) {
        send_status(core, out);
        core->status_due_us =
            next_due(core->status_due_us, core->cfg.status_period_us, core->now_us);
    }
}

/* Only what says how much of the output is meaningful is cleared: frames beyond n_can and
 * reply bytes without has_reply are left as they were (clearing all 112 bytes cost the plain
 * packet path a sixth of its instructions). changed_by_clock is the caller's to set. */
static void clear_out(estop_out_t *out)
{
    out->n_can = 0u;
    out->has_reply = 0u;
    out->reply_len = 0u;
    out->close_slot = 0u;
    out->state_changed = 0u;
}

estop_err_t estop__begin(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = ESTOP_OK;
    if ((core == NULL) || (out == NULL)) {
        err = ESTOP_ERR_NULL_ARG;
    } else {
        clear_out(out);
        if (core->magic != CORE_MAGIC) {
            out->changed_by_clock = 0u;
            err = ESTOP_ERR_NOT_INIT;
            /* Nothing of the core was written: said here, where it is plain, and not left to
             * the solvers at the end of both branches. */
            /*@ assert begin_step: \forall integer k; 0 <= k < 8 ==>
                    core->slots[k].open == \at(core->slots[k].open, Pre); */
            /*@ assert begin_step: \at(core->state, Pre) == 0 ==> core->state == 0; */
        } else {
            advance_clock(core, now_us, out); /* sets changed_by_clock */
            /* What the clauses over the whole core need, after each call (under Typed the
             * solvers ran out of time carrying them past all three at once; begin_carried's
             * facts took 15 to 35 s each before issue 24's twenty-ninth round). */
            /*@ assert begin_carry: begin_carried(now_us); */
            /*@ assert begin_step: inv(core); */
            /*@ assert begin_step: \forall integer k; 0 <= k < 8 ==>
                    core->slots[k].open == \at(core->slots[k].open, Pre); */
            /*@ assert begin_step: \at(core->state, Pre) == 0 ==> core->state == 0; */
            estop__age_tag_window(core);
            /* The clock's frame, if any, came with a brake due a whole period ahead: so
             * send_due_frames adds at most one (due_room). */
            /*@ assert begin_room_carry: out->n_can <= 1 && (out->n_can != 0 ==>
                    udiff(core->brake_due_us, core->now_us) == core->cfg.brake_period_us); */
            /*@ assert begin_carry: begin_carried(now_us); */
            /*@ assert begin_step: inv(core); */
            /*@ assert begin_step: \forall integer k; 0 <= k < 8 ==>
                    core->slots[k].open == \at(core->slots[k].open, Pre); */
            /*@ assert begin_step: \at(core->state, Pre) == 0 ==> core->state == 0; */
            send_due_frames(core, out);
            /*@ assert begin_room_carry: out->n_can <= 2; */
            /*@ assert begin_carry: begin_carried(now_us); */
            /*@ assert begin_step: inv(core); */
            /*@ assert begin_step: \forall integer k; 0 <= k < 8 ==>
                    core->slots[k].open == \at(core->slots[k].open, Pre); */
            /*@ assert begin_step: \at(core->state, Pre) == 0 ==> core->state == 0; */
        }
    }
    return err;
}

/*@ assigns \nothing;
    ensures \result == a || \result == b;
    ensures udiff(\result, now) <= udiff(a, now) && udiff(\result, now) <= udiff(b, now);
 */
static uint32_t earliest(uint32_t now, uint32_t a, uint32_t b)
{
    return ((uint32_t)(a - now) <= (uint32_t)(b - now)) ? a : b;
}

void estop__finish(const estop_core_t *core, estop_out_t *out)
{
    uint32_t next = earliest(core->now_us, core->brake_due_us, core->status_due_us);
    if (core->state == ESTOP_STATE_ARMED) {
        next = earliest(core->now_us, next, core->last_valid_us + core->cfg.slow_us);
    } else if (core->state == ESTOP_STATE_SLOWING) {
        next = earliest(core->now_us, next, core->last_valid_us + core->cfg.timeout_us);
    } else {
        /* STOPPED: only the periodic frames are due */
    }
    out->next_call_us = next;
    out->state = core->state;
    out->reason = core->reason;
    out->flags = estop__current_flags(core);
}

estop_err_t estop_tick(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = estop__begin(core, now_us, out);
    if (err == ESTOP_OK) {
        estop__finish(core, out);
    }
    return err;
}
