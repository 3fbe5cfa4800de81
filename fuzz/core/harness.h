/*
 * The core's fuzz harness (fuzz/fuzz_core.c) by job, behind this one header:
 *   program.c     reading the input program; control packets and request frames made from it
 *   codec.c       the harness's own codecs (bitwise CRCs, little-endian fields), not the core's
 *   frames.c      the shadow's TCP framing; checks of one CAN frame and of one reply
 *   invariants.c  everything checked after one call into the core (fz_after_call)
 *   ops.c         the host: one call into the core per operation, as estop_core.h asks
 * fuzz_core.c holds the entry point: the configuration header and the operations loop.
 */
#ifndef FUZZ_CORE_HARNESS_H
#define FUZZ_CORE_HARNESS_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

#include "estop_core.h"

#define SESSION 0x0123456789ABCDEFull /* PROTOCOL.md 5.4, so the spec's tagged vectors pass */
#define SLOTS_TRIED (ESTOP_MAX_SLOTS + 1u) /* one index past the end: ESTOP_ERR_SLOT */
#define MAX_OPS 128u
#define LEFT_MAX 64u /* control packets left unchecked under a placed id, remembered */
#define REC_MAX 8u   /* authenticated control packets recorded for replays */

#include "../fuzz_check.h"

/* ---- the input and the harness's world ------------------------------------------------- */

typedef struct {
    const uint8_t *p;
    size_t n;
} input_t;

typedef struct {
    int open;
    size_t fill;
    uint8_t buf[ESTOP_REQ_FRAME_LEN];
} shadow_slot_t;

typedef struct {
    estop_core_t core;
    estop_config_t cfg;
    uint8_t key[ESTOP_KEY_LEN];
    int has_key;
    uint64_t t;              /* the host's clock in 64 bits: the core sees its low 32 */
    uint32_t next_call;
    int booted;              /* the first call (the boot frames) has been made */
    /* shadow of the link */
    int have_valid;
    uint64_t last_valid_t;
    int last_neutral;
    uint32_t run;            /* valid packets since boot, the latest stop request, silence */
    uint32_t slow_run;       /* valid packets since SLOWING began */
    int link_dead;           /* silent for the timeout since the latest valid packet */
    /* shadow of the frames */
    uint64_t last_brake_t;
    uint64_t last_status_t;
    int brake_counter;       /* next expected alive counter, -1 before the first frame */
    int status_counter;
    shadow_slot_t slots[SLOTS_TRIED];
    uint64_t counter[10][2]; /* per remote id: what the harness sends next ([0]: one counter
                                for both channels, as a remote raises it, PROTOCOL.md 5) */
    estop_counters_t prev;   /* counters before the call */
    uint8_t prev_state;
    /* shadow of the budget's rule (issue 25): ids with a place (an authenticated message),
     * and the control packets the budget dropped unchecked under one of them: never valid
     * later, unless a RELEASE of that id below their counter was authenticated while the unit
     * was STOPPED (it forgives what lies above it). */
    uint32_t placed[ESTOP_MAX_REMOTES];
    uint32_t n_placed;
    struct {
        uint64_t hash;
        uint64_t counter;
        uint32_t id;
    } left[LEFT_MAX];
    uint32_t n_left;
    uint8_t rec[REC_MAX][ESTOP_UDP_AUTH_LEN]; /* the latest authenticated packets sent */
    uint32_t n_rec;
} world_t;

/* What the harness knows about the input of one call. */
typedef struct {
    int kind;                /* 0 clock only, 1 udp, 2 tcp bytes, 3 fault, 4 open/close */
    const uint8_t *data;
    size_t len;
    size_t consumed;
    int frame_done;          /* the shadow completed a frame with this call's bytes */
    uint8_t frame[ESTOP_REQ_FRAME_LEN];
    size_t frame_len;
    int slot_closed_call;    /* tcp_rx on a closed slot */
} call_t;


/* ---- program.c: reading the input ------------------------------------------------------- */

uint8_t fz_in_u8(input_t *in);
uint16_t fz_in_u16(input_t *in);
uint32_t fz_in_u32(input_t *in);
uint64_t fz_in_u64(input_t *in);
void fz_make_body(input_t *in, uint8_t body[20]);
void fz_tag(const world_t *w, uint8_t *msg, size_t covered, int corrupt);
void fz_auth_fields(world_t *w, input_t *in, uint8_t *session_at, uint8_t *counter_at,
                    uint32_t remote, int channel, uint8_t sel);
void fz_make_request(world_t *w, input_t *in, uint8_t f[ESTOP_REQ_FRAME_LEN], uint32_t msg_id);
uint32_t fz_pick_msg(const world_t *w, input_t *in);
uint64_t fz_later(const world_t *w, uint32_t dt);
uint64_t fz_host_time(const world_t *w, input_t *in);
void fz_record(world_t *w, const uint8_t p[ESTOP_UDP_AUTH_LEN]);

/* ---- codec.c: independent codecs (bitwise, not the core's table code) ------------------- */

uint32_t fz_crc32_bitwise(const uint8_t *d, size_t n);
uint8_t fz_crc8_e2e(uint16_t data_id, const uint8_t *d);
uint32_t fz_get32(const uint8_t *p);
uint64_t fz_get64(const uint8_t *p);
void fz_put32(uint8_t *p, uint32_t v);
void fz_put64(uint8_t *p, uint64_t v);

/* ---- frames.c: the shadow's framing, one frame, one reply ------------------------------- */

void fz_shadow_tcp(shadow_slot_t *s, call_t *c, int closed_by_core);
int fz_request_tag_ok(const world_t *w, const uint8_t *f);
uint32_t fz_frame_msg(const call_t *c, int *good);
void fz_check_frame(world_t *w, const estop_can_frame_t *f, uint64_t t);
void fz_check_reply(const world_t *w, const estop_out_t *out, const call_t *c);

/* ---- invariants.c: everything checked after one call ------------------------------------ */

void fz_after_call(world_t *w, estop_err_t err, const estop_out_t *out, call_t *c,
                   uint64_t t_new);

/* ---- ops.c: the host's calls ------------------------------------------------------------ */

void fz_do_tick(world_t *w, uint64_t t);
void fz_do_udp(world_t *w, const uint8_t *bytes, size_t len, uint64_t t);
void fz_do_slot(world_t *w, uint32_t slot, int open, uint64_t t);
void fz_do_tcp(world_t *w, uint32_t slot, const uint8_t *bytes, size_t len, uint64_t t,
               uint64_t step);

#endif /* FUZZ_CORE_HARNESS_H */
