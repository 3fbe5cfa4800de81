#include "canlog.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"
#include "outfd.h"

int canlog_open(canlog_t *l, const char *path, const char *iface, char *err, size_t errlen)
{
    memset(l, 0, sizeof *l);
    l->fd = -1;
    (void)snprintf(l->iface, sizeof l->iface, "%s", iface);
    if (path == NULL) {
        return 0;
    }
    if (strcmp(path, "-") == 0) {
        l->fd = 1;
    } else {
        /* Append: never clobber an earlier run's log. */
        l->fd = open(path, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
        if (l->fd < 0) {
            (void)snprintf(err, errlen, "cannot open --can-log '%s': %s", path, strerror(errno));
            return -1;
        }
        l->own = 1;
    }
    if (outfd_prepare(l->fd) != 0) {
        (void)snprintf(err, errlen, "cannot set up --can-log '%s': %s", path, strerror(errno));
        return -1;
    }
    return 0;
}

static void canlog_note(canlog_t *l, int ok, int err, uint64_t now_us)
{
    char ebuf[16];
    if (!ok && !l->failing) {
        log_kv_t kv[] = { KV_STR("err", log_errno_name(err, ebuf, sizeof ebuf)) };
        l->failing = 1;
        log_event(now_us, "can_log_error", NULL, kv, 1u);
    } else if (ok && l->failing) {
        log_kv_t kv[] = { KV_NUM("dropped", l->dropped) };
        l->failing = 0;
        log_event(now_us, "can_log_ok", NULL, kv, 1u);
        l->dropped = 0;
    }
}

void canlog_frame(canlog_t *l, const estop_can_frame_t *f, uint64_t now_us)
{
    static const char hex[] = "0123456789ABCDEF";
    char line[96];
    int64_t sec;
    uint32_t usec;
    int n;
    unsigned i, dlc;
    size_t len;

    if (l->fd < 0) {
        return;
    }
    clock_real(&sec, &usec);
    n = snprintf(line, sizeof line, "(%lld.%06u) %s %03X#", (long long)sec, (unsigned)usec,
                 l->iface, (unsigned)(f->id & ESTOP_CAN_ID_MAX));
    if (n < 0 || (size_t)n + 2u * ESTOP_CAN_DLC + 1u >= sizeof line) {
        return;
    }
    len = (size_t)n;
    dlc = f->dlc <= ESTOP_CAN_DLC ? f->dlc : ESTOP_CAN_DLC;
    for (i = 0; i < dlc; i++) {
        line[len++] = hex[f->data[i] >> 4];
        line[len++] = hex[f->data[i] & 0x0Fu];
    }
    line[len++] = '\n';
    if (outfd_write(l->fd, line, len) != 0) {
        l->dropped++;
        canlog_note(l, 0, errno, now_us);
    } else {
        canlog_note(l, 1, 0, now_us);
    }
}

void canlog_close(canlog_t *l)
{
    if (l->own && l->fd >= 0) {
        (void)close(l->fd);
    }
    l->fd = -1;
}
