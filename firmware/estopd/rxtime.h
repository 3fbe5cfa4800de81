/* Receive times of control packets (PROTOCOL.md 6): the kernel stamps a datagram on
 * CLOCK_REALTIME when it arrives; the daemon and its core run on the unit's clock
 * (CLOCK_BOOTTIME, clock.h; "mono" below). Pure
 * functions without clock reads, so they can be tested alone (tests/c/rxtime_check.c). */
#ifndef ESTOPD_RXTIME_H
#define ESTOPD_RXTIME_H

#include <stdint.h>
#include <time.h>

/* The receive time, in monotonic microseconds, of a datagram the kernel stamped `stamp` and
 * the daemon read when the clocks showed real_now and mono_now_us: the stamp moved by the
 * offset between the two clocks, but never later than the reading (a wall clock stepped back
 * since the arrival would put the packet in the future). A step of the wall clock is no error:
 * a stamp from the future gives the read time, one older than the monotonic clock itself 0. */
uint64_t rxtime_to_mono_us(const struct timespec *stamp, const struct timespec *real_now,
                           uint64_t mono_now_us);

/* The time to hand a datagram to the core: its receive time, but never before the previous
 * core call (the core takes a tick that goes backwards for a fault). */
uint64_t rxtime_feed_us(uint64_t recv_us, uint64_t last_call_us);

#endif
