#include "apply.h"

#include <stdio.h>

#include "log.h"
#include "net.h"

static void log_change(const apply_t *a, uint64_t now, uint8_t from_state, uint8_t to_state,
                       uint8_t reason, const char *addr, const char *cause)
{
    char head[32];
    const char *from = log_state_name(from_state);
    const char *to = log_state_name(to_state);

    (void)snprintf(head, sizeof head, "%s->%s", from, to);
    {
        log_kv_t kv[] = {
            KV_JSTR("from", from),
            KV_JSTR("to", to),
            KV_STR("reason", log_reason_name(reason)),
            KV_STR("src", addr),
            KV_STR("cause", cause),
        };
        log_event(now, "state", head, kv, sizeof kv / sizeof kv[0]);
    }
    notify_state(a->notify, to, to_state == ESTOP_STATE_STOPPED ? log_reason_name(reason) : NULL);
}

static void log_state(const apply_t *a, const unit_fx_t *fx, const struct sockaddr_in *src)
{
    char addr[NET_ADDR_LEN];

    if (fx->clock_first) { /* the clock's change came first in the same call: nobody's input */
        log_change(a, fx->now, fx->clock_from, fx->clock_to, fx->clock_reason, "-",
                   fx->clock_cause);
    }
    /* A change the clock made (timeout) is nobody's input, whatever call carried it. */
    if (src == NULL || fx->by_clock) {
        (void)snprintf(addr, sizeof addr, "-");
    } else {
        net_fmt_addr(src, addr, sizeof addr);
    }
    log_change(a, fx->now, fx->from, fx->to, fx->reason, addr, fx->cause);
}

void apply_fx(const apply_t *a, const unit_fx_t *fx, const struct sockaddr_in *src)
{
    uint32_t i;
    for (i = 0u; i < fx->n_frames; i++) {
        if (a->can != NULL) {
            can_send(a->can, &fx->frames[i], fx->now); /* logged once the kernel takes it */
        } else {
            canlog_frame(a->canlog, &fx->frames[i]);
        }
    }
    if (fx->changed) {
        log_state(a, fx, src);
    }
    if (fx->err != ESTOP_OK) {
        log_kv_t kv[] = { KV_STR("call", fx->call), KV_STR("err", estop_err_name(fx->err)) };
        log_event(fx->now, "core_error", NULL, kv, 2u);
    }
}

void apply_catch_up(const apply_t *a, unit_t *u, uint64_t t)
{
    unit_fx_t fx;
    while (unit_catch_up(u, t, &fx)) {
        apply_fx(a, &fx, NULL);
    }
}

void apply_fault(const apply_t *a, unit_t *u, uint64_t t, const char *cause)
{
    unit_fx_t fx;
    log_kv_t kv[] = { KV_STR("cause", cause) };
    log_event(t, "fault", NULL, kv, 1u);
    unit_fault(u, t, &fx);
    apply_fx(a, &fx, NULL);
}
