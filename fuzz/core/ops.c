/*
 * The host: each operation is one call into the core (TCP bytes fed until consumed, a slot
 * closed on request), its input copied to a buffer of its exact size for the sanitizers.
 */
#include <string.h>

#include "harness.h"

void fz_do_tick(world_t *w, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    fz_after_call(w, estop_tick(&w->core, (uint32_t)t, &out), &out, &c, t);
}

void fz_do_udp(world_t *w, const uint8_t *bytes, size_t len, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    /* An exact-size heap copy: the sanitizer sees a read past len. */
    uint8_t *copy = malloc(len > 0u ? len : 1u);
    const uint8_t *arg = NULL;
    if (copy == NULL) {
        abort();
    }
    if (len > 0u) {
        memcpy(copy, bytes, len);
        arg = copy;
    }
    c.kind = 1;
    c.data = arg;
    c.len = len;
    fz_after_call(w, estop_udp_rx(&w->core, arg, len, (uint32_t)t, &out), &out, &c, t);
    free(copy);
}

void fz_do_slot(world_t *w, uint32_t slot, int open, uint64_t t)
{
    estop_out_t out;
    call_t c = {0};
    estop_err_t err = open ? estop_tcp_open(&w->core, slot, (uint32_t)t, &out)
                           : estop_tcp_close(&w->core, slot, (uint32_t)t, &out);
    c.kind = 4;
    CHECK((slot < ESTOP_MAX_SLOTS) == (err != ESTOP_ERR_SLOT), "slot range");
    fz_after_call(w, err, &out, &c, t);
    if (err == ESTOP_OK) {
        w->slots[slot].open = open;
        w->slots[slot].fill = 0;
    }
}

/* The host's loop for TCP bytes: feed the rest until all is consumed or the slot closes. */
void fz_do_tcp(world_t *w, uint32_t slot, const uint8_t *bytes, size_t len, uint64_t t,
               uint64_t step)
{
    size_t at = 0;
    int calls = 0;
    do {
        estop_out_t out;
        call_t c = {0};
        size_t rest = len - at;
        size_t consumed = 0;
        uint8_t *copy = malloc(rest > 0u ? rest : 1u);
        estop_err_t err;
        if (copy == NULL) {
            abort();
        }
        if (rest > 0u) {
            memcpy(copy, bytes + at, rest);
        }
        c.kind = 2;
        c.data = copy;
        c.len = rest;
        c.slot_closed_call = slot < ESTOP_MAX_SLOTS && !w->slots[slot].open;
        err = estop_tcp_rx(&w->core, slot, rest > 0u ? copy : NULL, rest, &consumed, (uint32_t)t,
                           &out);
        CHECK(consumed <= rest, "tcp: consumed more than given");
        CHECK((slot < ESTOP_MAX_SLOTS) == (err != ESTOP_ERR_SLOT), "slot range");
        c.consumed = consumed;
        if (err == ESTOP_OK) {
            fz_shadow_tcp(&w->slots[slot], &c, out.close_slot);
        } else {
            CHECK(consumed == 0u, "tcp: consumed bytes on an error");
        }
        fz_after_call(w, err, &out, &c, t);
        free(copy);
        if (err != ESTOP_OK) {
            break;
        }
        at += consumed;
        if (out.close_slot) {
            CHECK(at == len, "tcp: a closed stream is dropped whole");
            CHECK(w->core.slots[slot].open == 0u, "tcp: slot marked closed");
            fz_do_slot(w, slot, 0, t);
            break;
        }
        t += step; /* the rest may come a little later */
        calls++;
    } while (at < len && calls < 64);
}

