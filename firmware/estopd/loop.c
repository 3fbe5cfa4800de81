#include "loop.h"

#include <errno.h>
#include <signal.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/signalfd.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include "clients.h"
#include "clock.h"
#include "core_io.h"
#include "frame.h"
#include "log.h"
#include "stats.h"
#include "udp.h"

#define MAX_EVENTS 16
#define EXIT_FLUSH_US 1000000u
/* At exit, what the clients have sent is handled within this long (all of them together): a
 * STOP already in a socket counts and is answered; a client that sends as fast as it is read
 * cannot hold the exit. */
#define EXIT_DRAIN_US 100000u

/* Arms the timerfd (absolute, on the unit's clock: CLOCK_BOOTTIME) for the next wakeup, when it
 * changed. */
static void arm_timer(daemon_t *d)
{
    struct itimerspec its;
    uint64_t wake = cio_wakeup(d);

    if (wake == d->armed_us) {
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
    uint64_t wake = cio_wakeup(d);
    if (wake <= now) {
        return 0;
    }
    return (int)((wake - now) / 1000u + 2u); /* the core's steps are < 2^31 us */
}

static void on_timer(daemon_t *d)
{
    uint64_t expirations;
    /* Clears the expiration; the work itself is cio_prepare's, as for every input. */
    if (read(d->timerfd, &expirations, sizeof expirations) < 0 && errno != EAGAIN) {
        d->armed_us = 0u;
    }
    d->armed_us = 0u; /* re-arm next round whatever the deadline is */
    (void)cio_prepare(d);
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
        (void)cio_prepare(d); /* the drain reads the datagrams (udp.h) */
    } else if (tag == TAG_TCP) {
        clients_accept(d);
    } else if (tag == TAG_CAN) {
        if (d->can_on) {
            can_on_event(&d->can, ev->events, cio_prepare(d));
        }
    } else if (tag >= TAG_CLIENT0 && tag < (uint64_t)TAG_CLIENT0 + ESTOP_MAX_SLOTS) {
        clients_event(d, (uint32_t)(tag - TAG_CLIENT0));
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

/* One last ESTOP_BRAKE frame that says brake. ARMED or SLOWING (neither is latched): a fault
 * makes the core itself send the STOPPED frame (valid counter and CRC). Already STOPPED (or
 * the core is broken): the next frame of the sequence is built here. */
static void last_frame(daemon_t *d)
{
    uint32_t before = d->frames_out;
    uint64_t now = d->fatal ? clock_unit_us() : cio_prepare(d);
    estop_can_frame_t f;
    uint8_t reason;

    if (!d->fatal && d->state != ESTOP_STATE_STOPPED) {
        cio_fault(d, now, "shutdown");
    }
    if (d->frames_out != before && d->last_frame.id == d->opt.cfg.brake_can_id &&
        d->last_frame.data[0] == 1u) {
        return;
    }
    reason = d->state == ESTOP_STATE_STOPPED ? d->reason : (uint8_t)ESTOP_REASON_FAULT;
    frame_next_stopped(d->have_brake ? &d->last_brake : NULL, d->opt.cfg.brake_can_id,
                       d->opt.cfg.brake_data_id, reason, &f);
    cio_emit(d, &f, now);
}

static int finish(daemon_t *d)
{
    int code = d->fatal ? 1 : 0;

    notify_send(&d->notify, "STOPPING=1");
    udp_round(d);
    if (!d->fatal) {
        clients_drain_all(d, EXIT_DRAIN_US);
    }
    last_frame(d);
    if (d->can_on) {
        can_drain(&d->can, d->opt.cfg.brake_period_us); /* a refused last frame gets a period */
        can_close(&d->can);
    }
    clients_close_all(d, "exit");
    stats_final(d, clock_unit_us());
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

    while (!d->fatal && d->stop_signal == 0) {
        uint64_t now;
        int n;
        int i;

        udp_round(d);
        now = cio_prepare(d); /* deadline work first, every round */
        if (d->fatal) {
            break;
        }
        stats_tick(d, now);
        notify_loop(&d->notify, now, d->fatal, d->frames_out);
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
        for (i = 0; i < n && !d->fatal; i++) {
            dispatch(d, &evs[i]);
        }
    }
    return finish(d);
}
