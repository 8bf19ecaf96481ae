/*
 * http.h - the HTTP front end of microrayd (libmicrohttpd): one route table,
 * RFC 9457 problem+json errors, body caps, request logging. Handlers only
 * parse, call the daemon/store and answer; they never render. Its parts
 * (lifecycle, routes, replies, handlers, event streams) share
 * http_internal.h.
 */
#ifndef MR_HTTP_H
#define MR_HTTP_H

#include "daemon.h"

typedef struct mr_http mr_http;

/* Starts listening on cfg->listen_host:cfg->port (port 0 = any free one). */
int mr_http_start(mr_daemon *d, const mr_daemon_config *cfg, mr_http **out, mr_error *err);
unsigned mr_http_port(const mr_http *h);
/* Stops accepting, closes connections (ending event streams), frees. */
void mr_http_stop(mr_http *h);

/* Counters the front end keeps for /metrics. */
typedef struct mr_http_counters {
    uint64_t requests;
    uint64_t responses[6]; /* by status class: [1] 1xx ... [5] 5xx */
} mr_http_counters;
void mr_http_counters_get(const mr_http *h, mr_http_counters *out);

#endif
