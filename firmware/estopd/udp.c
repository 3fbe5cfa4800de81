#include "udp.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>

#include "core_io.h"
#include "log.h"

#define UDP_BATCH 64
/* Larger than any valid packet. MSG_TRUNC reports the real length; a longer datagram is
 * handed over as exactly this many bytes, which is still an invalid length. */
#define UDP_BUF 64u

void udp_readable(daemon_t *d)
{
    uint8_t buf[UDP_BUF];
    int i;

    for (i = 0; i < UDP_BATCH; i++) {
        struct sockaddr_in src;
        socklen_t slen = sizeof src;
        estop_out_t out;
        estop_err_t err;
        uint64_t now;
        size_t len;
        ssize_t n = recvfrom(d->udp_fd, buf, sizeof buf, MSG_TRUNC, (struct sockaddr *)&src,
                             &slen);

        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            if (errno != EAGAIN) {
                char ebuf[16];
                log_kv_t kv[] = { KV_STR("err", log_errno_name(errno, ebuf, sizeof ebuf)) };
                log_limited(LOG_CLASS_NET, d->last_call_us, "udp_error", kv, 1u);
            }
            return;
        }
        len = (size_t)n > sizeof buf ? sizeof buf : (size_t)n;
        now = cio_prepare(d);
        memset(&out, 0, sizeof out);
        err = estop_udp_rx(&d->core, buf, len, (uint32_t)now, &out);
        (void)cio_done(d, err, "udp_rx", &out, now, &src, -1);
    }
}
