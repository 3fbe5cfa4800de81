/*
 * estop_auth: authentication of control packets and RELEASE requests (PROTOCOL.md section 5):
 * the tag, the session, and the table of remote ids with the counters kept for each.
 *
 * The cheap checks come first (session, a counter not above the kept one, a full table), so
 * that a replay or a message of another session costs no MAC. A MAC (one BLAKE2s block, about
 * 8,100 instructions on a Cortex-M0+) is then spent on a control packet only within a budget
 * (none with cfg.tag_checks ESTOP_TAG_CHECKS_ALL: every tag checked, as estopd does):
 * cfg.tag_checks per cfg.tag_window_us from the allowance of the packet's remote when its
 * counter is one of that remote's next ones (at most COUNTER_AHEAD above the one kept), and as
 * many from one shared allowance for everything else (new remote ids, counters far ahead).
 * The rest are dropped unchecked and counted (auth_unchecked), so a flood of forged packets
 * costs a bounded share of the CPU.
 *
 * A packet dropped unchecked may have been genuine, and its copy could be delivered again
 * later to keep a unit alive that its remote no longer drives (issue 25). So one that names a
 * remote id with a place raises that remote's UDP counter to its own, as an authenticated one
 * does: it can never be authenticated later; the budget may starve the remote (the unit
 * stops), it never prolongs motion. What a forgery costs the remote then: its packets at or
 * below a forged counter are refused until its own counter passes it, or until its next
 * RELEASE while the unit is STOPPED, which brings the UDP counter back down to the RELEASE's
 * counter (the channels share the remote's one counter: what is left above it was sent after
 * it). A RELEASE must be above the highest counter authenticated from its remote on either
 * channel. RELEASE frames (TCP) have no budget: the connection slots bound them. Stop requests
 * are never authenticated, so nothing here can delay a stop.
 */
#include "estop_core.h"

#include "estop_blake2s.h"
#include "estop_internal.h"

#define SESSION_AFTER_ID 4u        /* 5.1, 5.2: remote id (4 bytes), session (8), counter (8) */
#define COUNTER_AFTER_ID 12u
#define COUNTER_AHEAD 65536u       /* a remote's next counters: after up to this many losses
                                      (22 minutes at 50 Hz) */

/* The table entry of a remote id, or NULL when it has no place. (The table holds one place
 * per id, the first: take_place gives one only to an id this found no place for.) */
/*@ requires \valid(core);
    assigns \nothing;
    ensures in_table: \result == \null ||
        (\exists integer k; 0 <= k < 8 && \result == &core->remotes[k]);
    ensures found_first: \result != \null ==>
        (\exists integer k; 0 <= k < 8 && \result == &core->remotes[k] && first_place(core, id, k));
    ensures found_none: \result == \null ==>
        \forall integer k; 0 <= k < 8 ==> !place_of(core, id, k);
 */
static estop_remote_t *find_remote(estop_core_t *core, uint32_t id)
{
    estop_remote_t *found = NULL;
    uint32_t i;
    /*@ loop invariant 0 <= i <= 8;
        loop invariant found == \null ||
            (\exists integer k; 0 <= k < 8 && found == &core->remotes[k]);
        loop invariant found_first: found != \null ==>
            (\exists integer k; 0 <= k < i && found == &core->remotes[k] &&
             first_place(core, id, k));
        loop invariant found_none: found == \null ==>
            \forall integer k; 0 <= k < i ==> !place_of(core, id, k);
        loop assigns i, found;
        loop variant 8 - i;
     */
    for (i = 0u; (i < ESTOP_MAX_REMOTES) && (found == NULL); i++) {
        if ((core->remotes[i].used != 0u) && (core->remotes[i].id == id)) {
            found = &core->remotes[i];
        }
    }
    return found;
}

/* A free place for a new remote id, or NULL when all 8 are taken (places are never freed
 * within a session). */
/*@ requires \valid(core);
    assigns \nothing;
    ensures in_table: \result == \null ||
        (\exists integer k; 0 <= k < 8 && \result == &core->remotes[k]);
 */
static estop_remote_t *free_place(estop_core_t *core)
{
    estop_remote_t *found = NULL;
    uint32_t i;
    /*@ loop invariant 0 <= i <= 8;
        loop invariant found == \null ||
            (\exists integer k; 0 <= k < 8 && found == &core->remotes[k]);
        loop assigns i, found;
        loop variant 8 - i;
     */
    for (i = 0u; (i < ESTOP_MAX_REMOTES) && (found == NULL); i++) {
        if (core->remotes[i].used == 0u) {
            found = &core->remotes[i];
        }
    }
    return found;
}

/* One tag check from the allowance of r (NULL: the shared one) in the current window; false
 * when that allowance is spent. A window begins at the first check after the previous one
 * ended (estop__age_tag_window; a tick that went backwards ends it too). */
/*@ requires \valid(core);
    requires r == \null || \exists integer k; 0 <= k < 8 && r == &core->remotes[k];
    assigns core->tag_window_us, core->tag_window_open, core->newcomer_checks,
            core->remotes[0 .. 7];
    ensures \result == 0 || \result == 1;
 */
static int take_check(estop_core_t *core, estop_remote_t *r)
{
    uint8_t *used = (r != NULL) ? &r->checks : &core->newcomer_checks;
    int ok = 0;
    if (core->tag_window_open == 0u) {
        uint32_t i;
        core->tag_window_us = core->now_us;
        core->tag_window_open = 1u;
        core->newcomer_checks = 0u;
        /*@ loop invariant 0 <= i <= 8;
            loop assigns i, core->remotes[0 .. 7].checks;
            loop variant 8 - i;
         */
        for (i = 0u; i < ESTOP_MAX_REMOTES; i++) {
            core->remotes[i].checks = 0u;
        }
    }
    if (*used < core->cfg.tag_checks) {
        *used = (uint8_t)(*used + 1u);
        ok = 1;
    }
    return ok;
}

/* Every call looks at the window's age, so a window ends once it has lasted its length even
 * when no check comes for a while: a later check could find the wrapping tick back within it
 * (a gap of a multiple of 2^32 us) and draw on stale counts. Calls are at most 2^31 us apart,
 * so the age seen first past the length is the true one. */
void estop__age_tag_window(estop_core_t *core)
{
    if ((uint32_t)(core->now_us - core->tag_window_us) >= core->cfg.tag_window_us) {
        core->tag_window_open = 0u;
    }
}

/* The counter is one of remote r's next UDP counters: r has a place and a UDP counter kept,
 * and this one is above it (checked before) by at most COUNTER_AHEAD. */
/*@ requires r == \null || \valid_read(r);
    assigns \nothing;
    ensures \result == 0 || \result == 1;
 */
static int next_of(const estop_remote_t *r, uint64_t counter)
{
    return (r != NULL) && ((r->seen & (1u << CHANNEL_UDP)) != 0u) &&
           ((counter - r->counter[CHANNEL_UDP]) <= COUNTER_AHEAD);
}

/* Keeps an authenticated counter. counter[TCP] is the highest authenticated on either
 * channel: a RELEASE must be above it (the remote raises one counter for both channels, so a
 * RELEASE that never reached the unit, its connection closed first, is stale once anything
 * later of that remote was taken). A RELEASE of a unit STOPPED before its step (stopped) brings the UDP counter, when
 * packets dropped unchecked raised it above the RELEASE's, back down to the RELEASE's: they
 * were sent after the RELEASE, or forged (a forgery of a high counter would otherwise lock
 * the remote out for the session); it stays above every control packet authenticated. */
/*@ requires \valid(core) && channel <= 1;
    requires \exists integer k; 0 <= k < 8 && r == &core->remotes[k];
    assigns core->remotes[0 .. 7];
 */
static void keep(estop_core_t *core, estop_remote_t *r, uint32_t channel, uint64_t counter,
                 int stopped)
{
    (void)core; /* named by the contract: r lies in its table */
    /* (A counter not kept yet reads 0: places start zeroed and are never freed.) */
    if (channel == CHANNEL_UDP) {
        r->counter[CHANNEL_UDP] = counter;
        r->seen = (uint8_t)(r->seen | (1u << CHANNEL_UDP));
        if (r->counter[CHANNEL_TCP] < counter) {
            r->counter[CHANNEL_TCP] = counter;
        }
    } else {
        r->counter[CHANNEL_TCP] = counter;
        if ((stopped != 0) && (r->counter[CHANNEL_UDP] > counter)) {
            r->counter[CHANNEL_UDP] = counter;
        }
    }
    r->seen = (uint8_t)(r->seen | (1u << CHANNEL_TCP));
}

/* A control packet left unchecked uses up its counter under its remote id (issue 25). The
 * functions that write an entry of the table say they write the table, as
 * estop__authenticate does: WP matches equal ranges at once, where the inclusion of one
 * field's range in the table's is an existential goal the solvers time out on. */
/*@ requires \valid(core);
    requires \exists integer k; 0 <= k < 8 && r == &core->remotes[k];
    assigns core->remotes[0 .. 7];
 */
static void use_up(estop_core_t *core, estop_remote_t *r, uint64_t counter)
{
    (void)core; /* named by the contract: r lies in its table */
    r->counter[CHANNEL_UDP] = counter;
    r->seen = (uint8_t)(r->seen | (1u << CHANNEL_UDP));
}

/* A free place of the table taken by a new remote id. */
/*@ requires \valid(core);
    requires \exists integer k; 0 <= k < 8 && place == &core->remotes[k];
    assigns core->remotes[0 .. 7];
 */
static void take_place(estop_core_t *core, estop_remote_t *place, uint32_t id)
{
    (void)core; /* named by the contract: place lies in its table */
    place->used = 1u;
    place->id = id;
    place->seen = 0u;
}

/* Whether a tag check is left in the allowance of r (NULL: the shared one): what take_check
 * would grant, without spending it. */
/*@ requires \valid_read(core);
    requires r == \null || \exists integer k; 0 <= k < 8 && r == &core->remotes[k];
    assigns \nothing;
    ensures \result == 0 || \result == 1;
 */
static int can_check(const estop_core_t *core, const estop_remote_t *r)
{
    const uint8_t used = (r != NULL) ? r->checks : core->newcomer_checks;
    /* A window that is not open opens with every allowance unspent. */
    const uint8_t spent = (core->tag_window_open == 0u) ? 0u : used;
    return (spent < core->cfg.tag_checks) ? 1 : 0;
}

/* Section 5: the 16 bytes at msg[tag_at] are the MAC of msg[0 .. tag_at-1] under the unit's
 * key. Writes nothing but its own copy of the MAC. */
/*@ requires \valid_read(core) && (tag_at == 32 || tag_at == 44);
    requires \valid_read(msg + (0 .. tag_at + 15));
    requires \separated(msg + (0 .. tag_at + 15), &core->mac);
    requires core->mac.outlen <= 16;
    assigns \nothing;
    ensures \result == 0 || \result == 1;
    ensures tag_right: \result == 1 ==> core->mac.outlen == 16 && tag_ok(&core->mac, msg, tag_at);
 */
static int tag_right(const estop_core_t *core, const uint8_t *msg, size_t tag_at)
{
    uint8_t tag[ESTOP_TAG_LEN];
    int right = 0;
    /* A MAC that cannot be made (a broken key state, or one of another length, which would
     * leave bytes of tag unwritten) authenticates nothing. */
    if ((core->mac.outlen == ESTOP_TAG_LEN) &&
        (estop_b2s_mac(&core->mac, msg, tag_at, tag) == 0) &&
        (estop_ct_equal(tag, &msg[tag_at], ESTOP_TAG_LEN) != 0)) {
        /*@ assert compared: \forall integer i; 0 <= i < 16 ==> tag[i] == msg[tag_at + i]; */
        /* The lengths estop_b2s_mac's MAC clause holds for, named: left to the solvers inside
         * made, its search ran out of 90 s in one order of four (issue 24's forty-fifth
         * round); with this, about 5 s in every order. */
        /*@ assert made_len: 1 <= tag_at <= 64 && tag_at % 4 == 0; */
        /*@ assert made: \forall integer i; 0 <= i < 16 ==>
                tag[i] == MAC_BYTE(&core->mac, msg, tag_at, i); */
        right = 1;
    }
    return right;
}

/* Whether a control packet on channel is checked within the budget (estop_auth's head). */
/*@ requires \valid_read(core);
    assigns \nothing;
    ensures \result == 0 || \result == 1;
 */
static int budgeted(const estop_core_t *core, uint32_t channel)
{
    return (channel == CHANNEL_UDP) && (core->cfg.tag_checks != ESTOP_TAG_CHECKS_ALL);
}

/* Section 5: msg[0 .. tag_at-1] is covered by the tag at msg[tag_at]; the remote id, session
 * and counter follow one another from msg[ids_at] (5.1 and 5.2 lay them out alike). The
 * verdict, AUTH_OK when the message is authenticated, else the first check that failed.
 * Writes nothing: estop__auth_commit counts and keeps what it found, so that a caller may
 * take the step the verdict allows before the table is written (the TCP path: issue 24's
 * thirty-sixth round). */
uint32_t estop__auth_verdict(estop_core_t *core, const uint8_t *msg, size_t tag_at,
                             size_t ids_at, uint32_t channel)
{
    const uint8_t bit = (uint8_t)(1u << channel);
    const uint32_t id = rd_u32le(&msg[ids_at]);
    const uint64_t counter = rd_u64le(&msg[ids_at + COUNTER_AFTER_ID]);
    estop_remote_t *r = find_remote(core, id);
    const estop_remote_t *place = (r != NULL) ? r : free_place(core); /* NULL: the table is full */
    /* A control packet's check comes out of its remote's allowance when it is one of the
     * remote's next counters, else out of the newcomers' (take_check). */
    const int budget = budgeted(core, channel);
    const estop_remote_t *payer = next_of(r, counter) ? r : NULL;
    uint32_t verdict = AUTH_OK;
    /*@ assert ids_read: id == ids_remote(msg, ids_at) && counter == ids_counter(msg, ids_at); */
    if (rd_u64le(&msg[ids_at + SESSION_AFTER_ID]) != core->cfg.session) {
        verdict = AUTH_BAD_SESSION;
    } else if ((r != NULL) && (((uint32_t)r->seen & (uint32_t)bit) != 0u) &&
               (counter <= r->counter[channel])) {
        verdict = AUTH_OLD_COUNTER;
    } else if (place == NULL) {
        verdict = AUTH_TABLE_FULL;
    } else if ((budget != 0) && (can_check(core, payer) == 0)) {
        verdict = AUTH_UNCHECKED;
    } else {
        /* What auth_fresh (prove/contracts.h) says of an accepted message, at the checks. */
        /*@ assert session_same: ids_session(msg, ids_at) == core->cfg.session; */
        /*@ assert counter_fresh: r == \null || (r->seen & bit) == 0 ||
                counter > r->counter[channel]; */
        if (tag_right(core, msg, tag_at) == 0) {
            verdict = AUTH_BAD_TAG;
        }
    }
    return verdict;
}

/* What the verdict of the message of remote id with counter leaves in the core: a failure
 * counted by the first check that failed (none for AUTH_NOT_ASKED); a control packet over the
 * budget counted as unchecked, raising its remote's UDP counter; a tag check spent from the
 * budget; an authenticated counter kept, and a new remote id given its place. stopped: the
 * unit was STOPPED before the message's step (keep). */
void estop__auth_commit(estop_core_t *core, uint32_t id, uint64_t counter, uint32_t channel,
                        uint32_t verdict, int stopped)
{
    estop_remote_t *r = find_remote(core, id);
    estop_remote_t *place = (r != NULL) ? r : free_place(core); /* NULL: the table is full */
    estop_remote_t *payer = next_of(r, counter) ? r : NULL;
    int failed = 1;
    if (verdict == AUTH_NOT_ASKED) {
        failed = 0; /* no message to authenticate */
    } else if (verdict == AUTH_BAD_SESSION) {
        sat32_inc(&core->counters.auth_bad_session);
    } else if (verdict == AUTH_OLD_COUNTER) {
        sat32_inc(&core->counters.auth_old_counter);
    } else if (verdict == AUTH_TABLE_FULL) {
        sat32_inc(&core->counters.auth_table_full);
    } else if (verdict == AUTH_UNCHECKED) {
        sat32_inc(&core->counters.auth_unchecked);
        failed = 0; /* not looked at: invalid, but no authentication failure */
        if (r != NULL) {
            /* It may have been genuine: its counter is used up all the same. (An id without
             * a place gets none: forgeries would fill the table.) */
            use_up(core, r, counter);
        }
    } else {
        if (budgeted(core, channel) != 0) {
            (void)take_check(core, payer); /* the check is spent: can_check found it left */
        }
        if (verdict != AUTH_OK) {
            sat32_inc(&core->counters.auth_bad_tag);
        } else if (place != NULL) {
            if (r == NULL) {
                /* A new remote id gets a place only here, with a right tag and session. */
                take_place(core, place, id);
            }
            keep(core, place, channel, counter, stopped);
            failed = 0;
        } else {
            /* AUTH_OK with a full table: the verdict said otherwise (defensive) */
        }
    }
    if (failed != 0) {
        core->status_auth_failed = sat8_inc(core->status_auth_failed);
    }
}

/* Section 5: the verdict, then what it leaves in the core. True when the message is
 * authenticated; the new counter is then kept. Only called on a unit with a key. */
int estop__authenticate(estop_core_t *core, const uint8_t *msg, size_t tag_at, size_t ids_at,
                        uint32_t channel)
{
    const uint32_t verdict = estop__auth_verdict(core, msg, tag_at, ids_at, channel);
    estop__auth_commit(core, rd_u32le(&msg[ids_at]), rd_u64le(&msg[ids_at + COUNTER_AFTER_ID]),
                       channel, verdict, core->state == ESTOP_STATE_STOPPED);
    return (verdict == AUTH_OK) ? 1 : 0;
}

/* Section 5: a message that needs authentication on this unit but carries no tag it can check
 * (a plain control packet or a plain RELEASE, a 60-byte packet without the ESU2 magic) fails
 * it as a bad tag does (docs/PROTOCOL.md 4, ESTOP_STATUS byte 2). */
void estop__unauthenticated(estop_core_t *core)
{
    sat32_inc(&core->counters.auth_bad_tag);
    core->status_auth_failed = sat8_inc(core->status_auth_failed);
}
