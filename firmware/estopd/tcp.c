#include "tcp.h"

#include <errno.h>
#include <netinet/tcp.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"
#include "net.h"

#define ACCEPT_BATCH 16
#define TCP_READ_MAX 256u  /* per wakeup and client: a firehose gets no more than its share */
/* The drain's bound when the socket's receive buffer cannot be read back. */
#define DRAIN_FALLBACK 262144u
/* accept() failing for want of descriptors or memory: stop watching the listener this long
 * instead of spinning on it (it stays readable while the backlog is full). */
#define ACCEPT_PAUSE_US 100000u

void tcp_init(tcp_t *t)
{
    uint32_t i;
    memset(t, 0, sizeof *t);
    t->listen_fd = -1;
    t->epfd = -1;
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        t->clients[i].fd = -1;
    }
    t->accept_paused_until = 0u;
    t->accept_failures = 0u;
}

static void log_client(uint64_t now, const char *event, int slot,
                       const struct sockaddr_in *peer, const char *why, uint32_t dropped)
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

/* A free slot, or else the one quiet longest (no complete frame for the longest time). */
static int pick_slot(const tcp_t *t, int *evict)
{
    int i;
    int quietest = 0;
    for (i = 0; i < (int)ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd < 0) {
            *evict = 0;
            return i;
        }
        if (t->clients[i].quiet_since_us < t->clients[quietest].quiet_since_us) {
            quietest = i;
        }
    }
    *evict = 1;
    return quietest;
}

/* Closes the slot's socket and frees the core's slot. */
static void close_now(tcp_t *t, uint32_t slot, const char *why)
{
    client_t *c = &t->clients[slot];
    unit_fx_t fx;
    uint64_t now;

    if (c->fd < 0) {
        return;
    }
    (void)close(c->fd); /* also leaves epoll */
    c->fd = -1;
    now = t->prepare(t->prepare_ctx);
    unit_tcp_close(t->unit, slot, now, &fx);
    apply_fx(t->apply, &fx, NULL);
    log_client(now, "client_close", (int)slot, &c->peer, why, c->reply.dropped);
}

/* Feeds bytes to the core one frame at a time, as the core asks. Returns 0 while the
 * connection stays usable, -1 once it has been closed. A client whose connection broke while
 * a reply was written is not closed here: the rest of what it sent is handled first (see
 * retire). */
static int feed(tcp_t *t, uint32_t slot, const uint8_t *buf, size_t len)
{
    size_t off = 0;

    while (off < len) {
        unit_fx_t fx;
        size_t used = 0;
        uint64_t now = t->prepare(t->prepare_ctx); /* a due deadline goes before any input */

        unit_tcp_rx(t->unit, slot, buf + off, len - off, &used, now, &fx);
        apply_fx(t->apply, &fx, &t->clients[slot].peer);
        if (fx.err != ESTOP_OK) {
            close_now(t, slot, "core_error");
            return -1;
        }
        if (fx.has_reply) {
            /* A reply that cannot be written marks the client; it is closed once its input
             * is handled (tcp_event), never here in the middle of it. */
            (void)tcp_reply(t, slot, fx.reply, fx.reply_len);
        }
        if (fx.has_reply || fx.close_slot) {
            t->clients[slot].quiet_since_us = now; /* a complete frame */
        }
        if (fx.close_slot) {
            /* Framing is lost: the frames before this one have been handled. */
            log_client(now, "bad_crc", (int)slot, &t->clients[slot].peer, NULL, 0u);
            close_now(t, slot, "bad_crc");
            return -1;
        }
        if (used == 0u || used > len - off) {
            close_now(t, slot, "core_error"); /* would loop forever or overrun */
            return -1;
        }
        off += used;
    }
    return 0;
}

/* How much the drain before a close reads at most. Every byte the kernel has taken on this
 * connection is charged, with its bookkeeping, against the receive buffer (SO_RCVBUF as read
 * back, the doubled value), and the window it advertises never exceeds what is free of it: so
 * what is queued when the drain starts is at most that many bytes. Bytes that arrive while the
 * drain runs (reading opens the window) may add as much again: twice the buffer covers both,
 * and the drain stops earlier, at EAGAIN, when the socket is empty. The bound is there only so
 * a peer that sends as fast as we read cannot hold the loop. */
static size_t drain_bound(int fd)
{
    int rcvbuf = 0;
    socklen_t len = sizeof rcvbuf;
    if (getsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, &len) != 0 || rcvbuf <= 0) {
        return DRAIN_FALLBACK;
    }
    return 2u * (size_t)rcvbuf;
}

/* Handles everything the peer has sent so far (drain_bound), and until host time `until`
 * at most (0: no time limit). The slot may be closed on the way (bad crc, core error). */
static void drain(tcp_t *t, uint32_t slot, uint64_t until)
{
    uint8_t buf[TCP_READ_MAX];
    size_t total = 0;
    size_t bound = t->clients[slot].fd >= 0 ? drain_bound(t->clients[slot].fd) : 0u;

    while (t->clients[slot].fd >= 0 && total < bound &&
           (until == 0u || clock_unit_us() < until)) {
        ssize_t n = recv(t->clients[slot].fd, buf, sizeof buf, MSG_DONTWAIT);
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n <= 0 || feed(t, slot, buf, (size_t)n) != 0) {
            break; /* EAGAIN (all read), end of file, an error, or the core closed it */
        }
        total += (size_t)n;
    }
}

/* Handles everything the peer has sent so far, then closes the connection. */
static void retire(tcp_t *t, uint32_t slot, const char *why)
{
    drain(t, slot, 0u);
    close_now(t, slot, why);
}

/* Hands a fresh connection to the core and to epoll. Returns 0, or -1 (fd left open). */
static int client_start(tcp_t *t, int fd, int slot, const struct sockaddr_in *peer)
{
    struct epoll_event ev;
    unit_fx_t fx;
    uint64_t now = t->prepare(t->prepare_ctx);

    unit_tcp_open(t->unit, (uint32_t)slot, now, &fx);
    apply_fx(t->apply, &fx, peer);
    if (fx.err != ESTOP_OK) {
        return -1;
    }
    memset(&ev, 0, sizeof ev);
    ev.events = EPOLLIN | EPOLLRDHUP;
    ev.data.u64 = t->client_tag0 + (uint64_t)slot;
    if (epoll_ctl(t->epfd, EPOLL_CTL_ADD, fd, &ev) != 0) {
        unit_tcp_close(t->unit, (uint32_t)slot, now, &fx);
        apply_fx(t->apply, &fx, NULL);
        return -1;
    }
    t->clients[slot].fd = fd;
    t->clients[slot].peer = *peer;
    t->clients[slot].quiet_since_us = now;
    reply_reset(&t->clients[slot].reply);
    log_client(now, "client_open", slot, peer, NULL, 0u);
    return 0;
}

static void listener_events(tcp_t *t, uint32_t events)
{
    struct epoll_event ev;
    memset(&ev, 0, sizeof ev);
    ev.events = events;
    ev.data.u64 = t->listen_tag;
    (void)epoll_ctl(t->epfd, EPOLL_CTL_MOD, t->listen_fd, &ev);
}

/* Out of descriptors or memory: the listener stays readable, so stop watching it for a
 * while (the loop keeps serving everything else) and say so once per episode. */
static void pause_accept(tcp_t *t, int e)
{
    uint64_t now = clock_unit_us();
    if (t->accept_failures++ == 0u) {
        char ebuf[16];
        log_kv_t kv[] = { KV_STR("err", log_errno_name(e, ebuf, sizeof ebuf)),
                          KV_MS("retry_ms", ACCEPT_PAUSE_US) };
        log_event(now, "accept_error", NULL, kv, 2u);
    }
    listener_events(t, 0u);
    t->accept_paused_until = now + ACCEPT_PAUSE_US;
}

uint64_t tcp_next_wakeup(const tcp_t *t)
{
    return t->accept_paused_until;
}

void tcp_service(tcp_t *t, uint64_t now)
{
    uint32_t i;
    if (t->accept_paused_until != 0u && now >= t->accept_paused_until) {
        t->accept_paused_until = 0u;
        listener_events(t, EPOLLIN);
    }
    /* The end of a reply the kernel took in part goes out as soon as there is room (the loop
     * comes by at least every brake period). */
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd >= 0 && t->clients[i].reply.rest_len > 0u) {
            (void)reply_flush(&t->clients[i].reply, t->clients[i].fd);
        }
    }
}

void tcp_accept(tcp_t *t)
{
    int i;
    for (i = 0; i < ACCEPT_BATCH; i++) {
        struct sockaddr_in peer;
        socklen_t len = sizeof peer;
        int evict = 0;
        int slot;
        int fd = accept4(t->listen_fd, (struct sockaddr *)&peer, &len, SOCK_NONBLOCK | SOCK_CLOEXEC);

        if (fd < 0) {
            if (errno == EINTR || errno == ECONNABORTED) {
                continue;
            }
            if (errno == EMFILE || errno == ENFILE || errno == ENOBUFS || errno == ENOMEM) {
                pause_accept(t, errno);
            } else if (errno != EAGAIN) {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
                log_limited(LOG_CLASS_NET, clock_unit_us(), "accept_error", kv, 1u);
            }
            return;
        }
        if (t->accept_failures != 0u) {
            log_kv_t kv[] = { KV_NUM("pauses", t->accept_failures) };
            log_event(clock_unit_us(), "accept_ok", NULL, kv, 1u);
            t->accept_failures = 0u;
        }
        slot = pick_slot(t, &evict);
        if (evict) {
            log_client(clock_unit_us(), "client_evict", slot, &t->clients[slot].peer,
                       "make_room", 0u);
            retire(t, (uint32_t)slot, "evicted");
        }
        net_stop_socket_options(fd); /* inherited from the listener; set again all the same */
        if (client_start(t, fd, slot, &peer) != 0) {
            (void)close(fd);
        }
    }
}

int tcp_reply(tcp_t *t, uint32_t slot, const uint8_t *reply, size_t len)
{
    client_t *c = &t->clients[slot];
    reply_result_t res;

    if (c->fd < 0) {
        return -1;
    }
    res = reply_send(&c->reply, c->fd, reply, len);
    if (res == REPLY_DROPPED && c->reply.dropped == 1u) {
        /* Not reading is no reason to close (PROTOCOL.md 2). Whether a window that stays shut
         * counts toward the kernel's user timeout has varied between kernels, so that timeout
         * goes for this client; a peer that vanished still gives up its slot to the next
         * client that needs one (the quietest makes room). */
        unsigned off = 0u;
        (void)setsockopt(c->fd, IPPROTO_TCP, TCP_USER_TIMEOUT, &off, sizeof off);
        log_client(clock_unit_us(), "reply_dropped", (int)slot, &c->peer, "not_reading", 1u);
    }
    return res == REPLY_SENT ? 0 : -1;
}

void tcp_event(tcp_t *t, uint32_t slot)
{
    uint8_t buf[TCP_READ_MAX];
    ssize_t n;
    int fd = t->clients[slot].fd;

    if (fd < 0) {
        return;
    }
    n = recv(fd, buf, sizeof buf, 0);
    if (n == 0) {
        close_now(t, slot, "eof");
        return;
    }
    if (n < 0) {
        if (errno != EAGAIN && errno != EINTR) {
            char ebuf[16];
            close_now(t, slot, log_errno_name(errno, ebuf, sizeof ebuf));
        }
        return;
    }
    if (feed(t, slot, buf, (size_t)n) == 0 && t->clients[slot].reply.hard_err != 0) {
        /* The connection broke under a reply: what the client sent is handled, then it goes. */
        char ebuf[16];
        retire(t, slot, log_errno_name(t->clients[slot].reply.hard_err, ebuf, sizeof ebuf));
    }
}

void tcp_drain_all(tcp_t *t, uint64_t max_us)
{
    uint64_t until = clock_unit_us() + max_us;
    uint32_t i;
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        drain(t, i, until);
    }
}

void tcp_close_all(tcp_t *t, const char *why)
{
    uint32_t i;
    uint64_t now = clock_unit_us();
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd >= 0) {
            (void)close(t->clients[i].fd);
            t->clients[i].fd = -1;
            log_client(now, "client_close", (int)i, &t->clients[i].peer, why,
                       t->clients[i].reply.dropped);
        }
    }
}
