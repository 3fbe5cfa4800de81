/* The daemon's whole state (one static instance, no heap) and the hooks its parts share. */
#ifndef ESTOPD_DAEMON_H
#define ESTOPD_DAEMON_H

#include <netinet/in.h>
#include <stdint.h>

#include "can.h"
#include "canlog.h"
#include "estop_core.h"
#include "notify.h"
#include "opts.h"
#include "reply.h"

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
    int fd;                   /* -1: slot free */
    struct sockaddr_in peer;
    uint64_t quiet_since_us;  /* accepted, or its latest complete frame: who makes room */
    reply_state_t reply;      /* replies not read: dropped and counted, never waited for */
} client_t;

typedef struct {
    opts_t opt;
    estop_core_t core;
    int epfd;
    int timerfd;
    int sigfd;
    int udp_fd;
    uint32_t udp_budget;      /* datagrams the drain may still read this loop round */
    int udp_rcvbuf;           /* the receive buffer the kernel gave (bytes, as SO_RCVBUF says) */
    int udp_rcvbuf_wanted;
    uint32_t udp_drops;       /* the kernel's count of datagrams dropped for want of room */
    int tcp_fd;
    uint16_t udp_port;        /* bound ports (port 0 picks one) */
    uint16_t tcp_port;
    client_t clients[ESTOP_MAX_SLOTS];
    uint64_t accept_paused_until; /* listener unwatched until then (EMFILE...), 0: watched */
    uint32_t accept_failures;     /* pauses in the current episode */
    int can_on;
    can_t can;
    canlog_t canlog;
    uint64_t last_call_us;    /* host time of the latest successful core call */
    uint64_t deadline_us;     /* host time the core asked to be called back */
    uint64_t armed_us;        /* what the timerfd is armed for (0: never armed) */
    uint8_t state;
    uint8_t reason;
    estop_can_frame_t last_brake; /* latest brake frame the core produced */
    uint8_t have_brake;
    uint8_t clock_fault;      /* the unit's clock failed at its latest read (reported once) */
    uint32_t frames_out;      /* frames handed out so far */
    estop_can_frame_t last_frame;
    uint64_t stats_last_us;   /* the latest periodic read-out (stats.c) */
    uint64_t stats_auth_reported; /* authentication failures already in the log */
    uint32_t stats_valid_reported; /* valid packets in the latest link_histogram */
    uint32_t stats_slowdowns_reported; /* ... and slow-downs and timeouts */
    uint32_t stats_timeouts_reported;
    uint32_t stats_drops_reported; /* udp_drops in the latest udp_drops event */
    notify_t notify;          /* the systemd notify protocol (no-op without NOTIFY_SOCKET) */
    int fatal;                /* an unrecoverable error: leave the loop */
    int stop_signal;          /* the signal that asks us to stop, 0 if none */
} daemon_t;

#endif
