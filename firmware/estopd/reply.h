/* Replies to a stop-channel client, written without ever waiting (PROTOCOL.md 2, version 3).
 *
 * A client that does not read its replies is not closed for that: a reply that does not fit
 * in its socket is dropped and counted, and what the client sends is still read and handled,
 * so a STOP queued behind any number of unread requests still counts. A reply is never cut:
 * when the kernel takes only part of one, the rest is kept (one reply at most) and written
 * first when there is room again, so the client's stream stays framed. */
#ifndef ESTOPD_REPLY_H
#define ESTOPD_REPLY_H

#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

typedef struct {
    uint8_t rest[ESTOP_REPLY_MAX]; /* the unwritten end of a reply the kernel took in part */
    uint8_t rest_len;
    uint32_t dropped;              /* replies dropped for want of room since the client came */
    int hard_err;                  /* errno of a failed write other than "no room" (the
                                      connection is broken), 0 if none */
} reply_state_t;

typedef enum {
    REPLY_SENT = 0,     /* written whole, or begun with its rest kept for later */
    REPLY_DROPPED = 1,  /* no room: dropped and counted */
    REPLY_BROKEN = 2    /* the connection is broken (hard_err says how) */
} reply_result_t;

void reply_reset(reply_state_t *r);
/* Writes what is left of an earlier reply; returns 1 when nothing is left, else 0. */
int reply_flush(reply_state_t *r, int fd);
/* Writes one whole reply of len bytes (at most ESTOP_REPLY_MAX) without blocking. */
reply_result_t reply_send(reply_state_t *r, int fd, const uint8_t *reply, size_t len);

#endif
