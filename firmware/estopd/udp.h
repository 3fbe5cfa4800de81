/* UDP control port: every datagram goes to the core at its receive time (PROTOCOL.md 6). */
#ifndef ESTOPD_UDP_H
#define ESTOPD_UDP_H

#include <stddef.h>
#include <stdint.h>

#include "apply.h"
#include "unit.h"

/* Datagrams read per loop round at most: a flood cannot freeze the loop, and the TCP stop
 * channel is served within a round whatever arrives on UDP. */
#define UDP_ROUND_MAX 2048u

typedef struct {
    int fd;
    uint32_t budget;          /* datagrams the drain may still read this loop round */
    int rcvbuf;               /* the receive buffer the kernel gave (bytes, as SO_RCVBUF says) */
    int rcvbuf_wanted;
    uint32_t drops;           /* the kernel's count of datagrams dropped for want of room */
    uint32_t round_read;      /* datagrams read this loop round */
    uint32_t max_round;       /* the most read in one round so far (the stats' udp_reads) */
    uint32_t deadline_cuts;   /* drains cut short by a silence deadline that fell meanwhile */
} udp_t;

/* Asks the kernel for receive stamps on the open socket u->fd. Returns 0, or -1 with a
 * message. */
int udp_setup(udp_t *u, char *err, size_t errlen);
/* A new loop round: the read budget is UDP_ROUND_MAX again. */
void udp_round(udp_t *u);
/* The drain before any deadline is acted on: reads datagrams, oldest first, and hands each to
 * the core at its receive time, until the socket is empty, a datagram received at or after t0
 * (the moment the drain began) has been read, the round's budget is spent, or the unit's
 * silence deadline (unit_silence_due) has come while it read: the clock is looked at after
 * every batch of UDP_BATCH datagrams (32), so a deadline waits for one batch at most, not
 * for the rest of a budget (every tag checked: a MAC a datagram, milliseconds a budget).
 * Returns 1 when everything received before t0 has been handed over, 0 when it was cut short
 * first (more may be queued: the core's clock must then not pass the datagrams still unread,
 * except to act on a silence deadline that has come, loop.c). */
int udp_drain(udp_t *u, unit_t *unit, const apply_t *a, uint64_t t0);

#endif
