/* Stress test of the output ring (firmware/estopd/outq.c): the loop queues lines while the
 * writer thread is finishing a write, over and over, and after every pair waits for the ring
 * to drain. A wake-up lost between the two threads leaves the writer asleep with lines in the
 * ring: the log of the daemon would stop for good. Exit 0: every pair drained; 1: wedged. */
#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

#include "outq.h"

static outq_t q;

static uint64_t now_us(void)
{
    struct timespec ts;
    (void)clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

int main(int argc, char **argv)
{
    static char line[1024];
    char err[128];
    long pairs = argc > 1 ? atol(argv[1]) : 100000L;
    uint32_t rng = 12345u;
    long i;
    int fd = open("/dev/null", O_WRONLY);
    int rc = 0;

    for (i = 0; i < (long)sizeof line; i++) {
        line[i] = (char)('a' + i % 26);
    }
    if (fd < 0 || outq_start(&q, fd, err, sizeof err) != 0) {
        fprintf(stderr, "outq_stress: cannot start: %s\n", err);
        return 2;
    }
    for (i = 0; i < pairs && rc == 0; i++) {
        volatile uint32_t spin;
        uint64_t t0;
        rng = rng * 1103515245u + 12345u;
        (void)outq_put(&q, line, 64u + (rng >> 8) % 900u);
        for (spin = 0; spin < (rng >> 20) % 2000u; spin++) {
        }
        (void)outq_put(&q, line, 64u + (rng >> 4) % 900u);
        t0 = now_us();
        while (__atomic_load_n(&q.tail, __ATOMIC_ACQUIRE) != q.head) {
            if (now_us() - t0 > 2000000u) {
                fprintf(stderr, "outq_stress: writer asleep with %u bytes queued after %ld pairs\n",
                        q.head - q.tail, i + 1);
                rc = 1;
                break;
            }
        }
    }
    if (rc == 0 && outq_lost(&q) != 0u) {
        fprintf(stderr, "outq_stress: %llu lines lost\n", (unsigned long long)outq_lost(&q));
        rc = 1;
    }
    if (rc == 0) {
        printf("outq_stress: %ld pairs, every one drained\n", pairs);
    }
    return rc;
}
