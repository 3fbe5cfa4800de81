/* Host clocks for estopd: a 64-bit monotonic microsecond clock and the wall clock for logs. */
#ifndef ESTOPD_CLOCK_H
#define ESTOPD_CLOCK_H

#include <stdint.h>

/* CLOCK_MONOTONIC in microseconds (64 bits: never wraps in practice). */
uint64_t clock_mono_us(void);
/* CLOCK_REALTIME split into seconds and microseconds (for can-utils log lines). */
void clock_real(int64_t *sec, uint32_t *usec);

#endif
