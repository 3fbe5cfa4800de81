/* Vector table and the two instructions C cannot say: the semihosting trap and wait-for-
 * interrupt. Function symbols get the Thumb bit from the linker. */
    .syntax unified
    .thumb

    .section .vectors, "a"
    .word _stack_top            /* 0: initial stack pointer */
    .word reset_handler         /* 1: reset */
    .rept 13
    .word fault_handler         /* 2..14: NMI, faults, SVC, PendSV */
    .endr
    .word systick_handler       /* 15: SysTick, the core's clock */

    .text
    .global semihost_call       /* r0: operation, r1: argument; returns r0 */
    .thumb_func
semihost_call:
    bkpt 0xAB
    bx lr

    .global cpu_wait            /* sleep until the next interrupt */
    .thumb_func
cpu_wait:
    wfi
    bx lr
