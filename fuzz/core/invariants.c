/*
 * Everything checked after one call into the core, against the shadow record (the list is
 * in fuzz_core.c).
 */
#include "harness.h"

static int neutral_bits(uint32_t bits)
{
    return ((bits & 0x80000000u) != 0u) || (bits == 0u);
}

/* ---- the shadow of the budget's rule (issue 25) --------------------------------------------- */

static uint64_t fnv64(const uint8_t *d, size_t n)
{
    uint64_t h = 0xCBF29CE484222325ull;
    for (size_t i = 0; i < n; i++) {
        h = (h ^ d[i]) * 0x100000001B3ull;
    }
    return h;
}

static int is_placed(const world_t *w, uint32_t id)
{
    for (uint32_t i = 0; i < w->n_placed; i++) {
        if (w->placed[i] == id) {
            return 1;
        }
    }
    return 0;
}

static void place(world_t *w, uint32_t id)
{
    if (!is_placed(w, id)) {
        CHECK(w->n_placed < ESTOP_MAX_REMOTES, "a 9th remote id authenticated");
        w->placed[w->n_placed++] = id;
    }
}

static int left_unchecked(const world_t *w, uint64_t hash)
{
    for (uint32_t i = 0; i < w->n_left; i++) {
        if (w->left[i].hash == hash) {
            return 1;
        }
    }
    return 0;
}

/* A RELEASE of id at counter, authenticated while the unit was STOPPED: what was left above
 * its counter is forgiven (docs/PROTOCOL.md 5). */
static void forgive(world_t *w, uint32_t id, uint64_t counter)
{
    uint32_t kept = 0;
    for (uint32_t i = 0; i < w->n_left; i++) {
        if (w->left[i].id != id || w->left[i].counter <= counter) {
            w->left[kept++] = w->left[i];
        }
    }
    w->n_left = kept;
}

/* Everything checked after one call. err is the call's result. */
void fz_after_call(world_t *w, estop_err_t err, const estop_out_t *out, call_t *c,
                   uint64_t t_new)
{
    const estop_config_t *cfg = &w->cfg;
    estop_status_t st;
    uint64_t t_old = w->t;
    int backwards = t_new < t_old;
    uint32_t d;
    int brakes = 0;
    int stop_request = 0;

    if (err == ESTOP_ERR_SLOT) {
        return; /* refused before the clock: the core saw nothing, out is not filled */
    }
    CHECK(err == ESTOP_OK || (err == ESTOP_ERR_SLOT_CLOSED && c->slot_closed_call),
          "unexpected error");
    w->t = t_new;
    CHECK(estop_get_status(&w->core, &st) == ESTOP_OK, "status read-out");
    CHECK(out->n_can <= ESTOP_OUT_MAX_CAN, "at most 3 frames");
    CHECK(out->state == st.state && out->reason == st.reason, "out tells the state");

    /* The link as the unit must see it at this call's time, before the input. */
    if (backwards) {
        w->link_dead = 1;
        w->run = 0;
    } else if (w->have_valid && !w->link_dead && t_new >= w->last_valid_t + cfg->timeout_us) {
        w->link_dead = 1;
        w->run = 0;
    }

    /* Frames: a due brake (or status) frame is in this call's output. */
    {
        /* (A clock gone backwards is judged by next_call_us below.) */
        int brake_due = !w->booted ||
                        (!backwards && t_new >= w->last_brake_t + cfg->brake_period_us);
        int status_due = !w->booted ||
                         (!backwards && t_new >= w->last_status_t + cfg->status_period_us);
        int status_seen = 0;
        const estop_can_frame_t *last_brake = NULL;
        for (uint8_t i = 0; i < out->n_can; i++) {
            fz_check_frame(w, &out->can[i], t_new);
            if (out->can[i].id == cfg->brake_can_id) {
                brakes++;
                last_brake = &out->can[i];
            } else {
                status_seen = 1;
            }
        }
        CHECK(!brake_due || brakes > 0, "ESTOP_BRAKE later than its period");
        CHECK(!status_due || status_seen, "ESTOP_STATUS later than its period");
        if (last_brake != NULL) {
            CHECK(last_brake->data[2] == out->state && last_brake->data[3] == out->reason,
                  "the latest brake frame tells the state after the call");
        }
        CHECK(!out->state_changed || brakes > 0, "a state change sends ESTOP_BRAKE at once");
        w->booted = 1;
    }

    /* SLOWING only from ARMED (or by a RELEASE of a link already silent for the slow time,
     * checked with the other releases below), and only once the link was silent for the slow
     * time (the input comes after the clock, so the time of this call decides). */
    if (st.state == ESTOP_STATE_SLOWING && w->prev_state != ESTOP_STATE_SLOWING) {
        CHECK(t_new >= w->last_valid_t + cfg->slow_us, "SLOWING before the slow time");
        CHECK(cfg->slow_us < cfg->timeout_us, "SLOWING with the slow time = the timeout");
        CHECK(st.counters.slowdowns == w->prev.slowdowns + 1u, "slow-down counted");
        w->slow_run = 0;
    }

    /* The input. */
    if (w->has_key && c->kind == 1 && c->len == ESTOP_UDP_AUTH_LEN &&
        fz_get32(c->data) == ESTOP_MAGIC_CONTROL) {
        /* Issue 25: a control packet the budget dropped unchecked under an id with a place is
         * never taken later (its copy would keep alive a unit its remote no longer drives). */
        uint64_t hash = fnv64(c->data, c->len);
        uint32_t id = fz_get32(c->data + 4);
        if (st.counters.udp_valid != w->prev.udp_valid) {
            CHECK(!left_unchecked(w, hash), "a control packet left unchecked was taken later");
            place(w, id);
        } else if (st.counters.auth_unchecked != w->prev.auth_unchecked && is_placed(w, id) &&
                   w->n_left < LEFT_MAX) {
            w->left[w->n_left].hash = hash;
            w->left[w->n_left].counter = fz_get64(c->data + 16);
            w->left[w->n_left].id = id;
            w->n_left++;
        }
    }
    if (c->kind == 1 && st.counters.udp_valid != w->prev.udp_valid) {
        const uint8_t *body = c->len == ESTOP_UDP_AUTH_LEN ? c->data + 24 : c->data;
        CHECK(st.counters.udp_valid == w->prev.udp_valid + 1u, "one valid packet a datagram");
        CHECK(c->len == (w->has_key ? ESTOP_UDP_AUTH_LEN : ESTOP_UDP_LEN) ||
                  (!w->has_key && c->len == ESTOP_UDP_LEN_NO_HORN),
              "valid packet of the wrong form");
        w->have_valid = 1;
        w->last_valid_t = t_new;
        w->link_dead = 0;
        w->last_neutral = neutral_bits(fz_get32(body));
        if (w->run < 0xFFFFFFFFu) {
            w->run++;
        }
        if (w->prev_state == ESTOP_STATE_SLOWING || st.state == ESTOP_STATE_SLOWING) {
            w->slow_run++;
        }
    }
    if (c->kind == 1 && st.counters.udp_stops != w->prev.udp_stops) {
        stop_request = 1;
    }
    if (c->kind == 3) {
        stop_request = 1;
        CHECK(st.counters.faults > w->prev.faults, "fault counted");
    }
    if (c->kind == 2 && !c->slot_closed_call) {
        int good = 0;
        uint32_t msg = 0;
        if (c->frame_done) {
            msg = fz_frame_msg(c, &good);
        }
        CHECK(c->len == 0u || c->consumed > 0u, "tcp: no progress on an open slot");
        CHECK(out->close_slot == (c->frame_done && !good), "tcp: close exactly on a bad crc");
        CHECK(out->has_reply == (c->frame_done && good), "tcp: one reply a good frame");
        if (out->has_reply) {
            fz_check_reply(w, out, c);
        }
        if (w->has_key && c->frame_done && good && c->frame_len == ESTOP_REQ_FRAME_LEN &&
            msg == ESTOP_MSG_RELEASE && out->has_reply && out->reply[15] != ESTOP_NAK_NOT_AUTHENTICATED) {
            uint32_t id = fz_get32(c->frame + 12);
            place(w, id);
            if (out->clock_state == ESTOP_STATE_STOPPED) {
                forgive(w, id, fz_get64(c->frame + 24));
            }
        }
        if (c->frame_done && good && (msg == cfg->stop_id || msg == ESTOP_MSG_LIFT)) {
            stop_request = 1;
        }
    } else {
        CHECK(!out->has_reply && !out->close_slot, "reply or close without TCP bytes");
    }
    if (stop_request) {
        w->run = 0;
        CHECK(st.state == ESTOP_STATE_STOPPED, "a stop request leaves the unit STOPPED");
    }
    if (backwards) {
        CHECK(st.state == ESTOP_STATE_STOPPED, "a clock going backwards stops the unit");
    }

    /* The clock's part of the call (issue 25, item 5): the state after it, before the input. A
     * change by the clock leads away from the state before the call; an input that changed the
     * state again leaves it elsewhere. */
    if (out->changed_by_clock) {
        CHECK(out->clock_state != w->prev_state, "a change by the clock to the same state");
    } else {
        CHECK(out->clock_state == w->prev_state, "clock_state moved without a change");
    }
    CHECK(out->clock_state == st.state || out->state_changed, "two states, no change");
    /* A release is counted exactly when it takes the unit out of STOPPED. */
    CHECK((st.counters.releases_accepted != w->prev.releases_accepted) ==
              (w->prev_state == ESTOP_STATE_STOPPED && st.state != ESTOP_STATE_STOPPED),
          "release counted without leaving STOPPED (or not counted)");

    /* SLOWING -> ARMED: only a valid packet, the third since SLOWING began. */
    if (st.state == ESTOP_STATE_ARMED && w->prev_state == ESTOP_STATE_SLOWING) {
        CHECK(c->kind == 1 && st.counters.udp_valid == w->prev.udp_valid + 1u,
              "SLOWING left for ARMED without a valid packet");
        CHECK(w->slow_run == 3u, "SLOWING left for ARMED before 3 valid packets");
        CHECK(st.counters.rearms == w->prev.rearms + 1u, "way back to ARMED counted");
    }
    /* Never ARMED (or SLOWING) without an accepted RELEASE. */
    if (st.state != ESTOP_STATE_STOPPED && w->prev_state == ESTOP_STATE_STOPPED) {
        int good = 0;
        uint32_t msg;
        CHECK(c->kind == 2 && c->frame_done && out->has_reply, "ARMED without a RELEASE frame");
        msg = fz_frame_msg(c, &good);
        CHECK(good && msg == ESTOP_MSG_RELEASE, "ARMED by a frame that is no RELEASE");
        if (w->has_key) {
            CHECK(c->frame_len == ESTOP_REQ_FRAME_LEN && fz_request_tag_ok(w, c->frame) &&
                      fz_get64(c->frame + 16) == SESSION,
                  "ARMED by a RELEASE not made with the key");
        } else {
            CHECK(c->frame_len == ESTOP_TCP_FRAME_LEN, "ARMED by a request frame without a key");
        }
        CHECK(w->have_valid && !w->link_dead && w->run >= cfg->release_packets,
              "ARMED without a live link");
        CHECK(w->last_neutral, "ARMED with a latest packet that is not neutral");
        CHECK(st.counters.releases_accepted == w->prev.releases_accepted + 1u,
              "release counted");
    }
    /* Never ARMED past the slow time, never moving past the timeout. */
    if (st.state != ESTOP_STATE_STOPPED) {
        CHECK(w->have_valid && !w->link_dead && t_new < w->last_valid_t + cfg->timeout_us,
              "ARMED or SLOWING past the deadline");
        CHECK(st.state == ESTOP_STATE_SLOWING || t_new < w->last_valid_t + cfg->slow_us,
              "ARMED past the slow time");
        CHECK(st.reason == ESTOP_REASON_NONE, "ARMED or SLOWING with a reason");
    } else {
        CHECK(st.reason != ESTOP_REASON_NONE, "STOPPED without a reason");
    }
    CHECK(st.link_live == (uint8_t)(w->have_valid && !w->link_dead &&
                                    w->run >= cfg->release_packets),
          "link_live read-out");

    /* next_call_us: in the future, no later than the next due brake frame and the deadline. */
    d = out->next_call_us - (uint32_t)t_new;
    CHECK(d > 0u, "next_call_us in the past (or now)");
    CHECK(d <= cfg->brake_period_us, "next_call_us beyond a brake period");
    CHECK(t_new + d <= w->last_brake_t + cfg->brake_period_us || backwards,
          "next_call_us after the next brake frame is due");
    CHECK(t_new + d <= w->last_status_t + cfg->status_period_us || backwards,
          "next_call_us after the next status frame is due");
    if (st.state == ESTOP_STATE_ARMED) {
        CHECK(t_new + d <= w->last_valid_t + cfg->slow_us, "next_call_us after the slow time");
    } else if (st.state == ESTOP_STATE_SLOWING) {
        CHECK(t_new + d <= w->last_valid_t + cfg->timeout_us, "next_call_us after the deadline");
    }
    w->next_call = out->next_call_us;
    w->prev = st.counters;
    w->prev_state = st.state;
}

