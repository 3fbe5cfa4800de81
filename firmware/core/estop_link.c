/*
 * estop_link: the link's record (docs/LINK.md): the histogram of gaps between valid control
 * packets, the silences among them, and its read-out.
 */
#include "estop_core.h"

#include "estop_internal.h"

#define GAP_FIRST_EXP 10u          /* bin 1 starts at 2^10 us */
#define GAP_LONG_US 0x40000000u    /* past this age a gap is only "very long" (bin 31): the
                                      wrapping tick could not measure it much further */

/* floor(log2(v)) for v > 0: O(1). GCC and Clang count leading zeros (one instruction where
 * the target has it, a runtime helper where not); elsewhere a five-step binary search. */
static uint32_t log2_floor(uint32_t v)
{
#if defined(__GNUC__)
    return 31u - (uint32_t)__builtin_clz(v);
#else
    uint32_t e = 0u;
    uint32_t x = v;
    if (x >= 0x10000u) {
        e += 16u;
        x >>= 16;
    }
    if (x >= 0x100u) {
        e += 8u;
        x >>= 8;
    }
    if (x >= 0x10u) {
        e += 4u;
        x >>= 4;
    }
    if (x >= 0x4u) {
        e += 2u;
        x >>= 2;
    }
    if (x >= 0x2u) {
        e += 1u;
    }
    return e;
#endif
}

uint32_t estop_gap_bin(uint32_t gap_us)
{
    uint32_t bin = 0u;
    if (gap_us >= ((uint32_t)1u << GAP_FIRST_EXP)) {
        uint32_t e = log2_floor(gap_us);
        /* The half-octave bit, bit e-1 of the gap, is bit e of gap << 1: a shift by e, which
         * is below 32 for any v (e - 1 is too, as e >= 10 here, but an analyser cannot tell). */
        bin = 1u + (2u * (e - GAP_FIRST_EXP)) + (((gap_us << 1) >> e) & 1u);
        if (bin > (ESTOP_GAP_BINS - 1u)) {
            bin = ESTOP_GAP_BINS - 1u;
        }
    }
    return bin;
}

/* The link's record (issue 12): the gap since the previous valid packet, and a silence when
 * it reached the warn time. */
void estop__record_gap(estop_core_t *core)
{
    if (core->gap_known != 0u) {
        uint32_t gap = (uint32_t)(core->now_us - core->last_valid_us);
        uint32_t bin = estop_gap_bin(gap);
        sat32_inc(&core->gaps[bin]);
        if (gap >= core->cfg.warn_us) {
            sat32_inc(&core->silences);
        }
    }
    core->gap_known = 1u;
}

/* Called while the link is not fresh (the clock went backwards, or the latest valid packet is
 * older than the timeout): a gap the wrapping tick could no longer measure is recorded now. */
void estop__age_gap(estop_core_t *core, uint32_t step)
{
    if (step > ESTOP_MAX_STEP_US) {
        core->gap_known = 0u; /* the next gap cannot be measured: it is not recorded */
    } else if ((core->gap_known != 0u) &&
               ((uint32_t)(core->now_us - core->last_valid_us) >= GAP_LONG_US)) {
        estop__record_gap(core); /* bin 31, and a silence: longer than any warn time */
        core->gap_known = 0u;    /* recorded as "very long" now, before the tick can wrap */
    } else {
        /* a gap still measurable: estop__record_gap() records it at the next valid packet */
    }
}

estop_err_t estop_get_link_stats(const estop_core_t *core, estop_link_stats_t *stats)
{
    estop_err_t err = ESTOP_OK;
    if ((core == NULL) || (stats == NULL)) {
        err = ESTOP_ERR_NULL_ARG;
    } else if (core->magic != CORE_MAGIC) {
        err = ESTOP_ERR_NOT_INIT;
    } else {
        uint32_t i;
        stats->valid = core->counters.udp_valid;
        stats->silences = core->silences;
        stats->slowdowns = core->counters.slowdowns;
        stats->timeouts = core->counters.stops[ESTOP_REASON_UDP_TIMEOUT];
        /*@ loop invariant 0 <= i <= 32;
            loop assigns i, stats->gaps[0 .. 31];
            loop variant 32 - i; */
        for (i = 0u; i < ESTOP_GAP_BINS; i++) {
            stats->gaps[i] = core->gaps[i];
        }
    }
    return err;
}
