/* Line output to stderr / the can-log that can never stall the event loop. */
#ifndef ESTOPD_OUTFD_H
#define ESTOPD_OUTFD_H

#include <stddef.h>

/* Makes fd non-blocking when it is a pipe or socket: a reader that stops reading must not
 * stop the watchdog. Files and terminals stay as they are. Returns 0, or -1 (errno set). */
int outfd_prepare(int fd);
/* Writes one whole line. Returns 0, or -1 when (part of) it was dropped (errno set). */
int outfd_write(int fd, const char *buf, size_t len);

#endif
