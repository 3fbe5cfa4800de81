/* Checks of firmware/estopd/unit.c (run by tests/test_estopd_unit.py): the unit's clock, which
 * every core call moves, and the silence deadline read from the core. Prints one line per
 * failed check; exit status 0 when all pass. */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "opts.h"
#include "unit.h"

static int failures;

static void expect(const char *what, uint64_t got, uint64_t want)
{
    if (got != want) {
        (void)printf("FAIL %s: got %llu, want %llu\n", what, (unsigned long long)got,
                     (unsigned long long)want);
        failures++;
    }
}

static uint32_t faults(const unit_t *u)
{
    estop_status_t st;
    return estop_get_status(&u->core, &st) == ESTOP_OK ? st.counters.faults : UINT32_MAX;
}

/* A failed core call may have moved the core's clock: the next call must not be a tick
 * backwards (a fault that stops the unit). Before, last_call_us stayed where it was. */
static void error_moves_the_clock(const estop_config_t *cfg)
{
    static unit_t u;
    unit_fx_t fx;
    size_t used = 0u;
    const uint8_t frame[16] = { 0 };
    const uint8_t junk[7] = { 1, 1, 1, 1, 1, 1, 1 };

    memset(&u, 0, sizeof u);
    expect("boot", (uint64_t)unit_boot(&u, cfg, 1000000u, &fx), 0u);
    /* bytes for a slot that is not open: the core's clock moves, then the call fails */
    unit_tcp_rx(&u, 3u, frame, sizeof frame, &used, 2000000u, &fx);
    expect("the call failed", (uint64_t)(int64_t)fx.err, (uint64_t)(int64_t)ESTOP_ERR_SLOT_CLOSED);
    expect("last_call_us after a failed call", u.last_call_us, 2000000u);
    expect("a datagram received before it goes in at its time",
           unit_feed_time(&u, 1500000u), 2000000u);
    unit_udp(&u, junk, sizeof junk, unit_feed_time(&u, 1500000u), &fx);
    expect("no backwards tick", faults(&u), 0u);
    expect("not fatal", u.fatal, 0u);
}

/* The silence deadline: none while STOPPED. */
static void silence_due_while_stopped(const estop_config_t *cfg)
{
    static unit_t u;
    unit_fx_t fx;

    memset(&u, 0, sizeof u);
    expect("boot", (uint64_t)unit_boot(&u, cfg, 5000000u, &fx), 0u);
    expect("no silence deadline while STOPPED", unit_silence_due(&u), UINT64_MAX);
}

int main(void)
{
    static opts_t o;
    char err[256];
    char arg0[] = "estopd";
    char arg1[] = "--no-auth";
    char *argv[] = { arg0, arg1, NULL };

    if (opts_parse(2, argv, &o, err, sizeof err) != OPTS_RUN) {
        (void)printf("FAIL options: %s\n", err);
        return 1;
    }
    o.cfg.session = 0x1234u;
    error_moves_the_clock(&o.cfg);
    silence_due_while_stopped(&o.cfg);
    if (failures != 0) {
        return 1;
    }
    (void)printf("all unit checks passed\n");
    return 0;
}
