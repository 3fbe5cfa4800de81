#include "clock.h"

/* The latest time handed out, and CLOCK_BOOTTIME minus CLOCK_MONOTONIC when it was read: the
 * fallback when CLOCK_BOOTTIME fails. One clock per process, as there is one loop. */
static uint64_t last_us;
static uint64_t boot_minus_mono_us;

static int read_us(clockid_t id, uint64_t *t_us)
{
    struct timespec ts;
    if (clock_gettime(id, &ts) != 0 || ts.tv_sec < 0) {
        return -1;
    }
    *t_us = (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
    return 0;
}

int clock_read_us(uint64_t *t_us)
{
    uint64_t boot;
    uint64_t mono;
    int rc = 0;

    if (read_us(CLOCK_UNIT, &boot) == 0) {
        if (read_us(CLOCK_MONOTONIC, &mono) == 0 && boot >= mono) {
            boot_minus_mono_us = boot - mono;
        }
    } else {
        /* No verdict from the unit's clock: time must still move, or no deadline ever passes
         * and no frame goes out. The monotonic clock (which misses suspends) stands in. */
        rc = -1;
        boot = read_us(CLOCK_MONOTONIC, &mono) == 0 ? mono + boot_minus_mono_us : last_us;
    }
    if (boot < last_us) {
        boot = last_us; /* the stand-in may start a little behind */
    }
    last_us = boot;
    *t_us = boot;
    return rc;
}

uint64_t clock_unit_us(void)
{
    uint64_t t;
    (void)clock_read_us(&t);
    return t;
}

/* The wall clock is read between two readings of the unit's time, and paired with the
 * earlier one: a stamp converted with the pair is then too old by at most the gap between
 * them, which can bring a deadline forward, never push it back. A gap wider than
 * PAIR_GAP_US (the thread was preempted between the reads) is read again, up to PAIR_TRIES
 * times, and the narrowest kept. Before, one read after the other: a preemption between them
 * made every datagram of the batch look that much older, and the unit stopped that much
 * before its timeout (HIL under TCG: 2.1 ms; tests/daemon/test_estopd_clock_pair.py). */
#define PAIR_GAP_US 100u
#define PAIR_TRIES 4

void clock_pair(uint64_t *unit_us, struct timespec *real)
{
    uint64_t best_gap = UINT64_MAX;
    int i;

    for (i = 0; i < PAIR_TRIES && best_gap > PAIR_GAP_US; i++) {
        struct timespec r;
        uint64_t before = clock_unit_us();
        uint64_t after;
        if (clock_gettime(CLOCK_REALTIME, &r) != 0) {
            *unit_us = before;
            real->tv_sec = -1; /* no wall clock: rxtime takes the read time */
            real->tv_nsec = 0;
            return;
        }
        after = clock_unit_us(); /* never behind before: clock_read_us does not go back */
        if (after - before < best_gap) {
            best_gap = after - before;
            *unit_us = before;
            *real = r;
        }
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
