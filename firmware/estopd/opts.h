/* estopd command line (PROTOCOL.md 5). */
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
    estop_config_t cfg;
} opts_t;

typedef enum {
    OPTS_RUN = 0,
    OPTS_EXIT_OK = 1,  /* --help or --version was printed */
    OPTS_ERROR = 2     /* err holds a one-line message */
} opts_result_t;

opts_result_t opts_parse(int argc, char **argv, opts_t *o, char *err, size_t errlen);

#endif
