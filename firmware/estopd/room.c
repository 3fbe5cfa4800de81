#include "room.h"

#include <sys/ioctl.h>

int room_free_slot(const tcp_t *t)
{
    int i;
    for (i = 0; i < (int)ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd < 0) {
            return i;
        }
    }
    return -1;
}

int room_unread(const client_t *c)
{
    int n = 0;
    return ioctl(c->fd, FIONREAD, &n) == 0 ? n : 0;
}

/* Whether c goes before q (its input waiting: n, q's: q_unread) when room is made. */
static int quieter(const client_t *c, int n, const client_t *q, int q_unread)
{
    if (c->quiet_since_us != q->quiet_since_us) {
        return c->quiet_since_us < q->quiet_since_us;
    }
    if (n != q_unread) {
        return n > q_unread;
    }
    return c->framed == 0u && q->framed != 0u;
}

/* The client quiet longest among those served (-1: none): no complete frame for the most
 * rounds. Among clients as quiet as each other (every client with input is served each round)
 * the one with the most input waiting: a well-behaved client has a request or none waiting, a
 * flood of requests has many (and its drain is spread over rounds: tcp.h). Then one that has
 * never sent a frame: one accepted in the round in which another's frame was handled came out
 * of the same wait, so it may well have connected first, and it has shown no frame since. */
int room_quietest(const tcp_t *t)
{
    int i;
    int q = -1;
    int q_unread = 0;
    for (i = 0; i < (int)ESTOP_MAX_SLOTS; i++) {
        const client_t *c = &t->clients[i];
        int n;
        if (c->fd < 0 || c->retiring != NULL) {
            continue;
        }
        n = room_unread(c);
        if (q < 0 || quieter(c, n, &t->clients[q], q_unread)) {
            q = i;
            q_unread = n;
        }
    }
    return q;
}

uint32_t room_count(const tcp_t *t, int retiring)
{
    uint32_t i;
    uint32_t n = 0u;
    for (i = 0; i < ESTOP_MAX_SLOTS; i++) {
        if (t->clients[i].fd >= 0 && (t->clients[i].retiring != NULL) == (retiring != 0)) {
            n++;
        }
    }
    return n;
}

/* Room must be made: a connection waits for a place, or the spare descriptor was spent and
 * can come back only from a client (never the only one: it would make room for nobody). */
int room_needed(const tcp_t *t)
{
    return t->pending_fd >= 0 ||
           (t->spare_fd < 0 && t->spare_short && room_count(t, 0) >= 2u);
}

/* Nothing accepted now could be placed until room is made: a connection waits for its place,
 * or the spare is spent while a client is being emptied or is due to be (either gives a
 * descriptor back). Without that prospect accept() fails and pauses (pause_accept). */
int room_awaited(const tcp_t *t)
{
    return t->pending_fd >= 0 ||
           (t->spare_fd < 0 && t->spare_short &&
            (room_count(t, 1) != 0u || room_count(t, 0) >= 2u));
}
