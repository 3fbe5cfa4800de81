/*
 * take_frame's contract (docs/PROOF.md) checked on the C code itself, every case: every fill
 * 0..47, every call length 0..96, and three buffer forms (a plain frame's bytes, the request
 * magic already in the slot, the magic arriving in the call). WP proves the contract; this
 * also checks the clause Eva's over-approximation reports false and the contract leaves out
 * (a whole frame without the magic is 16 bytes). Includes estop_tcp.c for its static function.
 */
#include <stdio.h>
#include <string.h>

#include "estop_tcp.c"

static uint32_t need_of(const estop_slot_t *s)
{
    return (rd_u32le(s->buf) == ESTOP_MAGIC_REQUEST) ? 48u : 16u;
}

int main(void)
{
    static const uint8_t magic[4] = {0x45u, 0x53u, 0x51u, 0x32u}; /* "ESQ2" */
    long bad = 0;
    long cases = 0;
    int form;
    for (form = 0; form < 3; form++) {
        uint32_t fill;
        for (fill = 0u; fill < 48u; fill++) {
            size_t len;
            for (len = 0u; len <= 96u; len++) {
                estop_slot_t s;
                estop_slot_t old;
                uint8_t data[96];
                size_t took = 999u;
                size_t i;
                int ok = 1;
                int partial;
                int whole;
                memset(&s, 0, sizeof(s));
                for (i = 0u; i < sizeof(s.buf); i++) {
                    s.buf[i] = (uint8_t)(i * 7u + 1u);
                }
                for (i = 0u; i < sizeof(data); i++) {
                    data[i] = (uint8_t)(i * 13u + 5u);
                }
                if (form == 1) {
                    memcpy(s.buf, magic, sizeof(magic));
                } else if (form == 2) {
                    memcpy(data, magic, sizeof(magic));
                }
                s.fill = (uint8_t)fill;
                old = s;
                partial = (old.fill < 4u) || (old.fill < need_of(&old));
                whole = take_frame(&s, data, len, &took);
                cases++;
                ok = ok && (took <= len) && (whole == 0 || whole == 1) && (s.fill < 48u);
                ok = ok && (whole == 0 || s.fill == 0u);
                for (i = 0u; i < old.fill; i++) { /* take_kept */
                    ok = ok && (s.buf[i] == old.buf[i]);
                }
                for (i = 0u; (i < took) && (old.fill + i < 48u); i++) { /* take_bytes */
                    ok = ok && (s.buf[old.fill + i] == data[i]);
                }
                ok = ok && (old.fill + took <= 48u);
                ok = ok && (whole == 1 || s.fill == old.fill + took); /* take_partial */
                ok = ok && (whole == 0 || old.fill + took == need_of(&s)); /* take_whole, both */
                ok = ok && !(partial && whole == 0 && /* take_rest */
                             ((took != len) || !((s.fill < 4u) || (s.fill < need_of(&s)))));
                if (!ok) {
                    if (bad < 5) {
                        printf("form %d fill %u len %zu: whole %d took %zu fill %u\n", form,
                               (unsigned)fill, len, whole, took, (unsigned)s.fill);
                    }
                    bad++;
                }
            }
        }
    }
    printf("take_frame: %ld cases, %ld violations\n", cases, bad);
    return (bad == 0) ? 0 : 1;
}
