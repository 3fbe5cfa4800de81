#include "outq.h"

#include <errno.h>
#include <limits.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

#define OUTQ_MASK (OUTQ_SIZE - 1u)
#define WRITER_STACK 65536u /* the writer needs little; a small stack keeps --mlock small too */

static uint32_t load_acq(const uint32_t *p)
{
    return __atomic_load_n(p, __ATOMIC_ACQUIRE);
}

static void store_rel(uint32_t *p, uint32_t v)
{
    __atomic_store_n(p, v, __ATOMIC_RELEASE);
}

static uint64_t count_lines(const char *buf, size_t len)
{
    uint64_t n = 0;
    size_t i;
    for (i = 0; i < len; i++) {
        n += (buf[i] == '\n') ? 1u : 0u;
    }
    return n;
}

/* The next write: whole lines from the ring, at most PIPE_BUF bytes, copied into chunk (which
 * also joins a line across the end of the ring). On a pipe a write of at most PIPE_BUF bytes
 * is atomic, so when the log and the can-log share one pipe (estopd 2>&1 | ...) their lines
 * never interleave inside a line. Returns the byte count. */
static uint32_t gather(const outq_t *q, uint32_t tail, uint32_t head, char *chunk)
{
    uint32_t n = 0u;
    uint32_t whole = 0u;
    while (tail + n != head && n < (uint32_t)PIPE_BUF) {
        char c = q->ring[(tail + n) & OUTQ_MASK];
        chunk[n++] = c;
        if (c == '\n') {
            whole = n;
        }
    }
    return whole != 0u ? whole : n; /* no line is longer than PIPE_BUF (outq_put) */
}

/* Writes one chunk. A descriptor someone else made non-blocking is waited for with poll
 * (this is the writer's own thread, waiting is its job). Anything else that fails loses the
 * chunk: the lines are counted, the writer goes on. A file or terminal may take part of a
 * chunk; the rest goes with the next write. */
static void write_chunk(outq_t *q, uint32_t tail, const char *chunk, uint32_t len)
{
    ssize_t n = write(q->fd, chunk, len);

    if (n > 0) {
        store_rel(&q->tail, tail + (uint32_t)n);
    } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
        struct pollfd pfd;
        pfd.fd = q->fd;
        pfd.events = POLLOUT;
        pfd.revents = 0;
        (void)poll(&pfd, 1, 1000);
    } else if (!(n < 0 && errno == EINTR)) {
        __atomic_store_n(&q->last_errno, n < 0 ? errno : EIO, __ATOMIC_RELAXED);
        __atomic_add_fetch(&q->lines_failed, count_lines(chunk, len), __ATOMIC_RELAXED);
        store_rel(&q->tail, tail + len);
    }
}

static void *writer_main(void *arg)
{
    outq_t *q = arg;
    sigset_t all;
    char chunk[PIPE_BUF]; /* one write's worth (the writer's stack is 64 KiB) */

    (void)sigfillset(&all);
    (void)pthread_sigmask(SIG_BLOCK, &all, NULL); /* signals belong to the loop's signalfd */
    for (;;) {
        uint32_t head = load_acq(&q->head);
        uint32_t tail = q->tail;
        if (head == tail) {
            /* Say "asleep" first, then look again (both sequentially consistent, as the loop's
             * store of head and load of the flag): either this look sees the new line, or the
             * loop sees the flag and wakes us. Without it, a line queued while the writer was
             * finishing a write left it asleep with the ring non-empty, for good. */
            __atomic_store_n(&q->asleep, 1, __ATOMIC_SEQ_CST);
            if (__atomic_load_n(&q->head, __ATOMIC_SEQ_CST) == tail) {
                uint64_t v;
                (void)read(q->wake_fd, &v, sizeof v); /* sleeps until the loop queues more */
            }
            __atomic_store_n(&q->asleep, 0, __ATOMIC_SEQ_CST);
        } else {
            write_chunk(q, tail, chunk, gather(q, tail, head, chunk));
        }
    }
    return NULL;
}

int outq_start(outq_t *q, int fd, char *err, size_t errlen)
{
    pthread_attr_t attr;
    struct sched_param sp;
    int rc;

    q->fd = fd;
    /* Every page of the ring now, not as the lines first wrap round it: the resident set is
     * flat from the start (issue 25 item 7: it grew by 88 KiB over two minutes). */
    memset(q->ring, 0, sizeof q->ring);
    q->head = q->tail = 0u;
    q->lines_full = q->lines_failed = 0u;
    q->last_errno = 0;
    q->asleep = 0;
    q->running = 0;
    q->wake_fd = eventfd(0, EFD_CLOEXEC);
    if (q->wake_fd < 0) {
        (void)snprintf(err, errlen, "eventfd: %s", strerror(errno));
        return -1;
    }
    memset(&sp, 0, sizeof sp);
    /* Explicit, ordinary scheduling: under --rt-prio or systemd's CPUSchedulingPolicy the
     * writer must not inherit real-time priority and compete with the loop. */
    rc = pthread_attr_init(&attr);
    if (rc == 0) {
        (void)pthread_attr_setstacksize(&attr, WRITER_STACK);
        (void)pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
        (void)pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
        (void)pthread_attr_setschedparam(&attr, &sp);
        rc = pthread_create(&q->thread, &attr, writer_main, q);
        (void)pthread_attr_destroy(&attr);
    }
    if (rc != 0) {
        (void)snprintf(err, errlen, "cannot start an output thread: %s", strerror(rc));
        (void)close(q->wake_fd);
        q->wake_fd = -1;
        return -1;
    }
    q->running = 1;
    return 0;
}

int outq_put(outq_t *q, const char *line, size_t len)
{
    uint32_t head = q->head;
    uint32_t tail = load_acq(&q->tail);
    uint32_t used = head - tail;
    uint32_t i;

    if (!q->running || len == 0u || len > (size_t)PIPE_BUF ||
        len > (size_t)(OUTQ_SIZE - used)) {
        if (q->running && len > 0u) {
            q->lines_full++;
        }
        return -1;
    }
    for (i = 0; i < (uint32_t)len; i++) {
        q->ring[(head + i) & OUTQ_MASK] = line[i];
    }
    __atomic_store_n(&q->head, head + (uint32_t)len, __ATOMIC_SEQ_CST);
    if (__atomic_load_n(&q->asleep, __ATOMIC_SEQ_CST) != 0) {
        /* An eventfd counts: a wake-up sent just before the writer reads it is not lost, and
         * one too many only costs the writer a look at an empty ring. */
        uint64_t one = 1u;
        (void)write(q->wake_fd, &one, sizeof one);
    }
    return 0;
}

uint64_t outq_lost(const outq_t *q)
{
    return q->lines_full + __atomic_load_n(&q->lines_failed, __ATOMIC_RELAXED);
}

int outq_last_errno(const outq_t *q)
{
    return __atomic_load_n(&q->last_errno, __ATOMIC_RELAXED);
}

void outq_flush(outq_t *q, uint64_t max_us)
{
    uint64_t waited = 0u;
    const struct timespec step = { 0, 1000000L }; /* 1 ms */

    while (q->running && load_acq(&q->tail) != q->head && waited < max_us) {
        (void)nanosleep(&step, NULL);
        waited += 1000u;
    }
}
