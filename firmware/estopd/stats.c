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
static void report_link(stats_t *s, const stats_src_t *src, uint64_t now,
                        const estop_counters_t *c)
{
    estop_link_stats_t ls;
    uint32_t edges[ESTOP_GAP_BINS];
    char counts_s[LIST_MAX];
    char edges_s[LIST_MAX];
    uint32_t b;

    if (estop_get_link_stats(src->core, &ls) != ESTOP_OK ||
        (ls.valid == s->valid_reported && ls.slowdowns == s->slowdowns_reported &&
         ls.timeouts == s->timeouts_reported)) {
        return;
    }
    s->valid_reported = ls.valid;
    s->slowdowns_reported = ls.slowdowns;
    s->timeouts_reported = ls.timeouts;
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
            KV_NUM("warn_us", src->cfg->warn_us),
            KV_NUM("slow_us", src->cfg->slow_us),
            KV_NUM("timeout_us", src->cfg->timeout_us),
            KV_LIST("edges_us", edges_s),
            KV_LIST("counts", counts_s),
        };
        log_event(now, "link_histogram", NULL, kv, sizeof kv / sizeof kv[0]);
    }
}

/* auth_failures: control packets and RELEASEs that failed authentication, by the first check
 * that failed (PROTOCOL.md 5), and the control packets dropped unchecked over the tag-check
 * budget (unchecked), cumulative since start. Written only when they changed. */
static void report_auth(stats_t *s, uint64_t now, const estop_counters_t *c)
{
    uint64_t sum = (uint64_t)c->auth_bad_tag + c->auth_bad_session + c->auth_old_counter +
                   c->auth_table_full + c->auth_unchecked;
    if (sum != s->auth_reported) {
        log_kv_t kv[] = {
            KV_NUM("tag", c->auth_bad_tag),
            KV_NUM("session", c->auth_bad_session),
            KV_NUM("counter", c->auth_old_counter),
            KV_NUM("table_full", c->auth_table_full),
            KV_NUM("unchecked", c->auth_unchecked),
        };
        s->auth_reported = sum;
        log_event(now, "auth_failures", NULL, kv, 5u);
    }
}

/* udp_drops: datagrams the kernel dropped because the receive buffer was full (a flood, or a
 * loop that could not keep up), since start and since the last report. */
static void report_drops(stats_t *s, uint32_t drops, uint64_t now)
{
    if (drops != s->drops_reported) {
        log_kv_t kv[] = {
            KV_NUM("dropped", (uint32_t)(drops - s->drops_reported)),
            KV_NUM("total", drops),
        };
        s->drops_reported = drops;
        log_event(now, "udp_drops", NULL, kv, 2u);
    }
}

/* udp_reads: the most datagrams the loop read in one round so far, beside the budget that
 * bounds it (a backlog is read a budget per round, so TCP stops never wait behind more), and
 * how many drains a silence deadline cut short (it waits for one batch, not the budget).
 * Written when either grew. */
static void report_reads(stats_t *s, const stats_src_t *src, uint64_t now)
{
    uint32_t max_round = *src->udp_max_round;
    uint32_t cuts = *src->udp_deadline_cuts;
    if (max_round != s->max_round_reported || cuts != s->cuts_reported) {
        log_kv_t kv[] = {
            KV_NUM("max_round", max_round),
            KV_NUM("budget", src->udp_budget),
            KV_NUM("deadline_cuts", cuts),
        };
        s->max_round_reported = max_round;
        s->cuts_reported = cuts;
        log_event(now, "udp_reads", NULL, kv, 3u);
    }
}

static void report(stats_t *s, const stats_src_t *src, uint64_t now)
{
    estop_status_t st;
    s->last_us = now;
    if (estop_get_status(src->core, &st) == ESTOP_OK) {
        report_auth(s, now, &st.counters);
        report_link(s, src, now, &st.counters);
    }
    report_drops(s, *src->udp_drops, now);
    report_reads(s, src, now);
}

void stats_tick(stats_t *s, const stats_src_t *src, uint64_t now_us)
{
    if (now_us - s->last_us >= STATS_EVERY_US) {
        report(s, src, now_us);
    }
}

void stats_final(stats_t *s, const stats_src_t *src, uint64_t now_us)
{
    report(s, src, now_us);
}
