/*
 * A bare-metal unit on QEMU's mps2-an385: SysTick counts milliseconds and is the core's only
 * clock; a host loop calls estop_tick whenever the core asks (out.next_call_us). The program
 * runs the examples of PROTOCOL.md through the core (sections 1, 2, 4 and the 5.4 vectors, and
 * version 3's two-stage stop and LIFT),
 * prints one line per check over semihosting and exits with status 0 when every check passed.
 * No libc: the few byte copies are loops.
 */
#include <stddef.h>
#include <stdint.h>

#include "estop_blake2s.h"
#include "estop_core.h"
#include "estop_crc.h"

uint32_t semihost_call(uint32_t op, uint32_t arg);
void cpu_wait(void);
void reset_handler(void);
void systick_handler(void);
void fault_handler(void);
int main(void);

#define SYS_WRITE0 0x04u
#define SYS_EXIT 0x18u
#define ADP_STOPPED_APPLICATION_EXIT 0x20026u
#define ADP_STOPPED_RUNTIME_ERROR 0x20023u

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define CPU_HZ 25000000u /* the AN385's system clock */
#define MS 1000u

extern uint32_t _data_start, _data_end, _data_load, _bss_start, _bss_end;

static volatile uint32_t ticks_ms;

void systick_handler(void)
{
    ticks_ms++;
}

static void put(const char *s)
{
    (void)semihost_call(SYS_WRITE0, (uint32_t)(uintptr_t)s);
}

static void put_u32(uint32_t v)
{
    char buf[11];
    size_t i = sizeof(buf) - 1u;
    buf[i] = '\0';
    do {
        buf[--i] = (char)('0' + (v % 10u));
        v /= 10u;
    } while ((v != 0u) && (i > 0u));
    put(&buf[i]);
}

static void finish(uint32_t failed)
{
    (void)semihost_call(SYS_EXIT, (failed == 0u) ? ADP_STOPPED_APPLICATION_EXIT
                                                 : ADP_STOPPED_RUNTIME_ERROR);
    for (;;) {
        cpu_wait();
    }
}

void fault_handler(void)
{
    put("FAIL cpu fault\n");
    finish(1u);
}

void reset_handler(void)
{
    uint32_t *dst = &_data_start;
    const uint32_t *src = &_data_load;
    while (dst < &_data_end) {
        *dst++ = *src++;
    }
    for (dst = &_bss_start; dst < &_bss_end; dst++) {
        *dst = 0u;
    }
    finish((uint32_t)main());
}

/* ---- the unit: core, output and a host loop on the SysTick clock -------------------------- */

static estop_core_t core;
static estop_out_t out;
static estop_config_t cfg;
static uint32_t next_call_us;
static uint8_t last_brake[ESTOP_CAN_DLC];
static uint32_t brake_frames;
static uint32_t stopped_at_us;
static uint32_t last_packet_us;
static uint8_t reply[ESTOP_REPLY_MAX];
static uint32_t reply_len;
static uint32_t passed, failed;

static uint32_t now_us(void)
{
    return ticks_ms * MS;
}

static int same(const uint8_t *a, const uint8_t *b, size_t n)
{
    size_t i;
    int eq = 1;
    for (i = 0u; i < n; i++) {
        if (a[i] != b[i]) {
            eq = 0;
        }
    }
    return eq;
}

static void check(int ok, const char *what)
{
    put(ok ? "ok   " : "FAIL ");
    put(what);
    put("\n");
    if (ok) {
        passed++;
    } else {
        failed++;
    }
}

/* What a host does with every output: send the frames, keep the reply, note the next call. */
static void took(estop_err_t err, uint32_t t)
{
    uint32_t i, j;
    if (err == ESTOP_OK) {
        for (i = 0u; i < out.n_can; i++) {
            if (out.can[i].id == cfg.brake_can_id) {
                for (j = 0u; j < ESTOP_CAN_DLC; j++) {
                    last_brake[j] = out.can[i].data[j];
                }
                brake_frames++;
            }
        }
        if (out.has_reply != 0u) {
            reply_len = out.reply_len;
            for (j = 0u; j < reply_len; j++) {
                reply[j] = out.reply[j];
            }
        }
        if ((out.state_changed != 0u) && (out.changed_by_clock != 0u)) {
            stopped_at_us = t;
        }
        next_call_us = out.next_call_us;
    }
}

/* Ticks the core whenever it asks, sleeping between SysTick interrupts, until ms. */
static void run_until(uint32_t ms)
{
    while ((int32_t)(ticks_ms - ms) < 0) {
        uint32_t t = now_us();
        if ((int32_t)(t - next_call_us) >= 0) {
            took(estop_tick(&core, t, &out), t);
        }
        cpu_wait();
    }
}

static void wait_ms(uint32_t ms)
{
    run_until(ticks_ms + ms);
}

static void udp(const uint8_t *data, size_t len)
{
    uint32_t t = now_us();
    last_packet_us = t;
    took(estop_udp_rx(&core, data, len, t, &out), t);
}

static void tcp(const uint8_t *data, size_t len)
{
    size_t done = 0u;
    reply_len = 0u;
    while (done < len) {
        size_t used = 0u;
        uint32_t t = now_us();
        estop_err_t err = estop_tcp_rx(&core, 0u, data + done, len - done, &used, t, &out);
        took(err, t);
        if ((err != ESTOP_OK) || (used == 0u)) {
            break;
        }
        done += used;
    }
}

/* slow_us 0: the default times (S = T); else a two-stage unit with S = slow_us, T = 3 S. */
static void boot(const uint8_t *key, uint32_t slow_us)
{
    uint32_t i, t;
    estop_config_default(&cfg);
    cfg.session = 0x0123456789ABCDEFull;
    if (slow_us != 0u) {
        cfg.slow_us = slow_us;
        cfg.timeout_us = 3u * slow_us;
        cfg.warn_us = slow_us / 2u;
    }
    if (key != NULL) {
        cfg.key_len = (uint8_t)ESTOP_KEY_LEN;
        for (i = 0u; i < ESTOP_KEY_LEN; i++) {
            cfg.key[i] = key[i];
        }
    }
    t = now_us();
    check(estop_init(&core, &cfg, t) == ESTOP_OK,
          (key != NULL) ? "init with the key of 5.4"
                        : ((slow_us != 0u) ? "init a two-stage unit" : "init without a key"));
    took(estop_tick(&core, t, &out), t);
    took(estop_tcp_open(&core, 0u, t, &out), t);
}

static uint32_t udp_valid(void)
{
    estop_status_t st;
    return (estop_get_status(&core, &st) == ESTOP_OK) ? st.counters.udp_valid : 0u;
}

/* ---- PROTOCOL.md examples ------------------------------------------------------------------ */

static const uint8_t udp_example[20] = {0x9A, 0x99, 0x99, 0x3E, 0x00, 0x00, 0x80, 0xBE, 0x08, 0x00,
                                        0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00};
static const uint8_t neutral[20] = {0, 0, 0, 0, 0, 0, 0, 0, 4, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
static const uint8_t stop_example[16] = {0x70, 0xE5, 0x70, 0xE5, 0x01, 0x00, 0x00, 0x00,
                                         0x00, 0x00, 0x00, 0x00, 0xDC, 0x09, 0xBF, 0x43};
static const uint8_t release_example[16] = {0x02, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00,
                                            0x00, 0x00, 0x00, 0x00, 0x8D, 0x5F, 0xCB, 0xD5};
static const uint8_t brake_boot_0[8] = {0x01, 0x64, 0x00, 0x01, 0x00, 0x00, 0x00, 0x9C};
static const uint8_t brake_timeout_14[8] = {0x01, 0x64, 0x00, 0x03, 0x00, 0x00, 0x0E, 0x1D};
static const uint8_t lift_example[16] = {0x03, 0x00, 0x00, 0x00, 0x05, 0x00, 0x00, 0x00,
                                         0x00, 0x00, 0x00, 0x00, 0xFB, 0x1A, 0xAB, 0x44};

/* Section 5.4: key 00 01 .. 1F, session 0x0123456789ABCDEF, remote id 7. */
static const uint8_t v_control[60] = {
    0x45, 0x53, 0x55, 0x32, 0x07, 0x00, 0x00, 0x00, 0xEF, 0xCD, 0xAB, 0x89, 0x67, 0x45, 0x23,
    0x01, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x9A, 0x99, 0x99, 0x3E, 0x00, 0x00,
    0x80, 0xBE, 0x08, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x0C,
    0xEF, 0xFB, 0x40, 0xCD, 0x71, 0x1A, 0xF5, 0xA3, 0x87, 0x85, 0x67, 0xB9, 0x28, 0x7C, 0x72};
static const uint8_t v_status[48] = {
    0x45, 0x53, 0x51, 0x32, 0x01, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x88, 0x77, 0x66, 0x55, 0x44, 0x33, 0x22, 0x11,
    0xE0, 0x5B, 0x65, 0xD7, 0x00, 0xA8, 0x04, 0xC4, 0x65, 0x2A, 0x16, 0x32, 0xA0, 0xEA, 0xDD, 0x1E};
static const uint8_t v_status_reply[48] = {
    0x45, 0x53, 0x52, 0x32, 0x80, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00,
    0xEF, 0xCD, 0xAB, 0x89, 0x67, 0x45, 0x23, 0x01, 0x88, 0x77, 0x66, 0x55, 0x44, 0x33, 0x22, 0x11,
    0xE0, 0x3C, 0x40, 0x08, 0xC7, 0x26, 0x9C, 0x38, 0xB7, 0x4F, 0x4C, 0x23, 0x9E, 0x56, 0xE7, 0x0D};
static const uint8_t v_release[48] = {
    0x45, 0x53, 0x51, 0x32, 0x02, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00,
    0xEF, 0xCD, 0xAB, 0x89, 0x67, 0x45, 0x23, 0x01, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x15, 0x42, 0xBA, 0x83, 0xA0, 0xCE, 0x93, 0x39, 0xAA, 0x34, 0x55, 0xA8, 0x66, 0xEF, 0x4D, 0xE5};
static const uint8_t v_lift[48] = {
    0x45, 0x53, 0x51, 0x32, 0x03, 0x00, 0x00, 0x00, 0x04, 0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00,
    0xEF, 0xCD, 0xAB, 0x89, 0x67, 0x45, 0x23, 0x01, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x8E, 0xC2, 0x15, 0xCD, 0x4A, 0xAB, 0x10, 0xED, 0xAC, 0x0A, 0xF7, 0xA5, 0x91, 0x91, 0xC9, 0x6C};
static const uint8_t v_stop[48] = {
    0x45, 0x53, 0x51, 0x32, 0x70, 0xE5, 0x70, 0xE5, 0x03, 0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00,
    0xEF, 0xCD, 0xAB, 0x89, 0x67, 0x45, 0x23, 0x01, 0x03, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x2D, 0x87, 0x7B, 0x42, 0xF3, 0xEA, 0xAC, 0xD8, 0xBB, 0x0A, 0x03, 0x26, 0xF1, 0x8E, 0xD5, 0x2A};

/* A plain reply: ACK/NAK, seq, state, reason, nak code, and its CRC. */
static int plain_reply(uint32_t code, uint32_t seq, uint8_t state, uint8_t reason, uint8_t nak)
{
    uint32_t crc = estop_crc32(reply, 12u);
    return (reply_len == ESTOP_TCP_FRAME_LEN) && (reply[0] == code) && (reply[4] == seq) &&
           (reply[8] == state) && (reply[9] == reason) && (reply[11] == nak) &&
           (reply[12] == (uint8_t)(crc & 0xFFu)) && (reply[15] == (uint8_t)(crc >> 24));
}

static void drive(const uint8_t *packet, uint32_t n)
{
    uint32_t i;
    for (i = 0u; i < n; i++) {
        wait_ms(20u);
        udp(packet, ESTOP_UDP_LEN);
    }
}

/* An authenticated neutral heartbeat with this counter, tagged on the device (PROTOCOL.md 5.1),
 * from remote id 8: the vectors are remote 7's messages in order (control packet 1, RELEASE 2),
 * and a RELEASE must be above its remote's newest control packet (issue 25). */
static void auth_beat(const uint8_t *key, uint8_t counter)
{
    uint8_t p[ESTOP_UDP_AUTH_LEN];
    uint32_t i;
    for (i = 0u; i < 24u; i++) {
        p[i] = v_control[i];
    }
    p[4] = 8u;
    p[16] = counter;
    for (i = 0u; i < ESTOP_UDP_LEN; i++) {
        p[24u + i] = neutral[i];
    }
    (void)estop_blake2s(p + 44, ESTOP_TAG_LEN, key, ESTOP_KEY_LEN, p, 44u);
    wait_ms(20u);
    udp(p, sizeof(p));
}

int main(void)
{
    uint8_t key[ESTOP_KEY_LEN];
    uint32_t i, late;

    SYST_RVR = (CPU_HZ / 1000u) - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 7u; /* processor clock, interrupt, enable */
    put("estop on mps2-an385: the core's clock is SysTick\n");

    /* Plain unit: sections 1, 2 and 4. */
    boot(NULL, 0u);
    check(same(last_brake, brake_boot_0, 8u), "boot brake frame 01 64 00 01 00 00 00 9C");
    drive(udp_example, 5u);
    check(udp_valid() == 5u, "UDP example is a valid packet");
    tcp(release_example, sizeof(release_example));
    check(plain_reply(ESTOP_MSG_NAK, 2u, 0u, 1u, 3u), "RELEASE example refused: not neutral");
    drive(neutral, 5u);
    tcp(release_example, sizeof(release_example));
    check(plain_reply(ESTOP_MSG_ACK, 2u, 1u, 0u, 0u), "RELEASE example accepted: ARMED");
    tcp(stop_example, sizeof(stop_example));
    check(plain_reply(ESTOP_MSG_ACK, 1u, 0u, 2u, 0u), "STOP example: STOPPED, tcp stop");
    drive(neutral, 5u);
    tcp(release_example, sizeof(release_example));
    check(out.state == ESTOP_STATE_ARMED, "re-armed");
    stopped_at_us = 0u;
    run_until(ticks_ms + 300u);
    check((out.state == ESTOP_STATE_STOPPED) && (out.reason == ESTOP_REASON_UDP_TIMEOUT),
          "silence: STOPPED, udp timeout");
    /* The stop comes from a tick at the deadline the core asked for (SysTick has 1 ms steps). */
    late = (uint32_t)(stopped_at_us - last_packet_us) - cfg.timeout_us;
    check((stopped_at_us != 0u) && (late <= 2u * MS), "timeout stop at the deadline, by SysTick");
    for (i = 0u; (i < 100u) && !same(last_brake, brake_timeout_14, 8u); i++) {
        wait_ms(10u);
    }
    check(same(last_brake, brake_timeout_14, 8u), "brake frame 01 64 00 03 00 00 0E 1D");

    /* A two-stage unit (version 3): S 100 ms, T 300 ms, L 30 %; then the LIFT example. */
    boot(NULL, 100u * MS);
    drive(neutral, 5u);
    tcp(release_example, sizeof(release_example));
    stopped_at_us = 0u;
    run_until(ticks_ms + 150u);
    check((out.state == ESTOP_STATE_SLOWING) && (last_brake[0] == ESTOP_BRAKE_CONTROLLED) &&
              (last_brake[1] == cfg.slow_level),
          "silence: SLOWING, controlled stop at the slow level");
    late = (uint32_t)(stopped_at_us - last_packet_us) - cfg.slow_us;
    check((stopped_at_us != 0u) && (late <= 2u * MS), "slow-down at its deadline, by SysTick");
    for (i = 0u; i < 3u; i++) {
        udp(neutral, ESTOP_UDP_LEN);
    }
    check(out.state == ESTOP_STATE_ARMED, "3 valid packets: ARMED again");
    tcp(lift_example, sizeof(lift_example));
    check(plain_reply(ESTOP_MSG_ACK, 5u, 0u, 5u, 0u) && (last_brake[0] == ESTOP_BRAKE_EMERGENCY),
          "LIFT example: STOPPED, lift");

    /* Unit with the key of section 5.4. */
    for (i = 0u; i < ESTOP_KEY_LEN; i++) {
        key[i] = (uint8_t)i;
    }
    boot(key, 0u);
    tcp(v_status, sizeof(v_status));
    check((reply_len == 48u) && same(reply, v_status_reply, 48u),
          "5.4 STATUS reply, byte for byte");
    wait_ms(20u);
    udp(v_control, sizeof(v_control));
    check(udp_valid() == 1u, "5.4 control packet authenticated");
    for (i = 1u; i <= 5u; i++) {
        auth_beat(key, (uint8_t)i);
    }
    check(udp_valid() == 6u, "heartbeats tagged on the device authenticated");
    tcp(v_release, sizeof(v_release));
    check((reply_len == 48u) && (reply[4] == ESTOP_MSG_ACK) && (reply[12] == ESTOP_STATE_ARMED),
          "5.4 RELEASE: ACK, ARMED");
    udp(v_lift, sizeof(v_lift));
    check((out.state == ESTOP_STATE_STOPPED) && (out.reason == ESTOP_REASON_LIFT) &&
              (last_brake[0] == ESTOP_BRAKE_EMERGENCY) && (last_brake[3] == ESTOP_REASON_LIFT),
          "5.4 LIFT as a lift datagram: STOPPED, lift");
    tcp(v_stop, sizeof(v_stop));
    check((reply_len == 48u) && (reply[12] == ESTOP_STATE_STOPPED) &&
              (reply[13] == ESTOP_REASON_LIFT),
          "5.4 STOP: acknowledged, the first reason kept");

    put("systick: ");
    put_u32(ticks_ms);
    put(" ms, brake frames: ");
    put_u32(brake_frames);
    put("\n");
    put_u32(passed);
    put(" passed, ");
    put_u32(failed);
    put(" failed\n");
    return (int)failed;
}
