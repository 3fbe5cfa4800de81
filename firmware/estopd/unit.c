#include "unit.h"

#include <string.h>

#include "frame.h"
#include "rxtime.h"

/* Why the state changed (the `cause` key, docs/DESIGN.md): a stop by its reason, told apart by
 * the channel it came on; the other changes by where they lead from. by_clock: the change came
 * from the core's clock, not from the call's input. */
static const char *state_cause(uint8_t from, uint8_t to, uint8_t reason, int by_clock,
                               const char *call)
{
    int by_datagram = strcmp(call, "udp_rx") == 0;

    if (to == ESTOP_STATE_STOPPED) {
        switch (reason) {
        case ESTOP_REASON_TCP_STOP: return by_datagram ? "stop_datagram" : "tcp_stop";
        case ESTOP_REASON_LIFT: return by_datagram ? "lift_datagram" : "lift";
        case ESTOP_REASON_UDP_TIMEOUT: return "udp_timeout";
        case ESTOP_REASON_FAULT:
            /* Outside a reported fault, the clock's only way to a fault is a backwards tick. */
            return (by_clock && strcmp(call, "fault") != 0) ? "clock_backwards" : "fault";
        default: return "boot";
        }
    }
    if (from == ESTOP_STATE_STOPPED) {
        return "release"; /* to ARMED, or straight to SLOWING for a link silent for S */
    }
    return to == ESTOP_STATE_SLOWING ? "udp_silence" : "link_back";
}

static void fx_begin(unit_fx_t *fx, const char *call, uint64_t now, estop_out_t *out)
{
    memset(fx, 0, sizeof *fx);
    fx->call = call;
    fx->now = now;
    memset(out, 0, sizeof *out);
}

/* Everything a core call produced, into fx and the unit's own record. The core may have
 * advanced its clock before it found an error: what it produced still goes out. */
static void fx_end(unit_t *u, estop_err_t err, const estop_out_t *out, unit_fx_t *fx)
{
    uint32_t i;
    uint32_t delta;

    for (i = 0u; i < out->n_can && i < ESTOP_OUT_MAX_CAN; i++) {
        const estop_can_frame_t *f = &out->can[i];
        if (f->id == u->brake_can_id) {
            u->last_brake = *f;
            u->have_brake = 1u;
        }
        u->last_frame = *f;
        u->frames_out++;
        fx->frames[fx->n_frames++] = *f;
    }
    if (out->state_changed) {
        uint8_t from = u->state;
        int by_clock = out->changed_by_clock != 0u;
        if (by_clock && (out->clock_state != out->state || out->clock_reason != out->reason)) {
            /* The clock changed the state, then the input again (SLOWING, then a STOP): two
             * changes, each with its cause. */
            fx->clock_first = 1u;
            fx->clock_from = from;
            fx->clock_to = out->clock_state;
            fx->clock_reason = out->clock_reason;
            fx->clock_cause = state_cause(from, out->clock_state, out->clock_reason, 1, fx->call);
            from = out->clock_state;
            by_clock = 0;
        }
        fx->changed = 1u;
        fx->from = from;
        fx->to = out->state;
        fx->reason = out->reason;
        fx->by_clock = (uint8_t)(by_clock || out->reason == ESTOP_REASON_UDP_TIMEOUT);
        fx->cause = state_cause(from, out->state, out->reason, by_clock, fx->call);
        u->state = out->state;
        u->reason = out->reason;
    }
    fx->err = err;
    /* Even a call that failed may have moved the core's clock (the core checks some input
     * only after its clock step): the next call must not look like a tick backwards. */
    if (fx->now > u->last_call_us) {
        u->last_call_us = fx->now;
    }
    if (err != ESTOP_OK) {
        u->deadline_us = fx->now; /* next_call_us may be unset: let a tick tell */
        return;
    }
    if (out->has_reply && out->reply_len <= sizeof fx->reply) {
        fx->has_reply = 1u;
        fx->reply_len = out->reply_len;
        memcpy(fx->reply, out->reply, out->reply_len);
    }
    fx->close_slot = out->close_slot;
    u->state = out->state;
    u->reason = out->reason;
    /* next_call_us is a wrapping tick: a difference over half the range means "already
     * due". */
    delta = out->next_call_us - (uint32_t)fx->now;
    u->deadline_us = delta > ESTOP_MAX_STEP_US ? fx->now : fx->now + delta;
}

static void tick(unit_t *u, uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "tick", t, &out);
    fx_end(u, estop_tick(&u->core, (uint32_t)t, &out), &out, fx);
    if (fx->err != ESTOP_OK) {
        u->fatal = 1u; /* without ticks there is no watchdog: give up, the brake brakes */
    } else if (u->deadline_us <= t) {
        u->deadline_us = t + 1u; /* never spin on a core that keeps asking for "now" */
    }
}

int unit_boot(unit_t *u, const estop_config_t *cfg, uint64_t now, unit_fx_t *fx)
{
    estop_out_t out;

    u->brake_can_id = cfg->brake_can_id;
    u->brake_data_id = cfg->brake_data_id;
    u->slow_us = cfg->slow_us;
    u->timeout_us = cfg->timeout_us;
    fx_begin(fx, "init", now, &out);
    fx->err = estop_init(&u->core, cfg, (uint32_t)now);
    if (fx->err != ESTOP_OK) {
        return -1;
    }
    u->state = ESTOP_STATE_STOPPED;
    u->reason = ESTOP_REASON_BOOT;
    u->last_call_us = now;
    tick(u, now, fx); /* the boot frames are due at init time */
    return u->fatal ? -1 : 0;
}

int unit_catch_up(unit_t *u, uint64_t t, unit_fx_t *fx)
{
    /* A gap longer than the core's step (a suspend, a stalled host) goes in in steps. */
    if (u->fatal || t <= u->last_call_us || t - u->last_call_us <= ESTOP_MAX_STEP_US) {
        return 0;
    }
    tick(u, u->last_call_us + ESTOP_MAX_STEP_US, fx);
    return 1;
}

int unit_tick_due(unit_t *u, uint64_t t, unit_fx_t *fx)
{
    if (u->fatal || t < u->deadline_us) {
        return 0;
    }
    tick(u, t, fx);
    return 1;
}

uint64_t unit_feed_time(const unit_t *u, uint64_t rx_us)
{
    /* The core's clock never goes backwards: a datagram received before the latest call (read
     * late behind other input) goes in at that call's time. */
    return rxtime_feed_us(rx_us, u->last_call_us);
}

void unit_udp(unit_t *u, const uint8_t *data, size_t len, uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "udp_rx", t, &out);
    fx_end(u, estop_udp_rx(&u->core, data, len, (uint32_t)t, &out), &out, fx);
}

void unit_tcp_open(unit_t *u, uint32_t slot, uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "tcp_open", t, &out);
    fx_end(u, estop_tcp_open(&u->core, slot, (uint32_t)t, &out), &out, fx);
}

void unit_tcp_rx(unit_t *u, uint32_t slot, const uint8_t *buf, size_t len, size_t *used,
                 uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "tcp_rx", t, &out);
    *used = 0u;
    fx_end(u, estop_tcp_rx(&u->core, slot, buf, len, used, (uint32_t)t, &out), &out, fx);
}

void unit_tcp_close(unit_t *u, uint32_t slot, uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "tcp_close", t, &out);
    fx_end(u, estop_tcp_close(&u->core, slot, (uint32_t)t, &out), &out, fx);
}

void unit_fault(unit_t *u, uint64_t t, unit_fx_t *fx)
{
    estop_out_t out;
    fx_begin(fx, "fault", t, &out);
    fx_end(u, estop_fault(&u->core, (uint32_t)t, &out), &out, fx);
    if (fx->err != ESTOP_OK) {
        u->fatal = 1u;
    }
}

int unit_last_frame(unit_t *u, uint64_t t, int core_ok, unit_fx_t *fx)
{
    uint32_t before = u->frames_out;
    int faulted = 0;
    uint8_t reason;
    estop_can_frame_t f;

    if (core_ok && !u->fatal && u->state != ESTOP_STATE_STOPPED) {
        unit_fault(u, t, fx);
        faulted = 1;
        if (u->frames_out != before && u->last_frame.id == u->brake_can_id &&
            u->last_frame.data[0] == 1u) {
            return faulted; /* the core's own STOPPED frame */
        }
    } else {
        estop_out_t out;
        fx_begin(fx, "last_frame", t, &out);
    }
    /* Already STOPPED (or the core is broken): the next frame of the sequence, built here. */
    reason = u->state == ESTOP_STATE_STOPPED ? u->reason : (uint8_t)ESTOP_REASON_FAULT;
    frame_next_stopped(u->have_brake ? &u->last_brake : NULL, u->brake_can_id,
                       u->brake_data_id, reason, &f);
    u->last_brake = f;
    u->have_brake = 1u;
    u->last_frame = f;
    u->frames_out++;
    fx->frames[fx->n_frames++] = f; /* the core gave at most ESTOP_OUT_MAX_CAN */
    return faulted;
}

uint64_t unit_next_wakeup(const unit_t *u)
{
    return u->deadline_us;
}

uint64_t unit_silence_due(const unit_t *u)
{
    estop_status_t st;
    uint32_t limit;

    if (u->fatal || u->state == ESTOP_STATE_STOPPED ||
        estop_get_status(&u->core, &st) != ESTOP_OK) {
        return UINT64_MAX;
    }
    /* The link's age is the core's, at its latest call (last_call_us). */
    limit = u->state == ESTOP_STATE_ARMED ? u->slow_us : u->timeout_us;
    return st.link_age_us >= limit ? u->last_call_us
                                   : u->last_call_us + (uint64_t)(limit - st.link_age_us);
}
