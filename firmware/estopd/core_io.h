/* Calls into the core: host time (64-bit) to core ticks, gaps fed in steps, and everything
 * that must follow each call (frames out, reply, close request, state log, next deadline). */
#ifndef ESTOPD_CORE_IO_H
#define ESTOPD_CORE_IO_H

#include <netinet/in.h>
#include <stdint.h>

#include "daemon.h"
#include "estop_core.h"

/* Results of cio_done for the input's slot. */
#define CIO_CLOSE 0x2u  /* the core asked to close the slot (bad crc) */
#define CIO_ERROR 0x4u  /* the core call failed */

/* Boots the core at the current time and sends the boot frames. Returns 0 or -1. */
int cio_boot(daemon_t *d);
/* Reads the clock, drains the UDP socket (every datagram received so far goes to the core at
 * its receive time), then catches the core up (steps, due tick, CAN retries and faults) and
 * returns the time to hand to the next input call. Call it before every input: no deadline
 * is acted on before what was received before it has been looked at (PROTOCOL.md 6). */
uint64_t cio_prepare(daemon_t *d);
/* One datagram for the core, received at host time rx_us (the drain's; see udp.h). */
void cio_udp(daemon_t *d, const uint8_t *data, size_t len, const struct sockaddr_in *src,
             uint64_t rx_us);
/* Handles the output of a core call made at host time now. src: who caused it (NULL for
 * the clock or the host). slot: the TCP slot of the input, or -1. Returns CIO_* bits. */
unsigned cio_done(daemon_t *d, estop_err_t err, const char *what, const estop_out_t *out,
                  uint64_t now, const struct sockaddr_in *src, int slot);
/* Reports a host fault to the core (logged as cause). */
void cio_fault(daemon_t *d, uint64_t now, const char *cause);
/* Hands one frame to the CAN output (or the can-log when there is no CAN). */
void cio_emit(daemon_t *d, const estop_can_frame_t *f, uint64_t now);
/* Host time at which the loop must wake next (core deadline or CAN retry). */
uint64_t cio_wakeup(const daemon_t *d);

#endif
