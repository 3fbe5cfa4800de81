/* Host clocks for estopd: a 64-bit monotonic microsecond clock and the wall clock for logs. */
#ifndef ESTOPD_CLOCK_H
#define ESTOPD_CLOCK_H

#include <stdint.h>
#include <time.h>

/* CLOCK_MONOTONIC in microseconds (64 bits: never wraps in practice). */
uint64_t clock_mono_us(void);
/* CLOCK_MONOTONIC (microseconds) and CLOCK_REALTIME read one right after the other: their
 * offset at this moment, for converting the kernel's receive stamps (rxtime.h). */
void clock_pair(uint64_t *mono_us, struct timespec *real);
/* CLOCK_REALTIME split into seconds and microseconds (for can-utils log lines). */
void clock_real(int64_t *sec, uint32_t *usec);

#endif
