/* Stall monitor: tells the environment's stalls from the daemon's.
 *
 *     stallmon CPU OUTFILE
 *
 * Pinned to one CPU at real-time priority (SCHED_FIFO 60 when allowed: above the daemon's 50,
 * so a daemon busy at its own priority is never taken for a CPU that did not run), it wakes every
 * 2 ms and writes each interval in which it could not run for 2 ms or more beyond that, as
 * "start end" wall-clock seconds. An RT thread that cannot run means the CPU itself did not run
 * (a VM's vCPU descheduled by a busy host, or held up by the emulator), so nothing else on that
 * CPU could run either: a frame gap that coincides with such a stall is the environment's.
 *
 * In C since 2026-12-03: the Python monitor it replaces used 44 to 58 CPU seconds per CPU of a
 * 300-second HIL run under TCG (each wake-up a fraction of a ms of the guest's CPU). */
#define _GNU_SOURCE
#include "monitor.h"

#include <errno.h>
#include <sched.h>
#include <stdlib.h>
#include <string.h>

#define PERIOD_S 0.002
/* Beyond the period: hilstalls.STALL_EXCUSE_S, the least stall that excuses a late sample. */
#define REPORT_S 0.002

int main(int argc, char **argv)
{
    cpu_set_t set;
    char what[32];
    FILE *out;
    double prev;
    int cpu;
    if (argc != 3) {
        fprintf(stderr, "usage: stallmon CPU OUTFILE\n");
        return 2;
    }
    cpu = atoi(argv[1]);
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    if (sched_setaffinity(0, sizeof set, &set) != 0) {
        fprintf(stderr, "stallmon: cannot pin to CPU %d: %s\n", cpu, strerror(errno));
        return 1;
    }
    snprintf(what, sizeof what, "cpu %d", cpu);
    out = monitor_start(argv[2], what);
    if (out == NULL) {
        return 1;
    }
    prev = monitor_now();
    while (!monitor_stopping()) {
        double now;
        monitor_sleep(PERIOD_S);
        now = monitor_now();
        if (now - prev >= PERIOD_S + REPORT_S) {
            fprintf(out, "%.6f %.6f\n", prev + PERIOD_S, now);
        }
        prev = now;
    }
    fclose(out);
    return 0;
}
