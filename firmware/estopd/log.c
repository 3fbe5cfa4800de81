#include "log.h"

#include <errno.h>
#include <stdio.h>
#include <string.h>

#include "estop_core.h"
#include "outfd.h"

#define LOG_LINE_MAX 1024u

typedef struct {
    char buf[LOG_LINE_MAX];
    size_t len;
} line_t;

static int log_json;

void log_set_json(int json)
{
    log_json = json;
}

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

static void put_num(line_t *l, int64_t v)
{
    char tmp[24];
    (void)snprintf(tmp, sizeof tmp, "%lld", (long long)v);
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
        if (kv[i].is_num) {
            put_num(l, kv[i].num);
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
        if (kv[i].is_num) {
            put_num(l, kv[i].num);
        } else {
            put_json_string(l, kv[i].str != NULL ? kv[i].str : "-");
        }
    }
    if (l->len + 2u > LOG_LINE_MAX) {
        l->len = LOG_LINE_MAX - 2u; /* keep the object closed even when truncated */
    }
    l->buf[l->len++] = '}';
}

void log_event(uint64_t t_us, const char *event, const char *head, const log_kv_t *kv, size_t n)
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
    /* A stderr nobody reads must not stop the unit: the line is dropped instead. */
    (void)outfd_write(2, l.buf, l.len);
    errno = saved;
}

const char *log_state_name(uint32_t state)
{
    switch (state) {
    case ESTOP_STATE_STOPPED: return "STOPPED";
    case ESTOP_STATE_ARMED: return "ARMED";
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
