/* Periodic read-outs of the core's counters into the event log: every STATS_EVERY_US while
 * there is news, and once more at exit. */
#ifndef ESTOPD_STATS_H
#define ESTOPD_STATS_H

#include <stdint.h>

#include "daemon.h"

#define STATS_EVERY_US 10000000u

/* Call from the loop; cheap until the period has passed. */
void stats_tick(daemon_t *d, uint64_t now_us);
/* Exit: writes what has changed since the last report, whatever the time. */
void stats_final(daemon_t *d, uint64_t now_us);

#endif
