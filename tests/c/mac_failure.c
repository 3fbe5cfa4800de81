/*
 * The core when its MAC cannot make a tag (issue 16, defect 9): estop_b2s_mac's result is
 * checked. Run under valgrind by tests/test_core_mac_failure.py, so a tag compared without
 * having been written fails the run instead of passing by chance.
 * Prints "all mac failure checks passed" and exits 0 when every check holds.
 */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "estop_core.h"

static int failed;

static void check(int ok, const char *what)
{
    if (!ok) {
        printf("FAIL: %s\n", what);
        failed = 1;
    }
}

static void put_u32(uint8_t *p, uint32_t v)
{
    for (int i = 0; i < 4; i++) {
        p[i] = (uint8_t)(v >> (8 * i));
    }
}

static void put_u64(uint8_t *p, uint64_t v)
{
    for (int i = 0; i < 8; i++) {
        p[i] = (uint8_t)(v >> (8 * i));
    }
}

int main(void)
{
    estop_config_t cfg;
    estop_core_t core;
    estop_out_t out;
    estop_status_t st;
    uint8_t pkt[ESTOP_UDP_AUTH_LEN] = {0};
    uint8_t req[ESTOP_REQ_FRAME_LEN] = {0};
    size_t used = 0;

    estop_config_default(&cfg);
    cfg.session = 1;
    cfg.key_len = ESTOP_KEY_LEN;
    for (unsigned i = 0; i < ESTOP_KEY_LEN; i++) {
        cfg.key[i] = (uint8_t)i;
    }
    check(estop_init(&core, &cfg, 0) == ESTOP_OK, "init");
    core.mac.outlen = 0; /* a MAC state that can no longer make a tag: every MAC fails */

    /* An authenticated control packet: valid body, right session, some tag. */
    put_u32(pkt, ESTOP_MAGIC_CONTROL);
    put_u32(&pkt[4], 7u);
    put_u64(&pkt[8], 1u);
    put_u64(&pkt[16], 1u);
    put_u32(&pkt[32], 4u); /* gear neutral; gas, steering, turn, horn 0 */
    check(estop_udp_rx(&core, pkt, sizeof pkt, 1000u, &out) == ESTOP_OK, "udp_rx");
    check(estop_get_status(&core, &st) == ESTOP_OK, "status");
    check(st.counters.udp_valid == 0u, "a packet whose tag could not be made is not valid");
    check(st.counters.auth_bad_tag == 1u, "... and counts as a bad tag");

    /* A STATUS request frame: its reply carries a zero tag, never bytes left from before. */
    put_u32(req, ESTOP_MAGIC_REQUEST);
    put_u32(&req[4], ESTOP_MSG_STATUS);
    put_u32(&req[8], 1u);
    check(estop_tcp_open(&core, 0u, 2000u, &out) == ESTOP_OK, "tcp_open");
    memset(out.reply, 0xA5, sizeof out.reply);
    check(estop_tcp_rx(&core, 0u, req, sizeof req, &used, 2000u, &out) == ESTOP_OK, "tcp_rx");
    check(out.has_reply && out.reply_len == ESTOP_REPLY_MAX, "a 48-byte reply");
    for (unsigned i = 32; i < ESTOP_REPLY_MAX; i++) {
        check(out.reply[i] == 0u, "the reply's tag is zero when the MAC fails");
    }
    if (!failed) {
        printf("all mac failure checks passed\n");
    }
    return failed;
}
