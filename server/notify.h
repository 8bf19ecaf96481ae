/*
 * notify.h - completion notifications: a job that names a "notify" URL
 * gets its final state POSTed there as JSON when it succeeds, fails or is
 * canceled (issue 19).
 *
 * Deliveries run on a thread of their own (libcurl), never on a worker or
 * an HTTP thread, up to 64 attempts in flight at once, so a receiver that
 * never answers delays no one else's. An attempt that does not end in a
 * 2xx answer within
 * NOTIFY_TIMEOUT_S is tried again after 1, 2, 4, 8 and 16 s, at most
 * NOTIFY_ATTEMPTS times in all; then the delivery is given up (logged).
 * Each attempt carries `X-Microray-Attempt: N`. Redirects are not
 * followed. Pending deliveries do not survive the daemon's stop: the stop
 * waits for the attempts in flight, drops the rest and logs how many.
 * The daemon's address space is the receiver's to reach: a job may name
 * any http(s) URL the daemon can connect to (loopback included), so give
 * job submission (the token) only to those who may make the daemon send
 * such requests.
 */
#ifndef MR_NOTIFY_H
#define MR_NOTIFY_H

#include "microray.h"

#define NOTIFY_ATTEMPTS 6
#define NOTIFY_TIMEOUT_S 10

typedef struct mr_notifier mr_notifier;

/* log (may be NULL) receives one line per delivery given up or done after
 * a retry. curl_global_init must have run. */
int mr_notifier_start(void (*log)(void *user, const char *line), void *user, mr_notifier **out,
                      mr_error *err);
/* Queues a POST of body (JSON, copied) to url. Never blocks on the
 * network. */
void mr_notifier_send(mr_notifier *n, const char *url, const char *body);
/* Ends the thread after the attempts in flight; drops what is pending. */
void mr_notifier_stop(mr_notifier *n);

#endif
