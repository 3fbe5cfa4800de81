/* Who makes room on the stop port (tcp.h): free places, the client quiet longest, and whether
 * room is needed or on its way. Reads the stop port's state and its sockets' queues, changes
 * nothing. */
#ifndef ESTOPD_ROOM_H
#define ESTOPD_ROOM_H

#include <stdint.h>

#include "tcp.h"

/* A free place, -1: none. */
int room_free_slot(const tcp_t *t);
/* Bytes the client has sent that wait to be read (0 when that cannot be told). */
int room_unread(const client_t *c);
/* The client to close to make room: the one quiet longest among those served (-1: none). */
int room_quietest(const tcp_t *t);
/* Clients with a descriptor: those retiring (retiring != 0) or those served. */
uint32_t room_count(const tcp_t *t, int retiring);
/* Room must be made (an eviction): a connection waits for a place, or the spare descriptor is
 * spent and a client can give one back. */
int room_needed(const tcp_t *t);
/* Nothing accepted now could be placed before room is made, and room is on its way. */
int room_awaited(const tcp_t *t);

#endif
