/* The stop port: one core slot per TCP connection (client.h), replies written without waiting.
 *
 * PROTOCOL.md 2: a new connection is never turned away because old ones hold every place: the
 * one quiet longest (no complete frame received) is closed to make room, whether the places
 * run out or the descriptors do (a spare descriptor is freed for the accept). Every complete
 * frame received is handled, in order, before a connection is closed for any reason, so a STOP
 * that has arrived is never lost. That drain is spread over loop rounds: a piece of at most
 * TCP_RETIRE_STEP_US per round, one eviction begun per round, the other clients served between
 * the pieces, so a STOP on another connection never waits behind it. A client that does not
 * read its replies is not closed for that (reply.h). Dead peers (a Wi-Fi drop that lost the
 * FIN) are found by TCP keepalive and TCP_USER_TIMEOUT within a few seconds. */
#ifndef ESTOPD_TCP_H
#define ESTOPD_TCP_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

#include "client.h"

/* The drain before a close gets this long per loop round (issue 25 item 4). */
#define TCP_RETIRE_STEP_US 2000u

typedef struct {
    int listen_fd;
    int epfd;
    uint64_t listen_tag;      /* epoll tags: the listener, and client slot i at client_tag0+i */
    uint64_t client_tag0;
    client_t clients[ESTOP_MAX_SLOTS];
    client_ctx_t rx;          /* the way to the unit (client.h) */
    uint64_t accept_paused_until; /* listener unwatched until then (ENOBUFS...), 0: watched */
    uint32_t accept_failures;     /* pauses in the current episode */
    int pending_fd;               /* accepted, waiting for the slot being emptied; -1: none */
    struct sockaddr_in pending_peer;
    int spare_fd;                 /* /dev/null, closed to accept at the descriptor limit */
    uint8_t spare_short;          /* the spare was spent and no descriptor came back yet */
    uint8_t spare_retry;          /* a descriptor may have come back: try to reopen it */
    uint8_t listen_watched;       /* the listener is in the epoll set for EPOLLIN */
    uint32_t evictions;           /* evictions begun this loop round */
} tcp_t;

/* Every slot free; the caller sets the other fields. */
void tcp_init(tcp_t *t);
/* Opens the spare descriptor: call after every other descriptor of the start-up. */
void tcp_spare_open(tcp_t *t);
/* A new loop round: one more eviction may begin; a connection waiting for room gets it. */
void tcp_round(tcp_t *t);
/* The listening socket is readable: accept (making room when every place is taken). */
void tcp_accept(tcp_t *t);
/* Host time at which the stop port needs the loop: a paused listener to watch again, or room
 * to make for a waiting connection (at once); 0: none. */
uint64_t tcp_next_wakeup(const tcp_t *t);
/* Every round: resumes a paused listener when its time has come, writes the rest of replies. */
void tcp_service(tcp_t *t, uint64_t now);
/* The client in slot is readable or hung up. */
void tcp_event(tcp_t *t, uint32_t slot);
/* Exit, before the last frame: the connections waiting in the backlog are accepted, and what
 * every client has sent is handled and answered (a STOP already in a socket counts), the
 * clients in turns, within max_us for all of them together. */
void tcp_drain_all(tcp_t *t, uint64_t max_us);
/* Exit: closes every client (the core is not told any more). */
void tcp_close_all(tcp_t *t, const char *why);

#endif
