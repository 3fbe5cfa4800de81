/* The key file of PROTOCOL.md 5: 64 hex digits and an optional final newline, nothing else,
 * in a regular file that neither group nor others may read or write. */
#ifndef ESTOPD_KEYFILE_H
#define ESTOPD_KEYFILE_H

#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

/* Parses the contents of a key file (len bytes; no NUL needed). Returns 0 with the key in
 * key, or -1 with a one-line reason in err. Pure: no I/O (a fuzz target). */
int keyfile_parse(const char *text, size_t len, uint8_t key[ESTOP_KEY_LEN], char *err,
                  size_t errlen);
/* Opens, checks and parses path. Returns 0, or -1 with a one-line message in err. */
int keyfile_load(const char *path, uint8_t key[ESTOP_KEY_LEN], char *err, size_t errlen);

#endif
