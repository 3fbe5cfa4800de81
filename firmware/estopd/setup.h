/* Start-up: every fd, the core, and the start event. All allocation-free. */
#ifndef ESTOPD_SETUP_H
#define ESTOPD_SETUP_H

#include <stddef.h>

#include "daemon.h"

/* Returns 0, or -1 with a one-line message in err (exit code 1). */
int setup(daemon_t *d, char *err, size_t errlen);

#endif
