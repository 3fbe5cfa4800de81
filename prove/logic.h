/*
 * The logic that the rules about authentication speak in (docs/PROOF.md): facts of bitwise
 * arithmetic on bytes, and the MAC of PROTOCOL.md section 5 as a logic function. Read by Eva
 * and WP (predicates.h includes it). Frama-C only.
 *
 * Terms over bytes are value-level (each byte read on its own): under WP's Typed model a logic
 * function of a pointer takes the whole memory of its type, so a function of a buffer read
 * before a write to another byte of the core could not be related to the same function after.
 */
#ifndef ESTOP_PROVE_LOGIC_H
#define ESTOP_PROVE_LOGIC_H

/*@
  // Facts of bitwise arithmetic on bytes that the solvers here do not prove. Both hold for
  // every pair of bytes: tests/core/test_prove_axioms.py evaluates each over its domain.
  axiomatic ByteBits {
    axiom or_byte: \forall integer x, y; 0 <= x <= 255 && 0 <= y <= 255 ==>
        0 <= (x | y) <= 255;
    axiom xor_byte: \forall integer x, y; 0 <= x <= 255 && 0 <= y <= 255 ==>
        0 <= (x ^ y) <= 255;
  }
  // And facts the solvers prove (WP proves each lemma in the run that reads this file).
  lemma xor_zero: \forall integer x, y; 0 <= x < 4294967296 && 0 <= y < 4294967296 ==>
      (x ^ y) == 0 ==> x == y;
  lemma or_zero: \forall integer x, y; 0 <= x && 0 <= y ==> (x | y) == 0 ==> x == 0 && y == 0;
  lemma eq_bit: \forall integer e; 0 <= e <= 255 ==>
      (((uint32_t)(e - 1) >> 8) & 1) == 1 ==> e == 0;
*/

/* A little-endian 32-bit word of the bytes p[0..3], as a value-level term. */
#define u32le_v(p) ((uint32_t)((uint32_t)((uint32_t)((uint32_t)(p)[0] | \
    (uint32_t)((uint32_t)(p)[1] << 8)) | (uint32_t)((uint32_t)(p)[2] << 16)) | \
    (uint32_t)((uint32_t)(p)[3] << 24)))

/*@
  // BLAKE2s (RFC 7693): word j (0..7) of the chain value that the compression function F
  // makes of chain value h0..h7, message words m0..m15, byte counter t0, t1 and final-block
  // flag f. Uninterpreted here: the proofs need only that the MAC is this function of the
  // key state and the message's bytes. What F computes, the RFC's and the spec's vectors test
  // (docs/PROOF.md, "Assumed").
  axiomatic Blake2sF {
    logic integer b2s_F(integer h0, integer h1, integer h2, integer h3, integer h4,
                        integer h5, integer h6, integer h7,
                        integer m0, integer m1, integer m2, integer m3, integer m4,
                        integer m5, integer m6, integer m7, integer m8, integer m9,
                        integer m10, integer m11, integer m12, integer m13, integer m14,
                        integer m15, integer t0, integer t1, integer f, integer j);
  }
*/
/* Byte i (little-endian) of word w of a digest, as b2s_output writes it. */
#define hbyte(w, i) ((uint8_t)((w) >> (8 * ((i) % 4))))
/* Word j of a message of n bytes (a multiple of 4) zero-padded to a 64-byte block. */
#define MW(p, n, j) ((4 * (j) < (n)) ? u32le_v((p) + 4 * (j)) : 0)
#define BLOCKW(p, n) MW(p, n, 0), MW(p, n, 1), MW(p, n, 2), MW(p, n, 3), MW(p, n, 4), \
    MW(p, n, 5), MW(p, n, 6), MW(p, n, 7), MW(p, n, 8), MW(p, n, 9), MW(p, n, 10), \
    MW(p, n, 11), MW(p, n, 12), MW(p, n, 13), MW(p, n, 14), MW(p, n, 15)
#define HW(h) (h)[0], (h)[1], (h)[2], (h)[3], (h)[4], (h)[5], (h)[6], (h)[7]
/* Byte i of the MAC (keyed BLAKE2s, PROTOCOL.md 5) of the n bytes at p (1..64, a multiple of
 * 4) under key state k (estop_b2s_key_init's: the chain value after the key block, so the
 * message's block is the final one and the byte counter is 64 + n). */
#define MAC_BYTE(k, p, n, i) \
    hbyte(b2s_F(HW((k)->h), BLOCKW(p, n), 64 + (n), 0, 0xFFFFFFFF, (i) / 4), i)
/* The 16 bytes at p + at are the MAC of p[0 .. at-1] under key state k. */
#define tag_ok(k, p, at) \
    (\forall integer i; 0 <= i < 16 ==> (p)[(at) + i] == MAC_BYTE(k, p, at, i))

/*@
  // CRC-32 (PROTOCOL.md section 2: zlib's) of a plain frame's first 12 bytes b0..b11, as
  // estop_crc32 computes it (its admitted clause crc_value). Uninterpreted here: the TCP rule
  // needs only that a released frame's bytes 12..15 are this function of its first 12; that
  // it is CRC-32, tests/core/test_crc_value.py tests through the core.
  axiomatic Crc32 {
    logic integer crc32_12(integer b0, integer b1, integer b2, integer b3, integer b4,
                           integer b5, integer b6, integer b7, integer b8, integer b9,
                           integer b10, integer b11);
  }
*/
/* The CRC-32 of the 12 bytes at p, and a plain frame at b whose CRC (bytes 12..15) is right. */
#define CRC12(p) crc32_12((p)[0], (p)[1], (p)[2], (p)[3], (p)[4], (p)[5], (p)[6], (p)[7], \
                          (p)[8], (p)[9], (p)[10], (p)[11])
#define plain_crc_ok(b) (rd_u32le_l(&(b)[12]) == CRC12(b))

#endif /* ESTOP_PROVE_LOGIC_H */
