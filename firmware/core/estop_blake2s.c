#include "estop_blake2s.h"

/* RFC 7693 section 2.6: the SHA-256 IV. */
static const uint32_t b2s_iv[8] = {0x6A09E667u, 0xBB67AE85u, 0x3C6EF372u, 0xA54FF53Au,
                                   0x510E527Fu, 0x9B05688Cu, 0x1F83D9ABu, 0x5BE0CD19u};

#define B2S_ROUNDS 10u
#define B2S_WORDS 16u
/* Final-block flag f0 (RFC 7693 section 3.2): all ones on the last block. */
#define B2S_LAST 0xFFFFFFFFu
#define B2S_MORE 0u

/* Speed builds of GCC and Clang unroll the rounds completely: the sigma look-ups and the
 * index arithmetic of G then fold into constants and v lives in registers (about 1,300
 * x86-64 instructions per block instead of about 3,900). Size builds (-Os) and other
 * compilers keep the compact loops. Either way the same code runs. */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define B2S_UNROLL _Pragma("GCC unroll 16")
#else
#define B2S_UNROLL
#endif

/* n is 7, 8, 12 or 16: never 0, so both shifts stay below 32. */
/*@ assigns \nothing; */
static inline uint32_t rotr32(uint32_t x, uint32_t n)
{
    return (x >> n) | (x << (32u - n));
}

/* Little-endian 32-bit load, byte by byte (any alignment, any host byte order). */
/*@ requires \valid_read(p + (0 .. 3));
    assigns \nothing;
 */
static inline uint32_t load32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

/* Little-endian 32-bit store, byte by byte. */
/*@ requires \valid(p + (0 .. 3));
    assigns p[0 .. 3];
 */
static inline void store32(uint8_t *p, uint32_t w)
{
    p[0] = (uint8_t)w;
    p[1] = (uint8_t)(w >> 8);
    p[2] = (uint8_t)(w >> 16);
    p[3] = (uint8_t)(w >> 24);
}

/* Message words of one block from p[0 .. n-1] (n <= 64), zero-padded to 64 bytes. */
/*@ requires n <= 64 && \valid(m + (0 .. 15)) && \valid_read(p + (0 .. n - 1));
    assigns m[0 .. 15];
 */
static void load_block(uint32_t m[B2S_WORDS], const uint8_t *p, size_t n)
{
    size_t full = n / 4u;
    size_t i;
    /* Zero every word first, then load: the padding is zero and every word is written
     * whatever n is, which an analyser can follow (zeroing from m[full] on it cannot). */
    /*@ loop invariant 0 <= i <= 16;
        loop assigns i, m[0 .. 15];
        loop variant 16 - i; */
    for (i = 0u; i < B2S_WORDS; i++) {
        m[i] = 0u;
    }
    /*@ loop invariant 0 <= i <= full;
        loop assigns i, m[0 .. full - 1];
        loop variant full - i; */
    for (i = 0u; i < full; i++) {
        m[i] = load32(&p[4u * i]);
    }
    /* A partial last word (then full < 16). */
    /*@ loop invariant 4 * full <= i && full <= 16;
        loop assigns i, m[0 .. 15];
        loop variant n - i; */
    for (i = 4u * full; i < n; i++) {
        m[full] |= (uint32_t)p[i] << (8u * (uint32_t)(i % 4u));
    }
}

/* The mixing function G (RFC 7693 section 3.1) on v[a], v[b], v[c], v[d]. */
/*@ requires \valid(v + (0 .. 15)) && a < 16 && b < 16 && c < 16 && d < 16;
    assigns v[a], v[b], v[c], v[d];
 */
static inline void b2s_g(uint32_t v[B2S_WORDS], uint32_t a, uint32_t b, uint32_t c, uint32_t d,
                         uint32_t x, uint32_t y)
{
    v[a] = v[a] + v[b] + x;
    v[d] = rotr32(v[d] ^ v[a], 16u);
    v[c] = v[c] + v[d];
    v[b] = rotr32(v[b] ^ v[c], 12u);
    v[a] = v[a] + v[b] + y;
    v[d] = rotr32(v[d] ^ v[a], 8u);
    v[c] = v[c] + v[d];
    v[b] = rotr32(v[b] ^ v[c], 7u);
}

/* Compression function F (RFC 7693 section 3.2): t0/t1 the byte counter (low, high word),
 * f the final-block mask (B2S_LAST or B2S_MORE). */
/*@ requires n <= 64 && \valid(h + (0 .. 7)) && \valid_read(block + (0 .. n - 1));
    assigns h[0 .. 7];
 */
static void b2s_compress(uint32_t h[8], const uint8_t *block, size_t n, uint32_t t0, uint32_t t1,
                         uint32_t f)
{
    /* RFC 7693 section 2.7: message word order of each of the 10 rounds. */
    static const uint8_t b2s_sigma[10][16] = {
        {0u, 1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u, 9u, 10u, 11u, 12u, 13u, 14u, 15u},
        {14u, 10u, 4u, 8u, 9u, 15u, 13u, 6u, 1u, 12u, 0u, 2u, 11u, 7u, 5u, 3u},
        {11u, 8u, 12u, 0u, 5u, 2u, 15u, 13u, 10u, 14u, 3u, 6u, 7u, 1u, 9u, 4u},
        {7u, 9u, 3u, 1u, 13u, 12u, 11u, 14u, 2u, 6u, 5u, 10u, 4u, 0u, 15u, 8u},
        {9u, 0u, 5u, 7u, 2u, 4u, 10u, 15u, 14u, 1u, 11u, 12u, 6u, 8u, 3u, 13u},
        {2u, 12u, 6u, 10u, 0u, 11u, 8u, 3u, 4u, 13u, 7u, 5u, 15u, 14u, 1u, 9u},
        {12u, 5u, 1u, 15u, 14u, 13u, 4u, 10u, 0u, 7u, 6u, 3u, 9u, 2u, 8u, 11u},
        {13u, 11u, 7u, 14u, 12u, 1u, 3u, 9u, 5u, 0u, 15u, 4u, 8u, 6u, 2u, 10u},
        {6u, 15u, 14u, 9u, 11u, 3u, 0u, 8u, 12u, 2u, 13u, 7u, 1u, 4u, 10u, 5u},
        {10u, 2u, 8u, 4u, 7u, 6u, 1u, 5u, 15u, 11u, 9u, 14u, 3u, 12u, 13u, 0u}};
    uint32_t m[B2S_WORDS];
    uint32_t v[B2S_WORDS];
    uint32_t i;
    uint32_t r;
    load_block(m, block, n);
    /*@ loop invariant 0 <= i <= 8;
        loop assigns i, v[0 .. 15];
        loop variant 8 - i; */
    for (i = 0u; i < 8u; i++) {
        v[i] = h[i];
        v[i + 8u] = b2s_iv[i];
    }
    v[12] ^= t0;
    v[13] ^= t1;
    v[14] ^= f;
    B2S_UNROLL
    /*@ loop invariant 0 <= r <= 10;
        loop assigns r, i, v[0 .. 15];
        loop variant 10 - r; */
    for (r = 0u; r < B2S_ROUNDS; r++) {
        const uint8_t *s = b2s_sigma[r];
        B2S_UNROLL
        /* G on the four columns (i 0..3), then the four diagonals (i 4..7). */
        /*@ loop invariant 0 <= i <= 8;
            loop assigns i, v[0 .. 15];
            loop variant 8 - i; */
        for (i = 0u; i < 8u; i++) {
            /* % and / rather than & and >>: the same machine code (gcc -O2, and -Os for
             * the M0+), and the solvers bound a remainder, not a bitwise AND. */
            uint32_t j = i % 4u;
            uint32_t sh = i / 4u;
            b2s_g(v, j, 4u + ((j + sh) % 4u), 8u + ((j + (2u * sh)) % 4u),
                  12u + ((j + (3u * sh)) % 4u), m[s[2u * i]], m[s[(2u * i) + 1u]]);
        }
    }
    /*@ loop invariant 0 <= i <= 8;
        loop assigns i, h[0 .. 7];
        loop variant 8 - i; */
    for (i = 0u; i < 8u; i++) {
        h[i] ^= v[i] ^ v[i + 8u];
    }
}

/* h = IV xor the parameter block's first word (digest length, key length, fanout 1, depth 1). */
/*@ requires \valid(h + (0 .. 7));
    assigns h[0 .. 7];
 */
static void b2s_start(uint32_t h[8], size_t keylen, size_t outlen)
{
    uint32_t i;
    /*@ loop invariant 0 <= i <= 8;
        loop assigns i, h[0 .. 7];
        loop variant 8 - i; */
    for (i = 0u; i < 8u; i++) {
        h[i] = b2s_iv[i];
    }
    h[0] ^= 0x01010000u ^ ((uint32_t)keylen << 8) ^ (uint32_t)outlen;
}

/* Absorbs msg[0 .. len-1] (len >= 1) after t0 bytes already compressed (0 or one key block);
 * the last block, 1..64 bytes, gets the final flag. */
/*@ requires len >= 1 && \valid(h + (0 .. 7)) && \valid_read(msg + (0 .. len - 1));
    assigns h[0 .. 7];
 */
static void b2s_absorb(uint32_t h[8], uint32_t t0, const uint8_t *msg, size_t len)
{
    uint32_t lo = t0;
    uint32_t hi = 0u;
    size_t at = 0u;
    size_t left = len;
    /*@ loop invariant at + left == len;
        loop assigns lo, hi, at, left, h[0 .. 7];
        loop variant left; */
    while (left > ESTOP_B2S_BLOCK) {
        lo += ESTOP_B2S_BLOCK;
        hi += (lo < ESTOP_B2S_BLOCK) ? 1u : 0u; /* carry into the high word */
        b2s_compress(h, &msg[at], ESTOP_B2S_BLOCK, lo, hi, B2S_MORE);
        at += ESTOP_B2S_BLOCK;
        left -= ESTOP_B2S_BLOCK;
    }
    lo += (uint32_t)left;
    hi += (lo < (uint32_t)left) ? 1u : 0u;
    b2s_compress(h, &msg[at], left, lo, hi, B2S_LAST);
}

/* The first outlen bytes of h, little-endian. */
/*@ requires outlen <= 32 && \valid(out + (0 .. outlen - 1)) && \valid_read(h + (0 .. 7));
    assigns out[0 .. outlen - 1];
 */
static void b2s_output(uint8_t *out, const uint32_t h[8], size_t outlen)
{
    size_t full = outlen / 4u;
    size_t i;
    /*@ loop invariant 0 <= i <= full;
        loop assigns i, out[0 .. 4 * full - 1];
        loop variant full - i; */
    for (i = 0u; i < full; i++) {
        store32(&out[4u * i], h[i]);
    }
    /*@ loop assigns i, out[0 .. outlen - 1];
        loop variant outlen - i; */
    for (i = 4u * full; i < outlen; i++) {
        out[i] = (uint8_t)(h[full] >> (8u * (uint32_t)(i % 4u)));
    }
}

int estop_b2s_key_init(estop_b2s_key_t *k, const uint8_t *key, size_t keylen, size_t outlen)
{
    int rc = -1;
    if ((k != NULL) && (key != NULL) && (keylen >= 1u) && (keylen <= ESTOP_B2S_KEY_MAX) &&
        (outlen >= 1u) && (outlen <= ESTOP_B2S_OUT_MAX)) {
        b2s_start(k->h, keylen, outlen);
        b2s_compress(k->h, key, keylen, ESTOP_B2S_BLOCK, 0u, B2S_MORE);
        k->outlen = (uint8_t)outlen;
        rc = 0;
    }
    return rc;
}

int estop_b2s_mac(const estop_b2s_key_t *k, const uint8_t *msg, size_t len, uint8_t *out)
{
    int rc = -1;
    if ((k != NULL) && (msg != NULL) && (out != NULL) && (len >= 1u) && (k->outlen >= 1u) &&
        (k->outlen <= ESTOP_B2S_OUT_MAX)) {
        uint32_t h[8];
        uint32_t i;
        /*@ loop invariant 0 <= i <= 8;
            loop assigns i, h[0 .. 7];
            loop variant 8 - i; */
        for (i = 0u; i < 8u; i++) {
            h[i] = k->h[i];
        }
        b2s_absorb(h, ESTOP_B2S_BLOCK, msg, len);
        b2s_output(out, h, k->outlen);
        rc = 0;
    }
    return rc;
}

int estop_blake2s(uint8_t *out, size_t outlen, const uint8_t *key, size_t keylen,
                  const uint8_t *msg, size_t len)
{
    int rc = -1;
    if ((out != NULL) && (outlen >= 1u) && (outlen <= ESTOP_B2S_OUT_MAX) &&
        (keylen <= ESTOP_B2S_KEY_MAX) && ((key != NULL) || (keylen == 0u)) &&
        ((msg != NULL) || (len == 0u))) {
        uint32_t h[8];
        b2s_start(h, keylen, outlen);
        if (keylen > 0u) {
            /* The key block is the final block when there is no message. */
            b2s_compress(h, key, keylen, ESTOP_B2S_BLOCK, 0u, (len == 0u) ? B2S_LAST : B2S_MORE);
        } else if (len == 0u) {
            /* Unkeyed empty message: one all-zero final block with counter 0. */
            b2s_compress(h, msg, 0u, 0u, 0u, B2S_LAST);
        } else {
            /* Unkeyed, message follows: nothing to do before it. */
        }
        if (len > 0u) {
            b2s_absorb(h, (keylen > 0u) ? ESTOP_B2S_BLOCK : 0u, msg, len);
        }
        b2s_output(out, h, outlen);
        rc = 0;
    }
    return rc;
}

int estop_ct_equal(const uint8_t *a, const uint8_t *b, size_t n)
{
    uint32_t diff = 0u;
    uint32_t equal;
    if ((a == NULL) || (b == NULL)) {
        if (n > 0u) {
            diff = 1u;
        }
    } else {
        size_t i;
        /* Every byte is looked at, whatever an earlier one was: diff collects the bits in
         * which any pair differs (0..255). */
        /*@ loop invariant 0 <= i <= n && diff <= 255;
            loop invariant diff == 0 ==> \forall integer k; 0 <= k < i ==> a[k] == b[k];
            loop assigns i, diff;
            loop variant n - i; */
        for (i = 0u; i < n; i++) {
            /*@ assert xor_byte: 0 <= ((uint32_t)a[i] ^ (uint32_t)b[i]) <= 255; */
            diff |= (uint32_t)a[i] ^ (uint32_t)b[i];
            /*@ assert or_byte: diff <= 255; */
            /*@ assert or_is: diff == (\at(diff, LoopCurrent) | (a[i] ^ b[i])); */
            /*@ assert or_zero: diff == 0 ==> \at(diff, LoopCurrent) == 0 && (a[i] ^ b[i]) == 0; */
            /*@ assert xor_zero: diff == 0 ==> a[i] == b[i]; */
        }
    }
    /* diff is 0..255: diff - 1 has bit 8 set only when diff is 0. */
    equal = ((diff - 1u) >> 8) & 1u;
    /*@ assert equal_bit: (equal == 1 ==> diff == 0) && (equal == 0 || equal == 1); */
    return (int)equal;
}
