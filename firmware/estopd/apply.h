/* Applies what the unit asks for (unit.h) that is not the input's own business: frames go to
 * the CAN output (or the can-log without CAN), a state change is logged with its cause and told
 * to systemd, a failed core call is logged. Replies and closes are the stop port's (tcp.c). */
#ifndef ESTOPD_APPLY_H
#define ESTOPD_APPLY_H

#include <netinet/in.h>

#include "can.h"
#include "canlog.h"
#include "notify.h"
#include "unit.h"

typedef struct {
    can_t *can;          /* NULL without --can: frames go to the can-log */
    canlog_t *canlog;
    const notify_t *notify;
} apply_t;

/* src: the peer whose input made the call (NULL for the clock or the host). */
void apply_fx(const apply_t *a, const unit_fx_t *fx, const struct sockaddr_in *src);
/* Brings the unit up to host time t (unit_catch_up, each step applied). */
void apply_catch_up(const apply_t *a, unit_t *u, uint64_t t);
/* A fault the host found: logged (`fault cause=..`), reported to the core, applied. */
void apply_fault(const apply_t *a, unit_t *u, uint64_t t, const char *cause);

#endif
