/* Host clocks for estopd: the unit's 64-bit microsecond clock and the wall clock for logs.
 *
 * The unit's clock is CLOCK_BOOTTIME: it counts a suspend of the host, where CLOCK_MONOTONIC
 * stops. The watchdog measures silence of the link; a host suspended for minutes has heard
 * nothing for minutes, so a resume must look like a silence of that length (the normal timeout
 * stop; a STOPPED unit's run of valid packets starts over). The timerfd runs on the same clock
 * (setup.c), so a deadline that passed during the suspend fires at the resume. */
#ifndef ESTOPD_CLOCK_H
#define ESTOPD_CLOCK_H

#include <stdint.h>
#include <time.h>

/* The clock id of the unit's time (for timerfd_create). */
#define CLOCK_UNIT CLOCK_BOOTTIME

/* The unit's time in microseconds (64 bits: never wraps in practice). Returns 0, or -1 when
 * CLOCK_BOOTTIME could not be read: *t_us is then an estimate (CLOCK_MONOTONIC moved by the
 * two clocks' last known offset, or the last time read) that never goes backwards, and the
 * caller reports the failure to the core as a fault (loop.c). */
int clock_read_us(uint64_t *t_us);
/* The same time without the verdict, for log lines and bounds on waits. */
uint64_t clock_unit_us(void);
/* The unit's time (microseconds) and CLOCK_REALTIME read together: their offset at this
 * moment, for converting the kernel's receive stamps (rxtime.h). The unit's time is read
 * before and after the wall clock, and the earlier kept (a converted stamp is never younger
 * than it was); a wide gap between them is read again (clock.c). */
void clock_pair(uint64_t *unit_us, struct timespec *real);
/* CLOCK_REALTIME split into seconds and microseconds (for can-utils log lines). */
void clock_real(int64_t *sec, uint32_t *usec);

#endif
