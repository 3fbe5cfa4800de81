#include "opts.h"

#include <arpa/inet.h>
#include <errno.h>
#include <getopt.h>
#include <net/if.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_CAN = 256,
    OPT_CAN_LOG,
    OPT_UDP_PORT,
    OPT_TCP_PORT,
    OPT_BIND,
    OPT_TIMEOUT_MS,
    OPT_SLOW_MS,
    OPT_SLOW_LEVEL,
    OPT_WARN_MS,
    OPT_STOP_ID,
    OPT_LOG_JSON,
    OPT_KEY_FILE,
    OPT_NO_AUTH,
    OPT_RT_PRIO,
    OPT_MLOCK,
    OPT_CHECK
};

static const struct option long_opts[] = {
    { "channel", required_argument, NULL, OPT_CAN }, /* python-can's name for the bus */
    { "can", required_argument, NULL, OPT_CAN },     /* its older name, unlisted */
    { "can-log", required_argument, NULL, OPT_CAN_LOG },
    { "udp-port", required_argument, NULL, OPT_UDP_PORT },
    { "tcp-port", required_argument, NULL, OPT_TCP_PORT },
    { "bind", required_argument, NULL, OPT_BIND },
    { "timeout-ms", required_argument, NULL, OPT_TIMEOUT_MS },
    { "slow-ms", required_argument, NULL, OPT_SLOW_MS },
    { "slow-level", required_argument, NULL, OPT_SLOW_LEVEL },
    { "warn-ms", required_argument, NULL, OPT_WARN_MS },
    { "stop-id", required_argument, NULL, OPT_STOP_ID },
    { "log-json", no_argument, NULL, OPT_LOG_JSON },
    { "key-file", required_argument, NULL, OPT_KEY_FILE },
    { "no-auth", no_argument, NULL, OPT_NO_AUTH },
    { "rt-prio", required_argument, NULL, OPT_RT_PRIO },
    { "mlock", no_argument, NULL, OPT_MLOCK },
    { "check", no_argument, NULL, OPT_CHECK },
    { "help", no_argument, NULL, 'h' },
    { "version", no_argument, NULL, 'V' },
    { NULL, 0, NULL, 0 }
};

static void usage(void)
{
    (void)printf(
        "usage: estopd (--key-file PATH | --no-auth) [--channel IFACE] [--can-log PATH|-]\n"
        "              [--udp-port 5700] [--tcp-port 5701] [--bind 0.0.0.0]\n"
        "              [--timeout-ms 200] [--slow-ms T] [--slow-level 30] [--warn-ms S/2]\n"
        "              [--stop-id 0xE570E570]\n"
        "              [--rt-prio 1..99] [--mlock] [--log-json] [--check] [--help] [--version]\n"
        "\n"
        "Emergency-stop unit: watches UDP control packets and TCP stop frames and commands\n"
        "the brake on CAN (docs/PROTOCOL.md). No valid control packet for --slow-ms starts a\n"
        "controlled stop (SLOWING, braking at --slow-level percent; 3 packets end it), none\n"
        "for --timeout-ms the emergency stop (latched). --warn-ms raises the link-degraded\n"
        "flag (default: half the slow time, in whole ms). 0 < warn <= slow <= timeout.\n"
        "--key-file: only packets and RELEASEs made with this key (64 hex digits, mode 0600)\n"
        "keep the unit alive or release it; anyone may stop. --no-auth: a unit without a key.\n"
        "Without --channel (a SocketCAN interface), frames go to the can-log (stdout).\n"
        "Port 0 picks a free port; the start event on stderr shows the ports.\n"
        "--rt-prio: SCHED_FIFO for the watchdog loop; --mlock: mlockall, no paging stalls,\n"
        "and the core's MAC state (as good as the key) is never written to swap.\n"
        "--check: check what a start would refuse and no restart mends (the options, the key\n"
        "file, --rt-prio, --mlock, the CAN interface), opening no socket; exit as a start\n"
        "would, silently when all is well (the service's ExecCondition=).\n");
}

/* Strict unsigned number: digits only (no sign, no spaces), optional 0x prefix when
 * hex_ok, no trailing characters, at most max. Returns 0, or -1. */
static int parse_num(const char *s, int hex_ok, unsigned long long max, unsigned long long *v)
{
    int base = 10;
    char *end = NULL;

    if (hex_ok && s[0] == '0' && (s[1] == 'x' || s[1] == 'X')) {
        base = 16;
        s += 2;
        if (s[0] == '0' && (s[1] == 'x' || s[1] == 'X')) {
            return -1; /* strtoull would accept a second prefix */
        }
    }
    if (!((s[0] >= '0' && s[0] <= '9') ||
          (base == 16 && ((s[0] >= 'a' && s[0] <= 'f') || (s[0] >= 'A' && s[0] <= 'F'))))) {
        return -1;
    }
    errno = 0;
    *v = strtoull(s, &end, base);
    if (errno != 0 || end == NULL || *end != '\0' || *v > max) {
        return -1;
    }
    return 0;
}

static int bad_value(const char *name, const char *arg, const char *want, char *err,
                     size_t errlen)
{
    (void)snprintf(err, errlen, "invalid value '%s' for --%s (expected %s)", arg, name, want);
    return -1;
}

static int set_port(const char *name, const char *arg, uint16_t *port, char *err, size_t n)
{
    unsigned long long v;
    if (parse_num(arg, 0, 65535u, &v) != 0) {
        return bad_value(name, arg, "a port number 0..65535", err, n);
    }
    *port = (uint16_t)v;
    return 0;
}

/* Milliseconds in the range the core accepts for a timeout (checked again by the core). */
static int set_ms(const char *name, const char *arg, uint32_t *us, char *err, size_t n)
{
    unsigned long long v;
    if (parse_num(arg, 0, ESTOP_TIMEOUT_MAX_US / 1000u, &v) != 0 || v == 0u) {
        return bad_value(name, arg, "milliseconds 1..60000", err, n);
    }
    *us = (uint32_t)v * 1000u;
    return 0;
}

/* Which times were given: the others default from them once all options are read. */
typedef struct {
    int slow;
    int warn;
} given_t;

static int set_one(int c, const char *arg, opts_t *o, given_t *given, char *err, size_t n)
{
    unsigned long long v;

    switch (c) {
    case OPT_CAN:
        if (arg[0] == '\0' || strlen(arg) >= IF_NAMESIZE || strchr(arg, '/') != NULL) {
            return bad_value("channel", arg, "a network interface name", err, n);
        }
        o->can_iface = arg;
        return 0;
    case OPT_CAN_LOG:
        if (arg[0] == '\0') {
            return bad_value("can-log", arg, "a file path or -", err, n);
        }
        o->can_log = arg;
        return 0;
    case OPT_UDP_PORT:
        return set_port("udp-port", arg, &o->udp_port, err, n);
    case OPT_TCP_PORT:
        return set_port("tcp-port", arg, &o->tcp_port, err, n);
    case OPT_BIND:
        if (inet_pton(AF_INET, arg, &o->bind) != 1) {
            return bad_value("bind", arg, "an IPv4 address like 0.0.0.0", err, n);
        }
        o->bind_str = arg;
        return 0;
    case OPT_TIMEOUT_MS:
        return set_ms("timeout-ms", arg, &o->cfg.timeout_us, err, n);
    case OPT_SLOW_MS:
        given->slow = 1;
        return set_ms("slow-ms", arg, &o->cfg.slow_us, err, n);
    case OPT_SLOW_LEVEL:
        /* Any byte parses; the range 1..99 is the core's to check (config_hint). */
        if (parse_num(arg, 0, 255u, &v) != 0) {
            return bad_value("slow-level", arg, "a percent 1..99", err, n);
        }
        o->cfg.slow_level = (uint8_t)v;
        return 0;
    case OPT_WARN_MS:
        given->warn = 1;
        return set_ms("warn-ms", arg, &o->cfg.warn_us, err, n);
    case OPT_STOP_ID:
        if (parse_num(arg, 1, 0xFFFFFFFFu, &v) != 0) {
            return bad_value("stop-id", arg, "a 32-bit number, e.g. 0xE570E570", err, n);
        }
        o->cfg.stop_id = (uint32_t)v;
        return 0;
    case OPT_LOG_JSON:
        o->log_json = 1;
        return 0;
    case OPT_KEY_FILE:
        if (arg[0] == '\0') {
            return bad_value("key-file", arg, "a file path", err, n);
        }
        o->key_file = arg;
        return 0;
    case OPT_NO_AUTH:
        o->no_auth = 1;
        return 0;
    case OPT_RT_PRIO:
        if (parse_num(arg, 0, 99u, &v) != 0 || v == 0u) {
            return bad_value("rt-prio", arg, "a real-time priority 1..99", err, n);
        }
        o->rt_prio = (int)v;
        return 0;
    case OPT_MLOCK:
        o->mlock = 1;
        return 0;
    case OPT_CHECK:
        o->check = 1;
        return 0;
    default:
        (void)snprintf(err, n, "internal: unhandled option %d", c);
        return -1;
    }
}

static const char *config_hint(estop_err_t e)
{
    switch (e) {
    case ESTOP_ERR_TIMEOUT: return "--timeout-ms must be 1..60000";
    case ESTOP_ERR_SLOW: return "--slow-ms must be 1..--timeout-ms";
    case ESTOP_ERR_WARN: return "--warn-ms must be 1..--slow-ms";
    case ESTOP_ERR_SLOW_LEVEL: return "--slow-level must be 1..99";
    case ESTOP_ERR_STOP_ID: return "--stop-id may not be 0, 1, 2, 3 or 0x32515345";
    default: return "rejected by the core";
    }
}

/* getopt's own error for the option at optind, as one line. */
static void getopt_error(int c, char **argv, char *err, size_t n)
{
    const char *arg = argv[optind - 1];
    if (c == ':') {
        (void)snprintf(err, n, "option '%s' needs a value", arg);
    } else if (optopt != 0 && optopt < 256) {
        (void)snprintf(err, n, "unknown option '-%c'", optopt);
    } else {
        (void)snprintf(err, n, "unknown or ambiguous option '%s'", arg);
    }
}

/* PROTOCOL.md 3: W defaults to half the slow time, rounded down to a whole millisecond; where
 * that is 0 (S under 2 ms), 1 ms or S if shorter, as src/estop/core.py default_warn_us. */
static uint32_t default_warn_us(uint32_t slow_us)
{
    uint32_t half = slow_us / 2u / 1000u * 1000u;
    if (half > 0u) {
        return half;
    }
    return slow_us < 1000u ? slow_us : 1000u;
}

opts_result_t opts_parse(int argc, char **argv, opts_t *o, char *err, size_t errlen)
{
    given_t given = { 0, 0 };
    int c;
    estop_err_t ce;

    memset(o, 0, sizeof *o);
    o->udp_port = 5700u;
    o->tcp_port = 5701u;
    o->bind.s_addr = htonl(INADDR_ANY);
    o->bind_str = "0.0.0.0";
    estop_config_default(&o->cfg);

    opterr = 0; /* errors are reported here, as one line */
    while ((c = getopt_long(argc, argv, ":hV", long_opts, NULL)) != -1) {
        if (c == 'h') {
            usage();
            return OPTS_EXIT_OK;
        }
        if (c == 'V') {
            (void)printf("estopd %u.%u\n", ESTOP_VERSION_MAJOR, ESTOP_VERSION_MINOR);
            return OPTS_EXIT_OK;
        }
        if (c == '?' || c == ':') {
            getopt_error(c, argv, err, errlen);
            return OPTS_ERROR;
        }
        if (set_one(c, optarg, o, &given, err, errlen) != 0) {
            return OPTS_ERROR;
        }
    }
    if (optind < argc) {
        (void)snprintf(err, errlen, "unexpected argument '%s'", argv[optind]);
        return OPTS_ERROR;
    }
    /* --check may leave both out: there is no key to check then. */
    if ((o->key_file != NULL) == (o->no_auth != 0) && !(o->check && o->key_file == NULL)) {
        (void)snprintf(err, errlen, "%s", o->no_auth ? "--key-file and --no-auth exclude each other"
                                                      : "--key-file PATH or --no-auth is required"
                                                        " (a unit with a key, or one without)");
        return OPTS_ERROR;
    }
    if (!given.slow) {
        o->cfg.slow_us = o->cfg.timeout_us; /* S = T: never SLOWING, as in version 2 */
    }
    if (!given.warn) {
        o->cfg.warn_us = default_warn_us(o->cfg.slow_us);
    }
    o->cfg.session = 1u; /* checked here with a stand-in; the real one is drawn at start-up */
    ce = estop_config_check(&o->cfg);
    o->cfg.session = 0u;
    if (ce != ESTOP_OK) {
        (void)snprintf(err, errlen, "invalid configuration (%s): %s", estop_err_name(ce),
                       config_hint(ce));
        return OPTS_ERROR;
    }
    return OPTS_RUN;
}
