#include "net.h"

#include <arpa/inet.h>
#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#define TCP_BACKLOG 128 /* a connect storm queues here; room is made as they are accepted */

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
