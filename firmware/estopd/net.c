#include "net.h"

#include <arpa/inet.h>
#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <netinet/tcp.h>
#include <sys/socket.h>
#include <unistd.h>

#define TCP_BACKLOG 128 /* a connect storm queues here; room is made as they are accepted */
#define TCP_RCVBUF 8192    /* the kernel doubles it */
/* Replies a client has not read yet stay below this (the kernel doubles it): an honest
 * client has one or two outstanding; for one that never reads, replies are dropped soon. */
#define TCP_SNDBUF 4096
/* A peer that vanished without a FIN is found within about KEEP_IDLE + KEEP_CNT * KEEP_INTVL
 * seconds; one that stops acknowledging replies within USER_TIMEOUT_MS. */
#define KEEP_IDLE 2
#define KEEP_INTVL 1
#define KEEP_CNT 3
#define USER_TIMEOUT_MS 5000u

void net_stop_socket_options(int fd)
{
    /* Replies are single small frames: send them at once, and keep few unread ones. Dead
     * peers are found by keepalive. Failing here only costs latency or memory, or a slot
     * held longer (until it is the quietest and a new client needs it), so results are not
     * checked. */
    int one = 1;
    int sndbuf = TCP_SNDBUF;
    int rcvbuf = TCP_RCVBUF;
    int idle = KEEP_IDLE;
    int intvl = KEEP_INTVL;
    int cnt = KEEP_CNT;
    unsigned user_timeout = USER_TIMEOUT_MS;

    (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    (void)setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &sndbuf, sizeof sndbuf);
    (void)setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    (void)setsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &one, sizeof one);
    (void)setsockopt(fd, IPPROTO_TCP, TCP_KEEPIDLE, &idle, sizeof idle);
    (void)setsockopt(fd, IPPROTO_TCP, TCP_KEEPINTVL, &intvl, sizeof intvl);
    (void)setsockopt(fd, IPPROTO_TCP, TCP_KEEPCNT, &cnt, sizeof cnt);
    (void)setsockopt(fd, IPPROTO_TCP, TCP_USER_TIMEOUT, &user_timeout, sizeof user_timeout);
}

static int net_fail(int fd, const char *what, const char *proto, struct in_addr addr,
                    uint16_t port, char *err, size_t n)
{
    char ip[INET_ADDRSTRLEN];
    int e = errno;
    if (inet_ntop(AF_INET, &addr, ip, sizeof ip) == NULL) {
        (void)snprintf(ip, sizeof ip, "?");
    }
    (void)snprintf(err, n, "%s %s %s:%u: %s", what, proto, ip, (unsigned)port, strerror(e));
    if (fd >= 0) {
        (void)close(fd);
    }
    return -1;
}

static int net_open(int type, struct in_addr addr, uint16_t port, uint16_t *bound, char *err,
                    size_t n)
{
    const char *proto = type == SOCK_STREAM ? "TCP" : "UDP";
    struct sockaddr_in sa;
    socklen_t len = sizeof sa;
    int one = 1;
    int fd = socket(AF_INET, type | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);

    if (fd < 0) {
        return net_fail(-1, "cannot open", proto, addr, port, err, n);
    }
    /* TCP only: a restart must not wait for TIME_WAIT. On UDP it would let a second
     * daemon share the port and steal half the control packets. */
    if (type == SOCK_STREAM && setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) != 0) {
        return net_fail(fd, "cannot set SO_REUSEADDR on", proto, addr, port, err, n);
    }
    memset(&sa, 0, sizeof sa);
    sa.sin_family = AF_INET;
    sa.sin_addr = addr;
    sa.sin_port = htons(port);
    if (bind(fd, (struct sockaddr *)&sa, sizeof sa) != 0) {
        return net_fail(fd, "cannot bind", proto, addr, port, err, n);
    }
    /* Before listen(): a connection the kernel completes while it waits in the backlog is
     * a copy of the listener and queues what its peer sends in the listener's buffer. With
     * the default (tcp_rmem, 128 KiB) a client could queue more before its accept than the
     * drain before a close reads; set here, every connection has the small buffer from its
     * first byte, and accept() hands it on with the rest of these options. */
    if (type == SOCK_STREAM) {
        net_stop_socket_options(fd);
    }
    if (type == SOCK_STREAM && listen(fd, TCP_BACKLOG) != 0) {
        return net_fail(fd, "cannot listen on", proto, addr, port, err, n);
    }
    if (getsockname(fd, (struct sockaddr *)&sa, &len) != 0) {
        return net_fail(fd, "cannot read the address of", proto, addr, port, err, n);
    }
    *bound = ntohs(sa.sin_port);
    return fd;
}

int net_udp_open(struct in_addr addr, uint16_t port, uint16_t *bound, char *err, size_t n)
{
    return net_open(SOCK_DGRAM, addr, port, bound, err, n);
}

int net_tcp_open(struct in_addr addr, uint16_t port, uint16_t *bound, char *err, size_t n)
{
    return net_open(SOCK_STREAM, addr, port, bound, err, n);
}

void net_fmt_addr(const struct sockaddr_in *a, char *buf, size_t n)
{
    char ip[INET_ADDRSTRLEN];
    if (inet_ntop(AF_INET, &a->sin_addr, ip, sizeof ip) == NULL) {
        (void)snprintf(ip, sizeof ip, "?");
    }
    (void)snprintf(buf, n, "%s:%u", ip, (unsigned)ntohs(a->sin_port));
}
