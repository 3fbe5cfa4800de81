/* Run-queue wait monitor: when was the daemon ready to run, and not let?
 *
 *     waitmon PIDFILE OUTFILE
 *
 * Under TCG the harness runs the daemon as an ordinary process (hil/run), so the guest's own
 * scheduler may hold it back behind the harness's busy processes, which a deployed daemon at
 * SCHED_FIFO 50 never waits for. The kernel counts that time per thread: the second field of
 * /proc/PID/schedstat, nanoseconds runnable on a run queue but not running. At real-time
 * priority (SCHED_FIFO 60, as stallmon) this samples the daemon's main thread (its loop;
 * PIDFILE holds its pid, rewritten at each start) every 2 ms and writes each interval in which
 * that wait grew by more than 1 ms, as "start end" wall-clock seconds, ending at the sample and
 * as long as the growth. The kernel adds a wait when it ends (when the thread runs), so a wait
 * ended within the 2 ms before the sample (more when this monitor itself was held) and began
 * that long before its end: the interval is off by that much. Time in which the daemon slept,
 * blocked or ran is never written: a daemon that sends nothing because it waits for the wrong
 * time, blocks on a write or spins is judged as before (tests/harness/test_hil_waitmon.py).
 *
 * In C since 2026-12-03, and every 2 ms instead of 10: the Python monitor it replaces used 33
 * to 66 CPU seconds of a 300-second HIL run under TCG, and its intervals could lie 10 ms late,
 * past a latency sample of a few ms that the wait had delayed. */
#define _POSIX_C_SOURCE 200809L
#include "monitor.h"

#include <fcntl.h>
#include <stdlib.h>
#include <unistd.h>

#define PERIOD_S 0.002
#define REPORT_S 0.001  /* a growth of the wait beyond this is written */
#define PID_EVERY 25    /* samples between two reads of PIDFILE (50 ms); at once when gone */

static long read_pid(const char *path)
{
    char buf[32];
    ssize_t n;
    long pid;
    int fd = open(path, O_RDONLY);
    if (fd < 0) {
        return -1;
    }
    n = read(fd, buf, sizeof buf - 1);
    close(fd);
    if (n <= 0) {
        return -1;
    }
    buf[n] = '\0';
    pid = strtol(buf, NULL, 10);
    return pid > 0 ? pid : -1;
}

/* The thread's time on a run queue so far (seconds) from its open schedstat, or -1 (gone). */
static double run_wait_s(int fd)
{
    char buf[128];
    char *p;
    ssize_t n = pread(fd, buf, sizeof buf - 1, 0);
    if (n <= 0) {
        return -1.0;
    }
    buf[n] = '\0';
    strtoull(buf, &p, 10);  /* field 1: time on the CPU */
    if (p == buf) {
        return -1.0;
    }
    return (double)strtoull(p, NULL, 10) / 1e9;  /* field 2: time waiting on a run queue */
}

int main(int argc, char **argv)
{
    FILE *out;
    long pid = -1;
    int fd = -1;
    double prev_wait = -1.0;
    unsigned long n = 0;
    if (argc != 3) {
        fprintf(stderr, "usage: waitmon PIDFILE OUTFILE\n");
        return 2;
    }
    out = monitor_start(argv[2], "waits");
    if (out == NULL) {
        return 1;
    }
    while (!monitor_stopping()) {
        double now;
        double wait = -1.0;
        monitor_sleep(PERIOD_S);
        if (pid < 0 || n % PID_EVERY == 0) {
            long fresh = read_pid(argv[1]);
            if (fresh != pid) {  /* a new daemon: no growth to take yet */
                char path[64];
                pid = fresh;
                prev_wait = -1.0;
                if (fd >= 0) {
                    close(fd);
                    fd = -1;
                }
                if (pid > 0) {
                    snprintf(path, sizeof path, "/proc/%ld/schedstat", pid);
                    fd = open(path, O_RDONLY);
                }
            }
        }
        n++;
        now = monitor_now();
        if (fd >= 0) {
            wait = run_wait_s(fd);
        }
        if (wait < 0.0) {
            pid = -1;  /* gone: the pid file is read again at the next sample */
        } else if (prev_wait >= 0.0 && wait - prev_wait > REPORT_S) {
            fprintf(out, "%.6f %.6f\n", now - (wait - prev_wait), now);
        }
        prev_wait = wait;
    }
    if (fd >= 0) {
        close(fd);
    }
    fclose(out);
    return 0;
}
