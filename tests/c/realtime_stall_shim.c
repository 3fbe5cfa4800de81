/* LD_PRELOAD shim for tests/daemon/test_estopd_clock_pair.py: a preemption between estopd's
 * read of its own clock and its read of the wall clock, on demand: the pair it converts the
 * datagrams' kernel stamps with (firmware/estopd/clock.c, clock_pair).
 *
 * After a recvmmsg that returned datagrams, the thread's next read of CLOCK_REALTIME first
 * sleeps $ESTOP_REALTIME_STALL_US microseconds; the reads after it do not, as after a real
 * preemption a pair read again at once finds no gap. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <time.h>

typedef int (*gettime_fn)(clockid_t, struct timespec *);
typedef int (*recvmmsg_fn)(int, struct mmsghdr *, unsigned int, int, struct timespec *);

static __thread int armed;

int recvmmsg(int fd, struct mmsghdr *msgs, unsigned int vlen, int flags, struct timespec *tmo)
{
    static recvmmsg_fn real;
    int n;
    if (real == NULL) {
        real = (recvmmsg_fn)dlsym(RTLD_NEXT, "recvmmsg");
    }
    n = real(fd, msgs, vlen, flags, tmo);
    if (n > 0) {
        armed = 1;
    }
    return n;
}

int clock_gettime(clockid_t id, struct timespec *ts)
{
    static gettime_fn real;
    const char *env = getenv("ESTOP_REALTIME_STALL_US");
    if (real == NULL) {
        real = (gettime_fn)dlsym(RTLD_NEXT, "clock_gettime");
    }
    if (id == CLOCK_REALTIME && armed && env != NULL) {
        long us = strtol(env, NULL, 10);
        struct timespec d = { us / 1000000, (us % 1000000) * 1000 };
        armed = 0;
        (void)nanosleep(&d, NULL);
    }
    return real(id, ts);
}
