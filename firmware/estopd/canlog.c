#include "canlog.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"

int canlog_open(canlog_t *l, const char *path, const char *iface, char *err, size_t errlen)
{
    l->fd = -1;
    l->own = 0;
    (void)snprintf(l->iface, sizeof l->iface, "%s", iface);
    if (path == NULL) {
        return 0;
    }
    if (strcmp(path, "-") == 0) {
        l->fd = 1;
    } else {
        /* Append: never clobber an earlier run's log. O_NONBLOCK: opening a FIFO with no reader
         * would otherwise wait for one, with the shutdown signals already blocked. */
        l->fd = open(path, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC | O_NONBLOCK, 0644);
        if (l->fd < 0) {
            (void)snprintf(err, errlen, "cannot open --can-log '%s': %s", path,
                           errno == ENXIO ? "a FIFO with no reader (start the reader first)"
                                          : strerror(errno));
            return -1;
        }
        l->own = 1;
    }
    if (outq_start(&l->q, l->fd, err, errlen) != 0) {
        return -1;
    }
    log_watch("can_log", &l->q);
    return 0;
}

void canlog_frame(canlog_t *l, const estop_can_frame_t *f)
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
    (void)outq_put(&l->q, line, len); /* a dropped line is counted and reported by the log */
}

void canlog_close(canlog_t *l, uint64_t max_us)
{
    if (l->fd >= 0) {
        outq_flush(&l->q, max_us);
    }
}
