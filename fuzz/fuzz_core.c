/*
 * libFuzzer target of the firmware core (issue 9). Its parts by job are in fuzz/core/
 * (harness.h lists them); this file holds the entry point.
 *
 * The input is a small program: a configuration header, then operations with times (UDP
 * datagrams raw or well-formed, TCP bytes per slot, opens, closes, ticks, faults, time jumps
 * forwards and backwards, with or without a key). The harness plays the host exactly as
 * estop_core.h asks (frames sent, slots closed on request, TCP bytes fed until consumed) and,
 * after every call into the core, checks the safety invariants against its own shadow record,
 * kept with its own code (bitwise CRCs, its own TCP framing, its own clock in 64 bits):
 *   - never ARMED without an accepted RELEASE (the right form, an ACK, a good CRC or tag, a
 *     live link of enough valid packets since the latest stop, a neutral latest packet);
 *   - never ARMED past the slow time, never ARMED or SLOWING past the timeout (from the
 *     latest valid packet); SLOWING only from ARMED, and left for ARMED only after 3 valid
 *     packets since it began;
 *   - ESTOP_BRAKE and ESTOP_STATUS never later than their period, every frame's CRC, alive
 *     counter and content right, the latest brake frame telling the state after the call;
 *   - next_call_us never in the past and never after a due frame or the deadline;
 *   - replies of the right form (CRC, magic, session, echoed counter, tag);
 *   - every TCP call makes progress (the host would spin otherwise);
 * and AddressSanitizer sees every buffer at its exact size, so any read or write out of
 * bounds aborts. Any violation aborts with a message naming the invariant.
 */
#include <string.h>

#include "harness.h"

static void setup(world_t *w, input_t *in)
{
    uint8_t flags = fz_in_u8(in);
    uint32_t start = fz_in_u32(in);
    estop_config_default(&w->cfg);
    w->cfg.session = SESSION;
    w->has_key = (flags & 1u) != 0u;
    if (w->has_key) {
        for (uint32_t i = 0; i < ESTOP_KEY_LEN; i++) {
            w->key[i] = (uint8_t)i;
        }
        w->cfg.key_len = (uint8_t)ESTOP_KEY_LEN;
        memcpy(w->cfg.key, w->key, ESTOP_KEY_LEN);
    }
    if (flags & 2u) {
        /* Short times, so the timeouts, the warn time and the periods are all reached. */
        uint32_t to = 1000u + (uint32_t)fz_in_u16(in) * 8u;
        uint32_t bp = 1000u + (uint32_t)fz_in_u16(in) % 24001u;
        uint32_t sp = 10000u + (uint32_t)fz_in_u16(in) * 15u;
        uint16_t warn = fz_in_u16(in);
        w->cfg.timeout_us = to;
        w->cfg.release_packets = 1u + fz_in_u8(in) % 8u;
        /* Flag 4, a two-stage stop (protocol version 3): the slow time anywhere up to the
         * timeout, any slow level. Without it S = T (version 2). */
        w->cfg.slow_us = to;
        if (flags & 4u) {
            w->cfg.slow_us = 1u + (uint32_t)fz_in_u16(in) % to;
            w->cfg.slow_level = (uint8_t)(1u + fz_in_u8(in) % 99u);
        }
        w->cfg.warn_us = 1u + (uint32_t)warn % w->cfg.slow_us;
        w->cfg.brake_period_us = bp;
        w->cfg.status_period_us = sp < bp ? bp : sp;
    }
    if (flags & 8u) {
        /* Flag 8: a tight tag-check budget (1..3 a window, so that programs of a few packets
         * leave some unchecked), or none (0: every tag checked). */
        w->cfg.tag_checks = (uint8_t)(fz_in_u8(in) % 4u);
    }
    CHECK(estop_config_check(&w->cfg) == ESTOP_OK, "harness config");
    CHECK(estop_init(&w->core, &w->cfg, start) == ESTOP_OK, "init");
    w->cfg.key_len = 0u; /* the harness keeps its key in w->key; cfg is only compared */
    memset(w->cfg.key, 0, sizeof w->cfg.key);
    w->t = (uint64_t)start;
    w->next_call = start;
    w->brake_counter = 0;
    w->status_counter = 0;
    w->prev = (estop_counters_t){0};
    w->prev.stops[ESTOP_REASON_BOOT] = 1u;
    w->prev_state = ESTOP_STATE_STOPPED;
    /* Calling at init time sends the boot frames (the host contract). */
    fz_do_tick(w, w->t);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static world_t w;
    input_t in = {data, size};
    uint32_t ops = 0;
    memset(&w, 0, sizeof w);
    setup(&w, &in);
    while (in.n > 0u && ops < MAX_OPS) {
        uint8_t op = fz_in_u8(&in);
        ops++;
        switch (op % 16u) {
        case 0: /* tick at a host's time */
            fz_do_tick(&w, fz_host_time(&w, &in));
            break;
        case 1: /* tick exactly at next_call_us, several times */
        {
            uint8_t n = (uint8_t)(1u + fz_in_u8(&in) % 8u);
            for (uint8_t i = 0; i < n; i++) {
                fz_do_tick(&w, w.t + (uint32_t)(w.next_call - (uint32_t)w.t));
            }
            break;
        }
        case 2: /* a raw datagram */
        {
            uint64_t t = fz_host_time(&w, &in);
            size_t len = fz_in_u8(&in);
            if (len > in.n) {
                len = in.n;
            }
            fz_do_udp(&w, in.p, len, t);
            in.p += len;
            in.n -= len;
            break;
        }
        case 3: /* a plain control packet, 20 or 16 bytes */
        {
            uint8_t body[20];
            uint8_t s = fz_in_u8(&in);
            fz_make_body(&in, body);
            fz_do_udp(&w, body, (s & 1u) ? ESTOP_UDP_LEN_NO_HORN : ESTOP_UDP_LEN,
                      fz_host_time(&w, &in));
            break;
        }
        case 4: /* an authenticated control packet, or a copy of one sent before */
        {
            uint8_t p[ESTOP_UDP_AUTH_LEN];
            uint8_t sel = fz_in_u8(&in);
            uint32_t remote = (uint32_t)(fz_in_u8(&in) % 10u);
            if ((sel & 0x0Cu) == 0x0Cu && w.n_rec > 0u) {
                /* a recorder sends one again (issue 25: unchecked ones stay refused) */
                uint32_t n = w.n_rec < REC_MAX ? w.n_rec : REC_MAX;
                memcpy(p, w.rec[remote % n], sizeof p);
                fz_do_udp(&w, p, sizeof p, fz_host_time(&w, &in));
                break;
            }
            fz_put32(p, ESTOP_MAGIC_CONTROL);
            fz_put32(p + 4, remote);
            fz_auth_fields(&w, &in, p + 8, p + 16, remote, 0, sel);
            fz_make_body(&in, p + 24);
            fz_tag(&w, p, 44u, (sel & 0x20u) ? (sel >> 6) + 1 : 0);
            fz_record(&w, p);
            fz_do_udp(&w, p, sizeof p, fz_host_time(&w, &in));
            break;
        }
        case 5: /* a stop datagram (any tag) */
        {
            uint8_t f[ESTOP_REQ_FRAME_LEN];
            fz_make_request(&w, &in, f,
                            (fz_in_u8(&in) & 1u) ? w.cfg.stop_id : fz_pick_msg(&w, &in));
            fz_do_udp(&w, f, sizeof f, fz_host_time(&w, &in));
            break;
        }
        case 6:
        case 7: /* open (6) or close (7) a slot */
        {
            uint32_t slot = fz_in_u8(&in) % SLOTS_TRIED;
            fz_do_slot(&w, slot, op % 16u == 6u, fz_host_time(&w, &in));
            break;
        }
        case 8: /* raw TCP bytes */
        {
            uint32_t slot = fz_in_u8(&in) % SLOTS_TRIED;
            uint64_t t = fz_host_time(&w, &in);
            uint8_t step = fz_in_u8(&in);
            size_t len = fz_in_u8(&in);
            if (len > in.n) {
                len = in.n;
            }
            fz_do_tcp(&w, slot, in.p, len, t, step);
            in.p += len;
            in.n -= len;
            break;
        }
        case 9: /* a plain frame, right CRC or not, in pieces */
        {
            uint8_t f[ESTOP_TCP_FRAME_LEN];
            uint32_t slot = fz_in_u8(&in) % SLOTS_TRIED;
            uint8_t s = fz_in_u8(&in);
            fz_put32(f, fz_pick_msg(&w, &in));
            fz_put32(f + 4, fz_in_u8(&in));
            fz_put32(f + 8, 0u);
            fz_put32(f + 12, fz_crc32_bitwise(f, 12u) ^ ((s & 0x80u) ? 1u : 0u));
            fz_do_tcp(&w, slot, f, 1u + (s & 15u), fz_host_time(&w, &in), 100u);
            if ((s & 15u) < 15u) {
                fz_do_tcp(&w, slot, f + 1u + (s & 15u), 15u - (s & 15u), w.t + 100u, 0u);
            }
            break;
        }
        case 10: /* a request frame */
        {
            uint8_t f[ESTOP_REQ_FRAME_LEN];
            uint32_t slot = fz_in_u8(&in) % SLOTS_TRIED;
            fz_make_request(&w, &in, f, fz_pick_msg(&w, &in));
            fz_do_tcp(&w, slot, f, sizeof f, fz_host_time(&w, &in), 0u);
            break;
        }
        case 11:
        {
            estop_out_t out;
            call_t c = {0};
            uint64_t t = fz_host_time(&w, &in);
            c.kind = 3;
            fz_after_call(&w, estop_fault(&w.core, (uint32_t)t, &out), &out, &c, t);
            break;
        }
        case 12: /* a jump forwards, up to the longest step the contract allows */
            fz_do_tick(&w, fz_later(&w, fz_in_u32(&in) & ESTOP_MAX_STEP_US));
            break;
        case 13: /* the clock goes backwards */
        {
            uint32_t back = 1u + fz_in_u32(&in) % 0x7FFFFFFFu;
            fz_do_tick(&w, w.t >= back ? w.t - back : w.t + 0x100000000ull - back);
            break;
        }
        case 14: /* drive: n good packets, neutral or not, at a gap (ticking as a host does) */
        {
            uint8_t n = fz_in_u8(&in) % 8u;
            uint8_t s = fz_in_u8(&in);
            uint32_t gap = 1000u + (uint32_t)fz_in_u8(&in) * 100u;
            for (uint8_t i = 0; i < n; i++) {
                uint64_t due = w.t + gap;
                uint8_t p[ESTOP_UDP_AUTH_LEN];
                while (w.t + (uint32_t)(w.next_call - (uint32_t)w.t) < due) {
                    fz_do_tick(&w, w.t + (uint32_t)(w.next_call - (uint32_t)w.t));
                }
                memset(p, 0, sizeof p);
                fz_put32(p + 8, 4u);
                if (s & 1u) {
                    fz_put32(p, 0x3E800000u); /* gas 0.25: not neutral */
                }
                if (w.has_key) {
                    memmove(p + 24, p, 20u);
                    fz_put32(p, ESTOP_MAGIC_CONTROL);
                    fz_put32(p + 4, 3u);
                    fz_put64(p + 8, SESSION);
                    fz_put64(p + 16, ++w.counter[3][0]);
                    fz_tag(&w, p, 44u, 0);
                    fz_record(&w, p);
                    fz_do_udp(&w, p, ESTOP_UDP_AUTH_LEN, due);
                } else {
                    fz_do_udp(&w, p, ESTOP_UDP_LEN, due);
                }
            }
            break;
        }
        default: /* a NULL datagram and an empty TCP read */
        {
            uint32_t slot;
            fz_do_udp(&w, NULL, 0u, fz_host_time(&w, &in));
            slot = fz_in_u8(&in) % SLOTS_TRIED;
            fz_do_tcp(&w, slot, NULL, 0u, w.t, 0u);
        }
            break;
        }
    }
    return 0;
}

