#include "clock.h"

#include <time.h>

uint64_t clock_mono_us(void)
{
    struct timespec ts;
    /* CLOCK_MONOTONIC always exists on Linux; a failure would leave ts unset, so report 0
     * and let the caller's "never go backwards" clamp hold the time still. */
    if (clock_gettime(CLOCK_MONOTONIC, &ts) != 0) {
        return 0u;
    }
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

void clock_pair(uint64_t *mono_us, struct timespec *real)
{
    *mono_us = clock_mono_us();
    if (clock_gettime(CLOCK_REALTIME, real) != 0) {
        real->tv_sec = -1; /* no wall clock: rxtime takes the read time */
        real->tv_nsec = 0;
    }
}

void clock_real(int64_t *sec, uint32_t *usec)
{
    struct timespec ts;
    if (clock_gettime(CLOCK_REALTIME, &ts) != 0) {
        ts.tv_sec = 0;
        ts.tv_nsec = 0;
    }
    *sec = (int64_t)ts.tv_sec;
    *usec = (uint32_t)(ts.tv_nsec / 1000);
}
