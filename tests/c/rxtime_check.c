/* Checks of firmware/estopd/rxtime.c (run by tests/test_estopd_rxtime_unit.py): the kernel's
 * wall-clock receive stamp as the daemon's monotonic time, and the time a datagram is handed
 * to the core. Prints one line per failed check; exit status 0 when all pass. */
#include <stdint.h>
#include <stdio.h>
#include <time.h>

#include "rxtime.h"

static int failures;

static void expect(const char *what, uint64_t got, uint64_t want)
{
    if (got != want) {
        (void)printf("FAIL %s: got %llu, want %llu\n", what, (unsigned long long)got,
                     (unsigned long long)want);
        failures++;
    }
}

static struct timespec ts(long long sec, long nsec)
{
    struct timespec t;
    t.tv_sec = (time_t)sec;
    t.tv_nsec = nsec;
    return t;
}

int main(void)
{
    /* The read: wall clock 1700000000.500000000, monotonic 10000 s. */
    const struct timespec now = ts(1700000000LL, 500000000L);
    const uint64_t mono = 10000000000u;
    struct timespec s;

    s = ts(1700000000LL, 300000000L); /* received 200 ms before the read */
    expect("200 ms old", rxtime_to_mono_us(&s, &now, mono), mono - 200000u);
    s = now;
    expect("received at the read", rxtime_to_mono_us(&s, &now, mono), mono);
    s = ts(1699999999LL, 999999999L); /* a borrow across the second: 500.000001 ms old */
    expect("borrow", rxtime_to_mono_us(&s, &now, mono), mono - 500000u);
    s = ts(1700000000LL, 499999500L); /* 500 ns: not yet a whole microsecond */
    expect("sub-microsecond", rxtime_to_mono_us(&s, &now, mono), mono);
    /* The wall clock stepped back 3 s between arrival and read: the stamp lies in the future.
     * Converted it would be 3 s after the read; the earlier of the two is the read. */
    s = ts(1700000003LL, 500000000L);
    expect("stamp after the read (clock stepped back)", rxtime_to_mono_us(&s, &now, mono), mono);
    s = ts(1700000000LL, 500000001L);
    expect("1 ns after the read", rxtime_to_mono_us(&s, &now, mono), mono);
    /* ... stepped forward an hour: the packet looks an hour older (it only stops sooner). */
    s = ts(1699996400LL, 500000000L);
    expect("clock stepped forward", rxtime_to_mono_us(&s, &now, mono), mono - 3600000000u);
    /* Older than the monotonic clock (or a stamp of 0): 0, never a wrapped huge value. */
    s = ts(1699990000LL, 0L);
    expect("older than the monotonic clock", rxtime_to_mono_us(&s, &now, mono), 0u);
    s = ts(0LL, 0L);
    expect("stamp 0", rxtime_to_mono_us(&s, &now, mono), 0u);
    s = ts(1699990000LL, 500000000L); /* exactly the monotonic clock's age */
    expect("as old as the monotonic clock", rxtime_to_mono_us(&s, &now, mono), 0u);
    s = ts(-5LL, 0L);
    expect("negative stamp", rxtime_to_mono_us(&s, &now, mono), mono);
    s = ts(1700000000LL, 300000000L);
    {
        const struct timespec neg = ts(-1LL, 0L);
        expect("negative wall clock", rxtime_to_mono_us(&s, &neg, mono), mono);
    }
    /* Huge seconds either way: no overflow. */
    {
        const struct timespec far = ts(0x7FFFFFFFFFFFFFFFLL, 0L);
        s = ts(1LL, 0L);
        expect("far future wall clock", rxtime_to_mono_us(&s, &far, mono), 0u);
        expect("far future stamp", rxtime_to_mono_us(&far, &now, mono), mono);
    }
    /* Handed to the core: the receive time, never before the previous call. */
    expect("feed after the last call", rxtime_feed_us(500u, 400u), 500u);
    expect("feed before the last call", rxtime_feed_us(300u, 400u), 400u);
    expect("feed at the last call", rxtime_feed_us(400u, 400u), 400u);
    if (failures == 0) {
        (void)printf("all rxtime checks passed\n");
    }
    return failures == 0 ? 0 : 1;
}
