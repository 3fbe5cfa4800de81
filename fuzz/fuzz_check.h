/* The fuzz targets' one check: a broken invariant names itself and aborts, which libFuzzer
 * reports as a crash and keeps the input. */
#ifndef FUZZ_CHECK_H
#define FUZZ_CHECK_H

#include <stdio.h>
#include <stdlib.h>

#define CHECK(cond, what)                                                                      \
    do {                                                                                       \
        if (!(cond)) {                                                                         \
            fprintf(stderr, "invariant broken: %s (%s:%d)\n", what, __FILE__, __LINE__);       \
            abort();                                                                           \
        }                                                                                      \
    } while (0)

#endif
