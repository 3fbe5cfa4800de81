#include "setup.h"

#include <errno.h>
#include <net/if.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sched.h>
#include <sys/epoll.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/random.h>
#include <sys/resource.h>
#include <sys/signalfd.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include "clock.h"
#include "keyfile.h"
#include "log.h"
#include "loop.h"
#include "net.h"

static int fail(const char *what, char *err, size_t n)
{
    (void)snprintf(err, n, "%s: %s", what, strerror(errno));
    return -1;
}

static int watch(daemon_t *d, int fd, uint64_t tag, char *err, size_t n)
{
    struct epoll_event ev;
    memset(&ev, 0, sizeof ev);
    ev.events = EPOLLIN;
    ev.data.u64 = tag;
    return epoll_ctl(d->epfd, EPOLL_CTL_ADD, fd, &ev) == 0 ? 0 : fail("epoll_ctl", err, n);
}

/* SIGTERM/SIGINT/SIGHUP arrive through a signalfd, so they are handled in the loop (and
 * one that comes during start-up waits there). SIGPIPE is ignored: write errors are
 * handled where they happen. */
static int setup_signals(daemon_t *d, char *err, size_t n)
{
    sigset_t set;
    struct sigaction sa;

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = SIG_IGN;
    if (sigemptyset(&sa.sa_mask) != 0 || sigaction(SIGPIPE, &sa, NULL) != 0) {
        return fail("sigaction(SIGPIPE)", err, n);
    }
    if (sigemptyset(&set) != 0 || sigaddset(&set, SIGTERM) != 0 ||
        sigaddset(&set, SIGINT) != 0 || sigaddset(&set, SIGHUP) != 0) {
        return fail("sigset", err, n);
    }
    if (sigprocmask(SIG_BLOCK, &set, NULL) != 0) {
        return fail("sigprocmask", err, n);
    }
    d->sigfd = signalfd(-1, &set, SFD_NONBLOCK | SFD_CLOEXEC);
    if (d->sigfd < 0) {
        return fail("signalfd", err, n);
    }
    return 0;
}

static int setup_fds(daemon_t *d, char *err, size_t n)
{
    d->epfd = epoll_create1(EPOLL_CLOEXEC);
    if (d->epfd < 0) {
        return fail("epoll_create1", err, n);
    }
    d->timerfd = timerfd_create(CLOCK_UNIT, TFD_NONBLOCK | TFD_CLOEXEC);
    if (d->timerfd < 0) {
        return fail("timerfd_create", err, n);
    }
    if (watch(d, d->timerfd, TAG_TIMER, err, n) != 0 || watch(d, d->sigfd, TAG_SIGNAL, err, n) != 0) {
        return -1;
    }
    d->udp.fd = net_udp_open(d->opt.bind, d->opt.udp_port, &d->udp_port, err, n);
    if (d->udp.fd < 0 || udp_setup(&d->udp, err, n) != 0) {
        return -1;
    }
    d->tcp.listen_fd = net_tcp_open(d->opt.bind, d->opt.tcp_port, &d->tcp_port, err, n);
    if (d->tcp.listen_fd < 0) {
        return -1;
    }
    return (watch(d, d->udp.fd, TAG_UDP, err, n) != 0 ||
            watch(d, d->tcp.listen_fd, TAG_TCP, err, n) != 0)
               ? -1
               : 0;
}

/* Without --can the can-log is the output and defaults to stdout. */
static int setup_can(daemon_t *d, char *err, size_t n)
{
    const char *iface = d->opt.can_iface != NULL ? d->opt.can_iface : "estop";
    const char *path = d->opt.can_log;

    if (path == NULL && d->opt.can_iface == NULL) {
        path = "-";
    }
    if (canlog_open(&d->canlog, path, iface, err, n) != 0) {
        return -1;
    }
    if (d->opt.can_iface == NULL) {
        return 0;
    }
    d->can_on = 1;
    return can_open(&d->can, d->opt.can_iface, d->opt.cfg.brake_can_id,
                    d->opt.cfg.brake_period_us, &d->canlog, d->epfd, TAG_CAN, err, n);
}

/* PROTOCOL.md 5: a key from --key-file (or none with --no-auth) and a session drawn from
 * the kernel's cryptographic source at every start, never 0. */
static int setup_auth(daemon_t *d, char *err, size_t n)
{
    estop_config_t *cfg = &d->opt.cfg;
    uint64_t session = 0u;

    cfg->key_len = 0u;
    /* Every tag checked (issue 25): a packet left unchecked could be delivered again later
     * and keep the unit alive; a BLAKE2s block costs this host well under a microsecond. */
    cfg->tag_checks = (uint8_t)ESTOP_TAG_CHECKS_ALL;
    if (d->opt.key_file != NULL) {
        if (keyfile_load(d->opt.key_file, cfg->key, err, n) != 0) {
            return -1;
        }
        cfg->key_len = (uint8_t)ESTOP_KEY_LEN;
    }
    while (session == 0u) {
        /* Blocks only until the kernel's pool is first seeded: a guessable session would let
         * an earlier boot's recording be replayed. */
        ssize_t got = getrandom(&session, sizeof session, 0);
        if (got < 0 && errno != EINTR) {
            return fail("getrandom", err, n);
        }
        if (got != (ssize_t)sizeof session) {
            session = 0u;
        }
    }
    cfg->session = session;
    return 0;
}

/* --rt-prio N: SCHED_FIFO at N for the loop. A process that already runs under SCHED_FIFO at N
 * or higher keeps what it has: the shipped service (deploy/estopd.service.in) sets SCHED_FIFO
 * with CPUSchedulingResetOnFork and gives no capability, and the kernel lets an unprivileged
 * process neither raise its priority nor clear SCHED_RESET_ON_FORK. Otherwise it asks with
 * SCHED_RESET_ON_FORK (children start at normal priority, and an unprivileged process may not
 * ask without it when it already has it). The output threads were started with explicit
 * normal priority, so only the loop gets it. Returns 0, or -1 with the real cause in err. */
static int setup_rt_prio(int prio, char *err, size_t n)
{
    struct sched_param sp;
    struct rlimit rl;
    int policy = sched_getscheduler(0);
    int e;

    memset(&sp, 0, sizeof sp);
    if (policy >= 0 && (policy & ~SCHED_RESET_ON_FORK) == SCHED_FIFO &&
        sched_getparam(0, &sp) == 0 && sp.sched_priority >= prio) {
        return 0;
    }
    memset(&sp, 0, sizeof sp);
    sp.sched_priority = prio;
    if (sched_setscheduler(0, SCHED_FIFO | SCHED_RESET_ON_FORK, &sp) == 0) {
        return 0;
    }
    e = errno;
    if (e == EPERM && getrlimit(RLIMIT_RTPRIO, &rl) == 0) {
        (void)snprintf(err, n, "--rt-prio %d: sched_setscheduler(SCHED_FIFO): %s: needs "
                       "CAP_SYS_NICE, or RLIMIT_RTPRIO >= %d (it is %llu), or starting under "
                       "SCHED_FIFO at %d or higher (systemd: CPUSchedulingPolicy=fifo, "
                       "CPUSchedulingPriority=%d)", prio, strerror(e), prio,
                       (unsigned long long)rl.rlim_cur, prio, prio);
    } else {
        (void)snprintf(err, n, "--rt-prio %d: sched_setscheduler(SCHED_FIFO): %s", prio,
                       strerror(e));
    }
    return -1;
}

/* --mlock: every page locked before the key is read, so that neither the key on its way (a
 * stack buffer) nor the MAC state is ever in a page the kernel could have swapped out. */
static int setup_mlock(const daemon_t *d, char *err, size_t n)
{
    if (d->opt.mlock && mlockall(MCL_CURRENT | MCL_FUTURE) != 0) {
        return fail("--mlock: mlockall (needs CAP_IPC_LOCK or a high RLIMIT_MEMLOCK)", err, n);
    }
    return 0;
}

/* --rt-prio, for hosts without systemd's CPUSchedulingPolicy= and friends. */
static int setup_realtime(daemon_t *d, char *err, size_t n)
{
    return d->opt.rt_prio > 0 ? setup_rt_prio(d->opt.rt_prio, err, n) : 0;
}

int setup_check(daemon_t *d, char *err, size_t errlen)
{
    uint8_t key[ESTOP_KEY_LEN];
    int rc = 0;

    /* As at start: no core dump of a process that holds the key. */
    if (prctl(PR_SET_DUMPABLE, 0L, 0L, 0L, 0L) != 0) {
        return fail("prctl(PR_SET_DUMPABLE)", err, errlen);
    }
    if (d->opt.key_file != NULL) {
        rc = keyfile_load(d->opt.key_file, key, err, errlen);
        explicit_bzero(key, sizeof key);
    }
    if (rc == 0) {
        rc = setup_realtime(d, err, errlen);
    }
    if (rc == 0 && d->opt.can_iface != NULL && if_nametoindex(d->opt.can_iface) == 0u) {
        (void)snprintf(err, errlen, "no CAN interface '%s': %s", d->opt.can_iface,
                       strerror(errno));
        rc = -1;
    }
    return rc;
}

/* The real-time priority the loop (this thread) runs at, whoever set it: --rt-prio, or
 * systemd's CPUSchedulingPolicy= before estopd started (which --rt-prio then keeps or which
 * runs without it); 0 for a normal policy. */
static int loop_rt_prio(void)
{
    struct sched_param sp;
    int policy = sched_getscheduler(0);

    memset(&sp, 0, sizeof sp);
    if (policy < 0 || sched_getparam(0, &sp) != 0) {
        return 0;
    }
    policy &= ~SCHED_RESET_ON_FORK;
    return policy == SCHED_FIFO || policy == SCHED_RR ? sp.sched_priority : 0;
}

static void log_start_line(const daemon_t *d)
{
    char udp[48];
    char tcp[48];
    char stop_id[16];
    char session[24];
    const char *can_log = d->opt.can_log != NULL ? d->opt.can_log
                          : d->opt.can_iface == NULL ? "-" : "off";

    (void)snprintf(udp, sizeof udp, "%s:%u", d->opt.bind_str, (unsigned)d->udp_port);
    (void)snprintf(tcp, sizeof tcp, "%s:%u", d->opt.bind_str, (unsigned)d->tcp_port);
    (void)snprintf(stop_id, sizeof stop_id, "0x%08X", (unsigned)d->opt.cfg.stop_id);
    /* The session is no secret: every reply carries it. */
    (void)snprintf(session, sizeof session, "0x%016llX", (unsigned long long)d->opt.cfg.session);
    {
        log_kv_t kv[] = {
            KV_STR("udp", udp),
            KV_STR("tcp", tcp),
            KV_STR("can", d->opt.can_iface != NULL ? d->opt.can_iface : "-"),
            KV_STR("can_log", can_log),
            KV_MS("timeout_ms", d->opt.cfg.timeout_us),
            KV_MS("slow_ms", d->opt.cfg.slow_us),
            KV_NUM("slow_level", d->opt.cfg.slow_level),
            KV_MS("warn_ms", d->opt.cfg.warn_us),
            KV_STR("stop_id", stop_id),
            KV_STR("auth", d->opt.cfg.key_len != 0u ? "key" : "none"),
            KV_STR("session", session),
            KV_NUM("udp_rcvbuf", d->udp.rcvbuf),
            KV_NUM("rt_prio", loop_rt_prio()),
            KV_NUM("mlock", d->opt.mlock),
            KV_NUM("pid", getpid()),
            KV_NUM("version_major", ESTOP_VERSION_MAJOR),
            KV_NUM("version_minor", ESTOP_VERSION_MINOR),
        };
        log_event(clock_unit_us(), "start", NULL, kv, sizeof kv / sizeof kv[0]);
    }
    if (d->udp.rcvbuf < d->udp.rcvbuf_wanted) {
        /* Without CAP_NET_ADMIN the buffer stops at net.core.rmem_max (README: receive
         * buffer). */
        log_kv_t kv[] = {
            KV_NUM("bytes", d->udp.rcvbuf),
            KV_NUM("wanted", d->udp.rcvbuf_wanted),
            KV_STR("hint", "net.core.rmem_max"),
        };
        log_event(clock_unit_us(), "udp_rcvbuf_small", NULL, kv, 3u);
    }
}

int setup(daemon_t *d, char *err, size_t errlen)
{
    int rc;

    /* The core's MAC state is as good as the key: no core dump, and no process of our own
     * user may ptrace us or read our memory (/proc/PID/mem) for it. */
    if (prctl(PR_SET_DUMPABLE, 0L, 0L, 0L, 0L) != 0) {
        return fail("prctl(PR_SET_DUMPABLE)", err, errlen);
    }

    d->epfd = d->timerfd = d->sigfd = d->udp.fd = d->tcp.listen_fd = -1;
    d->canlog.fd = -1;
    d->can.fd = -1;
    tcp_init(&d->tcp);
    /* Signals are blocked first, so the output threads inherit the mask and leave them to
     * the loop's signalfd. */
    d->notify.fd = -1;
    if (setup_signals(d, err, errlen) != 0 || log_start(d->opt.log_json, err, errlen) != 0 ||
        notify_open(&d->notify, err, errlen) != 0 || setup_mlock(d, err, errlen) != 0 ||
        setup_auth(d, err, errlen) != 0 || setup_realtime(d, err, errlen) != 0 ||
        setup_fds(d, err, errlen) != 0 || setup_can(d, err, errlen) != 0 ||
        loop_init(d, err, errlen) != 0) {
        return -1;
    }
    tcp_spare_open(&d->tcp); /* last: every descriptor the daemon needs comes first */
    /* The ports go out before the first frame: tests and supervisors read them here. */
    log_start_line(d);
    rc = loop_boot(d);
    /* The core keeps only the state after the key block; no other copy of the key stays. */
    explicit_bzero(d->opt.cfg.key, sizeof d->opt.cfg.key);
    if (rc != 0) {
        (void)snprintf(err, errlen, "the core failed to start");
        return -1;
    }
    notify_send(&d->notify, "READY=1\nSTATUS=watching: STOPPED (boot)");
    return 0;
}
