/*
 * estop_auth: authentication of control packets and RELEASE requests (PROTOCOL.md section 5):
 * the tag, the session, and the table of remote ids with the highest counter kept per channel.
 */
#include "estop_core.h"

#include "estop_blake2s.h"
#include "estop_internal.h"

#define SESSION_AFTER_ID 4u        /* 5.1, 5.2: remote id (4 bytes), session (8), counter (8) */
#define COUNTER_AFTER_ID 12u

/*@ requires \valid(core);
    assigns core->remotes[0 .. 7];
    ensures in_table: \result == \null ||
        (\exists integer k; 0 <= k < 8 && \result == &core->remotes[k]);
 */
static estop_remote_t *find_remote(estop_core_t *core, uint32_t id)
{
    estop_remote_t *found = NULL;
    uint32_t i;
    /*@ loop invariant 0 <= i <= 8;
        loop invariant found == \null || (\exists integer k; 0 <= k < 8 && found == &core->remotes[k]);
        loop assigns i, found;
        loop variant 8 - i;
     */
    for (i = 0u; (i < ESTOP_MAX_REMOTES) && (found == NULL); i++) {
        if ((core->remotes[i].used != 0u) && (core->remotes[i].id == id)) {
            found = &core->remotes[i];
        }
    }
    /*@ loop invariant 0 <= i <= 8;
        loop invariant found == \null || (\exists integer k; 0 <= k < 8 && found == &core->remotes[k]);
        loop assigns i, found, core->remotes[0 .. 7];
        loop variant 8 - i;
     */
    for (i = 0u; (i < ESTOP_MAX_REMOTES) && (found == NULL); i++) {
        if (core->remotes[i].used == 0u) {
            found = &core->remotes[i];
            found->used = 1u;
            found->id = id;
            found->seen = 0u;
        }
    }
    return found;
}

/* Section 5: msg[0 .. tag_at-1] is covered by the tag at msg[tag_at]; the remote id, session
 * and counter follow one another from msg[ids_at] (5.1 and 5.2 lay them out alike). True when
 * the message is authenticated; the new counter is then kept. A failure is counted by the
 * first check that failed. Only called on a unit with a key. */
int estop__authenticate(estop_core_t *core, const uint8_t *msg, size_t tag_at, size_t ids_at,
                        uint32_t channel)
{
    uint8_t tag[ESTOP_TAG_LEN];
    const uint8_t bit = (uint8_t)(1u << channel);
    int ok = 0;
    (void)estop_b2s_mac(&core->mac, msg, tag_at, tag);
    if (!estop_ct_equal(tag, &msg[tag_at], ESTOP_TAG_LEN)) {
        core->counters.auth_bad_tag++;
    } else if (rd_u64le(&msg[ids_at + SESSION_AFTER_ID]) != core->cfg.session) {
        core->counters.auth_bad_session++;
    } else {
        /* A new remote id gets a place only here, with a right tag and session. */
        estop_remote_t *r = find_remote(core, rd_u32le(&msg[ids_at]));
        const uint64_t counter = rd_u64le(&msg[ids_at + COUNTER_AFTER_ID]);
        if (r == NULL) {
            core->counters.auth_table_full++;
        } else if (((r->seen & bit) != 0u) && (counter <= r->counter[channel])) {
            core->counters.auth_old_counter++;
        } else {
            r->counter[channel] = counter;
            r->seen = (uint8_t)(r->seen | bit);
            ok = 1;
        }
    }
    if (!ok) {
        core->status_auth_failed = sat8_inc(core->status_auth_failed);
    }
    return ok;
}
