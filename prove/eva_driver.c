/*
 * The Eva driver of `make prove` (docs/PROOF.md): every entry point of estop_core.h, called in
 * any order, any number of times, with inputs Eva treats as unknown. Eva's loop below reaches
 * a fixpoint that covers every sequence of calls, so 0 alarms means no call sequence of a host
 * that keeps the contract of estop_core.h reaches undefined behaviour.
 *
 * What the host contract fixes, and the driver therefore keeps:
 *  - estop_init() first; every call gets the core, a valid out and distinct buffers;
 *  - data points to len readable bytes: after the loop, from every state it reached, one
 *    datagram or one TCP chunk in an array of exactly len bytes (any content, every len from 0
 *    to DRIVER_MAX, a TCP chunk's to DRIVER_TCP_MAX, each length its own state), so a read past
 *    len is an alarm (exact_call); NULL with a non-zero length is tried too and must be
 *    refused. The loop's own datagrams and chunks, any length in one array a byte longer than
 *    the longest, only reach the states: a call that reads no byte past len computes the same
 *    from the same bytes in either array, and the exact calls show that none does, from every
 *    state the loop reaches (issue 24's thirty-third round: the keyed run took 68 s instead of
 *    155 s with every length its own state in the loop, the same statements reached);
 *  - consumed non-NULL for estop_tcp_rx (NULL is also tried: it must be refused).
 * Everything else is unknown: the configuration (any value estop_config_check accepts, keyed
 * or plain, any slow time and level of version 3, and any value at all for the refused
 * configurations), the clock (any tick, so steps of any size, backwards included), slots
 * (in range or not), bytes, lengths, and the order of the calls.
 *
 * The rules (assertions rule_*, which tools/proof/eva.py requires Eva to show valid in both
 * runs): from STOPPED, estop_tick, estop_udp_rx (any bytes, or NULL), estop_tcp_open and
 * estop_tcp_close leave the unit STOPPED; estop_fault that returns ESTOP_OK leaves it
 * STOPPED from any state; so does a stop datagram (LIFT, or the unit's stop ID where it is
 * the default one) that returns ESTOP_OK. Eva shows them for every state the loop reaches,
 * whatever came before; WP proves the first ones per function (never_leaves_stopped) under
 * its memory model, and the stops of a TCP frame and of the clock (msg_stops, clock_stops).
 */
#include <stddef.h>
#include <stdint.h>

#include "__fc_builtin.h"
#include "estop_core.h"

/* prove/run.py analyses the driver twice: a unit with a key (1) and one without (0). */
#ifndef DRIVER_KEYED
#define DRIVER_KEYED 1
#endif

/* The calls of the loop below that this run makes, one bit per case: all of them, except in a
 * self-test copy whose planted fault a few calls reach (prove/planted.txt, calls:). A fault
 * Eva finds with fewer calls is there with all of them: fewer calls reach fewer states. */
#ifndef DRIVER_CASES
#define DRIVER_CASES 0x1FFu
#endif

/* The longest datagram tried: every frame form (60 bytes at most) and bytes after it. */
#define DRIVER_MAX 64u
/* The longest TCP chunk tried: a frame (48 bytes at most) and a byte after it. estop_tcp_rx
 * takes at most one frame a call, and a byte past the frame only when it drops a broken
 * stream (it reads none), so a longer chunk reaches no other code (take_frame on every length
 * to 96: tests/c/take_frame_contract.c). The lengths past 49 were 40 % of Eva's time. */
#define DRIVER_TCP_MAX 49u
/* 1: a TCP chunk is one whole frame (16 or 48 bytes) in an array of exactly its length, and
 * no other length is tried: the run of a unit without a key (take_frame, the only code a
 * chunk's length reaches, reads no key: the keyed run tries every length; tools/proof/eva.py
 * RUNS), and a self-test copy whose planted fault needs no partial frame (prove/planted.txt,
 * chunks: whole). The lengths are most of Eva's time. */
#ifndef DRIVER_TCP_WHOLE
#define DRIVER_TCP_WHOLE 0
#endif
/* The buffer of the calls that must be refused before any byte is read. */
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

/* A stop datagram (PROTOCOL.md section 1): a request frame with this ID, every other byte
 * (session, counter, tag, ...) anything: anyone may stop. */
static void stop_datagram(estop_core_t *core, uint32_t id, uint32_t now, estop_out_t *out)
{
    uint8_t d[ESTOP_REQ_FRAME_LEN];
    uint32_t i;
    any_bytes(d, sizeof d);
    for (i = 0u; i < 4u; i++) {
        d[i] = (uint8_t)(ESTOP_MAGIC_REQUEST >> (8u * i));
        d[4u + i] = (uint8_t)(id >> (8u * i));
    }
    if (estop_udp_rx(core, d, sizeof d, now, out) == ESTOP_OK) {
        /*@ assert rule_stop_datagram_stops: core->state == ESTOP_STATE_STOPPED; */
    }
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

/* Every length 1 .. DRIVER_TCP_MAX (EXACT_CASES_TCP) or DRIVER_MAX (EXACT_CASES) as a case of
 * a switch, each with its own array of exactly that many bytes: Eva gives every local array a
 * base of its own size, so a read past len is an alarm (a variable-length array would share
 * one base of any size among the lengths). */
#define EXACT_CASES_TCP(CALL) \
    EXACT(1, CALL) EXACT(2, CALL) EXACT(3, CALL) EXACT(4, CALL) EXACT(5, CALL) EXACT(6, CALL) \
    EXACT(7, CALL) EXACT(8, CALL) EXACT(9, CALL) EXACT(10, CALL) EXACT(11, CALL) \
    EXACT(12, CALL) EXACT(13, CALL) EXACT(14, CALL) EXACT(15, CALL) EXACT(16, CALL) \
    EXACT(17, CALL) EXACT(18, CALL) EXACT(19, CALL) EXACT(20, CALL) EXACT(21, CALL) \
    EXACT(22, CALL) EXACT(23, CALL) EXACT(24, CALL) EXACT(25, CALL) EXACT(26, CALL) \
    EXACT(27, CALL) EXACT(28, CALL) EXACT(29, CALL) EXACT(30, CALL) EXACT(31, CALL) \
    EXACT(32, CALL) EXACT(33, CALL) EXACT(34, CALL) EXACT(35, CALL) EXACT(36, CALL) \
    EXACT(37, CALL) EXACT(38, CALL) EXACT(39, CALL) EXACT(40, CALL) EXACT(41, CALL) \
    EXACT(42, CALL) EXACT(43, CALL) EXACT(44, CALL) EXACT(45, CALL) EXACT(46, CALL) \
    EXACT(47, CALL) EXACT(48, CALL) EXACT(49, CALL)
#define EXACT_CASES(CALL) \
    EXACT_CASES_TCP(CALL) EXACT(50, CALL) EXACT(51, CALL) \
    EXACT(52, CALL) EXACT(53, CALL) EXACT(54, CALL) EXACT(55, CALL) EXACT(56, CALL) \
    EXACT(57, CALL) EXACT(58, CALL) EXACT(59, CALL) EXACT(60, CALL) EXACT(61, CALL) \
    EXACT(62, CALL) EXACT(63, CALL) EXACT(64, CALL)
#define EXACT(n, CALL) \
    case n: {                   \
        uint8_t data##n[n];     \
        any_bytes(data##n, n);  \
        CALL(data##n, n);       \
        break;                  \
    }

/* One datagram of len bytes (0 .. DRIVER_MAX) in an array of exactly len bytes. len 0 passes
 * a pointer one past a one-byte array: nothing may be read through it (exact_call). */
static void udp_exact(estop_core_t *core, size_t len, uint32_t now, estop_out_t *out)
{
    uint8_t none[1];
#define UDP_CALL(d, n) (void)estop_udp_rx(core, d, n, now, out)
    switch (len) {
    EXACT_CASES(UDP_CALL)
    default:
        (void)estop_udp_rx(core, &none[1], 0u, now, out);
        break;
    }
}

/* A TCP chunk of len bytes (0 .. DRIVER_TCP_MAX) in an array of exactly len bytes, as
 * udp_exact. */
static void tcp_exact(estop_core_t *core, uint32_t slot, size_t len, size_t *consumed,
                      uint32_t now, estop_out_t *out)
{
    uint8_t none[1];
#define TCP_CALL(d, n) (void)estop_tcp_rx(core, slot, d, n, consumed, now, out)
    switch (len) {
    EXACT_CASES_TCP(TCP_CALL)
    default:
        (void)estop_tcp_rx(core, slot, &none[1], 0u, consumed, now, out);
        break;
    }
}

/* The loop's datagram: any length 0 .. DRIVER_MAX, any bytes, in one array a byte longer than
 * the longest, so the byte past a datagram is no alarm here: exact_call's to find (the
 * self-test's read-past-datagram plant). It reaches the states a datagram of that length
 * reaches wherever no byte past len is read. */
static void udp_any_len(estop_core_t *core, uint32_t now, estop_out_t *out)
{
    uint8_t data[DRIVER_MAX + 1u];
    any_bytes(data, sizeof data);
    (void)estop_udp_rx(core, data, Frama_C_unsigned_int_interval(0u, DRIVER_MAX), now, out);
}

#if DRIVER_TCP_WHOLE
/* A TCP chunk of one whole frame, plain (16 bytes) or a request (48), any bytes, in an
 * array of exactly its length (EXACT, as tcp_exact). */
static void tcp_whole(estop_core_t *core, uint32_t slot, size_t *consumed, uint32_t now,
                      estop_out_t *out)
{
    switch ((Frama_C_nondet(0, 1) != 0) ? ESTOP_TCP_FRAME_LEN : ESTOP_REQ_FRAME_LEN) {
    EXACT(16, TCP_CALL)
    EXACT(48, TCP_CALL)
    default:
        break;
    }
}
#else
/* The loop's TCP chunk: any length 0 .. DRIVER_TCP_MAX, as udp_any_len (the self-test's
 * read-past-chunk plant reads the byte past a chunk: exact_call finds it, this does not). */
static void tcp_any_len(estop_core_t *core, uint32_t slot, size_t *consumed, uint32_t now,
                        estop_out_t *out)
{
    uint8_t data[DRIVER_TCP_MAX + 1u];
    any_bytes(data, sizeof data);
    (void)estop_tcp_rx(core, slot, data, Frama_C_unsigned_int_interval(0u, DRIVER_TCP_MAX),
                       consumed, now, out);
}
#endif

/* After the loop, from every state it reached (Eva's state at its exit joins them all): one
 * datagram or one TCP chunk of each length in an array of exactly that length, so that a
 * read past len is an alarm. Each from those states, not one after the other (the chunk after
 * a datagram would start from fewer states). The calls a self-test copy leaves out
 * (DRIVER_CASES) are left out here too; its chunks of whole frames are exact already. */
static void exact_call(estop_core_t *core, size_t *consumed, estop_out_t *out)
{
    if (Frama_C_nondet(0, 1) != 0) {
        if (((DRIVER_CASES >> 1u) & 1u) != 0u) {
            size_t len = Frama_C_unsigned_int_interval(0u, DRIVER_MAX);
            if (core->state == ESTOP_STATE_STOPPED) {
                udp_exact(core, len, any_u32(), out);
                /*@ assert rule_udp_never_leaves_stopped_exact:
                        core->state == ESTOP_STATE_STOPPED; */
            } else {
                udp_exact(core, len, any_u32(), out);
            }
        }
    } else {
#if !DRIVER_TCP_WHOLE
        if (((DRIVER_CASES >> 5u) & 1u) != 0u) {
            tcp_exact(core, Frama_C_unsigned_int_interval(0u, ESTOP_MAX_SLOTS),
                      Frama_C_unsigned_int_interval(0u, DRIVER_TCP_MAX), consumed, any_u32(),
                      out);
        }
#endif
    }
    read_outs(core);
}

int main(void)
{
    estop_core_t core;
    estop_config_t cfg;
    estop_out_t out;
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
        size_t len = Frama_C_unsigned_int_interval(0u, DRIVER_MAX);
        uint32_t now = any_u32();
        uint32_t slot = Frama_C_unsigned_int_interval(0u, ESTOP_MAX_SLOTS);
        estop_err_t err;
        int call = Frama_C_interval(0, 8);
        if (((DRIVER_CASES >> (unsigned)call) & 1u) == 0u) {
            continue; /* a call this run leaves out */
        }
        switch (call) {
        case 0:
            if (core.state == ESTOP_STATE_STOPPED) {
                (void)estop_tick(&core, now, &out);
                /*@ assert rule_tick_never_leaves_stopped: core.state == ESTOP_STATE_STOPPED; */
            } else {
                (void)estop_tick(&core, now, &out);
            }
            break;
        case 1:
            if (core.state == ESTOP_STATE_STOPPED) {
                udp_any_len(&core, now, &out);
                /*@ assert rule_udp_never_leaves_stopped: core.state == ESTOP_STATE_STOPPED; */
            } else {
                udp_any_len(&core, now, &out);
            }
            break;
        case 2:
            if (core.state == ESTOP_STATE_STOPPED) {
                (void)estop_udp_rx(&core, NULL, len, now, &out); /* NULL: an invalid datagram */
                /*@ assert rule_null_never_leaves_stopped: core.state == ESTOP_STATE_STOPPED; */
            } else {
                (void)estop_udp_rx(&core, NULL, len, now, &out);
            }
            break;
        case 3:
            if (core.state == ESTOP_STATE_STOPPED) {
                (void)estop_tcp_open(&core, slot, now, &out);
                /*@ assert rule_open_never_leaves_stopped: core.state == ESTOP_STATE_STOPPED; */
            } else {
                (void)estop_tcp_open(&core, slot, now, &out);
            }
            break;
        case 4:
            if (core.state == ESTOP_STATE_STOPPED) {
                (void)estop_tcp_close(&core, slot, now, &out);
                /*@ assert rule_close_never_leaves_stopped: core.state == ESTOP_STATE_STOPPED; */
            } else {
                (void)estop_tcp_close(&core, slot, now, &out);
            }
            break;
        case 5:
#if DRIVER_TCP_WHOLE
            tcp_whole(&core, slot, &consumed, now, &out);
#else
            tcp_any_len(&core, slot, &consumed, now, &out);
#endif
            break;
        case 6:
            if (Frama_C_nondet(0, 1) != 0) {
                (void)estop_tcp_rx(&core, slot, NULL, 0u, &consumed, now, &out); /* allowed */
            } else if (Frama_C_nondet(0, 1) != 0) {
                err = estop_tcp_rx(&core, slot, NULL,
                                   Frama_C_unsigned_int_interval(1u, DRIVER_MAX), &consumed,
                                   now, &out);
                /*@ assert null_data_refused: err == ESTOP_ERR_NULL_ARG || err == ESTOP_ERR_SLOT; */
            } else {
                uint8_t data[1] = {0u};
                err = estop_tcp_rx(&core, slot, data, 1u, NULL, now, &out);
                /*@ assert null_consumed_refused: err == ESTOP_ERR_NULL_ARG || err == ESTOP_ERR_SLOT; */
            }
            break;
        case 7:
            /* LIFT, whatever the configuration; the unit's stop ID where it is the default
             * one (Eva cannot relate the bytes of a datagram to a stop ID of any value; WP's
             * msg_stops covers every stop ID on the TCP path). */
            if (Frama_C_nondet(0, 1) != 0) {
                stop_datagram(&core, ESTOP_MSG_LIFT, now, &out);
            } else if (core.cfg.stop_id == ESTOP_DEFAULT_STOP_ID) {
                stop_datagram(&core, ESTOP_DEFAULT_STOP_ID, now, &out);
            } else {
                /* another stop ID: WP's msg_stops */
            }
            break;
        default:
            if (estop_fault(&core, now, &out) == ESTOP_OK) {
                /* A fault stops the unit whatever its state: a stop is never refused. */
                /*@ assert rule_fault_stops: core.state == ESTOP_STATE_STOPPED; */
            }
            break;
        }
        read_outs(&core);
    }
    exact_call(&core, &consumed, &out);
    return 0;
}
