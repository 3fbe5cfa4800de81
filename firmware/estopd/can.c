#include "can.h"

#include <errno.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <stdio.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"

#define CAN_RX_BATCH 16

/* Raw socket bound to c->iface, non-blocking, receiving error frames only. */
static int can_socket(can_t *c, char *err, size_t errlen)
{
    const can_err_mask_t mask = CAN_ERR_TX_TIMEOUT | CAN_ERR_CRTL | CAN_ERR_BUSOFF |
                                CAN_ERR_RESTARTED;
    struct sockaddr_can addr;
    struct epoll_event ev;
    unsigned idx;
    int fd;

    fd = socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW);
    if (fd < 0) {
        (void)snprintf(err, errlen, "socket(AF_CAN, CAN_RAW) failed: %s (no SocketCAN?)",
                       strerror(errno));
        return -1;
    }
    idx = if_nametoindex(c->iface);
    if (idx == 0u) {
        (void)snprintf(err, errlen, "no CAN interface '%s': %s", c->iface, strerror(errno));
        (void)close(fd);
        return -1;
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = (int)idx;
    /* No data frames in (an empty filter list), only the controller's error frames. */
    if (setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FILTER, NULL, 0) != 0 ||
        setsockopt(fd, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &mask, sizeof mask) != 0 ||
        bind(fd, (struct sockaddr *)&addr, sizeof addr) != 0) {
        (void)snprintf(err, errlen, "cannot set up CAN socket on '%s': %s", c->iface,
                       strerror(errno));
        (void)close(fd);
        return -1;
    }
    memset(&ev, 0, sizeof ev);
    ev.events = EPOLLIN;
    ev.data.u64 = c->ep_tag;
    if (epoll_ctl(c->epfd, EPOLL_CTL_ADD, fd, &ev) != 0) {
        (void)snprintf(err, errlen, "epoll_ctl(CAN): %s", strerror(errno));
        (void)close(fd);
        return -1;
    }
    c->fd = fd;
    return 0;
}

int can_open(can_t *c, const char *iface, uint32_t brake_id, uint32_t brake_period_us,
             canlog_t *log, int epfd, uint64_t ep_tag, char *err, size_t errlen)
{
    memset(c, 0, sizeof *c);
    c->fd = -1;
    c->epfd = epfd;
    c->ep_tag = ep_tag;
    (void)snprintf(c->iface, sizeof c->iface, "%s", iface);
    c->log = log;
    c->brake_id = brake_id;
    c->brake_period_us = brake_period_us;
    return can_socket(c, err, errlen);
}

static void can_log(const can_t *c, uint64_t now, const char *what, int err)
{
    char ebuf[16];
    log_kv_t kv[] = {
        KV_STR("what", what),
        KV_STR("iface", c->iface),
        KV_STR("err", log_errno_name(err, ebuf, sizeof ebuf)),
    };
    log_event(now, "can_error", NULL, kv, err != 0 ? 3u : 2u);
}

/* The interface vanished (ENODEV/ENXIO): drop the socket, look for it again later. */
static void can_lost(can_t *c, uint64_t now)
{
    if (c->fd >= 0) {
        (void)close(c->fd); /* closing also removes it from epoll */
        c->fd = -1;
        c->reopen_at = now + CAN_REOPEN_US;
    }
}

static void can_reopen(can_t *c, uint64_t now)
{
    char err[160];
    if (now < c->reopen_at) {
        return;
    }
    if (can_socket(c, err, sizeof err) != 0) {
        c->reopen_at = now + CAN_REOPEN_US;
        return;
    }
    {
        log_kv_t kv[] = { KV_STR("iface", c->iface) };
        log_event(now, "can_reopened", NULL, kv, 1u);
    }
}

/* One write; returns 0 or an errno value. */
static int can_write(const can_t *c, const estop_can_frame_t *f)
{
    struct can_frame cf;
    ssize_t n;

    if (c->fd < 0) {
        return ENODEV;
    }
    memset(&cf, 0, sizeof cf);
    cf.can_id = f->id & CAN_SFF_MASK;
    cf.can_dlc = f->dlc <= CAN_MAX_DLEN ? f->dlc : (uint8_t)CAN_MAX_DLEN;
    memcpy(cf.data, f->data, cf.can_dlc);
    do {
        n = write(c->fd, &cf, sizeof cf);
    } while (n < 0 && errno == EINTR);
    if (n == (ssize_t)sizeof cf) {
        return 0;
    }
    return n < 0 ? errno : EIO;
}

static void note_failure(can_t *c, int err, uint64_t now)
{
    c->tx_failures++;
    if (err != c->tx_err) {
        /* Once per episode (and when the cause changes), not once per retry. */
        can_log(c, now, "tx_failed", err);
        c->tx_err = err;
    }
    if (err == ENODEV || err == ENXIO) {
        can_lost(c, now);
    }
}

static void note_success(can_t *c, const estop_can_frame_t *f, uint64_t now)
{
    if (c->tx_err != 0) {
        log_kv_t kv[] = { KV_STR("iface", c->iface), KV_NUM("failures", c->tx_failures) };
        log_event(now, "can_recovered", NULL, kv, 2u);
        c->tx_err = 0;
        c->tx_failures = 0;
    }
    if (f->id == c->brake_id) {
        c->stuck = 0;
        c->fault_reported = 0;
    }
    canlog_frame(c->log, f);
}

static void queue_remove(can_t *c, size_t i)
{
    for (; i + 1u < c->n_queue; i++) {
        c->queue[i] = c->queue[i + 1u];
    }
    c->n_queue--;
}

/* Newest frame per CAN id: a newer frame (newer counter, newer state) replaces an old one. */
static void queue_add(can_t *c, const estop_can_frame_t *f)
{
    size_t i;
    for (i = 0; i < c->n_queue; i++) {
        if (c->queue[i].id == f->id) {
            queue_remove(c, i);
            break;
        }
    }
    if (c->n_queue == CAN_QUEUE_LEN) {
        queue_remove(c, 0);
    }
    c->queue[c->n_queue++] = *f;
}

/* Index of the next frame to send: brake frames go first. */
static size_t queue_next(const can_t *c)
{
    size_t i;
    for (i = 0; i < c->n_queue; i++) {
        if (c->queue[i].id == c->brake_id) {
            return i;
        }
    }
    return 0;
}

static void check_stuck(can_t *c, uint64_t now)
{
    size_t i;
    int brake_waiting = 0;

    for (i = 0; i < c->n_queue; i++) {
        brake_waiting |= (c->queue[i].id == c->brake_id);
    }
    if (brake_waiting && !c->stuck) {
        c->stuck = 1;
        c->stuck_since = now;
    }
    /* A brake frame that could not go out for a whole period: the bus may be starved of
     * brake frames; stop (once per episode) rather than hope. */
    if (c->stuck && !c->fault_reported && now - c->stuck_since >= c->brake_period_us) {
        c->fault_reported = 1;
        c->fault_pending = 1;
        c->fault_cause = "can_tx";
    }
}

static void flush(can_t *c, uint64_t now)
{
    if (c->fd < 0) {
        can_reopen(c, now);
    }
    while (c->fd >= 0 && c->n_queue > 0u) {
        size_t i = queue_next(c);
        estop_can_frame_t f = c->queue[i];
        int err = can_write(c, &f);
        if (err != 0) {
            note_failure(c, err, now);
            break;
        }
        queue_remove(c, i);
        note_success(c, &f, now);
    }
    if (c->n_queue > 0u) {
        /* While the interface is gone only a reopen can help: wait for that. */
        c->retry_at = c->fd < 0 ? c->reopen_at : now + CAN_RETRY_US;
    }
    check_stuck(c, now);
}

void can_send(can_t *c, const estop_can_frame_t *f, uint64_t now_us)
{
    queue_add(c, f);
    flush(c, now_us);
}

void can_service(can_t *c, uint64_t now_us)
{
    if (c->n_queue > 0u && now_us >= c->retry_at) {
        flush(c, now_us);
    } else {
        check_stuck(c, now_us);
    }
}

uint64_t can_next_wakeup(const can_t *c)
{
    if (c->n_queue == 0u) {
        return 0u;
    }
    return c->retry_at;
}

const char *can_take_fault(can_t *c)
{
    if (!c->fault_pending) {
        return NULL;
    }
    c->fault_pending = 0;
    return c->fault_cause;
}

static void on_error_frame(can_t *c, const struct can_frame *cf, uint64_t now)
{
    canid_t cls = cf->can_id & CAN_ERR_MASK;
    uint8_t ctrl = cf->data[1];

    if ((cls & CAN_ERR_BUSOFF) != 0u) {
        /* Frames queued in the driver will not reach the brake: stop. */
        can_log(c, now, "bus_off", 0);
        c->fault_pending = 1;
        c->fault_cause = "can_bus_off";
    }
    if ((cls & CAN_ERR_CRTL) != 0u) {
        if ((ctrl & CAN_ERR_CRTL_TX_PASSIVE) != 0u) {
            can_log(c, now, "error_passive_tx", 0);
        }
        if ((ctrl & CAN_ERR_CRTL_RX_PASSIVE) != 0u) {
            can_log(c, now, "error_passive_rx", 0);
        }
        if ((ctrl & (CAN_ERR_CRTL_TX_WARNING | CAN_ERR_CRTL_RX_WARNING)) != 0u) {
            can_log(c, now, "error_warning", 0);
        }
        if ((ctrl & (CAN_ERR_CRTL_TX_OVERFLOW | CAN_ERR_CRTL_RX_OVERFLOW)) != 0u) {
            can_log(c, now, "overflow", 0);
        }
#ifdef CAN_ERR_CRTL_ACTIVE
        if ((ctrl & CAN_ERR_CRTL_ACTIVE) != 0u) {
            can_log(c, now, "error_active", 0);
        }
#endif
    }
    if ((cls & CAN_ERR_RESTARTED) != 0u) {
        can_log(c, now, "restarted", 0);
    }
    if ((cls & CAN_ERR_TX_TIMEOUT) != 0u) {
        can_log(c, now, "tx_timeout", 0);
    }
}

/* A pending socket error (ENETDOWN when the link goes down, ENODEV when it is removed).
 * Reading SO_ERROR clears it, so epoll does not report it again and again. */
static void on_socket_error(can_t *c, int err, uint64_t now)
{
    if (err == 0) {
        return;
    }
    can_log(c, now, err == ENETDOWN ? "iface_down" : "socket", err);
    if (err == ENODEV || err == ENXIO) {
        can_lost(c, now);
    }
}

void can_on_event(can_t *c, uint32_t events, uint64_t now_us)
{
    struct can_frame cf;
    int i;

    if (c->fd < 0) {
        return;
    }
    if ((events & EPOLLERR) != 0u) {
        int err = 0;
        socklen_t len = sizeof err;
        if (getsockopt(c->fd, SOL_SOCKET, SO_ERROR, &err, &len) != 0) {
            err = errno;
        }
        on_socket_error(c, err, now_us);
    }
    for (i = 0; i < CAN_RX_BATCH && c->fd >= 0; i++) {
        ssize_t n = read(c->fd, &cf, sizeof cf);
        if (n < 0) {
            if (errno != EAGAIN && errno != EINTR) {
                on_socket_error(c, errno, now_us);
            }
            break;
        }
        if (n == (ssize_t)sizeof cf && (cf.can_id & CAN_ERR_FLAG) != 0u) {
            on_error_frame(c, &cf, now_us);
        }
    }
}

void can_drain(can_t *c, uint64_t max_us)
{
    uint64_t start = clock_unit_us();
    const struct timespec pause = { 0, 500000L };

    while (c->n_queue > 0u) {
        uint64_t now = clock_unit_us();
        if (now - start >= max_us) {
            break;
        }
        c->retry_at = now;
        can_service(c, now);
        if (c->n_queue > 0u) {
            (void)nanosleep(&pause, NULL);
        }
    }
}

void can_close(can_t *c)
{
    if (c->fd >= 0) {
        (void)close(c->fd);
    }
    c->fd = -1;
}
