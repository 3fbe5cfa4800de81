/* estopd event log on stderr: one line per event, text or JSON (docs/DESIGN.md).
 * Lines go through an output queue (outq.h), so a stderr nobody reads never holds up the loop.
 * Events a peer can provoke at will (connections) are rate-limited per class; state changes
 * and faults never are. Lost and suppressed lines are counted and reported once a second. */
#ifndef ESTOPD_LOG_H
#define ESTOPD_LOG_H

#include <stddef.h>
#include <stdint.h>

#include "outq.h"

typedef struct {
    const char *key;
    const char *str;   /* string value (used when is_num is 0) */
    int64_t num;       /* numeric value (used when is_num is not 0) */
    uint8_t is_num;    /* 1: an integer; 2: microseconds shown as milliseconds (0.5, 200) */
    uint8_t json_only; /* left out of text lines (already shown in the head) */
} log_kv_t;

#define KV_STR(k, v) { (k), (v), 0, 0u, 0u }
#define KV_NUM(k, v) { (k), NULL, (int64_t)(v), 1u, 0u }
#define KV_MS(k, us) { (k), NULL, (int64_t)(us), 2u, 0u }
#define KV_JSTR(k, v) { (k), (v), 0, 0u, 1u }

/* Classes of events a peer can provoke as often as it likes: each class may write a burst of
 * LOG_BURST lines, then LOG_RATE lines a second; the rest are counted as suppressed. */
typedef enum {
    LOG_CLASS_CLIENT = 0, /* client_open, client_close, client_evict, bad_crc */
    LOG_CLASS_NET,        /* udp_error and other per-packet trouble */
    LOG_CLASS_COUNT
} log_class_t;

/* Starts the log's writer thread on stderr. Before it, lines go straight to stderr. */
int log_start(int json, char *err, size_t errlen);
/* Another output whose lost lines the log reports (the can-log), under the name stream. */
void log_watch(const char *stream, const outq_t *q);
/* One event at monotonic time t_us. head is a text-only token after the event name
 * (e.g. "ARMED->STOPPED"), or NULL. Never suppressed. */
void log_event(uint64_t t_us, const char *event, const char *head, const log_kv_t *kv, size_t n);
/* The same, for an event of a rate-limited class. */
void log_limited(log_class_t cls, uint64_t t_us, const char *event, const log_kv_t *kv, size_t n);
/* Once a second at most: reports suppressed and lost lines (events log_suppressed and
 * output_dropped). Call from the loop; cheap when there is nothing to say. */
void log_housekeeping(uint64_t now_us);
/* Reports suppressed and lost lines now, whatever the time since the last report. */
void log_report(uint64_t now_us);
/* Shutdown: waits at most max_us for stderr to take what is queued. */
void log_flush(uint64_t max_us);

/* Names used in log lines (docs/DESIGN.md), independent of the core's own name tables. */
const char *log_state_name(uint32_t state);
const char *log_reason_name(uint32_t reason);
/* A short name for an errno value ("ENOBUFS"), or "E<number>". buf holds the fallback. */
const char *log_errno_name(int err, char *buf, size_t n);

#endif
