/* TCP stop-channel clients: one core slot per connection, replies written without waiting. */
#ifndef ESTOPD_CLIENTS_H
#define ESTOPD_CLIENTS_H

#include <stdint.h>

#include "daemon.h"

void clients_init(daemon_t *d);
/* The listening socket is readable: accept (extra clients are closed at once). */
void clients_accept(daemon_t *d);
/* The client in slot is readable or hung up. */
void clients_event(daemon_t *d, uint32_t slot);
/* Writes a 16-byte reply without blocking. Returns 0, or -1 (caller drops the client). */
int clients_reply(daemon_t *d, uint32_t slot, const uint8_t *reply);
/* Closes slot and tells the core. */
void clients_close(daemon_t *d, uint32_t slot, const char *why);
/* Exit: closes every client (the core is not told any more). */
void clients_close_all(daemon_t *d, const char *why);

#endif
