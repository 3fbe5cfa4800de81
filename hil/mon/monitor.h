/* What both HIL monitors share: the start (real-time priority where allowed, an exit at
 * SIGTERM, the output file and its header line) and the wall clock. See stallmon.c, waitmon.c. */
#ifndef HIL_MONITOR_H
#define HIL_MONITOR_H

#include <stdint.h>
#include <stdio.h>

/* Above the daemon's SCHED_FIFO 50 as deployed (hilrun.RT_PRIO): a daemon busy at its own
 * priority is never taken for a CPU that did not run. */
#define MONITOR_PRIORITY 60

/* Opens PATH (line-buffered), asks for SCHED_FIFO MONITOR_PRIORITY, writes the header
 * "# WHAT rt 0|1 pid N" (StallMonitor.realtime reads it), exits at SIGTERM. NULL on error,
 * with the reason on stderr. */
FILE *monitor_start(const char *path, const char *what);

/* Wall-clock seconds (CLOCK_REALTIME, as the harness's time.time()). */
double monitor_now(void);

/* Sleeps SECONDS (relative; a stall makes it late, which is what the monitors measure). */
void monitor_sleep(double seconds);

/* The process should stop (SIGTERM came). */
int monitor_stopping(void);

#endif
