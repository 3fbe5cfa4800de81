/* UDP control port: every datagram goes to the core. */
#ifndef ESTOPD_UDP_H
#define ESTOPD_UDP_H

#include "daemon.h"

/* Drains pending datagrams, at most a batch per wakeup, with the deadline checked
 * before each one so a flood cannot hold back the timeout stop. */
void udp_readable(daemon_t *d);

#endif
