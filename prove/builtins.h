/* Contracts of the compiler built-ins the core uses, for Frama-C only (prove/run.py passes this
 * file with -include). They state what GCC's documentation says; Frama-C has no body for them. */
#ifndef ESTOP_PROVE_BUILTINS_H
#define ESTOP_PROVE_BUILTINS_H
/*@ requires x != 0;
    assigns \result \from x;
    ensures 0 <= \result <= 31;
    ensures (x >> (31 - \result)) == 1;
 */
int __builtin_clz(unsigned int x);
#endif
