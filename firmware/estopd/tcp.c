#include "tcp.h"

#include <errno.h>
#include <fcntl.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"
#include "net.h"
#include "room.h"

#define ACCEPT_BATCH 16
/* accept() failing for want of memory (or of descriptors without a spare): stop watching the
 * listener this long instead of spinning on it (it stays readable while the backlog is full). */
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
    t->pending_fd = -1;
    t->spare_fd = -1;
    t->listen_watched = 1u;
}

void tcp_spare_open(tcp_t *t)
{
    /* Without one (a limit too low even for it) accept() at the limit pauses as before. */
    t->spare_fd = open("/dev/null", O_RDONLY | O_CLOEXEC);
}

/* ---- the listener ----------------------------------------------------------------------------- */

static void listener_events(tcp_t *t, uint32_t events)
{
    struct epoll_event ev;
    memset(&ev, 0, sizeof ev);
    ev.events = events;
    ev.data.u64 = t->listen_tag;
    (void)epoll_ctl(t->epfd, EPOLL_CTL_MOD, t->listen_fd, &ev);
}

/* The listener is watched unless accept() is paused or waits for room (watching a listener
 * that stays readable would spin). */
static void listener_sync(tcp_t *t)
{
    uint8_t want = (uint8_t)(t->accept_paused_until == 0u && !room_awaited(t));
    if (want != t->listen_watched && t->listen_fd >= 0) {
        listener_events(t, want ? EPOLLIN : 0u);
        t->listen_watched = want;
    }
}

/* ---- closing --------------------------------------------------------------------------------- */

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
    c->retiring = NULL;
    t->spare_retry = 1u; /* a descriptor came back */
    now = t->rx.prepare(t->rx.prepare_ctx);
    unit_tcp_close(t->rx.unit, slot, now, &fx);
    apply_fx(t->rx.apply, &fx, NULL);
    client_log(now, "client_close", (int)slot, &c->peer, why, c->reply.dropped);
}

/* The close of a retiring client: the errno that broke it, or why it was retired. */
static void close_retired(tcp_t *t, uint32_t slot)
{
    client_t *c = &t->clients[slot];
    char ebuf[16];
    close_now(t, slot, c->retire_err != 0 ? log_errno_name(c->retire_err, ebuf, sizeof ebuf)
                                          : c->retiring);
}

/* One piece of the drain before a close: what the client has sent is read and handled until
 * its socket is empty (then it is closed), its bound is reached, or host time `until`. */
static void retire_step(tcp_t *t, uint32_t slot, uint64_t until)
{
    client_t *c = &t->clients[slot];

    c->drained_round = t->rx.round_us;
    while (c->fd >= 0) {
        size_t n = 0u;
        int err = 0;
        const char *why = NULL;
        client_rx_t r;

        if (c->drained >= c->drain_max) {
            break; /* a peer that sends as fast as we read: what the kernel held is read */
        }
        r = client_read(&t->rx, c, slot, &n, &err, &why);
        if (r == CLIENT_BROKEN) {
            close_now(t, slot, why);
            return;
        }
        if (r != CLIENT_MORE) {
            break; /* empty, end of file or broken: everything it sent has been handled */
        }
        c->drained += n;
        if (clock_unit_us() >= until) {
            if (room_unread(c) > 0) {
                return; /* the rest in the next round (its event), the other clients first */
            }
            break; /* all read: no event would come back for it */
        }
    }
    close_retired(t, slot);
}

/* The client goes once what it has sent is handled (why, or the errno err names it). */
static void retire_begin(tcp_t *t, uint32_t slot, const char *why, int err)
{
    client_t *c = &t->clients[slot];
    c->retiring = why != NULL ? why : "broken";
    c->retire_err = err;
    c->drained = 0u;
    c->drain_max = client_drain_bound(c->fd);
    retire_step(t, slot, clock_unit_us() + TCP_RETIRE_STEP_US);
}

/* ---- placing --------------------------------------------------------------------------------- */

/* Hands a fresh connection to the core and to epoll. Returns 0, or -1 (fd left open). */
static int client_start(tcp_t *t, int fd, int slot, const struct sockaddr_in *peer)
{
    struct epoll_event ev;
    unit_fx_t fx;
    client_t *c = &t->clients[slot];
    uint64_t now = t->rx.prepare(t->rx.prepare_ctx);

    unit_tcp_open(t->rx.unit, (uint32_t)slot, now, &fx);
    apply_fx(t->rx.apply, &fx, peer);
    if (fx.err != ESTOP_OK) {
        return -1;
    }
    memset(&ev, 0, sizeof ev);
    ev.events = EPOLLIN | EPOLLRDHUP;
    ev.data.u64 = t->client_tag0 + (uint64_t)slot;
    if (epoll_ctl(t->epfd, EPOLL_CTL_ADD, fd, &ev) != 0) {
        unit_tcp_close(t->rx.unit, (uint32_t)slot, now, &fx);
        apply_fx(t->rx.apply, &fx, NULL);
        return -1;
    }
    memset(c, 0, sizeof *c);
    c->fd = fd;
    c->peer = *peer;
    c->quiet_since_us = t->rx.round_us;
    reply_reset(&c->reply);
    client_log(now, "client_open", slot, peer, NULL, 0u);
    return 0;
}

/* A fresh connection into a free place, or it waits (pending) for one being emptied. */
static void place(tcp_t *t, int fd, const struct sockaddr_in *peer)
{
    int slot = room_free_slot(t);
    if (slot < 0) {
        t->pending_fd = fd;
        t->pending_peer = *peer;
    } else if (client_start(t, fd, slot, peer) != 0) {
        (void)close(fd);
    }
}

/* Makes what progress it can on room: the spare back, the waiting connection placed, an
 * eviction begun when room is needed (one per round, and none while a client is still being
 * emptied: its place comes free by itself). Never called from prepare (it hands input to the
 * unit). */
static void settle(tcp_t *t)
{
    int pass;
    for (pass = 0; pass < 2; pass++) {
        int slot;
        if (t->spare_fd < 0 && t->spare_retry) {
            t->spare_retry = 0u;
            t->spare_fd = open("/dev/null", O_RDONLY | O_CLOEXEC);
            t->spare_short = (uint8_t)(t->spare_fd < 0 && (errno == EMFILE || errno == ENFILE));
        }
        if (t->spare_fd >= 0) {
            t->spare_short = 0u;
        }
        slot = room_free_slot(t);
        if (t->pending_fd >= 0 && slot >= 0) {
            int fd = t->pending_fd;
            t->pending_fd = -1;
            if (client_start(t, fd, slot, &t->pending_peer) != 0) {
                (void)close(fd);
            }
        }
        if (!room_needed(t) || t->evictions != 0u || room_count(t, 1) != 0u) {
            break;
        }
        slot = room_quietest(t);
        if (slot < 0) {
            break;
        }
        client_log(clock_unit_us(), "client_evict", slot, &t->clients[slot].peer,
                   t->pending_fd >= 0 ? "make_room" : "fd_limit", 0u);
        t->evictions++;
        retire_begin(t, (uint32_t)slot, "evicted", 0);
    }
    listener_sync(t);
}

/* The round's start, strictly later than the last one's (it also names the round). */
static void next_round(tcp_t *t)
{
    uint64_t now = clock_unit_us();
    t->rx.round_us = now > t->rx.round_us ? now : t->rx.round_us + 1u;
}

void tcp_round(tcp_t *t)
{
    next_round(t);
    t->evictions = 0u;
    t->spare_retry = 1u; /* a descriptor another part closed may have come back */
    settle(t);
}

/* Out of memory, or of descriptors without a spare: the listener stays readable, so stop
 * watching it for a while (the loop keeps serving everything else) and say so once per
 * episode. */
static void pause_accept(tcp_t *t, int e)
{
    uint64_t now = clock_unit_us();
    if (t->accept_failures++ == 0u) {
        char ebuf[16];
        log_kv_t kv[] = { KV_STR("err", log_errno_name(e, ebuf, sizeof ebuf)),
                          KV_MS("retry_ms", ACCEPT_PAUSE_US) };
        log_event(now, "accept_error", NULL, kv, 2u);
    }
    t->accept_paused_until = now + ACCEPT_PAUSE_US;
    listener_sync(t);
}

uint64_t tcp_next_wakeup(const tcp_t *t)
{
    if (room_needed(t) && room_count(t, 1) == 0u) {
        return 1u; /* room to make, left for the next round (one eviction per round): now */
    }
    return t->accept_paused_until;
}

void tcp_service(tcp_t *t, uint64_t now)
{
    uint32_t i;
    if (t->accept_paused_until != 0u && now >= t->accept_paused_until) {
        t->accept_paused_until = 0u;
        listener_sync(t);
    }
    /* The end of a reply the kernel took in part goes out as soon as there is room (the loop
     * comes by at least every brake period). */
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd >= 0 && t->clients[i].reply.rest_len > 0u) {
            (void)reply_flush(&t->clients[i].reply, t->clients[i].fd);
        }
    }
}

/* accept4(); at the descriptor limit the spare makes way for it, and the quietest client
 * gives a descriptor back (settle). */
static int accept_fd(tcp_t *t, struct sockaddr_in *peer)
{
    socklen_t len = sizeof *peer;
    int fd = accept4(t->listen_fd, (struct sockaddr *)peer, &len, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0 && (errno == EMFILE || errno == ENFILE) && t->spare_fd >= 0) {
        (void)close(t->spare_fd);
        t->spare_fd = -1;
        t->spare_short = 1u;
        t->spare_retry = 0u; /* nothing came back yet */
        len = sizeof *peer;
        fd = accept4(t->listen_fd, (struct sockaddr *)peer, &len, SOCK_NONBLOCK | SOCK_CLOEXEC);
    }
    return fd;
}

void tcp_accept(tcp_t *t)
{
    int i;
    settle(t);
    for (i = 0; i < ACCEPT_BATCH && !room_awaited(t); i++) {
        struct sockaddr_in peer;
        int fd = accept_fd(t, &peer);

        if (fd < 0) {
            int e = errno;
            if (e == EINTR || e == ECONNABORTED) {
                continue;
            }
            if (e == EMFILE || e == ENFILE || e == ENOBUFS || e == ENOMEM) {
                pause_accept(t, e);
            } else if (e != EAGAIN) {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(e, ebuf, sizeof ebuf)) };
                log_limited(LOG_CLASS_NET, clock_unit_us(), "accept_error", kv, 1u);
            }
            break;
        }
        if (t->accept_failures != 0u) {
            log_kv_t kv[] = { KV_NUM("pauses", t->accept_failures) };
            log_event(clock_unit_us(), "accept_ok", NULL, kv, 1u);
            t->accept_failures = 0u;
        }
        net_stop_socket_options(fd); /* inherited from the listener; set again all the same */
        place(t, fd, &peer);
        settle(t);
    }
    listener_sync(t);
}

void tcp_event(tcp_t *t, uint32_t slot)
{
    client_t *c = &t->clients[slot];
    size_t n = 0u;
    int err = 0;
    const char *why = NULL;
    char ebuf[16];
    client_rx_t r;

    if (c->fd < 0) {
        return;
    }
    if (c->retiring != NULL) {
        if (c->drained_round != t->rx.round_us) { /* one piece a round: its event comes back */
            retire_step(t, slot, clock_unit_us() + TCP_RETIRE_STEP_US);
        }
    } else {
        r = client_read(&t->rx, c, slot, &n, &err, &why);
        if (r == CLIENT_EOF) {
            close_now(t, slot, err != 0 ? log_errno_name(err, ebuf, sizeof ebuf) : "eof");
        } else if (r == CLIENT_BROKEN) {
            close_now(t, slot, why);
        } else if (r == CLIENT_MORE && c->reply.hard_err != 0) {
            /* The connection broke under a reply: what the client sent is handled, then it
             * goes. */
            retire_begin(t, slot, NULL, c->reply.hard_err);
        } else {
            /* still open */
        }
    }
    settle(t); /* a place or a descriptor may have come free */
}

void tcp_drain_all(tcp_t *t, uint64_t max_us)
{
    uint64_t until = clock_unit_us() + max_us;

    /* Passes as loop rounds: the backlog accepted (room made as in any round), then one read
     * of each client in turn, so a busy client in an early slot cannot starve a STOP in a
     * later one. Until nothing is left to read or the time is up. */
    while (clock_unit_us() < until) {
        uint32_t i;
        int more = 0;

        next_round(t);
        t->evictions = 0u;
        tcp_accept(t);
        for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
            client_t *c = &t->clients[i];
            size_t n = 0u;
            int err = 0;
            const char *why = NULL;
            client_rx_t r;

            if (c->fd < 0) {
                continue;
            }
            if (c->retiring != NULL) {
                uint64_t step = clock_unit_us() + TCP_RETIRE_STEP_US;
                retire_step(t, i, step < until ? step : until);
                more |= c->fd >= 0;
                continue;
            }
            r = client_read(&t->rx, c, i, &n, &err, &why);
            if (r == CLIENT_MORE) {
                more = 1;
            } else if (r == CLIENT_BROKEN) {
                close_now(t, i, why);
            } else if (r == CLIENT_EOF) {
                char ebuf[16];
                close_now(t, i, err != 0 ? log_errno_name(err, ebuf, sizeof ebuf) : "eof");
            } else {
                /* nothing more from this one now */
            }
        }
        if (!more && t->pending_fd < 0) {
            break; /* (the next pass's accept places a connection waiting for room) */
        }
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
            client_log(now, "client_close", (int)i, &t->clients[i].peer, why,
                       t->clients[i].reply.dropped);
        }
    }
    if (t->pending_fd >= 0) {
        (void)close(t->pending_fd); /* accepted, never placed: its input was never read */
        client_log(now, "client_close", -1, &t->pending_peer, why, 0u);
        t->pending_fd = -1;
    }
}
