#include "keyfile.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define KEY_HEX (2u * ESTOP_KEY_LEN)

static int hex_value(char c)
{
    int v = -1;
    if (c >= '0' && c <= '9') {
        v = c - '0';
    } else if (c >= 'a' && c <= 'f') {
        v = c - 'a' + 10;
    } else if (c >= 'A' && c <= 'F') {
        v = c - 'A' + 10;
    }
    return v;
}

int keyfile_parse(const char *text, size_t len, uint8_t key[ESTOP_KEY_LEN], char *err,
                  size_t errlen)
{
    size_t i;
    if (len == KEY_HEX + 1u && text[KEY_HEX] == '\n') {
        len = KEY_HEX; /* the optional final newline */
    }
    if (len != KEY_HEX) {
        (void)snprintf(err, errlen, "a key file holds 64 hex digits and an optional newline, "
                                    "this one has %zu bytes", len);
        return -1;
    }
    for (i = 0; i < KEY_HEX; i += 2u) {
        int hi = hex_value(text[i]);
        int lo = hex_value(text[i + 1u]);
        if (hi < 0 || lo < 0) {
            (void)snprintf(err, errlen, "not a hex digit at byte %zu of the key file",
                           hi < 0 ? i + 1u : i + 2u);
            explicit_bzero(key, ESTOP_KEY_LEN);
            return -1;
        }
        key[i / 2u] = (uint8_t)((hi << 4) | lo);
    }
    return 0;
}

int keyfile_load(const char *path, uint8_t key[ESTOP_KEY_LEN], char *err, size_t errlen)
{
    char buf[KEY_HEX + 2u]; /* one more than a valid file: a longer one is seen as such */
    char why[128];
    struct stat st;
    ssize_t n;
    int rc = -1;
    int fd = open(path, O_RDONLY | O_CLOEXEC | O_NOCTTY | O_NONBLOCK);

    if (fd < 0) {
        (void)snprintf(err, errlen, "--key-file '%s': %s", path, strerror(errno));
        return -1;
    }
    if (fstat(fd, &st) != 0) {
        (void)snprintf(err, errlen, "--key-file '%s': %s", path, strerror(errno));
    } else if (!S_ISREG(st.st_mode)) {
        (void)snprintf(err, errlen, "--key-file '%s': not a regular file", path);
    } else if (st.st_uid != geteuid() && st.st_uid != 0u) {
        /* Whoever owns the file can change the key (chmod it back, write another): only the
         * daemon's own user and root may. */
        (void)snprintf(err, errlen, "--key-file '%s': owned by uid %u, not by estopd's user "
                       "(uid %u) or root", path, (unsigned)st.st_uid, (unsigned)geteuid());
    } else if ((st.st_mode & (S_IRWXG | S_IRWXO)) != 0u) {
        /* Group or others may read or write the key (or run it): refuse, as ssh does. */
        (void)snprintf(err, errlen, "--key-file '%s': group or others have access (mode %04o);"
                       " chmod 600 it", path, (unsigned)(st.st_mode & 07777u));
    } else {
        do {
            n = read(fd, buf, sizeof buf);
        } while (n < 0 && errno == EINTR);
        if (n < 0) {
            (void)snprintf(err, errlen, "--key-file '%s': %s", path, strerror(errno));
        } else if (keyfile_parse(buf, (size_t)n, key, why, sizeof why) != 0) {
            (void)snprintf(err, errlen, "--key-file '%s': %s", path, why);
        } else {
            rc = 0;
        }
    }
    /* A memset of a buffer never read again is a dead store the compiler may drop. */
    explicit_bzero(buf, sizeof buf);
    (void)close(fd);
    return rc;
}
