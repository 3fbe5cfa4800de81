/*
 * estop_core: the emergency-stop state machine. See estop_core.h for the host contract and
 * PROTOCOL.md sections 1-4 for the rules implemented here.
 *
 * Every entry point runs the same three steps:
 *   1. begin(): advance the clock (timeout stop, link ageing), send what is due;
 *   2. the input itself (a datagram, a TCP frame, a fault...);
 *   3. finish(): state read-out and the next call time.
 * So a late input can never undo a stop that its own timestamp already implies.
 */
#include "estop_core.h"

#include "estop_crc.h"

#define CORE_MAGIC 0x45535450u    /* "ESTP" */
#define FLOAT_ONE_BITS 0x3F800000u  /* IEEE-754 single 1.0f */
#define FLOAT_ABS_MASK 0x7FFFFFFFu
#define FLOAT_SIGN_BIT 0x80000000u
#define COUNTER_MODULO 15u        /* alive counter runs 0..14; 15 is never sent */
#define SAT8_MAX 255u
#define SAT4_MAX 15u               /* the two nibbles of ESTOP_STATUS byte 3 */
#define LINK_AGE_NONE_MS 0xFFFFu
#define PLAIN_FRAME_LEN ESTOP_TCP_FRAME_LEN
#define MAGIC_LEN 4u               /* the first bytes of a frame decide its form */
#define CONTROL_BODY_AT 24u        /* 5.1: the control body inside an authenticated packet */
#define CONTROL_TAG_AT 44u         /* 5.1: the tag covers bytes 0..43 */
#define REQUEST_TAG_AT 32u         /* 5.2: the tag covers bytes 0..31 */
#define CHANNEL_UDP 0u
#define CHANNEL_TCP 1u
#define GAP_FIRST_EXP 10u          /* bin 1 starts at 2^10 us */
#define GAP_LONG_US 0x40000000u    /* past this age a gap is only "very long" (bin 31): the
                                      wrapping tick could not measure it much further */

/* ---- small helpers ------------------------------------------------------------------------ */

static uint32_t rd_u32le(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

static void wr_u32le(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static uint64_t rd_u64le(const uint8_t *p)
{
    return (uint64_t)rd_u32le(p) | ((uint64_t)rd_u32le(&p[4]) << 32);
}

static void wr_u64le(uint8_t *p, uint64_t v)
{
    wr_u32le(p, (uint32_t)(v & 0xFFFFFFFFu));
    wr_u32le(&p[4], (uint32_t)(v >> 32));
}

static uint8_t sat8_inc(uint8_t v)
{
    return (v < SAT8_MAX) ? (uint8_t)(v + 1u) : v;
}

static uint32_t sat32_inc(uint32_t v)
{
    return (v < 0xFFFFFFFFu) ? (uint32_t)(v + 1u) : v;
}

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

/* A float32 (as raw bits) is finite and within -1.0 .. 1.0. NaN and infinities have a
 * magnitude above 1.0's bit pattern, so one comparison covers all three; no FPU needed. */
static int unit_range_bits(uint32_t bits)
{
    return (bits & FLOAT_ABS_MASK) <= FLOAT_ONE_BITS;
}

/* gas_brake <= 0: any negative value, -0.0 or +0.0. */
static int non_positive_bits(uint32_t bits)
{
    return ((bits & FLOAT_SIGN_BIT) != 0u) || (bits == 0u);
}

/* Byte loops instead of struct assignment: gcc compiles a large struct copy or zeroing into a
 * call to memcpy/memset, which a freestanding build without libc cannot link (docs/MCU.md). */
static void zero_bytes(uint8_t *dst, size_t n)
{
    size_t i;
    for (i = 0u; i < n; i++) {
        dst[i] = 0u;
    }
}

static void copy_bytes(uint8_t *dst, const uint8_t *src, size_t n)
{
    size_t i;
    for (i = 0u; i < n; i++) {
        dst[i] = src[i];
    }
}

/* ---- configuration ------------------------------------------------------------------------ */

void estop_config_default(estop_config_t *cfg)
{
    if (cfg != NULL) {
        uint32_t i;
        cfg->timeout_us = ESTOP_DEFAULT_TIMEOUT_US;
        cfg->slow_us = ESTOP_DEFAULT_TIMEOUT_US; /* S = T: never SLOWING (version 2) */
        cfg->warn_us = ESTOP_DEFAULT_TIMEOUT_US / 2u;
        cfg->slow_level = (uint8_t)ESTOP_DEFAULT_SLOW_LEVEL;
        cfg->stop_id = ESTOP_DEFAULT_STOP_ID;
        cfg->brake_can_id = ESTOP_DEFAULT_BRAKE_CAN_ID;
        cfg->status_can_id = ESTOP_DEFAULT_STATUS_CAN_ID;
        cfg->brake_data_id = (uint16_t)ESTOP_DEFAULT_BRAKE_DATA_ID;
        cfg->status_data_id = (uint16_t)ESTOP_DEFAULT_STATUS_DATA_ID;
        cfg->release_packets = ESTOP_DEFAULT_RELEASE_PACKETS;
        cfg->brake_period_us = ESTOP_DEFAULT_BRAKE_PERIOD_US;
        cfg->status_period_us = ESTOP_DEFAULT_STATUS_PERIOD_US;
        cfg->session = 0u; /* the host's to draw (estop_init refuses 0) */
        cfg->key_len = 0u;
        for (i = 0u; i < ESTOP_KEY_LEN; i++) {
            cfg->key[i] = 0u;
        }
    }
}

estop_err_t estop_config_check(const estop_config_t *cfg)
{
    estop_err_t err = ESTOP_OK;
    if (cfg == NULL) {
        err = ESTOP_ERR_NULL_ARG;
    } else if ((cfg->timeout_us < ESTOP_TIMEOUT_MIN_US) ||
               (cfg->timeout_us > ESTOP_TIMEOUT_MAX_US)) {
        err = ESTOP_ERR_TIMEOUT;
    } else if ((cfg->slow_us == 0u) || (cfg->slow_us > cfg->timeout_us)) {
        err = ESTOP_ERR_SLOW;
    } else if ((cfg->warn_us == 0u) || (cfg->warn_us > cfg->slow_us)) {
        err = ESTOP_ERR_WARN;
    } else if ((cfg->slow_level < ESTOP_SLOW_LEVEL_MIN) ||
               (cfg->slow_level > ESTOP_SLOW_LEVEL_MAX)) {
        err = ESTOP_ERR_SLOW_LEVEL;
    } else if ((cfg->stop_id == 0u) || (cfg->stop_id == ESTOP_MSG_STATUS) ||
               (cfg->stop_id == ESTOP_MSG_RELEASE) || (cfg->stop_id == ESTOP_MSG_LIFT) ||
               (cfg->stop_id == ESTOP_MAGIC_REQUEST)) {
        err = ESTOP_ERR_STOP_ID;
    } else if ((cfg->brake_can_id > ESTOP_CAN_ID_MAX) || (cfg->status_can_id > ESTOP_CAN_ID_MAX) ||
               (cfg->brake_can_id == cfg->status_can_id)) {
        err = ESTOP_ERR_CAN_ID;
    } else if (cfg->brake_data_id == cfg->status_data_id) {
        err = ESTOP_ERR_DATA_ID;
    } else if (cfg->release_packets == 0u) {
        err = ESTOP_ERR_RELEASE_COUNT;
    } else if ((cfg->brake_period_us < ESTOP_BRAKE_PERIOD_MIN_US) ||
               (cfg->brake_period_us > ESTOP_BRAKE_PERIOD_MAX_US)) {
        err = ESTOP_ERR_BRAKE_PERIOD;
    } else if ((cfg->status_period_us < ESTOP_STATUS_PERIOD_MIN_US) ||
               (cfg->status_period_us > ESTOP_STATUS_PERIOD_MAX_US) ||
               (cfg->status_period_us < cfg->brake_period_us)) {
        err = ESTOP_ERR_STATUS_PERIOD;
    } else if ((cfg->key_len != 0u) && (cfg->key_len != ESTOP_KEY_LEN)) {
        err = ESTOP_ERR_KEY;
    } else if (cfg->session == 0u) {
        err = ESTOP_ERR_SESSION;
    } else {
        err = ESTOP_OK;
    }
    return err;
}

estop_err_t estop_init(estop_core_t *core, const estop_config_t *cfg, uint32_t now_us)
{
    estop_err_t err = ESTOP_ERR_NULL_ARG;
    if (core != NULL) {
        zero_bytes((uint8_t *)core, sizeof(*core)); /* magic 0: unusable until checked below */
        err = estop_config_check(cfg);
        if (err == ESTOP_OK) {
            uint32_t i;
            copy_bytes((uint8_t *)&core->cfg, (const uint8_t *)cfg, sizeof(*cfg));
            if (cfg->key_len == ESTOP_KEY_LEN) {
                /* Every tag starts from the state after the key block; the key itself is not
                 * kept (a key of valid length cannot fail here). */
                (void)estop_b2s_key_init(&core->mac, cfg->key, ESTOP_KEY_LEN, ESTOP_TAG_LEN);
            }
            for (i = 0u; i < ESTOP_KEY_LEN; i++) {
                core->cfg.key[i] = 0u;
            }
            core->now_us = now_us;
            core->state = (uint8_t)ESTOP_STATE_STOPPED;
            core->reason = (uint8_t)ESTOP_REASON_BOOT;
            core->counters.stops[ESTOP_REASON_BOOT] = 1u;
            core->brake_due_us = now_us; /* the boot frames are due at once */
            core->status_due_us = now_us;
            core->magic = CORE_MAGIC;
        }
    }
    return err;
}

/* ---- read-outs ---------------------------------------------------------------------------- */

static uint32_t link_age(const estop_core_t *core)
{
    return (uint32_t)(core->now_us - core->last_valid_us);
}

/* ARMED or SLOWING: the brake is not latched and the watchdog runs. */
static int moving(const estop_core_t *core)
{
    return core->state != ESTOP_STATE_STOPPED;
}

static uint8_t current_flags(const estop_core_t *core)
{
    uint8_t flags = 0u;
    if ((moving(core) != 0) && (link_age(core) >= core->cfg.warn_us)) {
        flags = (uint8_t)ESTOP_FLAG_LINK_DEGRADED;
    }
    return flags;
}

/* The link check of a RELEASE. begin() has already aged the link, so a fresh link is younger
 * than the timeout. */
static int link_live(const estop_core_t *core)
{
    return (core->link_fresh != 0u) && (core->valid_run >= core->cfg.release_packets);
}

/* ---- CAN frames --------------------------------------------------------------------------- */

static void push_frame(estop_out_t *out, uint32_t id, uint16_t data_id, const uint8_t *payload,
                       uint8_t *counter)
{
    /* Callers never exceed ESTOP_OUT_MAX_CAN (see the header); the guard keeps that true. */
    if (out->n_can < ESTOP_OUT_MAX_CAN) {
        estop_can_frame_t *f = &out->can[out->n_can];
        uint8_t i;
        f->id = id;
        f->dlc = (uint8_t)ESTOP_CAN_DLC;
        for (i = 0u; i < 6u; i++) {
            f->data[i] = payload[i];
        }
        f->data[6] = (uint8_t)(*counter & 0x0Fu);
        f->data[7] = estop_crc8_e2e(data_id, f->data, 7u);
        *counter = (uint8_t)((*counter + 1u) % COUNTER_MODULO);
        out->n_can++;
    }
}

static void send_brake(estop_core_t *core, estop_out_t *out)
{
    uint8_t p[6];
    if (core->state == ESTOP_STATE_ARMED) {
        p[0] = (uint8_t)ESTOP_BRAKE_RELEASE;
        p[1] = 0u;
    } else if (core->state == ESTOP_STATE_SLOWING) {
        p[0] = (uint8_t)ESTOP_BRAKE_CONTROLLED;
        p[1] = core->cfg.slow_level;
    } else {
        p[0] = (uint8_t)ESTOP_BRAKE_EMERGENCY; /* STOPPED, and any state it does not know */
        p[1] = (uint8_t)ESTOP_BRAKE_LEVEL_FULL;
    }
    p[2] = core->state;
    p[3] = core->reason;
    p[4] = current_flags(core);
    p[5] = 0u;
    push_frame(out, core->cfg.brake_can_id, core->cfg.brake_data_id, p, &core->brake_counter);
}

static void send_status(estop_core_t *core, estop_out_t *out)
{
    uint8_t p[6];
    uint32_t age_ms = LINK_AGE_NONE_MS;
    if (core->link_fresh != 0u) {
        age_ms = link_age(core) / 1000u; /* below the 60 s timeout limit, so fits in 16 bits */
    }
    p[0] = core->status_valid;
    p[1] = core->status_invalid;
    p[2] = core->status_auth_failed;
    p[3] = (uint8_t)(core->status_stops | (uint8_t)(core->status_slowdowns << 4));
    p[4] = (uint8_t)(age_ms & 0xFFu);
    p[5] = (uint8_t)((age_ms >> 8) & 0xFFu);
    push_frame(out, core->cfg.status_can_id, core->cfg.status_data_id, p, &core->status_counter);
    core->status_valid = 0u;
    core->status_invalid = 0u;
    core->status_auth_failed = 0u;
    core->status_stops = 0u;
    core->status_slowdowns = 0u;
}

/* ---- transitions -------------------------------------------------------------------------- */

/* A state change sends ESTOP_BRAKE at once and restarts its period from there. */
static void state_changed(estop_core_t *core, estop_out_t *out)
{
    out->state_changed = 1u;
    send_brake(core, out);
    core->brake_due_us = core->now_us + core->cfg.brake_period_us;
}

static uint8_t sat4_inc(uint8_t v)
{
    return (v < SAT4_MAX) ? (uint8_t)(v + 1u) : v;
}

/* Every stop request restarts the release count; only the first one sets the reason. */
static void stop(estop_core_t *core, uint8_t reason, estop_out_t *out)
{
    core->valid_run = 0u;
    if (moving(core) != 0) {
        core->state = (uint8_t)ESTOP_STATE_STOPPED;
        core->reason = reason;
        core->counters.stops[reason]++;
        core->status_stops = sat4_inc(core->status_stops);
        state_changed(core, out);
    }
}

/* SLOWING at the slow time: a controlled stop that the link's return ends. The caller sends
 * the state change. */
static void enter_slowing(estop_core_t *core)
{
    core->state = (uint8_t)ESTOP_STATE_SLOWING;
    core->slow_run = 0u;
    core->counters.slowdowns++;
    core->status_slowdowns = sat4_inc(core->status_slowdowns);
}

/* An accepted RELEASE. The link is younger than the timeout but may be older than the slow
 * time (S < T): then the slow-down is already due, and the unit goes straight to SLOWING, so
 * that no frame ever releases the brake for a link that has been silent for S. */
static void arm(estop_core_t *core, estop_out_t *out)
{
    core->state = (uint8_t)ESTOP_STATE_ARMED;
    core->reason = (uint8_t)ESTOP_REASON_NONE;
    if (link_age(core) >= core->cfg.slow_us) {
        enter_slowing(core);
    }
    state_changed(core, out);
}

/* ---- the common prologue and epilogue ----------------------------------------------------- */

static void advance_clock(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    uint32_t step = (uint32_t)(now_us - core->now_us);
    core->now_us = now_us;
    if (step > ESTOP_MAX_STEP_US) {
        /* The tick went backwards: the unit can no longer trust any age it computes. */
        core->link_fresh = 0u;
        core->counters.faults++;
        stop(core, (uint8_t)ESTOP_REASON_FAULT, out);
    }
    if (step > ESTOP_MAX_STEP_US) {
        core->gap_known = 0u; /* the next gap cannot be measured: it is not recorded */
    } else if ((core->link_fresh == 0u) && (core->gap_known != 0u) &&
               (link_age(core) >= GAP_LONG_US)) { /* a fresh link is younger than 60 s */
        core->gaps[ESTOP_GAP_BINS - 1u] = sat32_inc(core->gaps[ESTOP_GAP_BINS - 1u]);
        core->silences = sat32_inc(core->silences);
        core->gap_known = 0u; /* recorded as "very long" now, before the tick can wrap */
    } else {
        /* a gap still measurable: record_gap() records it when the next packet arrives */
    }
    if ((core->link_fresh != 0u) && (link_age(core) >= core->cfg.timeout_us)) {
        core->link_fresh = 0u; /* latched: a wrapped tick can never make this link young again */
        core->valid_run = 0u;  /* a RELEASE needs its packets from after the silence */
    }
    if ((moving(core) != 0) && (core->link_fresh == 0u)) {
        stop(core, (uint8_t)ESTOP_REASON_UDP_TIMEOUT, out);
    } else if ((core->state == ESTOP_STATE_ARMED) && (link_age(core) >= core->cfg.slow_us)) {
        enter_slowing(core); /* ARMED implies a fresh link, so the age is meaningful */
        state_changed(core, out);
    } else {
        /* nothing is due: the state stays */
    }
    if (out->state_changed != 0u) {
        out->changed_by_clock = 1u;
    }
}

/* A frame is due unless its due time lies in (now, now + period]. So a due time that has been
 * reached is due, and so is one that lies further ahead than a period: that only happens when
 * the tick went backwards, and the period must hold whatever the clock does. */
static int frame_due(uint32_t now, uint32_t due, uint32_t period)
{
    return ((uint32_t)(due - now) - 1u) >= period;
}

/* Next due time on a fixed grid; a caller that fell a whole period behind, or whose clock went
 * backwards, restarts the grid from now. */
static uint32_t next_due(uint32_t due, uint32_t period, uint32_t now)
{
    uint32_t next = due + period;
    if (frame_due(now, next, period) != 0) {
        next = now + period;
    }
    return next;
}

static void send_due_frames(estop_core_t *core, estop_out_t *out)
{
    if (frame_due(core->now_us, core->brake_due_us, core->cfg.brake_period_us) != 0) {
        send_brake(core, out);
        core->brake_due_us = next_due(core->brake_due_us, core->cfg.brake_period_us, core->now_us);
    }
    if (frame_due(core->now_us, core->status_due_us, core->cfg.status_period_us) != 0) {
        send_status(core, out);
        core->status_due_us =
            next_due(core->status_due_us, core->cfg.status_period_us, core->now_us);
    }
}

/* Only what says how much of the output is meaningful is cleared: frames beyond n_can and
 * reply bytes without has_reply are left as they were (clearing all 112 bytes cost the plain
 * packet path a sixth of its instructions). */
static void clear_out(estop_out_t *out)
{
    out->n_can = 0u;
    out->has_reply = 0u;
    out->reply_len = 0u;
    out->close_slot = 0u;
    out->state_changed = 0u;
    out->changed_by_clock = 0u;
}

static estop_err_t begin(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = ESTOP_OK;
    if ((core == NULL) || (out == NULL)) {
        err = ESTOP_ERR_NULL_ARG;
    } else {
        clear_out(out);
        if (core->magic != CORE_MAGIC) {
            err = ESTOP_ERR_NOT_INIT;
        } else {
            advance_clock(core, now_us, out);
            send_due_frames(core, out);
        }
    }
    return err;
}

static uint32_t earliest(uint32_t now, uint32_t a, uint32_t b)
{
    return ((uint32_t)(a - now) <= (uint32_t)(b - now)) ? a : b;
}

static void finish(const estop_core_t *core, estop_out_t *out)
{
    uint32_t next = earliest(core->now_us, core->brake_due_us, core->status_due_us);
    if (core->state == ESTOP_STATE_ARMED) {
        next = earliest(core->now_us, next, core->last_valid_us + core->cfg.slow_us);
    } else if (core->state == ESTOP_STATE_SLOWING) {
        next = earliest(core->now_us, next, core->last_valid_us + core->cfg.timeout_us);
    } else {
        /* STOPPED: only the periodic frames are due */
    }
    out->next_call_us = next;
    out->state = core->state;
    out->reason = core->reason;
    out->flags = current_flags(core);
}

/* ---- entry points ------------------------------------------------------------------------- */

estop_err_t estop_tick(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = begin(core, now_us, out);
    if (err == ESTOP_OK) {
        finish(core, out);
    }
    return err;
}

/* Section 1: every field of a control body in range (the 16-byte form has no horn). */
static int body_valid(const uint8_t *b, int has_horn)
{
    uint32_t gear = rd_u32le(&b[8]);
    uint32_t turn = rd_u32le(&b[12]);
    uint32_t horn = has_horn ? rd_u32le(&b[16]) : 0u;
    return unit_range_bits(rd_u32le(b)) && unit_range_bits(rd_u32le(&b[4])) &&
           ((gear == 1u) || (gear == 2u) || (gear == 4u) || (gear == 8u)) && (turn <= 3u) &&
           (horn <= 1u);
}

static estop_remote_t *find_remote(estop_core_t *core, uint32_t id)
{
    estop_remote_t *found = NULL;
    uint32_t i;
    for (i = 0u; (i < ESTOP_MAX_REMOTES) && (found == NULL); i++) {
        if ((core->remotes[i].used != 0u) && (core->remotes[i].id == id)) {
            found = &core->remotes[i];
        }
    }
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

/* Section 5: msg[0 .. tag_at-1] is covered by the tag at msg[tag_at]; remote id, session and
 * counter are at the offsets of both message forms' layouts (given by the caller). True when
 * the message is authenticated; the new counter is then kept. A failure is counted by the
 * first check that failed. Only called on a unit with a key. */
static int authenticate(estop_core_t *core, const uint8_t *msg, size_t tag_at, uint32_t remote,
                        uint64_t session, uint64_t counter, uint32_t channel)
{
    uint8_t tag[ESTOP_TAG_LEN];
    const uint8_t bit = (uint8_t)(1u << channel);
    int ok = 0;
    (void)estop_b2s_mac(&core->mac, msg, tag_at, tag);
    if (!estop_ct_equal(tag, &msg[tag_at], ESTOP_TAG_LEN)) {
        core->counters.auth_bad_tag++;
    } else if (session != core->cfg.session) {
        core->counters.auth_bad_session++;
    } else {
        /* A new remote id gets a place only here, with a right tag and session. */
        estop_remote_t *r = find_remote(core, remote);
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

/* Section 1: the control body of a valid packet of the form the unit expects (plain without
 * a key, authenticated with one), or NULL. */
static const uint8_t *valid_body(estop_core_t *core, const uint8_t *d, size_t len)
{
    const uint8_t *body = NULL;
    if (d == NULL) {
        body = NULL;
    } else if (core->cfg.key_len == 0u) {
        if ((len == ESTOP_UDP_LEN) && body_valid(d, 1)) {
            body = d;
        } else if ((len == ESTOP_UDP_LEN_NO_HORN) && body_valid(d, 0)) {
            body = d;
        } else {
            /* no valid plain packet: body stays NULL */
        }
    } else if ((len == ESTOP_UDP_AUTH_LEN) && (rd_u32le(d) == ESTOP_MAGIC_CONTROL) &&
               body_valid(&d[CONTROL_BODY_AT], 1) &&
               authenticate(core, d, CONTROL_TAG_AT, rd_u32le(&d[4]), rd_u64le(&d[8]),
                            rd_u64le(&d[16]), CHANNEL_UDP)) {
        body = &d[CONTROL_BODY_AT];
    } else {
        /* no valid authenticated packet: body stays NULL */
    }
    return body;
}

uint32_t estop_gap_bin(uint32_t gap_us)
{
    uint32_t bin = 0u;
    if (gap_us >= ((uint32_t)1u << GAP_FIRST_EXP)) {
        uint32_t e = log2_floor(gap_us);
        bin = 1u + (2u * (e - GAP_FIRST_EXP)) + ((gap_us >> (e - 1u)) & 1u);
        if (bin > (ESTOP_GAP_BINS - 1u)) {
            bin = ESTOP_GAP_BINS - 1u;
        }
    }
    return bin;
}

/* The link's record (issue 12): the gap since the previous valid packet. */
static void record_gap(estop_core_t *core, uint32_t now_us)
{
    if (core->gap_known != 0u) {
        uint32_t gap = (uint32_t)(now_us - core->last_valid_us);
        uint32_t bin = estop_gap_bin(gap);
        core->gaps[bin] = sat32_inc(core->gaps[bin]);
        if (gap >= core->cfg.warn_us) {
            core->silences = sat32_inc(core->silences);
        }
    }
    core->gap_known = 1u;
}

/* The reason a stop request of this msg_id stops the unit with: a STOP or a LIFT; 0 (none) for
 * any other msg_id. */
static uint8_t stop_reason(const estop_core_t *core, uint32_t msg_id)
{
    uint8_t reason = (uint8_t)ESTOP_REASON_NONE;
    if (msg_id == core->cfg.stop_id) {
        reason = (uint8_t)ESTOP_REASON_TCP_STOP;
    } else if (msg_id == ESTOP_MSG_LIFT) {
        reason = (uint8_t)ESTOP_REASON_LIFT;
    } else {
        /* not a stop request */
    }
    return reason;
}

/* Section 1: a request frame with the stop ID or LIFT; returns its stop reason, or 0. Anyone may
 * stop, so its tag, session and counter are never looked at. */
static uint8_t stop_datagram(const estop_core_t *core, const uint8_t *d, size_t len)
{
    uint8_t reason = (uint8_t)ESTOP_REASON_NONE;
    if ((d != NULL) && (len == ESTOP_REQ_FRAME_LEN) && (rd_u32le(d) == ESTOP_MAGIC_REQUEST)) {
        reason = stop_reason(core, rd_u32le(&d[4]));
    }
    return reason;
}

/* Section 3: a valid packet while SLOWING counts toward the way back to ARMED. */
static void count_rearm(estop_core_t *core, estop_out_t *out)
{
    core->slow_run++;
    if (core->slow_run >= ESTOP_REARM_PACKETS) {
        core->counters.rearms++;
        core->state = (uint8_t)ESTOP_STATE_ARMED;
        state_changed(core, out);
    }
}

estop_err_t estop_udp_rx(estop_core_t *core, const uint8_t *data, size_t len, uint32_t now_us,
                         estop_out_t *out)
{
    estop_err_t err = begin(core, now_us, out);
    if (err == ESTOP_OK) {
        const uint8_t *body = NULL;
        const uint8_t reason = stop_datagram(core, data, len);
        if (reason != ESTOP_REASON_NONE) {
            core->counters.udp_stops++;
            stop(core, reason, out);
        } else {
            body = valid_body(core, data, len);
            if (body != NULL) {
                record_gap(core, now_us);
                core->counters.udp_valid++;
                core->status_valid = sat8_inc(core->status_valid);
                core->valid_run = sat32_inc(core->valid_run);
                core->last_valid_us = now_us;
                core->link_fresh = 1u;
                core->last_neutral = non_positive_bits(rd_u32le(body)) ? 1u : 0u;
                if (core->state == ESTOP_STATE_SLOWING) {
                    count_rearm(core, out);
                }
            } else {
                core->counters.udp_invalid++;
                core->status_invalid = sat8_inc(core->status_invalid);
            }
        }
        finish(core, out);
    }
    return err;
}

static estop_err_t check_slot(const estop_core_t *core, uint32_t slot)
{
    estop_err_t err = ESTOP_OK;
    if (core == NULL) {
        err = ESTOP_ERR_NULL_ARG;
    } else if (slot >= ESTOP_MAX_SLOTS) {
        err = ESTOP_ERR_SLOT;
    } else {
        /* a slot in range: err stays ESTOP_OK */
    }
    return err;
}

/* Opening and closing a slot both start it empty; only the open mark differs. */
static estop_err_t set_slot(estop_core_t *core, uint32_t slot, uint8_t open, uint32_t now_us,
                            estop_out_t *out)
{
    estop_err_t err = check_slot(core, slot);
    if (err == ESTOP_OK) {
        err = begin(core, now_us, out);
    }
    if (err == ESTOP_OK) {
        core->slots[slot].open = open;
        core->slots[slot].fill = 0u;
        finish(core, out);
    }
    return err;
}

estop_err_t estop_tcp_open(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out)
{
    return set_slot(core, slot, 1u, now_us, out);
}

estop_err_t estop_tcp_close(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out)
{
    return set_slot(core, slot, 0u, now_us, out);
}

/* The reply fields shared by both forms: ACK/NAK, seq, state, reason, flags, nak code. */
static void reply_head(const estop_core_t *core, uint8_t *r, uint32_t seq, uint8_t nak_code)
{
    wr_u32le(r, (nak_code == ESTOP_NAK_NONE) ? ESTOP_MSG_ACK : ESTOP_MSG_NAK);
    wr_u32le(&r[4], seq);
    r[8] = core->state;
    r[9] = core->reason;
    r[10] = current_flags(core);
    r[11] = nak_code;
}

/* Section 2: the 16-byte reply to a plain frame. */
static void reply_plain(const estop_core_t *core, uint32_t seq, uint8_t nak_code, estop_out_t *out)
{
    reply_head(core, out->reply, seq, nak_code);
    wr_u32le(&out->reply[12], estop_crc32(out->reply, 12u));
    out->reply_len = (uint8_t)ESTOP_TCP_FRAME_LEN;
    out->has_reply = 1u;
}

/* Section 5.3: the 48-byte reply to a request frame, tagged over the request's tag and the
 * reply's first 32 bytes (zero tag without a key). */
static void reply_request(const estop_core_t *core, const uint8_t *req, uint8_t nak_code,
                          estop_out_t *out)
{
    uint8_t *r = out->reply;
    uint32_t i;
    wr_u32le(r, ESTOP_MAGIC_REPLY);
    reply_head(core, &r[4], rd_u32le(&req[8]), nak_code);
    wr_u64le(&r[16], core->cfg.session);
    wr_u64le(&r[24], rd_u64le(&req[24]));
    if (core->cfg.key_len != 0u) {
        uint8_t m[ESTOP_TAG_LEN + REQUEST_TAG_AT];
        for (i = 0u; i < ESTOP_TAG_LEN; i++) {
            m[i] = req[REQUEST_TAG_AT + i];
        }
        for (i = 0u; i < REQUEST_TAG_AT; i++) {
            m[ESTOP_TAG_LEN + i] = r[i];
        }
        (void)estop_b2s_mac(&core->mac, m, sizeof m, &r[REQUEST_TAG_AT]);
    } else {
        for (i = 0u; i < ESTOP_TAG_LEN; i++) {
            r[REQUEST_TAG_AT + i] = 0u;
        }
    }
    out->reply_len = (uint8_t)ESTOP_REPLY_MAX;
    out->has_reply = 1u;
}

/* Section 3: a RELEASE that is authenticated (or needs no authentication) still needs a live
 * link and a neutral latest packet. */
static uint8_t release(estop_core_t *core, int authenticated, estop_out_t *out)
{
    uint8_t nak = (uint8_t)ESTOP_NAK_NONE;
    if (!authenticated) {
        nak = (uint8_t)ESTOP_NAK_NOT_AUTHENTICATED;
    } else if (core->state == ESTOP_STATE_STOPPED) {
        if (!link_live(core)) {
            nak = (uint8_t)ESTOP_NAK_NO_LIVE_LINK;
        } else if (core->last_neutral == 0u) {
            nak = (uint8_t)ESTOP_NAK_NOT_NEUTRAL;
        } else {
            arm(core, out);
        }
    } else {
        nak = (uint8_t)ESTOP_NAK_NONE; /* ARMED or SLOWING: acknowledged, nothing changes */
    }
    if ((nak == ESTOP_NAK_NONE) && (out->state_changed != 0u)) {
        core->counters.releases_accepted++;
    } else if (nak != ESTOP_NAK_NONE) {
        core->counters.releases_refused++;
    } else {
        /* acknowledged while ARMED or SLOWING: neither accepted nor refused */
    }
    return nak;
}

/* What a good frame of either form asks for; returns the NAK code of its reply. */
static uint8_t handle_msg(estop_core_t *core, uint32_t msg_id, int release_authenticated,
                          estop_out_t *out)
{
    uint8_t nak = (uint8_t)ESTOP_NAK_NONE;
    const uint8_t reason = stop_reason(core, msg_id);
    core->counters.tcp_frames++;
    if (reason != ESTOP_REASON_NONE) {
        stop(core, reason, out);
    } else if (msg_id == ESTOP_MSG_RELEASE) {
        nak = release(core, release_authenticated, out);
    } else if (msg_id != ESTOP_MSG_STATUS) {
        core->counters.tcp_unknown_id++;
        nak = (uint8_t)ESTOP_NAK_UNKNOWN_ID;
    } else {
        /* STATUS: answered with ACK, changes nothing */
    }
    return nak;
}

/* Section 2: one whole 16-byte plain frame. A plain RELEASE is authenticated only on a unit
 * without a key. */
static void handle_plain(estop_core_t *core, estop_slot_t *slot, estop_out_t *out)
{
    const uint8_t *f = slot->buf;
    if (estop_crc32(f, 12u) != rd_u32le(&f[12])) {
        /* The stream has lost framing: nothing after this can be trusted. */
        core->counters.tcp_bad_crc++;
        slot->open = 0u;
        out->close_slot = 1u;
    } else {
        uint8_t nak = handle_msg(core, rd_u32le(f), core->cfg.key_len == 0u, out);
        reply_plain(core, rd_u32le(&f[4]), nak, out);
    }
}

/* Section 5.2: one whole 48-byte request frame. Only a RELEASE needs authentication; a STOP or
 * LIFT is honoured and a STATUS answered whatever the tag says. */
static void handle_request(estop_core_t *core, const estop_slot_t *slot, estop_out_t *out)
{
    const uint8_t *f = slot->buf;
    uint32_t msg_id = rd_u32le(&f[4]);
    int authenticated = 0;
    uint8_t nak;
    if ((msg_id == ESTOP_MSG_RELEASE) && (core->cfg.key_len != 0u)) {
        authenticated = authenticate(core, f, REQUEST_TAG_AT, rd_u32le(&f[12]),
                                     rd_u64le(&f[16]), rd_u64le(&f[24]), CHANNEL_TCP);
    }
    nak = handle_msg(core, msg_id, authenticated, out);
    reply_request(core, f, nak, out);
}

/* A frame's length, known once its first 4 bytes are in. */
static uint32_t frame_len(const estop_slot_t *s)
{
    return ((s->fill >= MAGIC_LEN) && (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST))
               ? ESTOP_REQ_FRAME_LEN
               : PLAIN_FRAME_LEN;
}

estop_err_t estop_tcp_rx(estop_core_t *core, uint32_t slot, const uint8_t *data, size_t len,
                         size_t *consumed, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = check_slot(core, slot);
    if ((err == ESTOP_OK) && ((consumed == NULL) || ((data == NULL) && (len > 0u)))) {
        err = ESTOP_ERR_NULL_ARG;
    }
    if (err == ESTOP_OK) {
        *consumed = 0u;
        err = begin(core, now_us, out);
    }
    if ((err == ESTOP_OK) && (core->slots[slot].open == 0u)) {
        err = ESTOP_ERR_SLOT_CLOSED;
        finish(core, out);
    }
    if (err == ESTOP_OK) {
        estop_slot_t *s = &core->slots[slot];
        size_t take = 0u;
        size_t want;
        /* Up to one whole frame: first its 4 magic bytes, which decide its length, then the
         * rest of it. */
        while ((take < len) && (s->fill < MAGIC_LEN)) {
            s->buf[s->fill] = data[take];
            s->fill++;
            take++;
        }
        want = (size_t)frame_len(s) - (size_t)s->fill;
        if (want > (len - take)) {
            want = len - take;
        }
        while (want > 0u) {
            s->buf[s->fill] = data[take];
            s->fill++;
            take++;
            want--;
        }
        *consumed = take;
        if (s->fill == frame_len(s)) {
            s->fill = 0u;
            if (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST) {
                handle_request(core, s, out);
            } else {
                handle_plain(core, s, out);
            }
            if (out->close_slot != 0u) {
                *consumed = len; /* the rest of a broken stream is dropped */
            }
        }
        finish(core, out);
    }
    return err;
}

estop_err_t estop_fault(estop_core_t *core, uint32_t now_us, estop_out_t *out)
{
    estop_err_t err = begin(core, now_us, out);
    if (err == ESTOP_OK) {
        core->counters.faults++;
        stop(core, (uint8_t)ESTOP_REASON_FAULT, out);
        finish(core, out);
    }
    return err;
}

estop_err_t estop_get_status(const estop_core_t *core, estop_status_t *status)
{
    estop_err_t err = ESTOP_OK;
    if ((core == NULL) || (status == NULL)) {
        err = ESTOP_ERR_NULL_ARG;
    } else if (core->magic != CORE_MAGIC) {
        err = ESTOP_ERR_NOT_INIT;
    } else {
        status->state = core->state;
        status->reason = core->reason;
        status->flags = current_flags(core);
        status->link_live = link_live(core) ? 1u : 0u;
        status->valid_run = core->valid_run;
        status->link_age_us = (core->link_fresh != 0u) ? link_age(core) : 0xFFFFFFFFu;
        copy_bytes((uint8_t *)&status->counters, (const uint8_t *)&core->counters,
                   sizeof(core->counters));
    }
    return err;
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
        for (i = 0u; i < ESTOP_GAP_BINS; i++) {
            stats->gaps[i] = core->gaps[i];
        }
    }
    return err;
}

/* ---- names for host logs ------------------------------------------------------------------ */

const char *estop_err_name(estop_err_t err)
{
    static const char *const names[] = {
        "ok",           "null_arg",         "bad_timeout",  "bad_warn_time",
        "bad_stop_id",  "bad_can_id",       "bad_data_id",  "bad_release_count",
        "bad_brake_period", "bad_status_period", "not_initialised", "bad_slot",
        "slot_closed",  "bad_key",          "bad_session",  "bad_slow_time",
        "bad_slow_level"};
    const char *name = "unknown_error";
    const size_t n = sizeof(names) / sizeof(names[0]);
    const int count = (int)n;
    /* Range first: negating an arbitrary int (INT_MIN) would overflow. */
    if (((int)err <= 0) && ((int)err > -count)) {
        name = names[-(int)err];
    }
    return name;
}

const char *estop_state_name(uint32_t state)
{
    static const char *const names[] = {"STOPPED", "ARMED", "SLOWING"};
    return (state < ESTOP_STATE_COUNT) ? names[state] : "?";
}

const char *estop_reason_name(uint32_t reason)
{
    static const char *const names[] = {"none",  "boot", "tcp_stop", "udp_timeout",
                                        "fault", "lift"};
    return (reason < ESTOP_REASON_COUNT) ? names[reason] : "?";
}
