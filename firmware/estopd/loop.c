#include "loop.h"

#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/signalfd.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"

#define MAX_EVENTS 16
#define EXIT_FLUSH_US 1000000u
/* At exit, what the clients have sent is handled within this long (all of them together): a
 * STOP already in a socket counts and is answered; a client that sends as fast as it is read
 * cannot hold the exit. */
#define EXIT_DRAIN_US 100000u

static int broken(const daemon_t *d)
{
    return d->fatal || d->unit.fatal;
}

/* Silence that has passed by host time t0 while datagrams still wait unread (behind the read
 * budget, or behind a drain cut short for that very deadline): acted on at its own time, with
 * what has been read (the car stops rather than waits for the rest). The core's clock goes no
 * further, so the datagrams still queued go in at their own receive times (or at the
 * deadline's, if they came before it). Returns the core's time after it. */
static uint64_t silence_first(daemon_t *d, uint64_t t0)
{
    uint64_t due = unit_silence_due(&d->unit);
    /* ARMED -> SLOWING -> STOPPED: two deadlines at most, each a tick at its own time. */
    while (!d->unit.fatal && due <= t0) {
        unit_fx_t fx;
        apply_catch_up(&d->apply, &d->unit, due);
        if (d->unit.fatal) {
            break;
        }
        if (unit_tick_due(&d->unit, due, &fx)) {
            apply_fx(&d->apply, &fx, NULL);
        }
        if (unit_silence_due(&d->unit) <= due) {
            break; /* the core did not act on it (it cannot happen): never spin */
        }
        due = unit_silence_due(&d->unit);
    }
    return d->unit.last_call_us;
}

/* One round's work before any input or deadline: reads the clock, drains the control port
 * (every datagram received so far goes to the unit at its receive time), catches the unit up
 * and runs every wake-up source (the unit's due tick first). Returns the host time for the
 * input that follows. No deadline is acted on before what was received before it has been
 * looked at (PROTOCOL.md 6). */
static uint64_t prepare(daemon_t *d)
{
    uint64_t t0;
    uint64_t now;
    /* A clock that cannot be read gives a stand-in time (clock.h) and is a fault: the core
     * stops and latches, reported once per episode. */
    int clock_bad = clock_read_us(&t0) != 0;

    if (t0 < d->unit.last_call_us) {
        t0 = d->unit.last_call_us; /* time handed to the core never goes backwards */
    }
    if (udp_drain(&d->udp, &d->unit, &d->apply, t0)) {
        now = t0 > d->unit.last_call_us ? t0 : d->unit.last_call_us;
    } else {
        /* Cut short by the round's budget, or by a silence deadline that came while the
         * drain read: datagrams received before t0 are still queued. A core call at t0 would
         * hand them over later than they arrived and so stretch the deadline by the backlog's
         * age; the core's clock stays at the latest datagram read, and only a silence that
         * has passed by now (during the drain too) moves it (to its own time). The periodic
         * frames follow the clock: late by the time the backlog takes to read, a few ms. */
        uint64_t t1 = clock_unit_us();
        now = silence_first(d, t1 > t0 ? t1 : t0);
    }
    apply_catch_up(&d->apply, &d->unit, now);
    if (!d->unit.fatal && clock_bad && !d->clock_fault) {
        apply_fault(&d->apply, &d->unit, now, "clock");
    }
    d->clock_fault = (uint8_t)clock_bad;
    wake_service(&d->wake, now);
    return now;
}

static uint64_t prepare_hook(void *ctx)
{
    return prepare(ctx);
}

/* ---- wake-up sources (wake.h) -------------------------------------------------------------- */

static uint64_t unit_next(const void *ctx)
{
    return unit_next_wakeup(&((const daemon_t *)ctx)->unit);
}

static void unit_service(void *ctx, uint64_t now)
{
    daemon_t *d = ctx;
    unit_fx_t fx;
    if (unit_tick_due(&d->unit, now, &fx)) {
        apply_fx(&d->apply, &fx, NULL);
    }
}

static uint64_t tcp_next(const void *ctx)
{
    return tcp_next_wakeup(ctx);
}

static void tcp_service_src(void *ctx, uint64_t now)
{
    tcp_service(ctx, now);
}

static void log_service(void *ctx, uint64_t now)
{
    (void)ctx;
    log_housekeeping(now);
}

static uint64_t can_next(const void *ctx)
{
    return can_next_wakeup(&((const daemon_t *)ctx)->can);
}

static void can_service_src(void *ctx, uint64_t now)
{
    daemon_t *d = ctx;
    const char *cause;
    if (d->unit.fatal) {
        return;
    }
    can_service(&d->can, now);
    cause = can_take_fault(&d->can);
    if (cause != NULL) {
        apply_fault(&d->apply, &d->unit, now, cause);
    }
}

int loop_init(daemon_t *d, char *err, size_t errlen)
{
    d->apply.can = d->can_on ? &d->can : NULL;
    d->apply.canlog = &d->canlog;
    d->apply.notify = &d->notify;
    d->tcp.epfd = d->epfd;
    d->tcp.listen_tag = TAG_TCP;
    d->tcp.client_tag0 = TAG_CLIENT0;
    d->tcp.rx.unit = &d->unit;
    d->tcp.rx.apply = &d->apply;
    d->tcp.rx.prepare = prepare_hook;
    d->tcp.rx.prepare_ctx = d;
    d->stats_src.core = &d->unit.core;
    d->stats_src.cfg = &d->opt.cfg;
    d->stats_src.udp_drops = &d->udp.drops;
    d->stats_src.udp_max_round = &d->udp.max_round;
    d->stats_src.udp_deadline_cuts = &d->udp.deadline_cuts;
    d->stats_src.udp_budget = UDP_ROUND_MAX;
    /* In this order every round: the unit's due tick, the stop port, the log, CAN. */
    if (wake_add(&d->wake, unit_next, unit_service, d) != 0 ||
        wake_add(&d->wake, tcp_next, tcp_service_src, &d->tcp) != 0 ||
        wake_add(&d->wake, NULL, log_service, NULL) != 0 ||
        (d->can_on && wake_add(&d->wake, can_next, can_service_src, d) != 0)) {
        (void)snprintf(err, errlen, "too many wake-up sources (WAKE_MAX)");
        return -1;
    }
    return 0;
}

int loop_boot(daemon_t *d)
{
    unit_fx_t fx;
    int rc = unit_boot(&d->unit, &d->opt.cfg, clock_unit_us(), &fx);
    apply_fx(&d->apply, &fx, NULL);
    return rc;
}

/* ---- the loop ------------------------------------------------------------------------------ */

/* Arms the timerfd (absolute, on the unit's clock: CLOCK_BOOTTIME) for the next wakeup, when it
 * changed. */
static void arm_timer(daemon_t *d)
{
    struct itimerspec its;
    uint64_t wake = wake_next(&d->wake);

    if (wake == d->armed_us || wake == UINT64_MAX) {
        return;
    }
    memset(&its, 0, sizeof its);
    its.it_value.tv_sec = (time_t)(wake / 1000000u);
    its.it_value.tv_nsec = (long)((wake % 1000000u) * 1000u);
    if (its.it_value.tv_sec == 0 && its.it_value.tv_nsec == 0) {
        its.it_value.tv_nsec = 1; /* all-zero would disarm it */
    }
    if (timerfd_settime(d->timerfd, TFD_TIMER_ABSTIME, &its, NULL) != 0) {
        char ebuf[16];
        log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
        log_event(clock_unit_us(), "timer_error", NULL, kv, 1u);
        d->armed_us = 0u; /* the epoll timeout below still wakes us */
        return;
    }
    d->armed_us = wake;
}

/* epoll timeout: a backstop just past the timerfd (which normally wins), never -1. */
static int backstop_ms(const daemon_t *d, uint64_t now)
{
    uint64_t wake = wake_next(&d->wake);
    if (wake <= now) {
        return 0;
    }
    if (wake - now > (uint64_t)ESTOP_MAX_STEP_US) {
        wake = now + ESTOP_MAX_STEP_US; /* nobody asked: the core's longest step */
    }
    return (int)((wake - now) / 1000u + 2u); /* the core's steps are < 2^31 us */
}

static void on_timer(daemon_t *d)
{
    uint64_t expirations;
    /* Clears the expiration; the work itself is prepare's, as for every input. */
    (void)read(d->timerfd, &expirations, sizeof expirations);
    d->armed_us = 0u; /* re-arm next round whatever the deadline is */
    (void)prepare(d);
}

static void on_signal(daemon_t *d)
{
    struct signalfd_siginfo si;
    ssize_t n = read(d->sigfd, &si, sizeof si);
    if (n == (ssize_t)sizeof si) {
        d->stop_signal = (int)si.ssi_signo;
    }
}

static void dispatch(daemon_t *d, const struct epoll_event *ev)
{
    uint64_t tag = ev->data.u64;

    if (tag == TAG_TIMER) {
        on_timer(d);
    } else if (tag == TAG_SIGNAL) {
        on_signal(d);
    } else if (tag == TAG_UDP) {
        (void)prepare(d); /* the drain reads the datagrams (udp.h) */
    } else if (tag == TAG_TCP) {
        tcp_accept(&d->tcp);
    } else if (tag == TAG_CAN) {
        if (d->can_on) {
            can_on_event(&d->can, ev->events, prepare(d));
        }
    } else if (tag >= TAG_CLIENT0 && tag < (uint64_t)TAG_CLIENT0 + ESTOP_MAX_SLOTS) {
        tcp_event(&d->tcp, (uint32_t)(tag - TAG_CLIENT0));
    }
}

static const char *signal_name(int sig)
{
    switch (sig) {
    case SIGTERM: return "SIGTERM";
    case SIGINT: return "SIGINT";
    case SIGHUP: return "SIGHUP";
    default: return "-";
    }
}

/* One last ESTOP_BRAKE frame that says brake (unit_last_frame). */
static void last_frame(daemon_t *d)
{
    uint64_t now = broken(d) ? clock_unit_us() : prepare(d);
    unit_fx_t fx;

    if (!broken(d) && d->unit.state != ESTOP_STATE_STOPPED) {
        log_kv_t kv[] = { KV_STR("cause", "shutdown") };
        log_event(now, "fault", NULL, kv, 1u);
    }
    (void)unit_last_frame(&d->unit, now, !broken(d), &fx);
    apply_fx(&d->apply, &fx, NULL);
}

static int finish(daemon_t *d)
{
    int code = broken(d) ? 1 : 0;

    notify_send(&d->notify, "STOPPING=1");
    udp_round(&d->udp);
    if (!broken(d)) {
        /* connections still in the backlog may hold a STOP too: accepted there */
        tcp_drain_all(&d->tcp, EXIT_DRAIN_US);
    }
    last_frame(d);
    if (d->can_on) {
        can_drain(&d->can, d->opt.cfg.brake_period_us); /* a refused last frame gets a period */
        can_close(&d->can);
    }
    tcp_close_all(&d->tcp, "exit");
    stats_final(&d->stats, &d->stats_src, clock_unit_us());
    log_report(clock_unit_us()); /* what is left to say about lost lines, before the exit line */
    {
        log_kv_t kv[] = { KV_NUM("code", code), KV_STR("signal", signal_name(d->stop_signal)) };
        log_event(clock_unit_us(), "exit", NULL, kv, 2u);
    }
    {
        /* Whatever the readers do, the exit is bounded: the outputs share one deadline. */
        uint64_t start = clock_unit_us();
        uint64_t spent;
        canlog_close(&d->canlog, EXIT_FLUSH_US);
        spent = clock_unit_us() - start;
        log_flush(spent < EXIT_FLUSH_US ? EXIT_FLUSH_US - spent : 0u);
    }
    return code;
}

int loop_run(daemon_t *d)
{
    struct epoll_event evs[MAX_EVENTS];

    while (!broken(d) && d->stop_signal == 0) {
        uint64_t now;
        int n;
        int i;

        udp_round(&d->udp);
        tcp_round(&d->tcp);
        now = prepare(d); /* deadline work first, every round */
        if (broken(d)) {
            break;
        }
        stats_tick(&d->stats, &d->stats_src, now);
        notify_loop(&d->notify, now, broken(d), d->unit.frames_out);
        arm_timer(d);
        n = epoll_wait(d->epfd, evs, MAX_EVENTS, backstop_ms(d, now));
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
                log_event(clock_unit_us(), "epoll_error", NULL, kv, 1u);
            }
            d->fatal = 1;
            break;
        }
        for (i = 0; i < n && !broken(d); i++) {
            dispatch(d, &evs[i]);
        }
    }
    return finish(d);
}
