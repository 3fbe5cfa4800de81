/* The HIL monitors' shared start; see monitor.h. */
#define _GNU_SOURCE
#include "monitor.h"

#include <errno.h>
#include <sched.h>
#include <signal.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

static volatile sig_atomic_t stopping = 0;

static void on_term(int sig)
{
    (void)sig;
    stopping = 1;
}

FILE *monitor_start(const char *path, const char *what)
{
    FILE *out = fopen(path, "w");
    struct sched_param sp;
    struct sigaction sa;
    int rt;
    if (out == NULL) {
        fprintf(stderr, "monitor: cannot open %s: %s\n", path, strerror(errno));
        return NULL;
    }
    setvbuf(out, NULL, _IOLBF, 0);
    memset(&sp, 0, sizeof sp);
    sp.sched_priority = MONITOR_PRIORITY;
    rt = sched_setscheduler(0, SCHED_FIFO, &sp) == 0;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_term;
    sigaction(SIGTERM, &sa, NULL);  /* no SA_RESTART: a sleep ends at once */
    fprintf(out, "# %s rt %d pid %ld\n", what, rt, (long)getpid());
    return out;
}

double monitor_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec / 1e9;
}

void monitor_sleep(double seconds)
{
    struct timespec ts;
    ts.tv_sec = (time_t)seconds;
    ts.tv_nsec = (long)((seconds - (double)ts.tv_sec) * 1e9);
    nanosleep(&ts, NULL);
}

int monitor_stopping(void)
{
    return stopping != 0;
}
