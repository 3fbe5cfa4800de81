/* The epoll loop: one timerfd armed for exactly the core's deadline, sockets, signals. */
#ifndef ESTOPD_LOOP_H
#define ESTOPD_LOOP_H

#include "daemon.h"

/* Runs until a signal (exit 0) or a fatal error (exit 1); sends the last brake frame
 * and returns the exit code. */
int loop_run(daemon_t *d);

#endif
