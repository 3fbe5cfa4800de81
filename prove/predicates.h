/*
 * The ACSL predicates of the core's proofs (docs/PROOF.md): read by both Eva and WP
 * (tools/prove.py passes this file with -include), since the contracts beside the core's
 * static functions use them. Frama-C only.
 */
#ifndef ESTOP_PROVE_PREDICATES_H
#define ESTOP_PROVE_PREDICATES_H

#include "estop_core.h"

/*@
  // The configuration estop_config_check accepts (the parts the proofs use).
  predicate cfg_ok(estop_core_t *c) =
      1000 <= c->cfg.timeout_us <= 60000000 && 1 <= c->cfg.slow_us <= c->cfg.timeout_us &&
      1 <= c->cfg.warn_us <= c->cfg.slow_us && 1 <= c->cfg.slow_level <= 99 &&
      c->cfg.brake_can_id != c->cfg.status_can_id &&
      1000 <= c->cfg.brake_period_us <= 25000 &&
      10000 <= c->cfg.status_period_us <= 1000000;

  // What holds between any two calls of an initialised core: a known state and reason, every
  // TCP slot's fill inside its buffer, and ARMED or SLOWING only with a fresh link.
  // Written out slot by slot: ground terms, which the solvers carry across memory updates far
  // more easily than a quantifier.
  predicate slots_ok(estop_core_t *c) =
      c->slots[0].fill < 48 && c->slots[1].fill < 48 && c->slots[2].fill < 48 &&
      c->slots[3].fill < 48 && c->slots[4].fill < 48 && c->slots[5].fill < 48 &&
      c->slots[6].fill < 48 && c->slots[7].fill < 48;
  predicate fills_kept{L1, L2}(estop_core_t *c) =
      \at(c->slots[0].fill, L1) == \at(c->slots[0].fill, L2) &&
      \at(c->slots[1].fill, L1) == \at(c->slots[1].fill, L2) &&
      \at(c->slots[2].fill, L1) == \at(c->slots[2].fill, L2) &&
      \at(c->slots[3].fill, L1) == \at(c->slots[3].fill, L2) &&
      \at(c->slots[4].fill, L1) == \at(c->slots[4].fill, L2) &&
      \at(c->slots[5].fill, L1) == \at(c->slots[5].fill, L2) &&
      \at(c->slots[6].fill, L1) == \at(c->slots[6].fill, L2) &&
      \at(c->slots[7].fill, L1) == \at(c->slots[7].fill, L2);

  predicate inv_base(estop_core_t *c) =
      cfg_ok(c) && c->state <= 2 && c->reason <= 5 &&
      slots_ok(c) && c->mac.outlen <= 16;
  predicate inv(estop_core_t *c) = inv_base(c) && (c->state != 0 ==> c->link_fresh != 0);

  predicate core_ok(estop_core_t *c) = c->magic == 0x45535450 ==> inv(c);

  // ESTOP_BRAKE byte 0 (brake_request) and byte 1 (brake_level) match byte 2 (the state):
  // 0/0 ARMED, 2/L SLOWING, 1/100 STOPPED.
  predicate brake_ok(estop_out_t *o, integer k, integer level) =
      (o->can[k].data[2] == 1 && o->can[k].data[0] == 0 && o->can[k].data[1] == 0) ||
      (o->can[k].data[2] == 2 && o->can[k].data[0] == 2 && o->can[k].data[1] == level) ||
      (o->can[k].data[2] == 0 && o->can[k].data[0] == 1 && o->can[k].data[1] == 100);

  predicate host(estop_core_t *c, estop_out_t *o) =
      \valid(c) && \valid(o) && \separated(c, o) && core_ok(c);
*/

#endif /* ESTOP_PROVE_PREDICATES_H */
