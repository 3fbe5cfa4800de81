#include "client.h"

#include <errno.h>
#include <netinet/tcp.h>
#include <string.h>
#include <sys/socket.h>

#include "clock.h"
#include "log.h"
#include "net.h"

/* The drain's bound when the socket's receive buffer cannot be read back. */
#define DRAIN_FALLBACK 262144u

void client_log(uint64_t now, const char *event, int slot, const struct sockaddr_in *peer,
                const char *why, uint32_t dropped)
{
    char addr[NET_ADDR_LEN];
    log_kv_t kv[4];
    size_t n = 0;

    net_fmt_addr(peer, addr, sizeof addr);
    if (slot >= 0) {
        log_kv_t k = KV_NUM("slot", slot);
        kv[n++] = k;
    }
    {
        log_kv_t k = KV_STR("src", addr);
        kv[n++] = k;
    }
    if (why != NULL) {
        log_kv_t k = KV_STR("why", why);
        kv[n++] = k;
    }
    if (dropped != 0u) {
        log_kv_t k = KV_NUM("replies_dropped", dropped);
        kv[n++] = k;
    }
    /* Anyone can connect as often as they like: these lines are rate-limited. */
    log_limited(LOG_CLASS_CLIENT, now, event, kv, n);
}

/* Writes a reply without blocking (reply.h). A reply dropped because the client does not read
 * is counted, the client stays; a connection broken under it is marked (reply.hard_err) and
 * closed by tcp.c once the input it sent has been handled. */
static void reply(client_t *c, uint32_t slot, const uint8_t *buf, size_t len)
{
    reply_result_t res = reply_send(&c->reply, c->fd, buf, len);
    if (res == REPLY_DROPPED && c->reply.dropped == 1u) {
        /* Not reading is no reason to close (PROTOCOL.md 2). Whether a window that stays shut
         * counts toward the kernel's user timeout has varied between kernels, so that timeout
         * goes for this client; a peer that vanished still gives up its slot to the next
         * client that needs one (the quietest makes room). */
        unsigned off = 0u;
        (void)setsockopt(c->fd, IPPROTO_TCP, TCP_USER_TIMEOUT, &off, sizeof off);
        client_log(clock_unit_us(), "reply_dropped", (int)slot, &c->peer, "not_reading", 1u);
    }
}

/* Feeds bytes to the core one frame at a time, as the core asks. Returns NULL while the
 * connection stays usable, else why the unit wants it closed now. */
static const char *feed(const client_ctx_t *x, client_t *c, uint32_t slot, const uint8_t *buf,
                        size_t len)
{
    size_t off = 0;

    while (off < len) {
        unit_fx_t fx;
        size_t used = 0;
        uint64_t now = x->prepare(x->prepare_ctx); /* a due deadline goes before any input */

        unit_tcp_rx(x->unit, slot, buf + off, len - off, &used, now, &fx);
        apply_fx(x->apply, &fx, &c->peer);
        if (fx.err != ESTOP_OK) {
            return "core_error";
        }
        if (fx.has_reply) {
            reply(c, slot, fx.reply, fx.reply_len);
            c->quiet_since_us = x->round_us; /* a complete frame */
            c->framed = 1u;
        }
        if (fx.close_slot) {
            /* Framing is lost: the frames before this one have been handled. */
            c->quiet_since_us = x->round_us;
            client_log(now, "bad_crc", (int)slot, &c->peer, NULL, 0u);
            return "bad_crc";
        }
        if (used == 0u || used > len - off) {
            return "core_error"; /* would loop forever or overrun */
        }
        off += used;
    }
    return NULL;
}

client_rx_t client_read(const client_ctx_t *x, client_t *c, uint32_t slot, size_t *n, int *err,
                        const char **why)
{
    uint8_t buf[CLIENT_READ_MAX];
    ssize_t got;

    *n = 0u;
    *err = 0;
    *why = NULL;
    do {
        got = recv(c->fd, buf, sizeof buf, MSG_DONTWAIT);
    } while (got < 0 && errno == EINTR);
    if (got == 0) {
        return CLIENT_EOF;
    }
    if (got < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK) {
            return CLIENT_EMPTY;
        }
        *err = errno;
        return CLIENT_EOF;
    }
    *n = (size_t)got;
    *why = feed(x, c, slot, buf, (size_t)got);
    return *why != NULL ? CLIENT_BROKEN : CLIENT_MORE;
}

/* Every byte the kernel has taken on this connection is charged, with its bookkeeping, against
 * the receive buffer (SO_RCVBUF as read back, the doubled value), and the window it advertises
 * never exceeds what is free of it: so what is queued when the drain starts is at most that
 * many bytes. Bytes that arrive while the drain runs (reading opens the window) may add as much
 * again: twice the buffer covers both, and the drain stops earlier, at EAGAIN, when the socket
 * is empty. The bound is there only so a peer that sends as fast as we read cannot hold the
 * loop. */
size_t client_drain_bound(int fd)
{
    int rcvbuf = 0;
    socklen_t len = sizeof rcvbuf;
    if (getsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, &len) != 0 || rcvbuf <= 0) {
        return DRAIN_FALLBACK;
    }
    return 2u * (size_t)rcvbuf;
}
