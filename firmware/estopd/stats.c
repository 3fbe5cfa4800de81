#include "stats.h"

#include "log.h"

/* auth_failures: control packets and RELEASEs that failed authentication, by the first check
 * that failed (PROTOCOL.md 5), cumulative since start. Written only when they changed. */
static void report_auth(daemon_t *d, uint64_t now, const estop_counters_t *c)
{
    uint64_t sum = (uint64_t)c->auth_bad_tag + c->auth_bad_session + c->auth_old_counter +
                   c->auth_table_full;
    if (sum != d->stats_auth_reported) {
        log_kv_t kv[] = {
            KV_NUM("tag", c->auth_bad_tag),
            KV_NUM("session", c->auth_bad_session),
            KV_NUM("counter", c->auth_old_counter),
            KV_NUM("table_full", c->auth_table_full),
        };
        d->stats_auth_reported = sum;
        log_event(now, "auth_failures", NULL, kv, 4u);
    }
}

static void report(daemon_t *d, uint64_t now)
{
    estop_status_t st;
    d->stats_last_us = now;
    if (estop_get_status(&d->core, &st) == ESTOP_OK) {
        report_auth(d, now, &st.counters);
    }
}

void stats_tick(daemon_t *d, uint64_t now_us)
{
    if (now_us - d->stats_last_us >= STATS_EVERY_US) {
        report(d, now_us);
    }
}

void stats_final(daemon_t *d, uint64_t now_us)
{
    report(d, now_us);
}
