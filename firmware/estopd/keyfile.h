/* The key file of PROTOCOL.md 5: 64 hex digits and an optional final newline, nothing else,
 * in a regular file that nobody but its owner (the daemon's user or root) and the daemon's user
 * may read or write: judged by the mode, or by the POSIX ACL where the file has one. */
#ifndef ESTOPD_KEYFILE_H
#define ESTOPD_KEYFILE_H

#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

/* Parses the contents of a key file (len bytes; no NUL needed). Returns 0 with the key in
 * key, or -1 with a one-line reason in err. Pure: no I/O (a fuzz target). */
int keyfile_parse(const char *text, size_t len, uint8_t key[ESTOP_KEY_LEN], char *err,
                  size_t errlen);
/* Judges a file's POSIX ACL (the raw system.posix_acl_access attribute, len bytes): 0 when no
 * entry but the owner's, the daemon's own user's (self_uid) and root's grants any access under
 * the mask, else -1 with a one-line reason in err. Pure: no I/O (a fuzz target). */
int keyfile_acl_check(const unsigned char *acl, size_t len, uint32_t self_uid, char *err,
                      size_t errlen);
/* Opens, checks and parses path. Returns 0, or -1 with a one-line message in err. */
int keyfile_load(const char *path, uint8_t key[ESTOP_KEY_LEN], char *err, size_t errlen);

#endif
