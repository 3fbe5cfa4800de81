#include "log.h"

#include <errno.h>
#include <stdio.h>
#include <string.h>

#include <unistd.h>

#include "estop_core.h"

#define LOG_LINE_MAX 1024u
#define LOG_BURST 40u
#define LOG_RATE 20u               /* lines a second, per class, after the burst */
#define REPORT_EVERY_US 1000000u
#define WATCH_MAX 2u

typedef struct {
    char buf[LOG_LINE_MAX];
    size_t len;
} line_t;

typedef struct {
    uint64_t tokens_us;   /* the bucket, in microseconds of credit (1 line = 1e6/LOG_RATE) */
    uint64_t last_us;
    uint64_t suppressed;  /* lines not written since the last report */
} bucket_t;

typedef struct {
    const char *stream;
    const outq_t *q;
    uint64_t reported;    /* lost lines already reported */
} watch_t;

/* The log is one per process and shared by every part of the daemon. */
static int log_json;
static outq_t log_q;
static bucket_t buckets[LOG_CLASS_COUNT];
static watch_t watches[WATCH_MAX + 1u]; /* [0] is stderr itself */
static size_t n_watches;
static uint64_t last_report_us;
static const char *const class_names[LOG_CLASS_COUNT] = { "client", "net" };

/* Appends raw text; truncates silently (one byte is always kept for the newline). */
static void put(line_t *l, const char *s)
{
    while (*s != '\0' && l->len + 1u < LOG_LINE_MAX) {
        l->buf[l->len++] = *s++;
    }
}

static void put_char(line_t *l, char c)
{
    if (l->len + 1u < LOG_LINE_MAX) {
        l->buf[l->len++] = c;
    }
}

/* Text values never contain spaces or control bytes, so a line splits on spaces. */
static void put_text_value(line_t *l, const char *s)
{
    for (; *s != '\0'; s++) {
        unsigned char c = (unsigned char)*s;
        put_char(l, (c <= 0x20u || c >= 0x7Fu) ? '?' : (char)c);
    }
}

/* JSON string body; bytes outside printable ASCII become '?' so the line stays valid UTF-8. */
static void put_json_string(line_t *l, const char *s)
{
    put_char(l, '"');
    for (; *s != '\0'; s++) {
        unsigned char c = (unsigned char)*s;
        if (c == '"' || c == '\\') {
            put_char(l, '\\');
            put_char(l, (char)c);
        } else {
            put_char(l, (c < 0x20u || c >= 0x7Fu) ? '?' : (char)c);
        }
    }
    put_char(l, '"');
}

static void put_num(line_t *l, int64_t v, uint8_t kind)
{
    char tmp[32];
    if (kind == 2u && v >= 0 && v % 1000 != 0) {
        /* microseconds as milliseconds without losing the fraction: 500 us is 0.5 ms */
        int len = snprintf(tmp, sizeof tmp, "%lld.%03lld", (long long)(v / 1000),
                           (long long)(v % 1000));
        while (len > 0 && tmp[len - 1] == '0') {
            tmp[--len] = '\0';
        }
    } else {
        (void)snprintf(tmp, sizeof tmp, "%lld", (long long)(kind == 2u ? v / 1000 : v));
    }
    put(l, tmp);
}

static void put_time(line_t *l, uint64_t t_us)
{
    char tmp[32];
    (void)snprintf(tmp, sizeof tmp, "%llu.%06u", (unsigned long long)(t_us / 1000000u),
                   (unsigned)(t_us % 1000000u));
    put(l, tmp);
}

static void build_text(line_t *l, uint64_t t_us, const char *event, const char *head,
                       const log_kv_t *kv, size_t n)
{
    size_t i;
    put(l, "estopd ");
    put_time(l, t_us);
    put_char(l, ' ');
    put(l, event);
    if (head != NULL) {
        put_char(l, ' ');
        put_text_value(l, head);
    }
    for (i = 0; i < n; i++) {
        if (kv[i].json_only) {
            continue;
        }
        put_char(l, ' ');
        put(l, kv[i].key);
        put_char(l, '=');
        if (kv[i].is_num == 3u) {
            put_text_value(l, kv[i].str);
        } else if (kv[i].is_num) {
            put_num(l, kv[i].num, kv[i].is_num);
        } else {
            put_text_value(l, kv[i].str != NULL ? kv[i].str : "-");
        }
    }
}

static void build_json(line_t *l, uint64_t t_us, const char *event, const log_kv_t *kv, size_t n)
{
    size_t i;
    put(l, "{\"t_mono\":");
    put_time(l, t_us);
    put(l, ",\"event\":");
    put_json_string(l, event);
    for (i = 0; i < n; i++) {
        put_char(l, ',');
        put_json_string(l, kv[i].key);
        put_char(l, ':');
        if (kv[i].is_num == 3u) {
            put_char(l, '[');
            put(l, kv[i].str); /* digits and commas, made by the daemon itself */
            put_char(l, ']');
        } else if (kv[i].is_num) {
            put_num(l, kv[i].num, kv[i].is_num);
        } else {
            put_json_string(l, kv[i].str != NULL ? kv[i].str : "-");
        }
    }
    if (l->len + 2u > LOG_LINE_MAX) {
        l->len = LOG_LINE_MAX - 2u; /* keep the object closed even when truncated */
    }
    l->buf[l->len++] = '}';
}

static void emit(uint64_t t_us, const char *event, const char *head, const log_kv_t *kv,
                 size_t n)
{
    line_t l;
    int saved = errno;

    l.len = 0;
    if (log_json) {
        build_json(&l, t_us, event, kv, n);
    } else {
        build_text(&l, t_us, event, head, kv, n);
    }
    l.buf[l.len++] = '\n';
    if (log_q.running) {
        (void)outq_put(&log_q, l.buf, l.len); /* a full queue drops the line and counts it */
    } else {
        (void)write(2, l.buf, l.len);         /* start-up, before the writer exists */
    }
    errno = saved;
}

int log_start(int json, char *err, size_t errlen)
{
    log_json = json;
    watches[0].stream = "log";
    watches[0].q = &log_q;
    n_watches = 1u;
    return outq_start(&log_q, 2, err, errlen);
}

void log_watch(const char *stream, const outq_t *q)
{
    if (n_watches <= WATCH_MAX) {
        watches[n_watches].stream = stream;
        watches[n_watches].q = q;
        watches[n_watches].reported = 0u;
        n_watches++;
    }
}

void log_event(uint64_t t_us, const char *event, const char *head, const log_kv_t *kv, size_t n)
{
    emit(t_us, event, head, kv, n);
}

/* Token bucket per class: LOG_BURST lines of credit, refilled at LOG_RATE lines a second. */
static int bucket_take(bucket_t *b, uint64_t now)
{
    const uint64_t line_us = 1000000u / LOG_RATE;
    const uint64_t cap = (uint64_t)LOG_BURST * line_us;
    if (b->last_us == 0u) {
        b->tokens_us = cap;
    } else if (now > b->last_us) {
        b->tokens_us += now - b->last_us;
        if (b->tokens_us > cap) {
            b->tokens_us = cap;
        }
    }
    b->last_us = now;
    if (b->tokens_us < line_us) {
        b->suppressed++;
        return 0;
    }
    b->tokens_us -= line_us;
    return 1;
}

void log_limited(log_class_t cls, uint64_t t_us, const char *event, const log_kv_t *kv, size_t n)
{
    if ((unsigned)cls < LOG_CLASS_COUNT && bucket_take(&buckets[cls], t_us)) {
        emit(t_us, event, NULL, kv, n);
    }
}

void log_report(uint64_t now)
{
    size_t i;
    for (i = 0; i < LOG_CLASS_COUNT; i++) {
        if (buckets[i].suppressed != 0u) {
            log_kv_t kv[] = { KV_STR("class", class_names[i]),
                              KV_NUM("lines", buckets[i].suppressed) };
            buckets[i].suppressed = 0u;
            emit(now, "log_suppressed", NULL, kv, 2u);
        }
    }
    for (i = 0; i < n_watches; i++) {
        uint64_t lost = outq_lost(watches[i].q);
        if (lost != watches[i].reported) {
            char ebuf[16];
            log_kv_t kv[] = {
                KV_STR("stream", watches[i].stream),
                KV_NUM("dropped", lost - watches[i].reported),
                KV_NUM("total", lost),
                KV_STR("err", outq_last_errno(watches[i].q) != 0
                                  ? log_errno_name(outq_last_errno(watches[i].q), ebuf, sizeof ebuf)
                                  : "full"),
            };
            watches[i].reported = lost;
            emit(now, "output_dropped", NULL, kv, 4u);
        }
    }
}

void log_housekeeping(uint64_t now_us)
{
    if (now_us - last_report_us >= REPORT_EVERY_US) {
        last_report_us = now_us;
        log_report(now_us);
    }
}

void log_flush(uint64_t max_us)
{
    outq_flush(&log_q, max_us);
}

const char *log_state_name(uint32_t state)
{
    switch (state) {
    case ESTOP_STATE_STOPPED: return "STOPPED";
    case ESTOP_STATE_ARMED: return "ARMED";
    case ESTOP_STATE_SLOWING: return "SLOWING";
    default: return "?";
    }
}

const char *log_reason_name(uint32_t reason)
{
    switch (reason) {
    case ESTOP_REASON_NONE: return "none";
    case ESTOP_REASON_BOOT: return "boot";
    case ESTOP_REASON_TCP_STOP: return "tcp_stop";
    case ESTOP_REASON_UDP_TIMEOUT: return "udp_timeout";
    case ESTOP_REASON_FAULT: return "fault";
    case ESTOP_REASON_LIFT: return "lift";
    default: return "?";
    }
}

const char *log_errno_name(int err, char *buf, size_t n)
{
    switch (err) {
    case 0: return "0";
    case EAGAIN: return "EAGAIN";
    case ENOBUFS: return "ENOBUFS";
    case ENETDOWN: return "ENETDOWN";
    case ENODEV: return "ENODEV";
    case ENXIO: return "ENXIO";
    case EIO: return "EIO";
    case EINVAL: return "EINVAL";
    case EPIPE: return "EPIPE";
    case ECONNRESET: return "ECONNRESET";
    case ENOMEM: return "ENOMEM";
    case EMFILE: return "EMFILE";
    case ENFILE: return "ENFILE";
    case EACCES: return "EACCES";
    case EPERM: return "EPERM";
    case EADDRINUSE: return "EADDRINUSE";
    case ENETUNREACH: return "ENETUNREACH";
    case EMSGSIZE: return "EMSGSIZE";
    case ETIMEDOUT: return "ETIMEDOUT";
    default:
        (void)snprintf(buf, n, "E%d", err);
        return buf;
    }
}
