/* estopd: the emergency-stop unit on a Linux host (PROTOCOL.md 5, docs/DESIGN.md). */
#include <stdio.h>

#include "daemon.h"
#include "loop.h"
#include "opts.h"
#include "setup.h"

/* The whole daemon, static: nothing is allocated after (or during) start-up. */
static daemon_t daemon_state;

int main(int argc, char **argv)
{
    char err[256];

    switch (opts_parse(argc, argv, &daemon_state.opt, err, sizeof err)) {
    case OPTS_EXIT_OK:
        return 0;
    case OPTS_ERROR:
        (void)fprintf(stderr, "estopd: error: %s\n", err);
        return 2;
    case OPTS_RUN:
    default:
        break;
    }
    if (setup(&daemon_state, err, sizeof err) != 0) {
        (void)fprintf(stderr, "estopd: error: %s\n", err);
        return 1;
    }
    return loop_run(&daemon_state);
}
