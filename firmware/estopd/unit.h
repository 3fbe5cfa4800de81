/* The unit: the core, its time and catch-up, and what each core call asks the host to do.
 *
 * Every function makes one core call at most and describes its outcome in a unit_fx_t (frames
 * to send, a state change and its cause, a reply and a close for the input's TCP slot, an
 * error); it calls no transport and writes no log. The transports (udp.c, tcp.c) hand the
 * effects to apply.c (frames, state lines) and act on replies and closes themselves. Host time
 * is 64-bit microseconds on the unit's clock (clock.h); the core's is a wrapping 32-bit tick. */
#ifndef ESTOPD_UNIT_H
#define ESTOPD_UNIT_H

#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

typedef struct {
    estop_core_t core;
    uint64_t last_call_us;        /* host time of the latest core call (the core's clock) */
    uint64_t deadline_us;         /* host time the core asked to be called back */
    uint8_t state;
    uint8_t reason;
    uint8_t fatal;                /* a tick or fault call failed: no watchdog any more */
    uint8_t have_brake;
    estop_can_frame_t last_brake; /* latest brake frame the core produced */
    estop_can_frame_t last_frame;
    uint32_t frames_out;          /* frames handed out so far */
    uint32_t brake_can_id;
    uint16_t brake_data_id;
    uint32_t slow_us;             /* S and T, for the silence deadline (unit_silence_due) */
    uint32_t timeout_us;
} unit_t;

/* What one core call asks of the host. */
typedef struct {
    const char *call;             /* "tick", "udp_rx", "tcp_rx", ... */
    uint64_t now;                 /* host time the core was given */
    estop_err_t err;              /* ESTOP_OK, or the call failed (log it) */
    estop_can_frame_t frames[ESTOP_OUT_MAX_CAN + 1u]; /* + the frame built at shutdown */
    uint32_t n_frames;
    uint8_t changed;              /* the state changed: from -> to, reason, cause */
    uint8_t from;
    uint8_t to;
    uint8_t reason;
    uint8_t by_clock;             /* the change is nobody's input (silence, a backwards tick) */
    const char *cause;            /* docs/DESIGN.md */
    uint8_t clock_first;          /* the clock changed the state before that: clock_from ->
                                     clock_to (clock_reason, clock_cause), logged first */
    uint8_t clock_from;
    uint8_t clock_to;
    uint8_t clock_reason;
    const char *clock_cause;
    uint8_t has_reply;            /* a reply for the input's slot */
    uint8_t reply[ESTOP_REPLY_MAX];
    size_t reply_len;
    uint8_t close_slot;           /* the core asked to close the input's slot (bad crc) */
} unit_fx_t;

/* Starts the core at host time now; fx holds the boot frames. Returns 0 or -1 (fx->err). The
 * caller wipes the key from cfg afterwards. */
int unit_boot(unit_t *u, const estop_config_t *cfg, uint64_t now, unit_fx_t *fx);
/* Catch-up: when host time t is more than the core's longest step past the latest call, one
 * tick a step later. Returns 1 when it made a call (apply fx and call again), else 0. */
int unit_catch_up(unit_t *u, uint64_t t, unit_fx_t *fx);
/* The tick the core asked for, when t has reached its deadline (after the catch-up). Returns
 * 1 when it made a call, else 0. */
int unit_tick_due(unit_t *u, uint64_t t, unit_fx_t *fx);
/* The time to hand a datagram received at rx_us to the core: never before the latest call. */
uint64_t unit_feed_time(const unit_t *u, uint64_t rx_us);
/* Input calls at host time t (caught up first). */
void unit_udp(unit_t *u, const uint8_t *data, size_t len, uint64_t t, unit_fx_t *fx);
void unit_tcp_open(unit_t *u, uint32_t slot, uint64_t t, unit_fx_t *fx);
void unit_tcp_rx(unit_t *u, uint32_t slot, const uint8_t *buf, size_t len, size_t *used,
                 uint64_t t, unit_fx_t *fx);
void unit_tcp_close(unit_t *u, uint32_t slot, uint64_t t, unit_fx_t *fx);
/* A fault the host found (CAN, clock, shutdown): the core stops and latches. */
void unit_fault(unit_t *u, uint64_t t, unit_fx_t *fx);
/* Shutdown: fx ends with a brake frame that says brake (the core's own STOPPED frame after a
 * fault while ARMED or SLOWING, else the next frame of the sequence built here). core_ok 0:
 * the host is broken, the core is not called. Returns 1
 * when a shutdown fault was reported to the core (log it as cause=shutdown), else 0. */
int unit_last_frame(unit_t *u, uint64_t t, int core_ok, unit_fx_t *fx);
/* Host time at which the core must be called next. */
uint64_t unit_next_wakeup(const unit_t *u);
/* Host time at which silence changes the state (ARMED -> SLOWING at S, SLOWING -> STOPPED at
 * T after the latest valid packet), UINT64_MAX when none is due (STOPPED, or a broken core).
 * Unlike unit_next_wakeup it leaves out the periodic frames. */
uint64_t unit_silence_due(const unit_t *u);

#endif
