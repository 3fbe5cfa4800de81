/*
 * The MISRA gate's self-test (tools/misra.py): every line marked "planted" breaks the rule it
 * names, so the checker must report each of them. A checker that is missing, broken or
 * silenced reports nothing here, and the gate fails instead of passing. Never compiled.
 */
#include <stdint.h>

uint32_t planted_value(uint32_t x);
uint8_t planted_narrow(uint32_t wide);
const uint8_t *planted_pointer(const uint8_t *p);
uint32_t planted_chain(uint32_t x);

uint32_t planted_value(uint32_t x)
{
    if (x > 3u) {
        return 1u; /* planted: 15.5 */
    }
    return 0u;
}

uint8_t planted_narrow(uint32_t wide)
{
    uint8_t narrow = wide; /* planted: 10.3 */
    return narrow;
}

const uint8_t *planted_pointer(const uint8_t *p)
{
    return p + 1; /* planted: 18.4 */
}

uint32_t planted_chain(uint32_t x)
{
    uint32_t r = 0u;
    int flag = (int)x;
    if (flag) { /* planted: 14.4 */
        r = 1u;
    } else if (x == 2u) {
        r = 2u;
    } /* planted: 15.7 */
    (void)planted_value(x);
    planted_value(r); /* planted: 17.7 */
    return r;
}
