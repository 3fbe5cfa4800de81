/* Start-up: every fd, the core, and the start event. All allocation-free. */
#ifndef ESTOPD_SETUP_H
#define ESTOPD_SETUP_H

#include <stddef.h>

#include "daemon.h"

/* Returns 0, or -1 with a one-line message in err (exit code 1). */
int setup(daemon_t *d, char *err, size_t errlen);
/* --check: what a start would refuse that no restart can mend, without opening a socket (the
 * key file, --rt-prio, --mlock, the CAN interface; the options were parsed already). Returns 0,
 * or -1 with the one-line message a start would give (exit code 1). */
int setup_check(daemon_t *d, char *err, size_t errlen);

#endif
