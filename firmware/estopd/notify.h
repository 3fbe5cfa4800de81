/* The systemd notify protocol (sd_notify(3)), spoken here without libsystemd: READY=1 once the
 * sockets are open and the core runs, STATUS= at every state change, WATCHDOG=1 from the loop
 * while it is healthy, STOPPING=1 at shutdown. Without $NOTIFY_SOCKET everything here is a no-op. */
#ifndef ESTOPD_NOTIFY_H
#define ESTOPD_NOTIFY_H

#include <stddef.h>
#include <stdint.h>
#include <sys/socket.h>
#include <sys/un.h>

typedef struct {
    int fd;                   /* -1: no notify socket */
    struct sockaddr_un addr;
    socklen_t addr_len;
    uint64_t interval_us;     /* between WATCHDOG=1 pings; 0: no watchdog asked for */
    uint64_t last_ping_us;
    uint32_t frames_at_ping;  /* frames the core had produced at the previous ping */
} notify_t;

/* Reads $NOTIFY_SOCKET ("/path" or "@abstract"), $WATCHDOG_USEC and $WATCHDOG_PID. A bad
 * value only disables the protocol (a supervisor that asked for nothing usable gets nothing);
 * returns 0, or -1 with a one-line message in err when the socket cannot be made at all. */
int notify_open(notify_t *n, char *err, size_t errlen);
/* One message; never blocks (a full or vanished supervisor socket drops it). */
void notify_send(const notify_t *n, const char *msg);
/* STATUS= for systemctl status: the state, and the reason while STOPPED (reason NULL). */
void notify_state(const notify_t *n, const char *state, const char *reason);
/* From the loop, every iteration: WATCHDOG=1 once per interval, but only while healthy: the
 * loop is running (this call), the core took its latest call (not fatal) and has produced
 * ESTOP_BRAKE frames since the previous ping. */
void notify_loop(notify_t *n, uint64_t now_us, int fatal, uint32_t frames_out);

#endif
