/* Line output that can never hold up the event loop (PROTOCOL.md 6).
 *
 * Each output (the event log, the can-log) owns a ring buffer that the loop fills and a writer
 * thread that empties it into the file descriptor with ordinary writes. A reader that stalls (a
 * terminal nobody reads, a full pipe, a stuck disk, a FIFO whose reader went to sleep) stalls
 * only that writer thread; once its ring is full, new lines are dropped and counted, never
 * waited for. The ring is single-producer (the loop) single-consumer (the writer): head, tail
 * and the writer's "asleep" flag are the only shared words, each written by one side. */
#ifndef ESTOPD_OUTQ_H
#define ESTOPD_OUTQ_H

#include <pthread.h>
#include <stddef.h>
#include <stdint.h>

#define OUTQ_SIZE 65536u /* bytes per ring; a power of two */

typedef struct {
    int fd;                    /* where the lines go; -1: nowhere (outq_put drops nothing) */
    int wake_fd;               /* eventfd: the loop tells a sleeping writer there is work */
    int running;               /* the writer thread exists */
    pthread_t thread;
    uint32_t head;             /* bytes queued so far (written by the loop only) */
    uint32_t tail;             /* bytes handed to write() so far (written by the writer only) */
    int asleep;                /* the writer is about to sleep or sleeps on wake_fd (writer) */
    uint64_t lines_full;       /* lines dropped because the ring was full (loop side) */
    uint64_t lines_failed;     /* lines lost to failed writes, EPIPE, ENOSPC... (writer side) */
    int last_errno;            /* of the latest failed write (writer side) */
    char ring[OUTQ_SIZE];
} outq_t;

/* Starts the writer thread for fd (at normal, non-real-time priority, all signals blocked).
 * Returns 0, or -1 with a one-line message in err. */
int outq_start(outq_t *q, int fd, char *err, size_t errlen);
/* Queues one whole line, or drops it when it does not fit. Never blocks. 0 queued, -1 dropped. */
int outq_put(outq_t *q, const char *line, size_t len);
/* Lines lost so far, for either cause. Safe to call from the loop at any time. */
uint64_t outq_lost(const outq_t *q);
/* errno of the latest failed write (0: none yet). */
int outq_last_errno(const outq_t *q);
/* Shutdown: waits at most max_us for the writer to empty the ring; never longer. */
void outq_flush(outq_t *q, uint64_t max_us);

#endif
