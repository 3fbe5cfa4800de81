#include "reply.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>

void reply_reset(reply_state_t *r)
{
    memset(r, 0, sizeof *r);
}

/* send() that never blocks or raises SIGPIPE: bytes written, 0 when there is no room, -1 on a
 * broken connection (errno set). */
static ssize_t write_some(int fd, const uint8_t *buf, size_t len)
{
    ssize_t n;
    do {
        n = send(fd, buf, len, MSG_NOSIGNAL | MSG_DONTWAIT);
    } while (n < 0 && errno == EINTR);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == ENOBUFS)) {
        n = 0;
    }
    return n;
}

int reply_flush(reply_state_t *r, int fd)
{
    if (r->rest_len > 0u && r->hard_err == 0) {
        ssize_t n = write_some(fd, r->rest, r->rest_len);
        if (n < 0) {
            r->hard_err = errno;
        } else if (n > 0) {
            size_t left = (size_t)r->rest_len - (size_t)n;
            memmove(r->rest, r->rest + n, left);
            r->rest_len = (uint8_t)left;
        }
    }
    return r->rest_len == 0u;
}

reply_result_t reply_send(reply_state_t *r, int fd, const uint8_t *reply, size_t len)
{
    ssize_t n;

    if (r->hard_err != 0) {
        return REPLY_BROKEN;
    }
    if (!reply_flush(r, fd)) {
        /* The end of the previous reply is still waiting: this one would cut into it. */
        if (r->hard_err != 0) {
            return REPLY_BROKEN;
        }
        r->dropped++;
        return REPLY_DROPPED;
    }
    if (len > sizeof r->rest) {
        r->dropped++; /* no reply is this long; were it cut, its rest could not be kept */
        return REPLY_DROPPED;
    }
    n = write_some(fd, reply, len);
    if (n < 0) {
        r->hard_err = errno;
        return REPLY_BROKEN;
    }
    if (n == 0) {
        r->dropped++;
        return REPLY_DROPPED;
    }
    /* Part of it went: the rest must follow before anything else, or the stream loses its
     * framing. */
    r->rest_len = (uint8_t)(len - (size_t)n);
    memcpy(r->rest, reply + n, r->rest_len);
    return REPLY_SENT;
}
