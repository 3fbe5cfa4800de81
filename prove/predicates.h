/*
 * The ACSL predicates of the core's proofs (docs/PROOF.md): read by both Eva and WP
 * (tools/prove.py passes this file with -include), since the contracts beside the core's
 * static functions use them. Frama-C only.
 */
#ifndef ESTOP_PROVE_PREDICATES_H
#define ESTOP_PROVE_PREDICATES_H

#include "estop_core.h"
#include "logic.h"

/* Written as macros, not ACSL predicates: Qed then sees each field read on its own and drops
 * the memory updates that cannot touch it (a predicate is opaque to Qed, and the solvers
 * time out on the separation of every field behind every havoc). */
/* What the invariant keeps of a configuration that estop_config_check accepted (g: the
 * configuration itself, not a pointer to it). */
#define config_ok(g) \
    (1000 <= (g).timeout_us <= 60000000 && 1 <= (g).slow_us <= (g).timeout_us && \
     1 <= (g).warn_us <= (g).slow_us && 1 <= (g).slow_level <= 99 && \
     (g).brake_can_id != (g).status_can_id && \
     1000 <= (g).brake_period_us <= 25000 && \
     10000 <= (g).status_period_us <= 1000000)
#define cfg_ok(c) config_ok((c)->cfg)
/* Everything estop_config_check asks of a configuration (estop_core.h's limits): config_ok's
 * ranges (the timeout, the slow level, both periods) and the rest. */
#define config_valid(g) \
    (config_ok(g) && \
     (g).stop_id != 0 && (g).stop_id != ESTOP_MSG_STATUS && (g).stop_id != ESTOP_MSG_RELEASE && \
     (g).stop_id != ESTOP_MSG_LIFT && (g).stop_id != ESTOP_MAGIC_REQUEST && \
     (g).brake_can_id <= ESTOP_CAN_ID_MAX && (g).status_can_id <= ESTOP_CAN_ID_MAX && \
     (g).brake_data_id != (g).status_data_id && (g).release_packets != 0 && \
     (g).brake_period_us <= (g).status_period_us && (g).tag_checks <= ESTOP_TAG_CHECKS_MAX && \
     ESTOP_TAG_WINDOW_MIN_US <= (g).tag_window_us <= ESTOP_TAG_WINDOW_MAX_US && \
     ((g).key_len == 0 || (g).key_len == ESTOP_KEY_LEN) && (g).session != 0)
#define slots_ok(c) (\forall integer i; 0 <= i < 8 ==> (c)->slots[i].fill < 48)
/* The length of the frame in a slot's buffer, once its first 4 bytes are in (estop_tcp.c's
 * frame_len: a request frame starts with its magic), and a slot holding part of a frame: fewer
 * bytes than that length (the reassembly keeps it; slots_ok asks only for fewer than 48). */
#define slot_need(s) (rd_u32le_l(&(s)->buf[0]) == ESTOP_MAGIC_REQUEST ? 48 : 16)
#define slot_partial(s) ((s)->fill < 4 || (s)->fill < slot_need(s))
#define known_ok(c) ((c)->state <= 2 && (c)->reason <= 5 && (c)->mac.outlen <= 16)
#define fresh_ok(c) ((c)->state != 0 ==> (c)->link_fresh != 0)
#define inv_base(c) (cfg_ok(c) && known_ok(c) && slots_ok(c))
#define inv(c) (inv_base(c) && fresh_ok(c))
/* The times between calls: both periodic frames due within their period, a fresh link younger
 * than the timeout, and an ARMED unit's link younger than the slow time. estop__begin makes
 * them, every step after it keeps them, and estop__finish turns them into next_call_us. */
#define brake_due_ok(c) (1 <= udiff((c)->brake_due_us, (c)->now_us) <= (c)->cfg.brake_period_us)
#define status_due_ok(c) \
    (1 <= udiff((c)->status_due_us, (c)->now_us) <= (c)->cfg.status_period_us)
#define link_ok(c) \
    ((c)->link_fresh != 0 ==> udiff((c)->now_us, (c)->last_valid_us) < (c)->cfg.timeout_us)
#define armed_ok(c) \
    ((c)->state == 1 ==> udiff((c)->now_us, (c)->last_valid_us) < (c)->cfg.slow_us)
#define times_ok(c) (brake_due_ok(c) && status_due_ok(c) && link_ok(c) && armed_ok(c))
/* The invariant and the times kept by a step, as separate clauses named tag_inv and tag_times:
 * one proof goal each (as one conjunction the solvers timed out). */
#define ENSURES_INV(tag) INV_PARTS(ENSURES_PART, tag)
/* The invariant's parts (inv's, in its order), each given to each(tag, part): the one list
 * ENSURES_INV and ENSURES_REPLY_KEEPS write their clauses from. */
#define INV_PARTS(each, tag) \
    each(tag, cfg_ok) each(tag, known_ok) each(tag, slots_ok) each(tag, fresh_ok)
#define ENSURES_PART(tag, part) ensures tag##_inv: part(core);
#define ENSURES_PART_KEPT(tag, part) ensures tag##_inv: \at(part(core), Pre) ==> part(core);
/* estop__finish's contract past its pointers (contracts.h), which finish_frame (estop_tcp.c)
 * repeats with what a frame's release rule reads stated kept: one text for both. */
#define FINISH_CONTRACT \
    requires finish_inv: cfg_ok(core); \
    requires finish_inv: known_ok(core); \
    requires finish_inv: fresh_ok(core); \
    requires finish_times: brake_due_ok(core); \
    requires finish_times: status_due_ok(core); \
    requires finish_times: link_ok(core); \
    requires finish_times: armed_ok(core); \
    assigns out->next_call_us, out->state, out->reason, out->flags; \
    ensures out->state == core->state && out->reason == core->reason; \
    ensures next_call_ahead: \
        1 <= udiff(out->next_call_us, core->now_us) <= core->cfg.brake_period_us; \
    ensures finish_keeps: core->magic == \old(core->magic) && \
        core->now_us == \old(core->now_us) && core->state == \old(core->state) && \
        core->cfg.brake_period_us == \old(core->cfg.brake_period_us) && \
        core->cfg.brake_can_id == \old(core->cfg.brake_can_id); \
    ensures finish_keeps_inv: \at(inv(core), Pre) ==> inv(core);
/* take_frame's clauses over slot s (estop_tcp.c), which fill_slot repeats over slot k of the
 * core with what estop_tcp_rx reads stated kept: one text for both. */
#define TAKE_ENSURES(tag, s) \
    ensures *took <= len; \
    ensures \result == 0 || \result == 1; \
    ensures \result == 1 ==> (s)->fill == 0; \
    ensures (s)->fill < 48; \
    ensures tag##_kept: \forall integer i; 0 <= i < \old((s)->fill) ==> \
        (s)->buf[i] == \old((s)->buf[i]); \
    ensures tag##_bytes: \forall integer i; 0 <= i < *took ==> \
        (s)->buf[\old((s)->fill) + i] == data[i]; \
    ensures tag##_partial: \result == 0 ==> (s)->fill == \old((s)->fill) + *took; \
    ensures tag##_rest: \old(slot_partial(s)) && \result == 0 ==> *took == len && slot_partial(s);
#define ENSURES_KEPT(tag) \
    ENSURES_INV(tag) \
    ensures tag##_times: brake_due_ok(core); \
    ensures tag##_times: status_due_ok(core); \
    ensures tag##_times: link_ok(core); \
    ensures tag##_times: armed_ok(core);
/* Where a call asks a stop (asks): the frames already in out kept, none taken out. Two
 * clauses named tag, one goal each; the last two of ENSURES_STOPS and ENSURES_STEP_STOPS. */
#define ENSURES_FRAMES_KEPT(tag, asks) \
    ensures tag: (asks) ==> \old(out->n_can) <= out->n_can; \
    ensures tag: (asks) && 1 <= \old(out->n_can) ==> frame_kept(Pre, Post, out, 0);
/* A step that answers a frame asking a stop (asks, a premise over its pre- and post-state):
 * the unit STOPPED, the reply's NAK byte (out->reply[at]) the ACK, the frames already in out
 * kept. Four clauses named tag, one goal each. */
#define ENSURES_STOPS(tag, asks, at) \
    ensures tag: (asks) ==> core->state == 0; \
    ensures tag: (asks) ==> out->reply[at] == 0; \
    ENSURES_FRAMES_KEPT(tag, asks)
/* A frame's message step (plain_step, msg_step, request_step) that asks a stop (asks, a
 * premise over its pre-state): the unit STOPPED with NAK 0, the frames already in out kept.
 * Three clauses named tag, one goal each. */
#define ENSURES_STEP_STOPS(tag, asks) \
    ensures tag: (asks) ==> core->state == 0 && \result == 0; \
    ENSURES_FRAMES_KEPT(tag, asks)
/* What estop__begin's clauses read (its core, out and times), asserted after each of its three
 * calls: left to the solvers at the return, past all three calls at once, its clauses took 15
 * to 35 s each (issue 24's twenty-ninth round). */
#define begin_carried(now) \
    (core->magic == 0x45535450 && core->now_us == (now) && out->has_reply == 0 && \
     out->close_slot == 0 && core->last_valid_us == \at(core->last_valid_us, Pre) && \
     core->cfg.timeout_us == \at(core->cfg.timeout_us, Pre) && \
     core->cfg.slow_us == \at(core->cfg.slow_us, Pre) && \
     core->cfg.stop_id == \at(core->cfg.stop_id, Pre) && out->clock_state == core->state && \
     out->clock_reason == core->reason && out->changed_by_clock == out->state_changed && \
     (\at(core->state, Pre) != 0 && core->state == 0 ==> \
      1 <= out->n_can && emergency(out, 0, core)) && \
     link_ok(core) && armed_ok(core))
/* A step that stops a moving unit (with room in out) appends one frame: the emergency one. */
#define stops_moving_unit (\old(core->state) != 0 && core->state == 0)
#define ENSURES_STOP_BRAKES(tag) \
    ensures tag: stops_moving_unit && \old(out->n_can) <= 2 ==> \
        out->n_can == \old(out->n_can) + 1 && emergency(out, \old(out->n_can), core);
/* The same rule one index at a time (out's count at the call 0, 1 or 2): a caller that writes
 * out's reply after the step reads the frame at a constant index through those writes, which
 * WP's simplifier does, where at the count (a value) it left the read to the solvers, which did
 * not find it in 90 s (issue 24's twenty-seventh round). */
#define ENSURES_STOP_BRAKES_AT(tag) \
    ensures tag: stops_moving_unit && \old(out->n_can) <= 2 ==> \
        out->n_can == \old(out->n_can) + 1; \
    STOP_BRAKE_AT(tag, 0) STOP_BRAKE_AT(tag, 1) STOP_BRAKE_AT(tag, 2)
#define STOP_BRAKE_AT(tag, n) \
    ensures tag: stops_moving_unit && \old(out->n_can) == n ==> emergency(out, n, core);
/* The frames of out a step leaves as they were: the first n keep their ID, brake_request and
 * state byte (what the stop rules read). */
#define frame_kept(L1, L2, o, k) \
    (\at((o)->can[k].id, L1) == \at((o)->can[k].id, L2) && \
     \at((o)->can[k].data[0], L1) == \at((o)->can[k].data[0], L2) && \
     \at((o)->can[k].data[2], L1) == \at((o)->can[k].data[2], L2))
#define frames_kept(L1, L2, o, n) (\forall integer k; 0 <= k < (n) ==> frame_kept(L1, L2, o, k))
/* A reply's step (core read only, out's reply written): what its caller's clauses read past
 * it, stated by the callee, since under Typed the solvers did not carry them past the call in
 * a handler's own context. handle_plain's proof relies on it (issue 24's twenty-eighth round);
 * the configuration its callers read, each reply states with ENSURES_CFG_KEPT below. */
#define ENSURES_REPLY_KEEPS(tag) \
    INV_PARTS(ENSURES_PART_KEPT, tag) \
    ensures tag##_times: \at(times_ok(core), Pre) ==> times_ok(core); \
    ensures tag##_core: core->state == \old(core->state); \
    ensures tag##_out: out->n_can == \old(out->n_can) && frames_kept(Pre, Post, out, 3);
/* Frame k of out is ESTOP_BRAKE with brake_request 1 (emergency) and the state STOPPED. */
#define emergency(o, k, c) \
    ((o)->can[k].id == (c)->cfg.brake_can_id && (o)->can[k].data[0] == 1 && \
     (o)->can[k].data[2] == 0)
/* The emergency frame of a call that stopped a moving unit: out's first frame (the clock's
 * stop) or its last (the input's stop, appended after the frames already due). */
#define emergency_sent(o, c) \
    (1 <= (o)->n_can && (emergency(o, 0, c) || emergency(o, (o)->n_can - 1, c)))
/* A whole TCP frame in a slot's buffer b (estop_tcp.c) that asks the unit to stop: a request
 * frame (its magic first) with the ID at byte 4, or a plain frame with the ID at byte 0. The
 * request's ID is not RELEASE: estop_init refuses that stop ID (ESTOP_ERR_STOP_ID), and the
 * invariant does not carry the configuration's check, so the proofs rule it out here (that
 * path would authenticate the frame before stopping, which the solvers then chase). */
#define request_asks_stop(b, stop_id) \
    (rd_u32le_l(&(b)[0]) == ESTOP_MAGIC_REQUEST && rd_u32le_l(&(b)[4]) != ESTOP_MSG_RELEASE && \
     stop_asked(rd_u32le_l(&(b)[4]), stop_id))
#define plain_asks_stop(b, stop_id) \
    (rd_u32le_l(&(b)[0]) != ESTOP_MAGIC_REQUEST && stop_asked(rd_u32le_l(&(b)[0]), stop_id))
/* A datagram of len bytes at d that asks the unit to stop (PROTOCOL.md section 1): a request
 * frame, 48 bytes with its magic first, with the stop ID or LIFT at byte 4. Its tag, session
 * and counter are never looked at: anyone may stop. */
#define datagram_asks_stop(d, len, stop_id) \
    ((len) == 48 && rd_u32le_l(&(d)[0]) == ESTOP_MAGIC_REQUEST && \
     stop_asked(rd_u32le_l(&(d)[4]), stop_id))
/* Authentication (PROTOCOL.md 5): the remote id, session and counter of a message whose ids
 * start at m[a] (5.1, 5.2 lay them out alike: id, session, counter). */
#define ids_remote(m, a) rd_u32le_l(&(m)[a])
#define ids_session(m, a) rd_u64le_l(&(m)[(a) + 4])
#define ids_counter(m, a) rd_u64le_l(&(m)[(a) + 12])
/* Place j of the table holds remote id rid, and is its first such place (find_remote's). */
#define place_of(c, rid, j) ((c)->remotes[j].used != 0 && (c)->remotes[j].id == (rid))
#define first_place(c, rid, j) \
    (place_of(c, rid, j) && \forall integer i_; 0 <= i_ < (j) ==> !place_of(c, rid, i_))
/* A counter above the one kept for remote id rid on channel ch (0 UDP, 1 TCP), where one is
 * kept: a remote with no place, or none seen on the channel, has none. */
#define counter_above(c, rid, ctr, ch) \
    (\forall integer j_; 0 <= j_ < 8 && first_place(c, rid, j_) && \
        ((c)->remotes[j_].seen & (uint8_t)(1u << (ch))) != 0 ==> (ctr) > (c)->remotes[j_].counter[ch])
/* A request frame at b (5.2: ids from byte 12) of this unit's session, with a counter above
 * the one kept for its remote on TCP: what a keyed RELEASE needs besides its tag. */
#define request_fresh(c, b) ids_fresh(c, &(b)[0], 12, 1)
/* A keyed unit's 60-byte control packet at d, authentic under the key state of c (its tag at
 * byte 44 the MAC of its first 44 bytes), of c's session, with a counter above its remote's
 * kept UDP counter (valid_body's body_keyed, estop_udp_rx's handled_keyed). */
#define datagram_keyed(c, d) \
    ((c)->mac.outlen == 16 && tag_ok(&(c)->mac, d, 44) && ids_fresh(c, d, 4, 0))
/* A message ID that asks the unit to stop: its stop ID (stop_id) or LIFT. */
#define stop_asked(id, stop_id) ((id) == (stop_id) || (id) == ESTOP_MSG_LIFT)
#define core_ok(c) ((c)->magic == 0x45535450 ==> inv(c))
#define host(c, o) (\valid(c) && \valid(o) && \separated(c, o) && core_ok(c))
/* The pointers of an entry point's call: core and out each valid or NULL (the API refuses NULL
 * with ESTOP_ERR_NULL_ARG), and apart when both are given. Each pointer on its own: a NULL out
 * says nothing of core, and the reverse. */
#define given(c, o) \
    (((c) == \null || \valid(c)) && ((o) == \null || \valid(o)) && \
     ((c) == \null || (o) == \null || \separated(c, o)))
/* An entry point's call that the unit answers (ESTOP_OK): both pointers given, the core
 * initialised. Every stop rule is stated for an ESTOP_OK return (ok_iff_given), so a call that
 * returned anything else for such a call would escape them. */
#define usable(c, o) ((c) != \null && (o) != \null && (c)->magic == 0x45535450)
#define byte_kept(L1, L2, c, j, i) \
    (\at((c)->slots[j].buf[i], L1) == \at((c)->slots[j].buf[i], L2))
#define head_kept(L1, L2, c, j) \
    (byte_kept(L1, L2, c, j, 0) && byte_kept(L1, L2, c, j, 1) && byte_kept(L1, L2, c, j, 2) && \
     byte_kept(L1, L2, c, j, 3) && byte_kept(L1, L2, c, j, 4) && byte_kept(L1, L2, c, j, 5) && \
     byte_kept(L1, L2, c, j, 6) && byte_kept(L1, L2, c, j, 7))
/* A slot's index, as a predicate: opaque to WP's simplifier Qed. A callee's clause over
 * every slot that writes a range of the core (the remote table) keeps this bound, so Qed does
 * not prove it away in its caller's goals and then fail to read through that range on the
 * goal's side (request_step's fills, issue 24's thirty-sixth round). */
/*@ predicate a_slot(integer j) = 0 <= j < 8; */
/* What a step on the way of a TCP frame keeps of the core for the frame's rules past it: the
 * configuration they read and every slot's fill, each as a clause of its own (left to the
 * solvers through the callees' assigns under Typed, the frame handlers' clauses ran out:
 * issue 24's thirty-first round). */
#define ENSURES_CFG_KEPT(tag) \
    ENSURES_CFG_FIELDS_KEPT(tag) \
    ensures tag##_fills: \forall integer j; 0 <= j < 8 ==> \
        core->slots[j].fill == \old(core->slots[j].fill);
#define ENSURES_CFG_FIELDS_KEPT(tag) \
    ensures tag##_cfg: core->magic == \old(core->magic); \
    ensures tag##_cfg: core->now_us == \old(core->now_us); \
    ensures tag##_cfg: core->cfg.stop_id == \old(core->cfg.stop_id); \
    ensures tag##_cfg: core->cfg.key_len == \old(core->cfg.key_len); \
    ensures tag##_cfg: core->cfg.brake_can_id == \old(core->cfg.brake_can_id); \
    ensures tag##_cfg: core->cfg.brake_period_us == \old(core->cfg.brake_period_us);
/* And the first 8 bytes of every slot (a frame's magic and message ID), in one of three forms
 * by where the clause stands, since the solvers instantiate a quantifier over two variables
 * only toward a goal with both free (-wp-print: a clause over j and i did not give slot k's
 * byte 0 in 20 s, the form over j alone in 2 s):
 * - ENSURES_SLOTS_KEPT, over slot and byte: the core's steps, which write fields;
 * - ENSURES_HEADS_KEPT, over the slot, each byte named: a step that calls them and whose
 *   caller reads one slot (plain_step, from the former in 10 s), and reply_plain;
 * - ENSURES_SLOT_KEPT, slot k alone: a frame handler. */
#define ENSURES_SLOTS_KEPT(tag) \
    ENSURES_CFG_KEPT(tag) \
    ensures tag##_heads: \forall integer j, i; 0 <= j < 8 && 0 <= i < 8 ==> \
        byte_kept(Pre, Post, core, j, i);
#define ENSURES_HEADS_KEPT(tag) \
    ENSURES_CFG_KEPT(tag) \
    ensures tag##_heads: \forall integer j; 0 <= j < 8 ==> head_kept(Pre, Post, core, j);
#define ENSURES_SLOT_KEPT(tag) \
    ENSURES_CFG_KEPT(tag) \
    ensures tag##_head: head_kept(Pre, Post, core, k);
/* A frame handler's slot k: its word at byte at (the magic at 0, a request's message ID at 4),
 * as the frame's rules read it, kept (from the bytes, for its caller). */
#define ENSURES_WORD_KEPT(tag, at) \
    ensures tag##_words: rd_u32le_l(&core->slots[k].buf[at]) == \
        \old(rd_u32le_l(&core->slots[k].buf[at]));

/*@
  // C99 6.3.1.3p2: a value converted to an unsigned type is reduced modulo 2^32. Why3's
  // to_uint32 (WP's model of the conversion) only says that its result is in range and that
  // an in-range value is kept; the solvers then cannot follow the core's wrapping time
  // arithmetic at all. These two axioms give the standard's rule for the range the core's
  // sums and differences of two 32-bit values take (docs/PROOF.md: assumptions).
  axiomatic U32Wrap {
    axiom u32_wrap_up: \forall integer x; 4294967296 <= x < 8589934592 ==>
        (uint32_t)x == x - 4294967296;
    axiom u32_wrap_down: \forall integer x; -4294967296 <= x < 0 ==>
        (uint32_t)x == x + 4294967296;
  }

  // How far time a lies ahead of time b on the 32-bit microsecond clock: (a - b) mod 2^32, as
  // the core computes it.
  logic integer udiff(integer a, integer b) = (uint32_t)(a - b);

  // ESTOP_BRAKE byte 0 (brake_request) and byte 1 (brake_level) match byte 2 (the state):
  // 0/0 ARMED, 2/L SLOWING, 1/100 STOPPED.
  predicate brake_ok(estop_out_t *o, integer k, integer level) =
      (o->can[k].data[2] == 1 && o->can[k].data[0] == 0 && o->can[k].data[1] == 0) ||
      (o->can[k].data[2] == 2 && o->can[k].data[0] == 2 && o->can[k].data[1] == level) ||
      (o->can[k].data[2] == 0 && o->can[k].data[0] == 1 && o->can[k].data[1] == 100);

*/

#endif /* ESTOP_PROVE_PREDICATES_H */
