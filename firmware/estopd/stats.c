#include "stats.h"

#include <stdio.h>

#include "log.h"

#define LIST_MAX 400u /* 32 numbers of at most 10 digits and their commas */

/* "a,b,c" of n numbers into buf. */
static void list_u32(char *buf, size_t size, const uint32_t *v, uint32_t n)
{
    size_t len = 0u;
    uint32_t i;
    buf[0] = '\0';
    for (i = 0u; i < n && len < size; i++) {
        int w = snprintf(buf + len, size - len, i == 0u ? "%u" : ",%u", (unsigned)v[i]);
        if (w < 0) {
            break;
        }
        len += (size_t)w;
    }
}

/* link_histogram (docs/LINK.md, read by `estop link`): cumulative since start, written when
 * valid packets arrived, or the link slowed the unit down or timed out, since the last one. */
static void report_link(daemon_t *d, uint64_t now, const estop_counters_t *c)
{
    estop_link_stats_t ls;
    uint32_t edges[ESTOP_GAP_BINS];
    char counts_s[LIST_MAX];
    char edges_s[LIST_MAX];
    uint32_t b;

    if (estop_get_link_stats(&d->core, &ls) != ESTOP_OK ||
        (ls.valid == d->stats_valid_reported && ls.slowdowns == d->stats_slowdowns_reported &&
         ls.timeouts == d->stats_timeouts_reported)) {
        return;
    }
    d->stats_valid_reported = ls.valid;
    d->stats_slowdowns_reported = ls.slowdowns;
    d->stats_timeouts_reported = ls.timeouts;
    /* The lower edge of every bin, from the core's own bin rule (bin 0 starts at 0). */
    edges[0] = 0u;
    for (b = 1u; b < ESTOP_GAP_BINS; b++) {
        uint32_t e = 10u + (b - 1u) / 2u;
        edges[b] = (1u << e) + (((b - 1u) % 2u) != 0u ? (1u << (e - 1u)) : 0u);
    }
    list_u32(counts_s, sizeof counts_s, ls.gaps, ESTOP_GAP_BINS);
    list_u32(edges_s, sizeof edges_s, edges, ESTOP_GAP_BINS);
    {
        log_kv_t kv[] = {
            KV_NUM("valid", ls.valid),
            KV_NUM("invalid", c->udp_invalid),
            KV_NUM("silences", ls.silences),
            KV_NUM("slowdowns", ls.slowdowns),
            KV_NUM("timeouts", ls.timeouts),
            KV_NUM("warn_us", d->opt.cfg.warn_us),
            KV_NUM("slow_us", d->opt.cfg.slow_us),
            KV_NUM("timeout_us", d->opt.cfg.timeout_us),
            KV_LIST("edges_us", edges_s),
            KV_LIST("counts", counts_s),
        };
        log_event(now, "link_histogram", NULL, kv, sizeof kv / sizeof kv[0]);
    }
}

/* auth_failures: control packets and RELEASEs that failed authentication, by the first check
 * that failed (PROTOCOL.md 5), and the control packets dropped unchecked over the tag-check
 * budget (unchecked), cumulative since start. Written only when they changed. */
static void report_auth(daemon_t *d, uint64_t now, const estop_counters_t *c)
{
    uint64_t sum = (uint64_t)c->auth_bad_tag + c->auth_bad_session + c->auth_old_counter +
                   c->auth_table_full + c->auth_unchecked;
    if (sum != d->stats_auth_reported) {
        log_kv_t kv[] = {
            KV_NUM("tag", c->auth_bad_tag),
            KV_NUM("session", c->auth_bad_session),
            KV_NUM("counter", c->auth_old_counter),
            KV_NUM("table_full", c->auth_table_full),
            KV_NUM("unchecked", c->auth_unchecked),
        };
        d->stats_auth_reported = sum;
        log_event(now, "auth_failures", NULL, kv, 5u);
    }
}

/* udp_drops: datagrams the kernel dropped because the receive buffer was full (a flood, or a
 * loop that could not keep up), since start and since the last report. */
static void report_drops(daemon_t *d, uint64_t now)
{
    if (d->udp_drops != d->stats_drops_reported) {
        log_kv_t kv[] = {
            KV_NUM("dropped", (uint32_t)(d->udp_drops - d->stats_drops_reported)),
            KV_NUM("total", d->udp_drops),
        };
        d->stats_drops_reported = d->udp_drops;
        log_event(now, "udp_drops", NULL, kv, 2u);
    }
}

static void report(daemon_t *d, uint64_t now)
{
    estop_status_t st;
    d->stats_last_us = now;
    if (estop_get_status(&d->core, &st) == ESTOP_OK) {
        report_auth(d, now, &st.counters);
        report_link(d, now, &st.counters);
    }
    report_drops(d, now);
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
