/* Every frame sent, in the can-utils log format: "(sec.usec) iface ID#DATA". */
#ifndef ESTOPD_CANLOG_H
#define ESTOPD_CANLOG_H

#include <net/if.h>
#include <stdint.h>

#include "estop_core.h"

typedef struct {
    int fd;            /* -1: no can-log */
    int own;           /* fd was opened here (close on exit) */
    char iface[IF_NAMESIZE];
    uint32_t dropped;  /* lines lost in the current failure episode */
    int failing;
} canlog_t;

/* path NULL: off; "-": stdout; else a file opened for appending. iface: name in the lines.
 * Returns 0, or -1 with a message in err. */
int canlog_open(canlog_t *l, const char *path, const char *iface, char *err, size_t errlen);
/* Writes one line, at once. now_us is only used to time-stamp log events about drops. */
void canlog_frame(canlog_t *l, const estop_can_frame_t *f, uint64_t now_us);
void canlog_close(canlog_t *l);

#endif
