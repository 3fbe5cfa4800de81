/* estopd: the emergency-stop unit on a Linux host (PROTOCOL.md 5, docs/DESIGN.md). */
#include <fcntl.h>
#include <stdio.h>
#include <unistd.h>

#include "daemon.h"
#include "loop.h"
#include "opts.h"
#include "setup.h"

/* The whole daemon, static: nothing is allocated after (or during) start-up. */
static daemon_t daemon_state;

/* Started with 0, 1 or 2 closed, the first descriptors the daemon opens (the signalfd, an
 * eventfd, a socket) would take those numbers, and log lines or can-log frames written to
 * "stderr" or "stdout" would go into them: /dev/null holds every closed one first. Returns 0,
 * or -1 when /dev/null cannot be opened (nothing can be said then: stderr may be closed). */
static int hold_std_fds(void)
{
    for (;;) {
        int fd = open("/dev/null", O_RDWR);
        if (fd < 0) {
            return -1;
        }
        if (fd > 2) {
            (void)close(fd);
            return 0;
        }
    }
}

int main(int argc, char **argv)
{
    char err[512];

    if (hold_std_fds() != 0) {
        return 1;
    }

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
    if (daemon_state.opt.check) {
        if (setup_check(&daemon_state, err, sizeof err) != 0) {
            (void)fprintf(stderr, "estopd: error: %s\n", err);
            return 1;
        }
        return 0;
    }
    if (setup(&daemon_state, err, sizeof err) != 0) {
        (void)fprintf(stderr, "estopd: error: %s\n", err);
        return 1;
    }
    return loop_run(&daemon_state);
}
