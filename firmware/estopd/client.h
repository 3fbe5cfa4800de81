/* One stop-port client: what it sends goes to the unit one frame at a time, its replies go
 * back without waiting (reply.h). Which clients there are, and when one goes, is tcp.c's. */
#ifndef ESTOPD_CLIENT_H
#define ESTOPD_CLIENT_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

#include "apply.h"
#include "reply.h"
#include "unit.h"

#define CLIENT_READ_MAX 256u /* per read: a firehose gets no more than its share of a round */

typedef struct {
    int fd;                   /* -1: slot free */
    struct sockaddr_in peer;
    uint64_t quiet_since_us;  /* the round it was accepted or sent its latest complete frame
                                 (client_ctx_t.round_us): who makes room */
    uint8_t framed;           /* it has sent a complete frame: of clients as quiet as each
                                 other by the round, one that never has goes first (room.c) */
    reply_state_t reply;      /* replies not read: dropped and counted, never waited for */
    const char *retiring;     /* NULL: served; else why it goes once its input is handled */
    int retire_err;           /* the errno that broke it, which the close names instead */
    size_t drained;           /* bytes read since it began to go */
    size_t drain_max;         /* what its going reads at most (client_drain_bound) */
    uint64_t drained_round;   /* the round (client_ctx_t.round_us) of its latest drain piece */
} client_t;

/* Called before every input handed to the unit: drains what arrived before it and acts on a
 * due deadline (the loop's round); returns the host time for the input. */
typedef uint64_t (*client_prepare_fn)(void *ctx);

/* The way to the unit, the same for every client. */
typedef struct {
    unit_t *unit;
    const apply_t *apply;
    client_prepare_fn prepare;
    void *prepare_ctx;
    /* The current loop round's start (host time). Quietness is counted in rounds: every
     * client served in a round is as active as any other, whatever its turn in the round. */
    uint64_t round_us;
} client_ctx_t;

typedef enum {
    CLIENT_MORE = 0,  /* bytes were read and handled; more may wait */
    CLIENT_EMPTY,     /* nothing to read now */
    CLIENT_EOF,       /* the peer closed, or the connection broke (*err: its errno, else 0) */
    CLIENT_BROKEN     /* the unit wants it closed (*why: bad_crc, core_error) */
} client_rx_t;

/* Reads what the client sent, CLIENT_READ_MAX bytes at most, and hands it to the unit frame by
 * frame (each after the round's prepare), replies written. *n: bytes read. */
client_rx_t client_read(const client_ctx_t *x, client_t *c, uint32_t slot, size_t *n, int *err,
                         const char **why);
/* How much the drain before a close reads at most (see client.c). */
size_t client_drain_bound(int fd);
/* One rate-limited line of the client class (client_open, client_close, client_evict...). */
void client_log(uint64_t now, const char *event, int slot, const struct sockaddr_in *peer,
                const char *why, uint32_t dropped);

#endif
