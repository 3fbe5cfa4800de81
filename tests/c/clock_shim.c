/* LD_PRELOAD shim for estopd's clock tests (tests/test_estopd_clock.py): a suspend of the host
 * and a failing clock, on demand.
 *
 * $ESTOP_CLOCK_SHIM names a file of 16 bytes the test rewrites while the daemon runs:
 *   bytes 0..7   int64 (little-endian) microseconds added to CLOCK_BOOTTIME: a suspend of
 *                that length, as CLOCK_BOOTTIME counts it and CLOCK_MONOTONIC does not
 *   bytes 8..15  uint64, non-zero: clock_gettime(CLOCK_BOOTTIME) fails with EINVAL
 * A timerfd on CLOCK_BOOTTIME armed at an absolute time is armed that much earlier on the
 * real clock, so it fires when the shifted clock says it should. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/timerfd.h>
#include <time.h>
#include <unistd.h>

#define MAX_FD 1024

typedef int (*gettime_fn)(clockid_t, struct timespec *);
typedef int (*tfd_create_fn)(int, int);
typedef int (*tfd_settime_fn)(int, int, const struct itimerspec *, struct itimerspec *);

static volatile const int64_t *ctl; /* [0] offset, [1] fail */
static unsigned char boot_fd[MAX_FD];

static void attach(void)
{
    const char *path;
    int fd;
    void *p;
    if (ctl != NULL) {
        return;
    }
    path = getenv("ESTOP_CLOCK_SHIM");
    if (path == NULL) {
        return;
    }
    fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        return;
    }
    p = mmap(NULL, 16, PROT_READ, MAP_SHARED, fd, 0);
    (void)close(fd);
    if (p != MAP_FAILED) {
        ctl = p;
    }
}

static int64_t offset_us(void)
{
    attach();
    return ctl != NULL ? ctl[0] : 0;
}

int clock_gettime(clockid_t id, struct timespec *ts)
{
    static gettime_fn real;
    int rc;
    if (real == NULL) {
        real = (gettime_fn)dlsym(RTLD_NEXT, "clock_gettime");
    }
    if (id != CLOCK_BOOTTIME) {
        return real(id, ts);
    }
    attach();
    if (ctl != NULL && ctl[1] != 0) {
        errno = EINVAL;
        return -1;
    }
    rc = real(id, ts);
    if (rc == 0) {
        int64_t ns = (int64_t)ts->tv_sec * 1000000000 + ts->tv_nsec + offset_us() * 1000;
        ts->tv_sec = (time_t)(ns / 1000000000);
        ts->tv_nsec = (long)(ns % 1000000000);
    }
    return rc;
}

int timerfd_create(int id, int flags)
{
    static tfd_create_fn real;
    int fd;
    if (real == NULL) {
        real = (tfd_create_fn)dlsym(RTLD_NEXT, "timerfd_create");
    }
    fd = real(id, flags);
    if (fd >= 0 && fd < MAX_FD) {
        boot_fd[fd] = id == CLOCK_BOOTTIME;
    }
    return fd;
}

int timerfd_settime(int fd, int flags, const struct itimerspec *nv, struct itimerspec *old)
{
    static tfd_settime_fn real;
    struct itimerspec its;
    if (real == NULL) {
        real = (tfd_settime_fn)dlsym(RTLD_NEXT, "timerfd_settime");
    }
    if (fd >= 0 && fd < MAX_FD && boot_fd[fd] && (flags & TFD_TIMER_ABSTIME) != 0 &&
        nv != NULL) {
        int64_t ns = (int64_t)nv->it_value.tv_sec * 1000000000 + nv->it_value.tv_nsec -
                     offset_us() * 1000;
        its = *nv;
        if (ns < 1) {
            ns = 1; /* already due: fire at once (0 would disarm) */
        }
        its.it_value.tv_sec = (time_t)(ns / 1000000000);
        its.it_value.tv_nsec = (long)(ns % 1000000000);
        nv = &its;
    }
    return real(fd, flags, nv, old);
}
