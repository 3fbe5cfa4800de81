/* estopd command line (docs/PROTOCOL.md section 6). */
#ifndef ESTOPD_OPTS_H
#define ESTOPD_OPTS_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

#include "estop_core.h"

typedef struct {
    const char *can_iface;  /* NULL: no SocketCAN output */
    const char *can_log;    /* NULL: default (stdout without --can, off with --can); "-": stdout */
    uint16_t udp_port;      /* 0: pick a free port */
    uint16_t tcp_port;
    struct in_addr bind;
    const char *bind_str;
    int log_json;
    const char *key_file;   /* --key-file: the unit has a key (loaded at start-up) */
    int no_auth;            /* --no-auth: the unit has none; exactly one of the two is given */
    int rt_prio;            /* --rt-prio N: SCHED_FIFO priority of the loop, 0: unchanged */
    int mlock;              /* --mlock: lock all memory (mlockall) */
    int check;              /* --check: check the set-up as a start would, then exit */
    estop_config_t cfg;     /* session and key are filled in at start-up, not here */
} opts_t;

typedef enum {
    OPTS_RUN = 0,
    OPTS_EXIT_OK = 1,  /* --help or --version was printed */
    OPTS_ERROR = 2     /* err holds a one-line message */
} opts_result_t;

opts_result_t opts_parse(int argc, char **argv, opts_t *o, char *err, size_t errlen);

#endif
