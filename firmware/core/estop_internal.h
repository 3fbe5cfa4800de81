/*
 * estop_internal: what the core's own files share, and nothing a host may use. Not part of
 * the public interface (estop_core.h is): hosts, the Python binding and the MCU tools never
 * include it.
 *
 * - Wire helpers: little-endian loads and stores, saturating increments, byte copies. They
 *   are static inline so that each file gets them inlined as before the split (a call per
 *   byte field would cost the packet paths their budget).
 * - The functions one job of the core calls in another, named estop__*: the state machine
 *   (estop_core.c), the clock step and the CAN frames (estop_clock.c), a datagram's step
 *   (estop_udp.c), authentication (estop_auth.c), TCP framing and replies (estop_tcp.c) and the
 *   link statistics (estop_link.c).
 */
#ifndef ESTOP_INTERNAL_H
#define ESTOP_INTERNAL_H

#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

#define CORE_MAGIC 0x45535450u  /* "ESTP": set by a successful estop_init */
#define CHANNEL_UDP 0u          /* the counter kept per remote and channel (5) */
#define CHANNEL_TCP 1u
#define SAT8_MAX 255u
#define SAT4_MAX 15u            /* the two nibbles of ESTOP_STATUS byte 3 */

/* ---- wire helpers ------------------------------------------------------------------------- */

/*@ logic uint32_t rd_u32le_l(uint8_t *p) =
        (uint32_t)((uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
                   ((uint32_t)p[3] << 24));
 */
/* The value is admitted: the solvers here cannot relate C's OR of shifted bytes to the logic
 * function (prove/assumed.txt names the test that fails were it false). */
/*@ requires \valid_read(p + (0 .. 3));
    assigns \nothing;
    admit ensures rd_value: \result == rd_u32le_l(p);
 */
static inline uint32_t rd_u32le(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

/*@ requires \valid(p + (0 .. 3));
    assigns p[0 .. 3];
 */
static inline void wr_u32le(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

/*@ logic uint64_t rd_u64le_l(uint8_t *p) =
        (uint64_t)((uint64_t)rd_u32le_l(p) | ((uint64_t)rd_u32le_l(p + 4) << 32));
 */
/* A message whose ids start at m[a] (PROTOCOL.md 5.1, 5.2) of this unit's session, with a
 * counter above the one kept for its remote id on channel ch (prove/predicates.h). A predicate,
 * not a macro: opaque to WP's simplifier Qed, so that the goals of a caller that do not need
 * it do not unfold it (as a macro, it slowed two of them past their limit). */
/*@ predicate ids_fresh(estop_core_t *c, uint8_t *m, integer a, integer ch) =
        ids_session(m, a) == c->cfg.session &&
        counter_above(c, ids_remote(m, a), ids_counter(m, a), ch);
 */
/* The 16 bytes at m + at are the MAC of m[0 .. at-1] under the unit's key state
 * (prove/logic.h, tag_ok), made with a key state of 16-byte MACs. A predicate, not a macro:
 * opaque to WP's simplifier Qed, as ids_fresh above: the clauses of request_step
 * (estop_tcp.c) carry it from the verdict's to handle_request's rule. */
/*@ predicate tag_made(estop_core_t *c, uint8_t *m, integer at) =
        c->mac.outlen == 16 && tag_ok(&c->mac, m, at);
 */
/*@ requires \valid_read(p + (0 .. 7));
    assigns \nothing;
    ensures rd64_value: \result == rd_u64le_l(p);
 */
static inline uint64_t rd_u64le(const uint8_t *p)
{
    return (uint64_t)rd_u32le(p) | ((uint64_t)rd_u32le(&p[4]) << 32);
}

/*@ requires \valid(p + (0 .. 7));
    assigns p[0 .. 7];
 */
static inline void wr_u64le(uint8_t *p, uint64_t v)
{
    wr_u32le(p, (uint32_t)(v & 0xFFFFFFFFu));
    wr_u32le(&p[4], (uint32_t)(v >> 32));
}

/*@ assigns \nothing; */
static inline uint8_t sat4_inc(uint8_t v)
{
    return (v < SAT4_MAX) ? (uint8_t)(v + 1u) : v;
}

/*@ assigns \nothing; */
static inline uint8_t sat8_inc(uint8_t v)
{
    return (v < SAT8_MAX) ? (uint8_t)(v + 1u) : v;
}

/* Adds 1 unless the count is at its top, UINT32_MAX: a counter never wraps to a small one
 * (in place: a store skipped at the top is cheaper than a select on every count). */
/*@ requires \valid(count);
    assigns *count;
 */
static inline void sat32_inc(uint32_t *count)
{
    const uint32_t next = *count + 1u;
    if (next != 0u) {
        *count = next;
    }
}

/* Byte loops instead of struct assignment: gcc compiles a large struct copy or zeroing into a
 * call to memcpy/memset, which a freestanding build without libc cannot link (docs/MCU.md). */
/*@ requires \valid(dst + (0 .. n - 1));
    assigns dst[0 .. n - 1];
    ensures \forall integer k; 0 <= k < n ==> dst[k] == 0;
 */
static inline void zero_bytes(uint8_t *dst, size_t n)
{
    size_t i;
    /*@ loop invariant 0 <= i <= n;
        loop invariant \forall integer k; 0 <= k < i ==> dst[k] == 0;
        loop assigns i, dst[0 .. n - 1];
        loop variant n - i;
     */
    for (i = 0u; i < n; i++) {
        dst[i] = 0u;
    }
}

/*@ requires \valid(dst + (0 .. n - 1)) && \valid_read(src + (0 .. n - 1));
    requires \separated(dst + (0 .. n - 1), src + (0 .. n - 1));
    assigns dst[0 .. n - 1];
 */
static inline void copy_bytes(uint8_t *dst, const uint8_t *src, size_t n)
{
    size_t i;
    /*@ loop invariant 0 <= i <= n;
        loop assigns i, dst[0 .. n - 1];
        loop variant n - i;
     */
    for (i = 0u; i < n; i++) {
        dst[i] = src[i];
    }
}

/* ---- the state machine (estop_core.c, estop_clock.c) -------------------------------------- */

/* Every entry point: estop__begin() advances the clock and sends what is due; estop__finish()
 * fills the state read-out and the next call time (estop_clock.c). */
estop_err_t estop__begin(estop_core_t *core, uint32_t now_us, estop_out_t *out);
void estop__finish(const estop_core_t *core, estop_out_t *out);
/* The flags byte of frames and replies. */
uint8_t estop__current_flags(const estop_core_t *core);
/* A state change: ESTOP_BRAKE at once, its period restarted from there (estop_clock.c). */
void estop__state_changed(estop_core_t *core, estop_out_t *out);
/* The link's age: the time since its last valid packet (wraps with the clock). */
uint32_t estop__link_age(const estop_core_t *core);
/* SLOWING at the slow time; the caller sends the state change (estop_clock.c). */
void estop__enter_slowing(estop_core_t *core);
/* A stop request (reason 1..5): a moving unit STOPPED with its brake frame; the release count
 * restarts either way (estop_clock.c). */
void estop__stop(estop_core_t *core, uint8_t reason, estop_out_t *out);
/* The reason a stop request of msg_id stops the unit with (its stop ID, LIFT), or 0
 * (estop_core.c). */
uint8_t estop__stop_reason(const estop_core_t *core, uint32_t msg_id);
/* What a good TCP frame of either form asks for (STOP, LIFT, RELEASE, STATUS, unknown);
 * returns the NAK code of its reply. release_authenticated: a RELEASE may pass. */
uint8_t estop__handle_msg(estop_core_t *core, uint32_t msg_id, int release_authenticated,
                          estop_out_t *out);

/* ---- authentication (estop_auth.c) -------------------------------------------------------- */

/* estop__auth_verdict's verdicts: authenticated, or the first check that failed. */
#define AUTH_OK 0u
#define AUTH_BAD_SESSION 1u
#define AUTH_OLD_COUNTER 2u
#define AUTH_TABLE_FULL 3u
#define AUTH_UNCHECKED 4u   /* a control packet over the tag-check budget */
#define AUTH_BAD_TAG 5u
#define AUTH_NOT_ASKED 6u   /* no message to authenticate: estop__auth_commit does nothing */

/* The verdict on msg (laid out as for estop__authenticate), writing nothing. */
uint32_t estop__auth_verdict(estop_core_t *core, const uint8_t *msg, size_t tag_at,
                             size_t ids_at, uint32_t channel);
/* What a verdict on the message of remote id with counter leaves in the core: the failure
 * counted, the tag check spent, the authenticated counter kept. stopped: the unit was STOPPED
 * before the message's step. */
void estop__auth_commit(estop_core_t *core, uint32_t id, uint64_t counter, uint32_t channel,
                        uint32_t verdict, int stopped);

/* msg[0 .. tag_at-1] is covered by the tag at msg[tag_at]; remote id, session and counter
 * follow one another from msg[ids_at]. The verdict, then the commit. True when authentic, of this session, fresh and from a
 * remote the table holds; the counter is then kept. A control packet dropped unchecked by the
 * budget raises the UDP counter of its remote id (when it has a place) all the same. Only
 * called on a unit with a key. */
int estop__authenticate(estop_core_t *core, const uint8_t *msg, size_t tag_at, size_t ids_at,
                        uint32_t channel);

/* A control packet or RELEASE that needs authentication but has no tag to check (plain form,
 * wrong magic): counted as a bad tag. */
void estop__unauthenticated(estop_core_t *core);

/* Every call, after the clock: closes the tag-check window once it has lasted its length. */
void estop__age_tag_window(estop_core_t *core);

/* ---- link statistics (estop_link.c) ------------------------------------------------------- */

/* The clock advanced by step: a gap too long to measure later is recorded now. */
void estop__age_gap(estop_core_t *core, uint32_t step);
/* A valid control packet at core->now_us: the gap since the previous one. */
void estop__record_gap(estop_core_t *core);

#endif /* ESTOP_INTERNAL_H */
