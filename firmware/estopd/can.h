/* SocketCAN output: a raw CAN socket that sends the core's frames, retries a frame the
 * kernel could not take, reports a fault when brake frames stay stuck, and logs CAN
 * controller errors (bus-off, error-passive). */
#ifndef ESTOPD_CAN_H
#define ESTOPD_CAN_H

#include <net/if.h>
#include <stddef.h>
#include <stdint.h>

#include "canlog.h"
#include "estop_core.h"

#define CAN_QUEUE_LEN 4u
#define CAN_RETRY_US 2000u     /* retry a refused frame this soon: several tries per period */
#define CAN_REOPEN_US 100000u  /* look for a vanished interface this often */

typedef struct {
    int fd;                   /* -1 while the interface is gone */
    int epfd;
    uint64_t ep_tag;
    char iface[IF_NAMESIZE];
    canlog_t *log;            /* frames are logged once the kernel took them */
    uint32_t brake_id;
    uint32_t brake_period_us;
    estop_can_frame_t queue[CAN_QUEUE_LEN]; /* refused frames, newest per CAN id */
    size_t n_queue;
    uint64_t retry_at;        /* meaningful while n_queue > 0 */
    uint64_t reopen_at;       /* meaningful while fd < 0 */
    uint64_t stuck_since;     /* a brake frame has been waiting since then */
    uint8_t stuck;
    uint8_t fault_reported;   /* this stuck episode has been reported */
    uint8_t fault_pending;    /* the loop must call estop_fault() */
    const char *fault_cause;
    int tx_err;               /* errno of the current failure episode, 0 while sending works */
    uint32_t tx_failures;     /* failed writes in the current episode */
} can_t;

/* Opens iface (must exist). Returns 0, or -1 with a one-line message in err. */
int can_open(can_t *c, const char *iface, uint32_t brake_id, uint32_t brake_period_us,
             canlog_t *log, int epfd, uint64_t ep_tag, char *err, size_t errlen);
/* Sends f after any waiting frames (brake frames first); queues it when refused. */
void can_send(can_t *c, const estop_can_frame_t *f, uint64_t now_us);
/* Retries waiting frames when due and checks for stuck brake frames. */
void can_service(can_t *c, uint64_t now_us);
/* Host time of the next retry, or 0 when nothing waits. */
uint64_t can_next_wakeup(const can_t *c);
/* The socket is readable or has an error: error frames, interface down/gone. */
void can_on_event(can_t *c, uint32_t events, uint64_t now_us);
/* Takes a pending fault request; returns its cause, or NULL when there is none. */
const char *can_take_fault(can_t *c);
/* Shutdown: keeps retrying waiting frames for at most max_us. */
void can_drain(can_t *c, uint64_t max_us);
void can_close(can_t *c);

#endif
