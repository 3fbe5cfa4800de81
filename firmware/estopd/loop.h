/* The epoll loop: one round drains the control port, catches the unit up and runs every
 * wake-up source (wake.h); then it waits for input or the earliest wake-up. */
#ifndef ESTOPD_LOOP_H
#define ESTOPD_LOOP_H

#include "daemon.h"

/* Wires the parts together (the stop port's prepare hook, the wake-up sources); call once the
 * sockets and CAN are open. Returns 0, or -1 with a message. */
int loop_init(daemon_t *d, char *err, size_t errlen);
/* Boots the unit and sends its boot frames. Returns 0 or -1. */
int loop_boot(daemon_t *d);
/* Runs until a stop signal or a fatal error; returns the exit code. */
int loop_run(daemon_t *d);

#endif
