#include "udp.h"

#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

#include "clock.h"
#include "log.h"
#include "rxtime.h"

#define UDP_BATCH 32u /* datagrams per recvmmsg */
/* Larger than any valid packet. MSG_TRUNC reports the real length; a longer datagram is
 * handed over as exactly this many bytes, which is still an invalid length. */
#define UDP_BUF 64u
/* Room for the control messages asked for, with their headers: SCM_TIMESTAMPNS (a timespec,
 * 32 bytes in all) and SO_RXQ_OVFL (a u32, 24 bytes). */
#define UDP_CTL 64u
/* Receive buffer asked for (the kernel doubles it for its bookkeeping): an 80,000/s flood of
 * 60-byte packets (832 bytes each in the queue on loopback) fills 8 MiB in about 125 ms, so a
 * scheduling hiccup of that long loses nothing. */
#define UDP_RCVBUF (4 * 1024 * 1024)

typedef struct {
    struct mmsghdr msg[UDP_BATCH];
    struct iovec iov[UDP_BATCH];
    struct sockaddr_in src[UDP_BATCH];
    uint8_t buf[UDP_BATCH][UDP_BUF];
    uint64_t ctl[UDP_BATCH][UDP_CTL / 8u]; /* as aligned as a cmsghdr wants (size_t) */
} batch_t;

/* One loop, one batch: static, no heap and no large stack frame. */
static batch_t batch;

int udp_setup(udp_t *u, char *err, size_t errlen)
{
    int one = 1;
    int size = UDP_RCVBUF;
    socklen_t len = sizeof u->rcvbuf;

    /* Without receive stamps a backlog would stretch the deadlines: refuse to run. */
    if (setsockopt(u->fd, SOL_SOCKET, SO_TIMESTAMPNS, &one, sizeof one) != 0) {
        (void)snprintf(err, errlen, "cannot enable SO_TIMESTAMPNS on the UDP socket: %s",
                       strerror(errno));
        return -1;
    }
    /* Past net.core.rmem_max only with CAP_NET_ADMIN; else as much as that allows. A small
     * buffer costs dropped packets under a flood (false stops, never a missed one). */
    if (setsockopt(u->fd, SOL_SOCKET, SO_RCVBUFFORCE, &size, sizeof size) != 0) {
        (void)setsockopt(u->fd, SOL_SOCKET, SO_RCVBUF, &size, sizeof size);
    }
    if (getsockopt(u->fd, SOL_SOCKET, SO_RCVBUF, &u->rcvbuf, &len) != 0) {
        u->rcvbuf = 0;
    }
    u->rcvbuf_wanted = 2 * UDP_RCVBUF;
    /* With every datagram, the kernel's count so far of those it dropped for want of room. */
    (void)setsockopt(u->fd, SOL_SOCKET, SO_RXQ_OVFL, &one, sizeof one);
    /* Every page of the batch now, not under the first flood (memory flat from the start). */
    memset(&batch, 0, sizeof batch);
    udp_round(u);
    return 0;
}

void udp_round(udp_t *u)
{
    u->budget = UDP_ROUND_MAX;
    u->round_read = 0u;
}

static void batch_reset(uint32_t vlen)
{
    uint32_t i;
    for (i = 0u; i < vlen; i++) {
        struct msghdr *h = &batch.msg[i].msg_hdr;
        batch.iov[i].iov_base = batch.buf[i];
        batch.iov[i].iov_len = UDP_BUF;
        memset(h, 0, sizeof *h);
        h->msg_name = &batch.src[i];
        h->msg_namelen = sizeof batch.src[i];
        h->msg_iov = &batch.iov[i];
        h->msg_iovlen = 1u;
        h->msg_control = batch.ctl[i];
        h->msg_controllen = sizeof batch.ctl[i];
        batch.msg[i].msg_len = 0u;
    }
}

/* The kernel's receive stamp (CLOCK_REALTIME) of one datagram: returns 1, or 0 without one.
 * Notes the socket's drop count on the way. */
static int rx_stamp(udp_t *u, struct msghdr *h, struct timespec *ts)
{
    struct cmsghdr *c;
    int found = 0;
    for (c = CMSG_FIRSTHDR(h); c != NULL; c = CMSG_NXTHDR(h, c)) {
        if (c->cmsg_level != SOL_SOCKET) {
            continue;
        }
        if (c->cmsg_type == SCM_TIMESTAMPNS && c->cmsg_len >= CMSG_LEN(sizeof *ts)) {
            memcpy(ts, CMSG_DATA(c), sizeof *ts);
            found = 1;
        } else if (c->cmsg_type == SO_RXQ_OVFL && c->cmsg_len >= CMSG_LEN(sizeof u->drops)) {
            memcpy(&u->drops, CMSG_DATA(c), sizeof u->drops);
        }
    }
    return found;
}

/* One datagram to the unit at its receive time (caught up first), its effects applied. */
static void feed(unit_t *unit, const apply_t *a, const uint8_t *data, size_t len,
                 const struct sockaddr_in *src, uint64_t rx_us)
{
    uint64_t t = unit_feed_time(unit, rx_us);
    unit_fx_t fx;

    apply_catch_up(a, unit, t);
    if (unit->fatal) {
        return;
    }
    unit_udp(unit, data, len, t, &fx);
    apply_fx(a, &fx, src);
}

int udp_drain(udp_t *u, unit_t *unit, const apply_t *a, uint64_t t0)
{
    while (u->budget > 0u && !unit->fatal) {
        uint32_t vlen = u->budget < UDP_BATCH ? u->budget : UDP_BATCH;
        uint64_t read_us;
        struct timespec real_now;
        int reached = 0;
        int n;
        int i;

        batch_reset(vlen);
        n = recvmmsg(u->fd, batch.msg, vlen, MSG_DONTWAIT | MSG_TRUNC, NULL);
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            if (errno != EAGAIN && errno != EWOULDBLOCK) {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
                log_limited(LOG_CLASS_NET, unit->last_call_us, "udp_error", kv, 1u);
            }
            return 1;
        }
        clock_pair(&read_us, &real_now);
        u->budget -= (uint32_t)n;
        u->round_read += (uint32_t)n;
        if (u->round_read > u->max_round) {
            u->max_round = u->round_read;
        }
        for (i = 0; i < n; i++) {
            struct timespec stamp;
            size_t len = batch.msg[i].msg_len < UDP_BUF ? batch.msg[i].msg_len : UDP_BUF;
            uint64_t rx_us = rx_stamp(u, &batch.msg[i].msg_hdr, &stamp) != 0
                                 ? rxtime_to_mono_us(&stamp, &real_now, read_us)
                                 : read_us;
            feed(unit, a, batch.buf[i], len, &batch.src[i], rx_us);
            if (rx_us >= t0) {
                reached = 1; /* arrived after the drain began: what came before is all in */
            }
        }
        /* Fewer than asked for: recvmmsg met an empty socket. */
        if (reached || (uint32_t)n < vlen) {
            return 1;
        }
        /* The silence deadline came while this batch was read (a datagram received after it
         * would have had it acted on in the catch-up): the car stops at it rather than waits
         * for the rest of the round; the caller acts on it at its own time (loop.c). */
        if (clock_unit_us() >= unit_silence_due(unit)) {
            u->deadline_cuts++;
            return unit->fatal ? 1 : 0;
        }
    }
    return unit->fatal ? 1 : 0; /* the budget is spent: what is still queued waits a round */
}
