/* TCP stop-channel clients: one core slot per connection, replies written without waiting.
 *
 * PROTOCOL.md 2: a new connection is never turned away because old ones hold every place: the
 * one quiet longest (no complete frame received) is closed to make room. Every complete frame
 * received is handled, in order, before a connection is closed for any reason, so a STOP that
 * has arrived is never lost. A client that does not read its replies is not closed for that
 * (reply.h). Dead peers (a Wi-Fi drop that lost the FIN) are found by TCP keepalive and
 * TCP_USER_TIMEOUT within a few seconds. */
#ifndef ESTOPD_CLIENTS_H
#define ESTOPD_CLIENTS_H

#include <stdint.h>

#include "daemon.h"

void clients_init(daemon_t *d);
/* The listening socket is readable: accept (making room when every slot is taken). */
void clients_accept(daemon_t *d);
/* Host time at which a paused listener (EMFILE and friends) is to be watched again, 0: none. */
uint64_t clients_next_wakeup(const daemon_t *d);
/* Resumes a paused listener when its time has come. */
void clients_service(daemon_t *d, uint64_t now);
/* The client in slot is readable or hung up. */
void clients_event(daemon_t *d, uint32_t slot);
/* Writes a reply without blocking (reply.h). Returns 0, or -1 when it was dropped (the client
 * does not read: counted, the client stays) or the connection broke (the client is closed
 * once the input it sent has been handled). */
int clients_reply(daemon_t *d, uint32_t slot, const uint8_t *reply, size_t len);
/* Exit, before the last frame: what every client has sent is handled and answered (a STOP
 * already in a socket counts), within max_us for all of them together. */
void clients_drain_all(daemon_t *d, uint64_t max_us);
/* Exit: closes every client (the core is not told any more). */
void clients_close_all(daemon_t *d, const char *why);

#endif
