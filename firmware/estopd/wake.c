#include "wake.h"

#include <stddef.h>

int wake_add(wake_t *w, wake_next_fn next, wake_service_fn service, void *ctx)
{
    if (w->n >= WAKE_MAX) {
        return -1;
    }
    w->src[w->n].next = next;
    w->src[w->n].service = service;
    w->src[w->n].ctx = ctx;
    w->n++;
    return 0;
}

uint64_t wake_next(const wake_t *w)
{
    uint64_t wake = UINT64_MAX;
    uint32_t i;
    for (i = 0u; i < w->n; i++) {
        uint64_t t = w->src[i].next != NULL ? w->src[i].next(w->src[i].ctx) : 0u;
        if (t != 0u && t < wake) {
            wake = t;
        }
    }
    return wake;
}

void wake_service(const wake_t *w, uint64_t now)
{
    uint32_t i;
    for (i = 0u; i < w->n; i++) {
        if (w->src[i].service != NULL) {
            w->src[i].service(w->src[i].ctx, now);
        }
    }
}
