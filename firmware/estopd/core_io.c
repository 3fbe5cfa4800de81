#include "core_io.h"

#include <stdio.h>
#include <string.h>

#include "clients.h"
#include "clock.h"
#include "log.h"
#include "net.h"
#include "rxtime.h"
#include "udp.h"

void cio_emit(daemon_t *d, const estop_can_frame_t *f, uint64_t now)
{
    if (f->id == d->opt.cfg.brake_can_id) {
        d->last_brake = *f;
        d->have_brake = 1u;
    }
    d->last_frame = *f;
    d->frames_out++;
    if (d->can_on) {
        can_send(&d->can, f, now); /* logged to the can-log once the kernel takes it */
    } else {
        canlog_frame(&d->canlog, f);
    }
}

/* Why the state changed (the `cause` key, docs/DESIGN.md): a stop by its reason, told apart by
 * the channel it came on; the other changes by where they lead from. what: the core call. */
static const char *state_cause(uint8_t from, const estop_out_t *out, const char *what)
{
    int by_datagram = strcmp(what, "udp_rx") == 0;

    if (out->state == ESTOP_STATE_STOPPED) {
        switch (out->reason) {
        case ESTOP_REASON_TCP_STOP: return by_datagram ? "stop_datagram" : "tcp_stop";
        case ESTOP_REASON_LIFT: return by_datagram ? "lift_datagram" : "lift";
        case ESTOP_REASON_FAULT:
            /* Outside a reported fault, the clock's only way to a fault is a backwards tick. */
            return (out->changed_by_clock && strcmp(what, "fault") != 0) ? "clock_backwards"
                                                                          : "fault";
        default: return log_reason_name(out->reason);
        }
    }
    if (from == ESTOP_STATE_STOPPED) {
        return "release"; /* to ARMED, or straight to SLOWING for a link silent for S */
    }
    return out->state == ESTOP_STATE_SLOWING ? "udp_silence" : "link_back";
}

static void log_state(const daemon_t *d, const estop_out_t *out, uint64_t now, const char *what,
                      const struct sockaddr_in *src)
{
    char head[32];
    char addr[NET_ADDR_LEN];
    const char *from = log_state_name(d->state);
    const char *to = log_state_name(out->state);
    const char *cause = state_cause(d->state, out, what);

    (void)snprintf(head, sizeof head, "%s->%s", from, to);
    /* A change the clock made (timeout) is nobody's input, whatever call carried it. */
    if (src == NULL || out->changed_by_clock || out->reason == ESTOP_REASON_UDP_TIMEOUT) {
        (void)snprintf(addr, sizeof addr, "-");
    } else {
        net_fmt_addr(src, addr, sizeof addr);
    }
    {
        log_kv_t kv[] = {
            KV_JSTR("from", from),
            KV_JSTR("to", to),
            KV_STR("reason", log_reason_name(out->reason)),
            KV_STR("src", addr),
            KV_STR("cause", cause),
        };
        log_event(now, "state", head, kv, sizeof kv / sizeof kv[0]);
    }
    notify_state(&d->notify, to, out->state == ESTOP_STATE_STOPPED
                                     ? log_reason_name(out->reason) : NULL);
}

static void emit_all(daemon_t *d, const estop_out_t *out, uint64_t now)
{
    unsigned i;
    for (i = 0; i < out->n_can && i < ESTOP_OUT_MAX_CAN; i++) {
        cio_emit(d, &out->can[i], now);
    }
}

unsigned cio_done(daemon_t *d, estop_err_t err, const char *what, const estop_out_t *out,
                  uint64_t now, const struct sockaddr_in *src, int slot)
{
    unsigned res = 0u;
    uint32_t delta;

    /* The core may have advanced its clock before it found the error: whatever it produced
     * (frames, a state change) still goes out. Callers zero out before each call. */
    emit_all(d, out, now);
    if (out->state_changed) {
        log_state(d, out, now, what, src);
        d->state = out->state;
        d->reason = out->reason;
    }
    if (err != ESTOP_OK) {
        log_kv_t kv[] = { KV_STR("call", what), KV_STR("err", estop_err_name(err)) };
        log_event(now, "core_error", NULL, kv, 2u);
        d->deadline_us = now; /* next_call_us may be unset: let a tick tell */
        return CIO_ERROR;
    }
    d->last_call_us = now;
    if (out->has_reply && slot >= 0) {
        /* A reply that cannot be written marks the client; it is closed once its input is
         * handled (clients.c), never here in the middle of it. */
        (void)clients_reply(d, (uint32_t)slot, out->reply, out->reply_len);
    }
    if (out->close_slot) {
        res |= CIO_CLOSE;
    }
    d->state = out->state;
    d->reason = out->reason;
    /* next_call_us is a wrapping tick: a difference over half the range means "already
     * due". */
    delta = out->next_call_us - (uint32_t)now;
    d->deadline_us = delta > ESTOP_MAX_STEP_US ? now : now + delta;
    return res;
}

static void cio_tick(daemon_t *d, uint64_t t)
{
    estop_out_t out;
    estop_err_t err;

    memset(&out, 0, sizeof out);
    err = estop_tick(&d->core, (uint32_t)t, &out);
    if ((cio_done(d, err, "tick", &out, t, NULL, -1) & CIO_ERROR) != 0u) {
        d->fatal = 1; /* without ticks there is no watchdog: give up, the brake brakes */
        return;
    }
    if (d->deadline_us <= t) {
        d->deadline_us = t + 1u; /* never spin on a core that keeps asking for "now" */
    }
}

void cio_fault(daemon_t *d, uint64_t now, const char *cause)
{
    estop_out_t out;
    estop_err_t err;
    log_kv_t kv[] = { KV_STR("cause", cause) };

    log_event(now, "fault", NULL, kv, 1u);
    memset(&out, 0, sizeof out);
    err = estop_fault(&d->core, (uint32_t)now, &out);
    if ((cio_done(d, err, "fault", &out, now, NULL, -1) & CIO_ERROR) != 0u) {
        d->fatal = 1;
    }
}

int cio_boot(daemon_t *d)
{
    uint64_t now = clock_unit_us();
    estop_err_t err = estop_init(&d->core, &d->opt.cfg, (uint32_t)now);

    if (err != ESTOP_OK) {
        log_kv_t kv[] = { KV_STR("call", "init"), KV_STR("err", estop_err_name(err)) };
        log_event(now, "core_error", NULL, kv, 2u);
        return -1;
    }
    d->state = ESTOP_STATE_STOPPED;
    d->reason = ESTOP_REASON_BOOT;
    d->last_call_us = now;
    cio_tick(d, now); /* the boot frames are due at init time */
    return d->fatal ? -1 : 0;
}

/* A gap longer than the core's step (suspend, a stalled host) goes in in steps. */
static void catch_up(daemon_t *d, uint64_t t)
{
    while (!d->fatal && t > d->last_call_us && t - d->last_call_us > ESTOP_MAX_STEP_US) {
        cio_tick(d, d->last_call_us + ESTOP_MAX_STEP_US);
    }
}

void cio_udp(daemon_t *d, const uint8_t *data, size_t len, const struct sockaddr_in *src,
             uint64_t rx_us)
{
    /* The core's clock never goes backwards: a datagram received before the latest call
     * (read late behind other input) goes in at that call's time. */
    uint64_t t = rxtime_feed_us(rx_us, d->last_call_us);
    estop_out_t out;
    estop_err_t err;

    catch_up(d, t);
    if (d->fatal) {
        return;
    }
    memset(&out, 0, sizeof out);
    err = estop_udp_rx(&d->core, data, len, (uint32_t)t, &out);
    (void)cio_done(d, err, "udp_rx", &out, t, src, -1);
}

uint64_t cio_prepare(daemon_t *d)
{
    uint64_t t0;
    uint64_t now;
    const char *cause;
    /* A clock that cannot be read gives a stand-in time (clock.h) and is a fault: the core
     * stops and latches, reported once per episode. */
    int clock_bad = clock_read_us(&t0) != 0;

    if (t0 < d->last_call_us) {
        t0 = d->last_call_us; /* time handed to the core never goes backwards */
    }
    /* Drain first: the unit looks at what it has received before it acts on a deadline. A
     * drain cut short by its budget leaves the rest unread: the deadline is not delayed for
     * packets not yet looked at (the car stops rather than waits). */
    udp_drain(d, t0);
    now = t0 > d->last_call_us ? t0 : d->last_call_us;
    catch_up(d, now);
    if (!d->fatal && now >= d->deadline_us) {
        cio_tick(d, now);
    }
    if (!d->fatal && clock_bad && !d->clock_fault) {
        cio_fault(d, now, "clock");
    }
    d->clock_fault = (uint8_t)clock_bad;
    clients_service(d, now);
    log_housekeeping(now);
    if (!d->fatal && d->can_on) {
        can_service(&d->can, now);
        cause = can_take_fault(&d->can);
        if (cause != NULL) {
            cio_fault(d, now, cause);
        }
    }
    return now;
}

uint64_t cio_wakeup(const daemon_t *d)
{
    uint64_t wake = d->deadline_us;
    uint64_t resume = clients_next_wakeup(d);
    if (resume != 0u && resume < wake) {
        wake = resume;
    }
    if (d->can_on) {
        uint64_t retry = can_next_wakeup(&d->can);
        if (retry != 0u && retry < wake) {
            wake = retry;
        }
    }
    return wake;
}
