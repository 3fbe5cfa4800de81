/* estopd event log on stderr: one line per event, text or JSON (docs/DESIGN.md). */
#ifndef ESTOPD_LOG_H
#define ESTOPD_LOG_H

#include <stddef.h>
#include <stdint.h>

typedef struct {
    const char *key;
    const char *str;   /* string value (used when is_num is 0) */
    int64_t num;       /* numeric value (used when is_num is 1) */
    uint8_t is_num;
    uint8_t json_only; /* left out of text lines (already shown in the head) */
} log_kv_t;

#define KV_STR(k, v) { (k), (v), 0, 0u, 0u }
#define KV_NUM(k, v) { (k), NULL, (int64_t)(v), 1u, 0u }
#define KV_JSTR(k, v) { (k), (v), 0, 0u, 1u }

void log_set_json(int json);
/* One event at monotonic time t_us. head is a text-only token after the event name
 * (e.g. "ARMED->STOPPED"), or NULL. */
void log_event(uint64_t t_us, const char *event, const char *head, const log_kv_t *kv, size_t n);

/* Names used in log lines (docs/DESIGN.md), independent of the core's own name tables. */
const char *log_state_name(uint32_t state);
const char *log_reason_name(uint32_t reason);
/* A short name for an errno value ("ENOBUFS"), or "E<number>". buf holds the fallback. */
const char *log_errno_name(int err, char *buf, size_t n);

#endif
