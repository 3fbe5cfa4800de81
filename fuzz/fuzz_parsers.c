/*
 * libFuzzer target of the daemon's parsers of outside input (issue 9): the key file
 * (keyfile_parse), its POSIX ACL (keyfile_acl_check) and the command line (opts_parse).
 *
 * Input: one selector byte, then
 *   - selector 0 mod 4: a key file's contents; byte 1 sets the size of the error buffer;
 *   - selector 2 mod 4: a key file's ACL attribute; bytes 1-4 the daemon's uid, byte 5 the
 *     size of the error buffer;
 *   - selector odd: a command line, arguments separated by NUL bytes (argv[0] is "estopd").
 * Every buffer is a heap copy of its exact size (the sanitizer sees any overrun); getopt's
 * hidden state is reset before every parse (optind = 0: glibc's full re-initialisation), and
 * stdout goes to /dev/null so --help and --version print nowhere. After each parse the
 * results are checked: a key only from exactly 64 hex digits (and an optional newline) that
 * decode to it, an error message always NUL-terminated inside its buffer, a command line that
 * is accepted only with exactly one of --key-file and --no-auth and a configuration the core
 * accepts, and pointers only into the arguments given.
 */
#include <getopt.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "keyfile.h"
#include "opts.h"

#define MAX_ARGS 64

#include "fuzz_check.h"

int LLVMFuzzerInitialize(int *argc, char ***argv);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc;
    (void)argv;
    if (freopen("/dev/null", "w", stdout) == NULL) {
        abort();
    }
    return 0;
}

static int hex_digit(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

static void fuzz_keyfile(const uint8_t *data, size_t size)
{
    size_t errlen = size > 0u ? data[0] % 160u : 0u;
    const uint8_t *text = size > 0u ? data + 1 : data;
    size_t len = size > 0u ? size - 1u : 0u;
    char *copy = malloc(len > 0u ? len : 1u);
    char *err = malloc(errlen > 0u ? errlen : 1u);
    uint8_t key[ESTOP_KEY_LEN];
    int valid = 1;
    int rc;
    if (copy == NULL || err == NULL) {
        abort();
    }
    memcpy(copy, text, len);
    memset(err, 'x', errlen > 0u ? errlen : 1u);
    memset(key, 0xA5, sizeof key);
    rc = keyfile_parse(copy, len, key, err, errlen);
    /* The expectation, computed here independently. */
    if (!(len == 64u || (len == 65u && text[64] == '\n'))) {
        valid = 0;
    }
    for (size_t i = 0; valid && i < 64u; i++) {
        valid = hex_digit((char)text[i]) >= 0;
    }
    CHECK(rc == (valid ? 0 : -1), "keyfile: accepted exactly the valid files");
    if (valid) {
        for (size_t i = 0; i < ESTOP_KEY_LEN; i++) {
            CHECK(key[i] == (uint8_t)((hex_digit((char)text[2 * i]) << 4) |
                                      hex_digit((char)text[2 * i + 1])),
                  "keyfile: key decoded");
        }
    } else if (errlen > 0u) {
        CHECK(memchr(err, '\0', errlen) != NULL, "keyfile: error message terminated");
        CHECK(err[0] != '\0' || errlen == 1u, "keyfile: error message given");
    }
    free(err);
    free(copy);
}

static uint32_t fz_le(const uint8_t *p, size_t n)
{
    uint32_t v = 0;
    while (n-- > 0u) {
        v = (v << 8) | p[n];
    }
    return v;
}

/* An ACL is taken only when, by the kernel's rules (named users and groups and the owning
 * group under the mask, other unmasked), nobody but the owner, self and root has access. */
static void fuzz_acl(const uint8_t *data, size_t size)
{
    uint32_t self = size >= 4u ? fz_le(data, 4u) : 0u;
    size_t errlen = size >= 5u ? data[4] % 160u : 0u;
    size_t len = size >= 5u ? size - 5u : 0u;
    unsigned char *copy = malloc(len > 0u ? len : 1u);
    char *err = malloc(errlen > 0u ? errlen : 1u);
    uint32_t mask = 7u;
    int ok;
    int rc;
    if (copy == NULL || err == NULL) {
        abort();
    }
    if (len > 0u) {
        memcpy(copy, data + 5, len);
    }
    memset(err, 'x', errlen > 0u ? errlen : 1u);
    rc = keyfile_acl_check(copy, len, self, err, errlen);
    ok = len >= 4u && (len - 4u) % 8u == 0u && fz_le(copy, 4u) == 2u;
    for (size_t i = 4u; ok && i < len; i += 8u) {
        if (fz_le(copy + i, 2u) == 0x10u) {
            mask = fz_le(copy + i + 2u, 2u) & 7u;
        }
    }
    for (size_t i = 4u; ok && i < len; i += 8u) {
        uint32_t tag = fz_le(copy + i, 2u);
        uint32_t perm = fz_le(copy + i + 2u, 2u) & 7u;
        uint32_t id = fz_le(copy + i + 4u, 4u);
        if (tag == 0x02u) {
            ok = id == self || id == 0u || (perm & mask) == 0u;
        } else if (tag == 0x04u || tag == 0x08u) {
            ok = (perm & mask) == 0u;
        } else if (tag == 0x20u) {
            ok = perm == 0u;
        } else {
            ok = tag == 0x01u || tag == 0x10u;
        }
    }
    CHECK(rc == (ok ? 0 : -1), "acl: taken exactly when nobody else has access");
    if (!ok && errlen > 0u) {
        CHECK(memchr(err, '\0', errlen) != NULL, "acl: error message terminated");
        CHECK(err[0] != '\0' || errlen == 1u, "acl: error message given");
    }
    free(err);
    free(copy);
}

/* p points into one of the argument strings (or is NULL or the default). */
static int in_args(const char *p, char **args, int n)
{
    if (p == NULL) {
        return 1;
    }
    for (int i = 0; i < n; i++) {
        if (p >= args[i] && p <= args[i] + strlen(args[i])) {
            return 1;
        }
    }
    return 0;
}

static void fuzz_opts(const uint8_t *data, size_t size)
{
    char *args[MAX_ARGS + 1];
    char *argv[MAX_ARGS + 2];
    char err[200];
    opts_t o;
    int n = 0;
    size_t at = 0;
    opts_result_t r;
    /* The arguments: NUL-separated pieces of the input, each in its own exact-size copy. */
    while (at <= size && n < MAX_ARGS) {
        const uint8_t *end = memchr(data + at, '\0', size - at);
        size_t len = end != NULL ? (size_t)(end - (data + at)) : size - at;
        args[n] = malloc(len + 1u);
        if (args[n] == NULL) {
            abort();
        }
        memcpy(args[n], data + at, len);
        args[n][len] = '\0';
        n++;
        at += len + 1u;
    }
    argv[0] = (char *)"estopd";
    for (int i = 0; i < n; i++) {
        argv[i + 1] = args[i];
    }
    argv[n + 1] = NULL;
    memset(err, 'x', sizeof err);
    optind = 0; /* glibc: re-initialise getopt completely (it keeps a pointer into argv) */
    r = opts_parse(n + 1, argv, &o, err, sizeof err);
    CHECK(r == OPTS_RUN || r == OPTS_EXIT_OK || r == OPTS_ERROR, "opts: result");
    if (r == OPTS_ERROR) {
        CHECK(memchr(err, '\0', sizeof err) != NULL && err[0] != '\0', "opts: one-line error");
    } else if (r == OPTS_RUN) {
        estop_config_t cfg = o.cfg;
        cfg.session = 1u;
        /* --check alone may name neither (it checks no key then) */
        CHECK((o.key_file != NULL) != (o.no_auth != 0) ||
              (o.check && o.key_file == NULL && o.no_auth == 0),
              "opts: exactly one of key or no key");
        CHECK(estop_config_check(&cfg) == ESTOP_OK, "opts: a configuration the core accepts");
        CHECK(o.cfg.session == 0u && o.cfg.key_len == 0u, "opts: no session or key from argv");
        CHECK(in_args(o.can_iface, args, n) && in_args(o.can_log, args, n) &&
                  in_args(o.key_file, args, n),
              "opts: pointers into the arguments");
        CHECK(strcmp(o.bind_str, "0.0.0.0") == 0 || in_args(o.bind_str, args, n),
              "opts: bind address");
        CHECK(o.rt_prio >= 0 && o.rt_prio <= 99, "opts: rt priority");
        CHECK(o.can_iface == NULL || (o.can_iface[0] != '\0' && strlen(o.can_iface) < 16u),
              "opts: interface name");
    }
    for (int i = 0; i < n; i++) {
        free(args[i]);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size == 0u) {
        return 0;
    }
    if ((data[0] & 3u) == 0u) {
        fuzz_keyfile(data + 1, size - 1u);
    } else if ((data[0] & 3u) == 2u) {
        fuzz_acl(data + 1, size - 1u);
    } else {
        fuzz_opts(data + 1, size - 1u);
    }
    return 0;
}
