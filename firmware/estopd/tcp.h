/* The stop port: one core slot per TCP connection, replies written without waiting.
 *
 * PROTOCOL.md 2: a new connection is never turned away because old ones hold every place: the
 * one quiet longest (no complete frame received) is closed to make room. Every complete frame
 * received is handled, in order, before a connection is closed for any reason, so a STOP that
 * has arrived is never lost. A client that does not read its replies is not closed for that
 * (reply.h). Dead peers (a Wi-Fi drop that lost the FIN) are found by TCP keepalive and
 * TCP_USER_TIMEOUT within a few seconds. */
#ifndef ESTOPD_TCP_H
#define ESTOPD_TCP_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

#include "apply.h"
#include "reply.h"
#include "unit.h"

typedef struct {
    int fd;                   /* -1: slot free */
    struct sockaddr_in peer;
    uint64_t quiet_since_us;  /* accepted, or its latest complete frame: who makes room */
    reply_state_t reply;      /* replies not read: dropped and counted, never waited for */
} client_t;

/* Called before every input handed to the unit: drains what arrived before it and acts on a
 * due deadline (the loop's round); returns the host time for the input. */
typedef uint64_t (*tcp_prepare_fn)(void *ctx);

typedef struct {
    int listen_fd;
    int epfd;
    uint64_t listen_tag;      /* epoll tags: the listener, and client slot i at client_tag0+i */
    uint64_t client_tag0;
    client_t clients[ESTOP_MAX_SLOTS];
    uint64_t accept_paused_until; /* listener unwatched until then (EMFILE...), 0: watched */
    uint32_t accept_failures;     /* pauses in the current episode */
    unit_t *unit;
    const apply_t *apply;
    tcp_prepare_fn prepare;
    void *prepare_ctx;
} tcp_t;

/* Every slot free; the caller sets the other fields. */
void tcp_init(tcp_t *t);
/* The listening socket is readable: accept (making room when every slot is taken). */
void tcp_accept(tcp_t *t);
/* Host time at which a paused listener (EMFILE and friends) is to be watched again, 0: none. */
uint64_t tcp_next_wakeup(const tcp_t *t);
/* Every round: resumes a paused listener when its time has come, writes the rest of replies. */
void tcp_service(tcp_t *t, uint64_t now);
/* The client in slot is readable or hung up. */
void tcp_event(tcp_t *t, uint32_t slot);
/* Writes a reply without blocking (reply.h). Returns 0, or -1 when it was dropped (the client
 * does not read: counted, the client stays) or the connection broke (the client is closed
 * once the input it sent has been handled). */
int tcp_reply(tcp_t *t, uint32_t slot, const uint8_t *reply, size_t len);
/* Exit, before the last frame: what every client has sent is handled and answered (a STOP
 * already in a socket counts), within max_us for all of them together. */
void tcp_drain_all(tcp_t *t, uint64_t max_us);
/* Exit: closes every client (the core is not told any more). */
void tcp_close_all(tcp_t *t, const char *why);

#endif
