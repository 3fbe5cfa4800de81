#include "notify.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

/* Pings come four times per WATCHDOG_USEC: one late loop iteration does not trip it. */
#define PINGS_PER_INTERVAL 4u

static uint64_t env_u64(const char *name, int *ok)
{
    const char *s = getenv(name);
    char *end = NULL;
    unsigned long long v;
    *ok = 0;
    if (s == NULL || s[0] < '0' || s[0] > '9') {
        return 0u;
    }
    errno = 0;
    v = strtoull(s, &end, 10);
    *ok = (errno == 0 && end != NULL && *end == '\0');
    return (uint64_t)v;
}

int notify_open(notify_t *n, char *err, size_t errlen)
{
    const char *path = getenv("NOTIFY_SOCKET");
    size_t len;
    int ok;
    uint64_t usec;
    uint64_t pid;

    memset(n, 0, sizeof *n);
    n->fd = -1;
    if (path == NULL || (path[0] != '/' && path[0] != '@')) {
        return 0;
    }
    len = strlen(path);
    if (len < 2u || len >= sizeof n->addr.sun_path) {
        return 0;
    }
    n->addr.sun_family = AF_UNIX;
    memcpy(n->addr.sun_path, path, len);
    if (path[0] == '@') {
        n->addr.sun_path[0] = '\0'; /* the abstract namespace */
    }
    n->addr_len = (socklen_t)(offsetof(struct sockaddr_un, sun_path) + len +
                              (path[0] == '@' ? 0u : 1u));
    n->fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    if (n->fd < 0) {
        (void)snprintf(err, errlen, "NOTIFY_SOCKET: socket: %s", strerror(errno));
        return -1;
    }
    usec = env_u64("WATCHDOG_USEC", &ok);
    if (ok && usec > 0u) {
        pid = env_u64("WATCHDOG_PID", &ok);
        if (!ok || pid == (uint64_t)getpid()) {
            n->interval_us = usec / PINGS_PER_INTERVAL;
        }
    }
    return 0;
}

void notify_send(const notify_t *n, const char *msg)
{
    if (n->fd >= 0) {
        ssize_t r;
        do {
            r = sendto(n->fd, msg, strlen(msg), MSG_DONTWAIT | MSG_NOSIGNAL,
                       (const struct sockaddr *)&n->addr, n->addr_len);
        } while (r < 0 && errno == EINTR);
    }
}

void notify_state(const notify_t *n, const char *state, const char *reason)
{
    char msg[64];
    if (n->fd >= 0) {
        if (reason != NULL) {
            (void)snprintf(msg, sizeof msg, "STATUS=watching: %s (%s)", state, reason);
        } else {
            (void)snprintf(msg, sizeof msg, "STATUS=watching: %s", state);
        }
        notify_send(n, msg);
    }
}

void notify_loop(notify_t *n, uint64_t now_us, int fatal, uint32_t frames_out)
{
    if (n->interval_us == 0u || now_us - n->last_ping_us < n->interval_us) {
        return;
    }
    if (!fatal && frames_out != n->frames_at_ping) {
        notify_send(n, "WATCHDOG=1");
        n->frames_at_ping = frames_out;
        n->last_ping_us = now_us;
    }
}
