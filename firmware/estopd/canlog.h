/* Every frame sent, in the can-utils log format: "(sec.usec) iface ID#DATA". Lines go through
 * an output queue (outq.h): a slow or stalled reader loses lines, counted, and never holds up
 * the loop. The event log reports the count (output_dropped stream=can_log). */
#ifndef ESTOPD_CANLOG_H
#define ESTOPD_CANLOG_H

#include <net/if.h>
#include <stdint.h>

#include "estop_core.h"
#include "outq.h"

typedef struct {
    int fd;            /* -1: no can-log */
    int own;           /* fd was opened here (close on exit) */
    char iface[IF_NAMESIZE];
    outq_t q;
} canlog_t;

/* path NULL: off; "-": stdout; else a file opened for appending (never blocking: a FIFO with
 * no reader is refused at once). iface: name in the lines. Returns 0, or -1 with a message in
 * err. */
int canlog_open(canlog_t *l, const char *path, const char *iface, char *err, size_t errlen);
/* Queues one line. */
void canlog_frame(canlog_t *l, const estop_can_frame_t *f);
/* Shutdown: gives the writer at most max_us to catch up. */
void canlog_close(canlog_t *l, uint64_t max_us);

#endif
