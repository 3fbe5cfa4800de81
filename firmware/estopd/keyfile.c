#include "keyfile.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/xattr.h>
#include <unistd.h>

#define KEY_HEX (2u * ESTOP_KEY_LEN)

/* The kernel's POSIX ACL attribute (linux/posix_acl_xattr.h): a little-endian u32 version 2,
 * then entries of u16 tag, u16 permissions, u32 id. Read raw: no libacl. */
#define ACL_XATTR "system.posix_acl_access"
#define ACL_VERSION 2u
#define ACL_HEADER 4u
#define ACL_ENTRY 8u
#define ACL_MAX_ENTRIES 64u
#define ACL_TAG_USER_OBJ 0x01u
#define ACL_TAG_USER 0x02u
#define ACL_TAG_GROUP_OBJ 0x04u
#define ACL_TAG_GROUP 0x08u
#define ACL_TAG_MASK 0x10u
#define ACL_TAG_OTHER 0x20u
#define ACL_NO_ID 0xffffffffu

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

static uint32_t le16(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8);
}

static uint32_t le32(const unsigned char *p)
{
    return le16(p) | (le16(p + 2) << 16);
}

static void perm_text(uint32_t perm, char out[4])
{
    out[0] = (perm & 4u) != 0u ? 'r' : '-';
    out[1] = (perm & 2u) != 0u ? 'w' : '-';
    out[2] = (perm & 1u) != 0u ? 'x' : '-';
    out[3] = '\0';
}

int keyfile_acl_check(const unsigned char *acl, size_t len, uint32_t self_uid, char *err,
                      size_t errlen)
{
    uint32_t mask = 7u; /* no mask entry: a minimal ACL, nothing to mask */
    size_t i;
    size_t n;
    char perm[4];

    if (len < ACL_HEADER || (len - ACL_HEADER) % ACL_ENTRY != 0u || le32(acl) != ACL_VERSION) {
        (void)snprintf(err, errlen, "its ACL is not one this daemon can read (%zu bytes)", len);
        return -1;
    }
    n = (len - ACL_HEADER) / ACL_ENTRY;
    for (i = 0; i < n; i++) {
        if (le16(acl + ACL_HEADER + i * ACL_ENTRY) == ACL_TAG_MASK) {
            mask = le16(acl + ACL_HEADER + i * ACL_ENTRY + 2u) & 7u;
        }
    }
    /* Whoever an entry names reads with its permissions under the mask (other is never
     * masked). The owner was judged by the caller; the daemon's own user and root (who reads
     * every file anyway) may be named. Anyone else with any access is refused. */
    for (i = 0; i < n; i++) {
        const unsigned char *e = acl + ACL_HEADER + i * ACL_ENTRY;
        uint32_t tag = le16(e);
        uint32_t id = le32(e + 4u);
        uint32_t eff = le16(e + 2u) & 7u;
        const char *who;
        switch (tag) {
        case ACL_TAG_USER_OBJ:
        case ACL_TAG_MASK:
            continue;
        case ACL_TAG_USER:
            if (id == self_uid || id == 0u) {
                continue;
            }
            who = "user";
            eff &= mask;
            break;
        case ACL_TAG_GROUP_OBJ:
            who = "group";
            id = ACL_NO_ID;
            eff &= mask;
            break;
        case ACL_TAG_GROUP:
            who = "group";
            eff &= mask;
            break;
        case ACL_TAG_OTHER:
            who = "other";
            id = ACL_NO_ID;
            break;
        default:
            (void)snprintf(err, errlen, "its ACL has an entry of unknown type 0x%x", (unsigned)tag);
            return -1;
        }
        if (eff != 0u) {
            perm_text(eff, perm);
            if (id == ACL_NO_ID) {
                (void)snprintf(err, errlen, "its ACL lets %s access it (%s::%s)", who, who, perm);
            } else {
                (void)snprintf(err, errlen, "its ACL lets %s %u access it (%s:%u:%s)", who,
                               (unsigned)id, who, (unsigned)id, perm);
            }
            return -1;
        }
    }
    return 0;
}

/* Who besides the owner may access the open file fd: its ACL where it has one (systemd 254+
 * hands a credential root-owned, mode 0400, with an entry for the service's user, and stat
 * shows the ACL's mask as the group bits), else the group and other bits. */
static int judge_access(int fd, const struct stat *st, const char *path, char *err,
                        size_t errlen)
{
    unsigned char acl[ACL_HEADER + ACL_MAX_ENTRIES * ACL_ENTRY];
    char why[160];
    ssize_t n;

    if ((st->st_mode & S_IRWXO) != 0u) {
        (void)snprintf(err, errlen, "--key-file '%s': group or others have access (mode %04o);"
                       " chmod 600 it", path, (unsigned)(st->st_mode & 07777u));
        return -1;
    }
    n = fgetxattr(fd, ACL_XATTR, acl, sizeof acl);
    if (n < 0 && (errno == ENODATA || errno == EOPNOTSUPP)) {
        if ((st->st_mode & S_IRWXG) != 0u) {
            /* Group or others may read or write the key (or run it): refuse, as ssh does. */
            (void)snprintf(err, errlen, "--key-file '%s': group or others have access "
                           "(mode %04o); chmod 600 it", path, (unsigned)(st->st_mode & 07777u));
            return -1;
        }
        return 0;
    }
    if (n < 0) {
        (void)snprintf(err, errlen, "--key-file '%s': cannot read its ACL: %s", path,
                       errno == ERANGE ? "more than 64 entries" : strerror(errno));
        return -1;
    }
    if (keyfile_acl_check(acl, (size_t)n, (uint32_t)geteuid(), why, sizeof why) != 0) {
        (void)snprintf(err, errlen, "--key-file '%s': %s; setfacl -b and chmod 600 it", path,
                       why);
        return -1;
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
    } else if (judge_access(fd, &st, path, err, errlen) != 0) {
        /* err says who else has access */
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
