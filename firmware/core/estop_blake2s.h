/*
 * estop_blake2s: BLAKE2s (RFC 7693) for the message tags of PROTOCOL.md section 5.
 *
 * Tag = MAC(K, m) = keyed BLAKE2s with a 16-byte digest, equal to Python's
 * hashlib.blake2s(m, key=K, digest_size=16).digest().
 *
 * Portable C99: no heap, no mutable global, no libc call; loads and stores are done byte by
 * byte, so the result does not depend on the target's endianness or alignment. Every branch
 * depends on lengths only, never on key or message contents.
 *
 * Contract:
 *  - Every function returns 0 on success and -1 when an argument is out of range (then
 *    nothing is written to the output). A pointer may be NULL only where its length is 0.
 *  - estop_b2s_key_init() absorbs the key block once; estop_b2s_mac() then costs one
 *    compression per started 64-byte block of the message (one for every message of
 *    1..64 bytes, e.g. the 44-, 32- and 48-byte messages of section 5).
 *  - estop_b2s_mac() refuses an empty message (-1): BLAKE2s makes the key block itself the
 *    final block then, which the state after the key block cannot undo. Use estop_blake2s()
 *    for the empty message.
 *  - Output and input buffers must not overlap.
 *  - Secrets stay in the caller's estop_b2s_key_t; copies left on the stack are not wiped.
 *  - Stack: about 300 bytes at most (Cortex-M0+, -Os).
 */
#ifndef ESTOP_BLAKE2S_H
#define ESTOP_BLAKE2S_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ESTOP_B2S_KEY_MAX 32u
#define ESTOP_B2S_OUT_MAX 32u
#define ESTOP_B2S_BLOCK 64u

/* State after the key block (the chain value h) and the digest length it was made for. */
typedef struct {
    uint32_t h[8];
    uint8_t outlen;
} estop_b2s_key_t;

/* Precomputes the state after the key block: keylen 1..32, outlen 1..32.
 * Returns 0, or -1 (k untouched) for a NULL pointer or a length out of range. */
int estop_b2s_key_init(estop_b2s_key_t *k, const uint8_t *key, size_t keylen, size_t outlen);

/* MAC of msg[0 .. len-1] from the state of estop_b2s_key_init(): writes k->outlen bytes to out.
 * len must be at least 1 (see the contract above). Returns 0, or -1 for a NULL pointer,
 * len 0 or a k whose outlen is out of range (a zeroed, never initialised k has outlen 0).
 * k is not changed, so one k serves any number of messages. */
int estop_b2s_mac(const estop_b2s_key_t *k, const uint8_t *msg, size_t len, uint8_t *out);

/* General BLAKE2s of msg[0 .. len-1], any len: keyed (keylen 1..32) or unkeyed (keylen 0),
 * outlen 1..32 bytes written to out. Returns 0, or -1 for an argument out of range. */
int estop_blake2s(uint8_t *out, size_t outlen, const uint8_t *key, size_t keylen,
                  const uint8_t *msg, size_t len);

/* Constant-time comparison of a[0 .. n-1] and b[0 .. n-1]: the time depends on n only.
 * Returns 1 when equal (always for n 0), 0 when they differ or a is NULL or b is NULL with
 * n > 0. */
int estop_ct_equal(const uint8_t *a, const uint8_t *b, size_t n);

#ifdef __cplusplus
}
#endif

#endif /* ESTOP_BLAKE2S_H */
