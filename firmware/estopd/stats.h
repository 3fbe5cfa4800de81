/* Periodic read-outs of the core's counters into the event log: every STATS_EVERY_US while
 * there is news, and once more at exit. */
#ifndef ESTOPD_STATS_H
#define ESTOPD_STATS_H

#include <stdint.h>

#include "estop_core.h"

#define STATS_EVERY_US 10000000u

/* Where the numbers come from. */
typedef struct {
    const estop_core_t *core;
    const estop_config_t *cfg;
    const uint32_t *udp_drops;    /* the kernel's drop count (udp.h) */
    const uint32_t *udp_max_round; /* the most datagrams read in one loop round (udp.h) */
    uint32_t udp_budget;          /* ... and the most a round may read (UDP_ROUND_MAX) */
    const uint32_t *udp_deadline_cuts; /* drains cut short by a silence deadline (udp.h) */
} stats_src_t;

/* What has been reported so far. */
typedef struct {
    uint64_t last_us;             /* the latest read-out */
    uint64_t auth_reported;       /* authentication failures already in the log */
    uint32_t valid_reported;      /* valid packets in the latest link_histogram */
    uint32_t slowdowns_reported;  /* ... and slow-downs and timeouts */
    uint32_t timeouts_reported;
    uint32_t drops_reported;      /* udp_drops in the latest udp_drops event */
    uint32_t max_round_reported;  /* max_round in the latest udp_reads event */
    uint32_t cuts_reported;       /* ... and deadline_cuts */
} stats_t;

/* Call from the loop; cheap until the period has passed. */
void stats_tick(stats_t *s, const stats_src_t *src, uint64_t now_us);
/* Exit: writes what has changed since the last report, whatever the time. */
void stats_final(stats_t *s, const stats_src_t *src, uint64_t now_us);

#endif
