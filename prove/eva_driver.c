/*
 * The Eva driver of `make prove` (docs/PROOF.md): every entry point of estop_core.h, called in
 * any order, any number of times, with inputs Eva treats as unknown. Eva's loop below reaches
 * a fixpoint that covers every sequence of calls, so 0 alarms means no call sequence of a host
 * that keeps the contract of estop_core.h reaches undefined behaviour.
 *
 * What the host contract fixes, and the driver therefore keeps:
 *  - estop_init() first; every call gets the core, a valid out and distinct buffers;
 *  - data points to len readable bytes (any content, any len up to the buffer's size);
 *  - consumed non-NULL for estop_tcp_rx (NULL is also tried: it must be refused).
 * Everything else is unknown: the configuration (any value estop_config_check accepts, keyed
 * or plain, any slow time and level of version 3, and any value at all for the refused
 * configurations), the clock (any tick, so steps of any size, backwards included), slots
 * (in range or not), bytes, lengths, and the order of the calls.
 */
#include <stddef.h>
#include <stdint.h>

#include "__fc_builtin.h"
#include "estop_core.h"

/* prove/run.py analyses the driver twice: a unit with a key (1) and one without (0). */
#ifndef DRIVER_KEYED
#define DRIVER_KEYED 1
#endif

/* Large enough for every frame form (60 bytes) and the bytes after it. */
#define DRIVER_BUF 96u

static uint32_t any_u32(void)
{
    return Frama_C_unsigned_int_interval(0u, 0xFFFFFFFFu);
}

static void any_bytes(uint8_t *p, size_t n)
{
    size_t i;
    for (i = 0u; i < n; i++) {
        p[i] = (uint8_t)Frama_C_interval(0, 255);
    }
}

/* Any configuration estop_init accepts: every field anywhere in its range. */
static void any_valid_config(estop_config_t *cfg)
{
    estop_config_default(cfg);
    cfg->timeout_us = Frama_C_unsigned_int_interval(ESTOP_TIMEOUT_MIN_US, ESTOP_TIMEOUT_MAX_US);
    cfg->slow_us = Frama_C_unsigned_int_interval(1u, cfg->timeout_us);
    cfg->warn_us = Frama_C_unsigned_int_interval(1u, cfg->slow_us);
    cfg->slow_level = (uint8_t)Frama_C_interval(ESTOP_SLOW_LEVEL_MIN, ESTOP_SLOW_LEVEL_MAX);
    cfg->stop_id = any_u32();
    cfg->brake_can_id = Frama_C_unsigned_int_interval(0u, ESTOP_CAN_ID_MAX);
    cfg->status_can_id = Frama_C_unsigned_int_interval(0u, ESTOP_CAN_ID_MAX);
    cfg->brake_data_id = (uint16_t)Frama_C_interval(0, 0xFFFF);
    cfg->status_data_id = (uint16_t)Frama_C_interval(0, 0xFFFF);
    cfg->release_packets = any_u32();
    cfg->brake_period_us =
        Frama_C_unsigned_int_interval(ESTOP_BRAKE_PERIOD_MIN_US, ESTOP_BRAKE_PERIOD_MAX_US);
    cfg->status_period_us =
        Frama_C_unsigned_int_interval(ESTOP_STATUS_PERIOD_MIN_US, ESTOP_STATUS_PERIOD_MAX_US);
    cfg->session = Frama_C_unsigned_long_long_interval(0u, 0xFFFFFFFFFFFFFFFFu);
    cfg->tag_checks = (uint8_t)Frama_C_interval(ESTOP_TAG_CHECKS_ALL, ESTOP_TAG_CHECKS_MAX);
    cfg->tag_window_us =
        Frama_C_unsigned_int_interval(ESTOP_TAG_WINDOW_MIN_US, ESTOP_TAG_WINDOW_MAX_US);
    cfg->key_len = (uint8_t)(DRIVER_KEYED ? ESTOP_KEY_LEN : 0u);
    any_bytes(cfg->key, ESTOP_KEY_LEN);
}

/* Any configuration at all (most are refused). */
static void any_config(estop_config_t *cfg)
{
    cfg->timeout_us = any_u32();
    cfg->slow_us = any_u32();
    cfg->warn_us = any_u32();
    cfg->stop_id = any_u32();
    cfg->brake_can_id = any_u32();
    cfg->status_can_id = any_u32();
    cfg->brake_data_id = (uint16_t)Frama_C_interval(0, 0xFFFF);
    cfg->status_data_id = (uint16_t)Frama_C_interval(0, 0xFFFF);
    cfg->release_packets = any_u32();
    cfg->brake_period_us = any_u32();
    cfg->status_period_us = any_u32();
    cfg->session = Frama_C_unsigned_long_long_interval(0u, 0xFFFFFFFFFFFFFFFFu);
    cfg->slow_level = (uint8_t)Frama_C_interval(0, 255);
    cfg->tag_checks = (uint8_t)Frama_C_interval(0, 255);
    cfg->tag_window_us = any_u32();
    cfg->key_len = (uint8_t)Frama_C_interval(0, 255);
    any_bytes(cfg->key, ESTOP_KEY_LEN);
}

/* The read-outs and pure functions, with any argument. */
static void read_outs(const estop_core_t *core)
{
    estop_status_t status;
    estop_link_stats_t stats;
    (void)estop_get_status(core, &status);
    (void)estop_get_link_stats(core, &stats);
    (void)estop_get_status(NULL, &status);
    (void)estop_get_link_stats(core, NULL);
    (void)estop_gap_bin(any_u32());
    (void)estop_err_name((estop_err_t)Frama_C_interval(-2147483647 - 1, 2147483647));
    (void)estop_state_name(any_u32());
    (void)estop_reason_name(any_u32());
}

/* The general BLAKE2s of estop_blake2s.h (the core itself uses the keyed-state form), any
 * lengths, NULL where a length is 0. */
static void any_blake2s(void)
{
    uint8_t key[ESTOP_B2S_KEY_MAX];
    uint8_t msg[2u * ESTOP_B2S_BLOCK + 1u];
    uint8_t digest[ESTOP_B2S_OUT_MAX];
    size_t keylen = Frama_C_unsigned_int_interval(0u, ESTOP_B2S_KEY_MAX + 1u);
    size_t len = Frama_C_unsigned_int_interval(0u, sizeof msg);
    any_bytes(key, sizeof key);
    any_bytes(msg, sizeof msg);
    (void)estop_blake2s(digest, Frama_C_unsigned_int_interval(0u, ESTOP_B2S_OUT_MAX + 1u),
                        (keylen == 0u) ? NULL : key, keylen, msg, len);
    (void)estop_blake2s(digest, ESTOP_B2S_OUT_MAX, key, keylen, NULL, 0u);
    (void)estop_ct_equal(key, NULL, Frama_C_unsigned_int_interval(0u, ESTOP_B2S_KEY_MAX));
}

/* Calls before a successful init (the core zeroed by a refused one) must be refused. */
static void refused_calls(void)
{
    estop_core_t core;
    estop_config_t cfg;
    estop_out_t out;
    size_t consumed;
    uint8_t buf[DRIVER_BUF];
    any_bytes(buf, DRIVER_BUF);
    any_config(&cfg);
    (void)estop_config_check(&cfg);
    (void)estop_config_check(NULL);
    (void)estop_init(NULL, &cfg, any_u32());
    (void)estop_init(&core, &cfg, any_u32());
    cfg.session = 0u; /* refused whatever the rest */
    if (estop_init(&core, &cfg, any_u32()) != ESTOP_OK) {
        (void)estop_tick(&core, any_u32(), &out);
        (void)estop_udp_rx(&core, buf, DRIVER_BUF, any_u32(), &out);
        (void)estop_tcp_open(&core, 0u, any_u32(), &out);
        (void)estop_tcp_rx(&core, 0u, buf, DRIVER_BUF, &consumed, any_u32(), &out);
        (void)estop_tcp_close(&core, 0u, any_u32(), &out);
        (void)estop_fault(&core, any_u32(), &out);
        read_outs(&core);
    }
    (void)estop_tick(NULL, any_u32(), &out);
    (void)estop_tick(&core, any_u32(), NULL);
}

int main(void)
{
    estop_core_t core;
    estop_config_t cfg;
    estop_out_t out;
    uint8_t buf[DRIVER_BUF];
    size_t consumed;

    refused_calls();
    any_blake2s();
    any_valid_config(&cfg);
    if (estop_init(&core, &cfg, any_u32()) != ESTOP_OK) {
        return 0;
    }
    (void)estop_tick(&core, any_u32(), &out);
    /* Any number of calls, any of them each time. */
    while (Frama_C_nondet(0, 1) != 0) {
        size_t len = Frama_C_unsigned_int_interval(0u, DRIVER_BUF);
        uint32_t now = any_u32();
        uint32_t slot = Frama_C_unsigned_int_interval(0u, ESTOP_MAX_SLOTS);
        any_bytes(buf, DRIVER_BUF);
        switch (Frama_C_interval(0, 7)) {
        case 0:
            (void)estop_tick(&core, now, &out);
            break;
        case 1:
            (void)estop_udp_rx(&core, buf, len, now, &out);
            break;
        case 2:
            (void)estop_udp_rx(&core, NULL, 0u, now, &out);
            break;
        case 3:
            (void)estop_tcp_open(&core, slot, now, &out);
            break;
        case 4:
            (void)estop_tcp_close(&core, slot, now, &out);
            break;
        case 5:
            (void)estop_tcp_rx(&core, slot, buf, len, &consumed, now, &out);
            break;
        case 6:
            if (Frama_C_nondet(0, 1) != 0) {
                (void)estop_tcp_rx(&core, slot, NULL, 0u, &consumed, now, &out);
            } else {
                (void)estop_tcp_rx(&core, slot, buf, len, NULL, now, &out);
            }
            break;
        default:
            (void)estop_fault(&core, now, &out);
            break;
        }
        read_outs(&core);
    }
    return 0;
}
