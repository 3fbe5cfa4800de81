/*
 * The ACSL contracts of the core's entry points and of the functions its files call in one
 * another (docs/PROOF.md). Frama-C only: tools/prove.py passes this file with -include, and
 * Frama-C merges each contract with the function's declaration in estop_core.h or
 * estop_internal.h. The loop annotations and the contracts of static functions with loops
 * live beside their code in firmware/core, and so does estop__stop's (estop_clock.c): Eva reads
 * no contract of this file, and its rule that a fault stops the unit needs that one.
 *
 * The host contract of estop_core.h, as preconditions: the core, out and every buffer are
 * valid and distinct; data holds len bytes; estop_init() came first (core_ok: either magic
 * is not set, or the state is one estop_init and the entry points make).
 */
#ifndef ESTOP_PROVE_CONTRACTS_H
#define ESTOP_PROVE_CONTRACTS_H

#include "estop_crc.h"
#include "estop_internal.h"
#include "predicates.h"

/* ---- the state machine's steps (estop_core.c, estop_clock.c) ------------------------------ */

/* begin_keeps_slots once per result: as one clause over both branches the solvers paid for
 * their merge (12 to 15 s), although each branch ends on an assertion of the clause itself. */

/*@ requires begin_given: given(core, out);
    requires core != \null ==> core_ok(core);
    assigns *core, *out;
    ensures begin_always: core != \null ==> core_ok(core);
    behavior bad_args:
      assumes core == \null || out == \null;
      ensures \result == ESTOP_ERR_NULL_ARG;
      ensures core != \null ==> core->state == \old(core->state);
    behavior run:
      assumes core != \null && out != \null;
      ensures ok_iff_init: \result == ESTOP_OK <==> core->magic == 0x45535450;
      ensures begin_errs: \result == ESTOP_OK || \result == ESTOP_ERR_NOT_INIT;
      ensures begin_inv: \result == ESTOP_OK ==> inv(core);
      ensures begin_times: \result == ESTOP_OK ==> times_ok(core);
      ensures begin_out: \result == ESTOP_OK ==> core->now_us == now_us && out->n_can <= 3 &&
          out->has_reply == 0 && out->close_slot == 0;
      ensures refused_keeps_state: \result != ESTOP_OK ==> core->state == \old(core->state);
      ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
      ensures begin_room: \result == ESTOP_OK ==> out->n_can <= 2;
      ensures begin_clock_stop: \result == ESTOP_OK && \old(core->state) != 0 &&
          core->state == 0 ==> 1 <= out->n_can && emergency(out, 0, core);
      ensures begin_keeps: \result == ESTOP_OK ==>
          core->last_valid_us == \old(core->last_valid_us) &&
          core->cfg.timeout_us == \old(core->cfg.timeout_us) &&
          core->cfg.slow_us == \old(core->cfg.slow_us) &&
          core->cfg.stop_id == \old(core->cfg.stop_id);
      ensures begin_keeps_slots: \result == ESTOP_OK ==> \forall integer k; 0 <= k < 8 ==>
          core->slots[k].open == \old(core->slots[k].open);
      ensures begin_keeps_slots_refused: \result != ESTOP_OK ==> \forall integer k;
          0 <= k < 8 ==> core->slots[k].open == \old(core->slots[k].open);
      ensures begin_reports: \result == ESTOP_OK ==> out->clock_state == core->state &&
          out->clock_reason == core->reason && out->changed_by_clock == out->state_changed;
      ensures refused_reports: \result != ESTOP_OK ==>
          out->changed_by_clock == 0 && out->state_changed == 0 && out->n_can == 0;
    complete behaviors; disjoint behaviors;
 */
estop_err_t estop__begin(estop_core_t *core, uint32_t now_us, estop_out_t *out);

/*@ requires \valid(core) && \valid(out) && \separated(core, out);
    FINISH_CONTRACT
 */
void estop__finish(const estop_core_t *core, estop_out_t *out);

/*@ requires \valid_read(core);
    assigns \nothing;
    ensures \result == 0 || \result == 1;
 */
uint8_t estop__current_flags(const estop_core_t *core);

/*@ requires host(core, out) && core->magic == 0x45535450 && inv(core) && times_ok(core);
    requires out->n_can <= 3;
    assigns core->counters, core->valid_run, core->state, core->reason, core->slow_run,
            core->status_stops, core->status_slowdowns, core->brake_counter,
            core->brake_due_us, out->can[0 .. 2], out->n_can, out->state_changed;
    ENSURES_KEPT(msg)
    ensures msg_frames: out->n_can <= 3;
    ensures msg_keeps_clock: core->now_us == \old(core->now_us) &&
        core->magic == \old(core->magic);
    ensures leaves_stopped_only_by_release: \old(core->state) == 0 && core->state != 0 ==>
        msg_id == ESTOP_MSG_RELEASE && release_authenticated != 0 && \result == 0;
    ensures msg_stops: msg_id == \old(core->cfg.stop_id) || msg_id == ESTOP_MSG_LIFT ==>
        core->state == 0 && \result == 0;
    ensures msg_stop_brakes: (msg_id == \old(core->cfg.stop_id) || msg_id == ESTOP_MSG_LIFT) &&
        \old(core->state) != 0 && \old(out->n_can) <= 2 ==>
        out->n_can == \old(out->n_can) + 1 && emergency(out, \old(out->n_can), core);
    ENSURES_STOP_BRAKES(msg_stopping_brakes)
    ENSURES_STOP_BRAKES_AT(msg_stopping_brakes_at)
    ensures msg_stop_keeps: stop_asked(msg_id, \old(core->cfg.stop_id)) ==>
        \old(out->n_can) <= out->n_can && frames_kept(Pre, Post, out, \old(out->n_can));
    ensures msg_release_acked: msg_id == ESTOP_MSG_RELEASE &&
        !stop_asked(msg_id, \old(core->cfg.stop_id)) && \result == 0 ==> core->state != 0;
    ensures msg_status: msg_id == ESTOP_MSG_STATUS &&
        !stop_asked(msg_id, \old(core->cfg.stop_id)) ==>
        \result == 0 && core->state == \old(core->state);
    ensures msg_unknown: msg_id != ESTOP_MSG_RELEASE && msg_id != ESTOP_MSG_STATUS &&
        !stop_asked(msg_id, \old(core->cfg.stop_id)) ==>
        \result == ESTOP_NAK_UNKNOWN_ID && core->state == \old(core->state);
    ensures nak_code: \result <= 4;
    ENSURES_SLOTS_KEPT(msg)
 */
uint8_t estop__handle_msg(estop_core_t *core, uint32_t msg_id, int release_authenticated,
                          estop_out_t *out);

/* ---- authentication and link statistics: what they may touch ------------------------------- */

/*@ requires \valid(core) && \valid_read(msg + (0 .. tag_at + 15)) && \valid_read(msg + (ids_at .. ids_at + 19));
    requires (tag_at == 32 || tag_at == 44) && (ids_at == 4 || ids_at == 12) && channel <= 1 &&
        core->mac.outlen <= 16;
    requires \separated(msg + (0 .. tag_at + 15), &core->mac);
    assigns \nothing;
    ensures verdict_range: \result <= 5;
    ensures verdict_tag: \result == 0 ==> core->mac.outlen == 16 && tag_ok(&core->mac, msg, tag_at);
    ensures verdict_fresh: \result == 0 ==> ids_fresh(core, msg, ids_at, channel);
 */
uint32_t estop__auth_verdict(estop_core_t *core, const uint8_t *msg, size_t tag_at,
                             size_t ids_at, uint32_t channel);

/*@ requires \valid(core) && channel <= 1;
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks;
    ensures commit_fills: \forall integer j; a_slot(j) ==>
        core->slots[j].fill == \old(core->slots[j].fill);
    ensures commit_state: core->state == \old(core->state);
 */
void estop__auth_commit(estop_core_t *core, uint32_t id, uint64_t counter, uint32_t channel,
                        uint32_t verdict, int stopped);

/*@ requires \valid(core) && \valid_read(msg + (0 .. tag_at + 15)) && \valid_read(msg + (ids_at .. ids_at + 19));
    requires (tag_at == 32 || tag_at == 44) && (ids_at == 4 || ids_at == 12) && channel <= 1 &&
        core->mac.outlen <= 16;
    requires \separated(msg + (0 .. tag_at + 15), &core->counters, &core->status_auth_failed,
        core->remotes + (0 .. 7), &core->tag_window_us, &core->tag_window_open,
        &core->newcomer_checks, &core->mac);
    assigns core->counters, core->status_auth_failed, core->remotes[0 .. 7],
            core->tag_window_us, core->tag_window_open, core->newcomer_checks;
    ensures auth_result: \result == 0 || \result == 1;
    ensures auth_tag: \result == 1 ==>
        \at(core->mac.outlen == 16 && tag_ok(&core->mac, msg, tag_at), Pre);
    ensures auth_fresh: \result == 1 ==> \at(ids_fresh(core, msg, ids_at, channel), Pre);
 */
int estop__authenticate(estop_core_t *core, const uint8_t *msg, size_t tag_at, size_t ids_at,
                        uint32_t channel);

/*@ requires \valid(core);
    assigns core->counters, core->status_auth_failed;
    ENSURES_SLOTS_KEPT(unauth)
 */
void estop__unauthenticated(estop_core_t *core);

/*@ requires \valid(core);
    assigns core->tag_window_open;
 */
void estop__age_tag_window(estop_core_t *core);

/*@ requires \valid(core);
    assigns core->gaps[0 .. 31], core->silences, core->gap_known;
 */
void estop__record_gap(estop_core_t *core);

/*@ assigns \nothing;
    ensures \result < 32;
 */
uint32_t estop_gap_bin(uint32_t gap_us);

/*@ requires \valid(core);
    assigns core->gaps[0 .. 31], core->silences, core->gap_known;
 */
void estop__age_gap(estop_core_t *core, uint32_t step);

/* ---- CRCs and BLAKE2s (estop_crc.c, estop_blake2s.c): what they read and write ------------ */

/*@ requires \valid_read(payload + (0 .. len - 1));
    assigns \nothing;
 */
uint8_t estop_crc8_e2e(uint16_t data_id, const uint8_t *payload, size_t len);

/*@ requires \valid_read(data + (0 .. len - 1));
    assigns \nothing;
    admit ensures crc_value: len == 12 ==> \result == CRC12(data);
 */
uint32_t estop_crc32(const uint8_t *data, size_t len);

/*@ requires \valid(k) && \valid_read(key + (0 .. keylen - 1)) && \separated(k, key + (0 .. keylen - 1));
    assigns *k;
    ensures key_outlen: 1 <= keylen <= 32 && 1 <= outlen <= 32 ==> k->outlen == outlen;
 */
int estop_b2s_key_init(estop_b2s_key_t *k, const uint8_t *key, size_t keylen, size_t outlen);

/*@ requires \valid_read(k) && k->outlen <= 16 && \valid_read(msg + (0 .. len - 1));
    requires \valid(out + (0 .. 15)) && \separated(out + (0 .. 15), k, msg + (0 .. len - 1));
    assigns out[0 .. 15];
    ensures mac_made: \result == 0 ==> 1 <= k->outlen;
    admit ensures mac_value: \result == 0 && k->outlen == 16 && 1 <= len <= 64 && len % 4 == 0 ==>
        \forall integer i; 0 <= i < 16 ==> out[i] == MAC_BYTE(k, msg, len, i);
 */
int estop_b2s_mac(const estop_b2s_key_t *k, const uint8_t *msg, size_t len, uint8_t *out);

/*@ requires \valid(out + (0 .. outlen - 1));
    requires key == \null || \valid_read(key + (0 .. keylen - 1));
    requires msg == \null || \valid_read(msg + (0 .. len - 1));
    assigns out[0 .. outlen - 1];
 */
int estop_blake2s(uint8_t *out, size_t outlen, const uint8_t *key, size_t keylen,
                  const uint8_t *msg, size_t len);

/*@ requires a == \null || \valid_read(a + (0 .. n - 1));
    requires b == \null || \valid_read(b + (0 .. n - 1));
    assigns \nothing;
    ensures \result == 0 || \result == 1;
    ensures equal: \result == 1 ==> n == 0 || (a != \null && b != \null &&
        \forall integer i; 0 <= i < n ==> a[i] == b[i]);
 */
int estop_ct_equal(const uint8_t *a, const uint8_t *b, size_t n);

/* ---- the entry points (estop_core.h) ------------------------------------------------------- */

/*@ requires cfg == \null || \valid_read(cfg);
    assigns \nothing;
    ensures config_null: cfg == \null ==> \result == ESTOP_ERR_NULL_ARG;
    ensures config_accepted: \result == ESTOP_OK <==> (cfg != \null && config_valid(*cfg));
 */
estop_err_t estop_config_check(const estop_config_t *cfg);

/* The base case of the invariant: a core estop_init made is STOPPED (the boot), its
 * configuration one the check accepted; a refused one is unusable (magic 0). Either way
 * core_ok holds, which every entry point requires. */
/*@ requires core == \null || \valid(core);
    requires cfg == \null || (\valid_read(cfg) && \separated(core, cfg));
    assigns *core;
    ensures init_null: core == \null ==> \result == ESTOP_ERR_NULL_ARG;
    ensures init_refused: core != \null && \result != ESTOP_OK ==> core->magic == 0;
    ensures init_boots_stopped: \result == ESTOP_OK ==>
        core->magic == 0x45535450 && core->state == 0 && core->reason == 1;
    ensures init_clock: \result == ESTOP_OK ==>
        core->now_us == now_us && core->brake_due_us == now_us && core->status_due_us == now_us;
    ensures init_counts: \result == ESTOP_OK ==>
        core->counters.stops[1] == 1 && core->link_fresh == 0 && core->valid_run == 0;
    ensures init_tag_window: \result == ESTOP_OK ==>
        core->tag_window_us == now_us && core->tag_window_open == 1;
    ensures init_key: \result == ESTOP_OK ==>
        core->mac.outlen == (cfg->key_len == ESTOP_KEY_LEN ? ESTOP_TAG_LEN : 0);
    ensures init_inv: \result == ESTOP_OK ==> cfg_ok(core);
    ensures init_inv: \result == ESTOP_OK ==> known_ok(core);
    ensures init_inv: \result == ESTOP_OK ==> slots_ok(core);
    ensures init_inv: \result == ESTOP_OK ==> fresh_ok(core);
    ensures init_always: core != \null ==> core_ok(core);
 */
estop_err_t estop_init(estop_core_t *core, const estop_config_t *cfg, uint32_t now_us);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    assigns *core, *out;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
    ensures clock_stops: \result == ESTOP_OK &&
        udiff(now_us, \old(core->last_valid_us)) >= \old(core->cfg.timeout_us) ==>
        core->state == 0;
    ensures clock_slows: \result == ESTOP_OK && \old(core->state) == 1 &&
        udiff(now_us, \old(core->last_valid_us)) >= \old(core->cfg.slow_us) ==>
        core->state != 1;
    ensures stop_brakes: \result == ESTOP_OK && \old(core->state) != 0 && core->state == 0 ==>
        1 <= out->n_can && emergency(out, 0, core);
    ensures ok_iff_given: \result == ESTOP_OK <==> usable(core, out);
 */
estop_err_t estop_tick(estop_core_t *core, uint32_t now_us, estop_out_t *out);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    requires data == \null || (\valid_read(data + (0 .. len - 1)) &&
        \separated(data + (0 .. len - 1), core, out));
    assigns *core, *out;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
    ensures datagram_stops: \result == ESTOP_OK && data != \null &&
        \at(datagram_asks_stop(data, len, core->cfg.stop_id), Pre) ==> core->state == 0;
    ensures datagram_brakes: \result == ESTOP_OK && data != \null && \old(core->state) != 0 &&
        \at(datagram_asks_stop(data, len, core->cfg.stop_id), Pre) ==>
        emergency_sent(out, core);
    ensures ok_iff_given: \result == ESTOP_OK <==> usable(core, out);
 */
estop_err_t estop_udp_rx(estop_core_t *core, const uint8_t *data, size_t len, uint32_t now_us,
                         estop_out_t *out);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    assigns *core, *out;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
    ensures fault_stops: \result == ESTOP_OK ==> core->state == 0;
    ensures stop_brakes: \result == ESTOP_OK && \old(core->state) != 0 ==>
        emergency_sent(out, core);
    ensures ok_iff_given: \result == ESTOP_OK <==> usable(core, out);
 */
estop_err_t estop_fault(estop_core_t *core, uint32_t now_us, estop_out_t *out);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    assigns *core, *out;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
    ensures ok_iff_given: \result == ESTOP_OK <==> usable(core, out) && slot < 8;
 */
estop_err_t estop_tcp_open(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    assigns *core, *out;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures never_leaves_stopped: core != \null ==> (\old(core->state) == 0 ==> core->state == 0);
    ensures ok_iff_given: \result == ESTOP_OK <==> usable(core, out) && slot < 8;
 */
estop_err_t estop_tcp_close(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out);

/*@ requires pointers_given: given(core, out);
    requires core_given: core != \null ==> core_ok(core);
    requires consumed == \null || (\valid(consumed) && \separated(consumed, core, out));
    requires data == \null || (\valid_read(data + (0 .. len - 1)) &&
        \separated(data + (0 .. len - 1), core, out, consumed));
    assigns *core, *out, *consumed;
    ensures inv_kept: \result == ESTOP_OK ==> inv(core);
    ensures inv_always: core != \null ==> core_ok(core);
    ensures next_call_ahead: \result == ESTOP_OK ==>
        1 <= udiff(out->next_call_us, now_us) <= core->cfg.brake_period_us;
    ensures consumed_bound: \result == ESTOP_OK ==> *consumed <= len;
    ensures consumed_refused:
        (\result == ESTOP_ERR_NOT_INIT || \result == ESTOP_ERR_SLOT_CLOSED) ==> *consumed == 0;
    ensures closed_refused: \result == ESTOP_ERR_SLOT_CLOSED ==>
        slot < 8 && \old(core->slots[slot].open) == 0;
    ensures ok_iff_given: \result == ESTOP_OK ==> usable(core, out) && slot < 8 &&
        consumed != \null && (data != \null || len == 0);
    ensures ok_iff_given: usable(core, out) && slot < 8 && consumed != \null &&
        (data != \null || len == 0) ==> \result == ESTOP_OK || \result == ESTOP_ERR_SLOT_CLOSED;
    ensures leaves_stopped_only_by_release: core != \null && \old(core->state) == 0 &&
        core->state != 0 ==> \result == ESTOP_OK && out->has_reply == 1 &&
        slot < 8 && core->slots[slot].fill == 0 &&
        ((core->cfg.key_len == 0 && out->reply[11] == 0 &&
          rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MSG_RELEASE) ||
         (core->cfg.key_len != 0 && out->reply[15] == 0 &&
          rd_u32le_l(&core->slots[slot].buf[0]) == ESTOP_MAGIC_REQUEST &&
          rd_u32le_l(&core->slots[slot].buf[4]) == ESTOP_MSG_RELEASE));
 */
estop_err_t estop_tcp_rx(estop_core_t *core, uint32_t slot, const uint8_t *data, size_t len,
                         size_t *consumed, uint32_t now_us, estop_out_t *out);

#endif /* ESTOP_PROVE_CONTRACTS_H */
