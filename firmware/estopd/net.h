/* IPv4 sockets for the UDP control port and the TCP stop port. */
#ifndef ESTOPD_NET_H
#define ESTOPD_NET_H

#include <netinet/in.h>
#include <stddef.h>
#include <stdint.h>

#define NET_ADDR_LEN 32u /* "255.255.255.255:65535" and a NUL */

/* Non-blocking UDP socket bound to addr:port (0 picks a port, *bound tells which).
 * Returns the fd, or -1 with a message in err. */
int net_udp_open(struct in_addr addr, uint16_t port, uint16_t *bound, char *err, size_t n);
/* Non-blocking listening TCP socket, SO_REUSEADDR. Same conventions. */
int net_tcp_open(struct in_addr addr, uint16_t port, uint16_t *bound, char *err, size_t n);
/* The stop port's socket options (small buffers, TCP_NODELAY, keepalive, user timeout): set
 * on the listener before listen() and on every accepted socket. */
void net_stop_socket_options(int fd);
/* "a.b.c.d:port". */
void net_fmt_addr(const struct sockaddr_in *a, char *buf, size_t n);

#endif
