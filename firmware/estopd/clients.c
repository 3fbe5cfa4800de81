#include "clients.h"

#include <errno.h>
#include <netinet/tcp.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "clock.h"
#include "core_io.h"
#include "log.h"
#include "net.h"

#define ACCEPT_BATCH 16
#define TCP_READ_MAX 256u /* per wakeup and client: a firehose gets no more than its share */
/* Replies a client has not read yet stay below this (the kernel doubles it): an honest
 * client has one or two outstanding, one that never reads is dropped soon. */
#define TCP_SNDBUF 4096

void clients_init(daemon_t *d)
{
    uint32_t i;
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        d->clients[i].fd = -1;
    }
}

static void log_client(uint64_t now, const char *event, int slot,
                       const struct sockaddr_in *peer, const char *why)
{
    char addr[NET_ADDR_LEN];
    log_kv_t kv[3];
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
    log_event(now, event, NULL, kv, n);
}

static int free_slot(const daemon_t *d)
{
    int i;
    for (i = 0; i < (int)ESTOP_MAX_SLOTS; i++) {
        if (d->clients[i].fd < 0) {
            return i;
        }
    }
    return -1;
}

/* Hands a fresh connection to the core and to epoll. Returns 0, or -1 (fd left open). */
static int client_start(daemon_t *d, int fd, int slot, const struct sockaddr_in *peer)
{
    struct epoll_event ev;
    estop_out_t out;
    estop_err_t err;
    uint64_t now = cio_prepare(d);

    memset(&out, 0, sizeof out);
    err = estop_tcp_open(&d->core, (uint32_t)slot, (uint32_t)now, &out);
    if ((cio_done(d, err, "tcp_open", &out, now, peer, -1) & CIO_ERROR) != 0u) {
        return -1;
    }
    memset(&ev, 0, sizeof ev);
    ev.events = EPOLLIN | EPOLLRDHUP;
    ev.data.u64 = (uint64_t)TAG_CLIENT0 + (uint64_t)slot;
    if (epoll_ctl(d->epfd, EPOLL_CTL_ADD, fd, &ev) != 0) {
        memset(&out, 0, sizeof out);
        err = estop_tcp_close(&d->core, (uint32_t)slot, (uint32_t)now, &out);
        (void)cio_done(d, err, "tcp_close", &out, now, NULL, -1);
        return -1;
    }
    d->clients[slot].fd = fd;
    d->clients[slot].peer = *peer;
    log_client(now, "client_open", slot, peer, NULL);
    return 0;
}

void clients_accept(daemon_t *d)
{
    int i;
    for (i = 0; i < ACCEPT_BATCH; i++) {
        struct sockaddr_in peer;
        socklen_t len = sizeof peer;
        int one = 1;
        int sndbuf = TCP_SNDBUF;
        int slot;
        int fd = accept4(d->tcp_fd, (struct sockaddr *)&peer, &len, SOCK_NONBLOCK | SOCK_CLOEXEC);

        if (fd < 0) {
            if (errno == EINTR || errno == ECONNABORTED) {
                continue;
            }
            if (errno != EAGAIN) {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
                log_event(clock_mono_us(), "accept_error", NULL, kv, 1u);
            }
            return;
        }
        slot = free_slot(d);
        if (slot < 0) {
            log_client(clock_mono_us(), "client_reject", -1, &peer, "no_free_slot");
            (void)close(fd);
            continue;
        }
        /* Replies are single small frames: send them at once, and keep few unread ones.
         * Failing here only costs latency or memory, so the results do not matter. */
        (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        (void)setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &sndbuf, sizeof sndbuf);
        if (client_start(d, fd, slot, &peer) != 0) {
            (void)close(fd);
        }
    }
}

int clients_reply(daemon_t *d, uint32_t slot, const uint8_t *reply)
{
    ssize_t n;
    int fd = d->clients[slot].fd;

    if (fd < 0) {
        return -1;
    }
    do {
        n = send(fd, reply, ESTOP_TCP_FRAME_LEN, MSG_NOSIGNAL | MSG_DONTWAIT);
    } while (n < 0 && errno == EINTR);
    /* A client that does not read its replies is dropped, never waited for; a partial
     * write would break its framing, so that drops it too. */
    return n == (ssize_t)ESTOP_TCP_FRAME_LEN ? 0 : -1;
}

void clients_close(daemon_t *d, uint32_t slot, const char *why)
{
    client_t *c = &d->clients[slot];
    estop_out_t out;
    estop_err_t err;
    uint64_t now;

    if (c->fd < 0) {
        return;
    }
    (void)close(c->fd); /* also leaves epoll */
    c->fd = -1;
    now = cio_prepare(d);
    memset(&out, 0, sizeof out);
    err = estop_tcp_close(&d->core, slot, (uint32_t)now, &out);
    (void)cio_done(d, err, "tcp_close", &out, now, NULL, -1);
    log_client(now, "client_close", (int)slot, &c->peer, why);
}

/* Feeds bytes to the core one frame at a time, as the core asks. */
static void feed(daemon_t *d, uint32_t slot, const uint8_t *buf, size_t len)
{
    size_t off = 0;

    while (off < len) {
        estop_out_t out;
        size_t used = 0;
        uint64_t now = cio_prepare(d); /* a due deadline goes before any input */
        estop_err_t err;
        unsigned res;

        memset(&out, 0, sizeof out);
        err = estop_tcp_rx(&d->core, slot, buf + off, len - off, &used, (uint32_t)now, &out);
        res = cio_done(d, err, "tcp_rx", &out, now, &d->clients[slot].peer, (int)slot);
        if ((res & CIO_ERROR) != 0u) {
            clients_close(d, slot, "core_error");
            return;
        }
        if ((res & CIO_CLOSE) != 0u) {
            log_client(now, "bad_crc", (int)slot, &d->clients[slot].peer, NULL);
            clients_close(d, slot, "bad_crc");
            return;
        }
        if ((res & CIO_DROP) != 0u) {
            clients_close(d, slot, "reply_blocked");
            return;
        }
        if (used == 0u || used > len - off) {
            clients_close(d, slot, "core_error"); /* would loop forever or overrun */
            return;
        }
        off += used;
    }
}

void clients_event(daemon_t *d, uint32_t slot)
{
    uint8_t buf[TCP_READ_MAX];
    ssize_t n;
    int fd = d->clients[slot].fd;

    if (fd < 0) {
        return;
    }
    n = recv(fd, buf, sizeof buf, 0);
    if (n == 0) {
        clients_close(d, slot, "eof");
        return;
    }
    if (n < 0) {
        if (errno != EAGAIN && errno != EINTR) {
            clients_close(d, slot, "error");
        }
        return;
    }
    feed(d, slot, buf, (size_t)n);
}

void clients_close_all(daemon_t *d, const char *why)
{
    uint32_t i;
    uint64_t now = clock_mono_us();
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        if (d->clients[i].fd >= 0) {
            (void)close(d->clients[i].fd);
            d->clients[i].fd = -1;
            log_client(now, "client_close", (int)i, &d->clients[i].peer, why);
        }
    }
}
