/* The whole daemon (one static instance, no heap): what the loop and the start-up put
 * together. The parts below it each get the narrow struct they need, never this one. */
#ifndef ESTOPD_DAEMON_H
#define ESTOPD_DAEMON_H

#include <stdint.h>

#include "apply.h"
#include "can.h"
#include "canlog.h"
#include "notify.h"
#include "opts.h"
#include "stats.h"
#include "tcp.h"
#include "udp.h"
#include "unit.h"
#include "wake.h"

/* epoll tags (data.u64). */
enum {
    TAG_TIMER = 1,
    TAG_SIGNAL,
    TAG_UDP,
    TAG_TCP,
    TAG_CAN,
    TAG_CLIENT0 = 16 /* + slot */
};

typedef struct {
    opts_t opt;
    unit_t unit;              /* the core, its time and catch-up */
    apply_t apply;            /* where the unit's frames and state lines go */
    udp_t udp;
    tcp_t tcp;
    int can_on;
    can_t can;
    canlog_t canlog;
    notify_t notify;          /* the systemd notify protocol (no-op without NOTIFY_SOCKET) */
    stats_t stats;
    stats_src_t stats_src;
    wake_t wake;              /* who needs the loop when (wake.h) */
    int epfd;
    int timerfd;
    int sigfd;
    uint16_t udp_port;        /* bound ports (port 0 picks one) */
    uint16_t tcp_port;
    uint64_t armed_us;        /* what the timerfd is armed for (0: never armed) */
    uint8_t clock_fault;      /* the unit's clock failed at its latest read (reported once) */
    int fatal;                /* an unrecoverable error of the loop itself: leave it */
    int stop_signal;          /* the signal that asks us to stop, 0 if none */
} daemon_t;

#endif
