/* The loop's wake-ups, sd-event style: each source registers the time it next needs the loop
 * (0: none) and a service the loop runs every round, after the drain, in the order the sources
 * were added. The loop arms its one timer for the earliest time any source asks for. */
#ifndef ESTOPD_WAKE_H
#define ESTOPD_WAKE_H

#include <stdint.h>

#define WAKE_MAX 8u

typedef uint64_t (*wake_next_fn)(const void *ctx);
typedef void (*wake_service_fn)(void *ctx, uint64_t now);

typedef struct {
    struct {
        wake_next_fn next;        /* NULL: never asks for a wake-up of its own */
        wake_service_fn service;  /* NULL: nothing to do each round */
        void *ctx;
    } src[WAKE_MAX];
    uint32_t n;
} wake_t;

/* Returns 0, or -1 when the registry is full (a build error: WAKE_MAX is too small). */
int wake_add(wake_t *w, wake_next_fn next, wake_service_fn service, void *ctx);
/* The earliest time a source asks for, or UINT64_MAX when none asks. */
uint64_t wake_next(const wake_t *w);
/* Runs every source's service at host time now. */
void wake_service(const wake_t *w, uint64_t now);

#endif
