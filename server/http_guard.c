/*
 * http_guard.c - the connection guard of the HTTP front end
 * (http_internal.h): a global connection budget that keeps slots for new
 * clients, and deadlines for the request head and body.
 *
 * libmicrohttpd's connection timeout is an idle timeout: a client that
 * sends one byte of its request head every second is never idle and keeps
 * its connection (and its slot) for ever; enough of them ("slowloris") take
 * every slot. So every connection is tracked from libmicrohttpd's
 * NOTIFY_CONNECTION STARTED to CLOSED, the request cycle (http.c) says
 * which phase it is in, and a reaper thread shuts down the socket of a
 * connection whose phase is past its deadline:
 *   head    request line and headers complete within request_timeout_s of
 *           the connection's start or the previous request's end (a
 *           keep-alive connection idles at most that long);
 *   body    request_timeout_s of grace, then an average of at least
 *           MIN_BODY_RATE bytes per second (a large upload on a slow link
 *           is fine, a trickle is not);
 *   answer  no deadline: handlers and responses (event streams included)
 *           are the server's business, and libmicrohttpd's idle timeout
 *           still ends a client that stopped reading.
 * shutdown(2) of the socket makes libmicrohttpd see the end of the stream
 * and close the connection the ordinary way (request completed, upload
 * aborted, slot freed). It runs under conns_mu, and libmicrohttpd 0.9.75
 * calls CLOSED (which takes conns_mu to untrack the connection) before it
 * closes the socket (daemon.c: MHD_cleanup_connections and the failure
 * path of new_connection_process_), so the reaper never shuts down a
 * descriptor that was closed and reused.
 *
 * The budget: libmicrohttpd refuses a connection beyond the per-address
 * limit (exact, its own count); the accept policy here refuses one beyond
 * max_connections, and once three quarters of the budget are in use, one
 * from an address that already holds RESERVE_SHARE or more (IPv6 addresses
 * counted per /64, what one host usually gets), so a few addresses cannot
 * take every slot. libmicrohttpd splits its own connection limit evenly
 * over its threads, which would refuse a client on a full thread while
 * another has room; it is therefore set to the budget per thread and is a
 * backstop only: the budget is counted here, over all threads (several
 * threads accepting at the same instant may pass it by one each).
 */
#include <errno.h>
#include <netinet/in.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <time.h>

#include "http_internal.h"
#include "microray.h"

/* How often the reaper looks at the deadlines. */
#define REAP_INTERVAL_MS 250
/* A body must arrive at this many bytes per second on average (after the
 * grace of request_timeout_s): 32 kbit/s. */
#define MIN_BODY_RATE 4096
/* In the last quarter of the budget, only addresses holding fewer than
 * this many connections get another. */
#define RESERVE_SHARE 2
/* Descriptors the daemon needs besides its connections (sqlite, assets,
 * frames being written, epoll, the listening socket). */
#define SPARE_FDS 256

struct conn_track {
    struct MHD_Connection *c;
    int fd;
    unsigned char key[16]; /* the address, IPv4-mapped; an IPv6 one cut to its /64 */
    _Atomic int phase;     /* conn_phase */
    _Atomic int64_t since_ms;
    _Atomic uint64_t body_bytes;
    bool reaped;
    conn_track *prev, *next;
};

static void address_key(const struct sockaddr *sa, socklen_t len, unsigned char key[16])
{
    memset(key, 0, 16);
    if (sa && sa->sa_family == AF_INET && len >= (socklen_t)sizeof(struct sockaddr_in)) {
        key[10] = key[11] = 0xff;
        memcpy(key + 12, &((const struct sockaddr_in *)sa)->sin_addr, 4);
    } else if (sa && sa->sa_family == AF_INET6 && len >= (socklen_t)sizeof(struct sockaddr_in6)) {
        const unsigned char *a = ((const struct sockaddr_in6 *)sa)->sin6_addr.s6_addr;
        static const unsigned char mapped[12] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff};
        memcpy(key, a, memcmp(a, mapped, 12) == 0 ? 16 : 8);
    }
}

static void describe(const conn_track *t, char *out, size_t n)
{
    static const unsigned char mapped[12] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff};
    if (memcmp(t->key, mapped, 12) == 0)
        snprintf(out, n, "%u.%u.%u.%u", t->key[12], t->key[13], t->key[14], t->key[15]);
    else
        snprintf(out, n, "%02x%02x:%02x%02x:%02x%02x:%02x%02x::/64", t->key[0], t->key[1], t->key[2],
                 t->key[3], t->key[4], t->key[5], t->key[6], t->key[7]);
}

enum MHD_Result http_guard_accept(void *cls, const struct sockaddr *addr, socklen_t len)
{
    mr_http *h = cls;
    unsigned char key[16];
    address_key(addr, len, key);
    pthread_mutex_lock(&h->conns_mu);
    unsigned total = h->conn_count, mine = 0;
    for (const conn_track *t = h->conns; t; t = t->next)
        mine += memcmp(t->key, key, sizeof key) == 0;
    pthread_mutex_unlock(&h->conns_mu);
    unsigned budget = h->max_connections;
    bool ok = total < budget && (total < budget - budget / 4 || mine < RESERVE_SHARE);
    if (!ok)
        atomic_fetch_add(&h->connections_refused, 1);
    return ok ? MHD_YES : MHD_NO;
}

void http_guard_notify(void *cls, struct MHD_Connection *c, void **socket_context,
                       enum MHD_ConnectionNotificationCode code)
{
    mr_http *h = cls;
    if (code == MHD_CONNECTION_NOTIFY_STARTED) {
        conn_track *t = calloc(1, sizeof *t);
        const union MHD_ConnectionInfo *fd = MHD_get_connection_info(c, MHD_CONNECTION_INFO_CONNECTION_FD);
        const union MHD_ConnectionInfo *addr =
            MHD_get_connection_info(c, MHD_CONNECTION_INFO_CLIENT_ADDRESS);
        *socket_context = t;
        if (!t) /* untracked: only the budget's count misses it */
            return;
        t->c = c;
        t->fd = fd ? fd->connect_fd : -1;
        address_key(addr ? addr->client_addr : NULL,
                    addr && addr->client_addr && addr->client_addr->sa_family == AF_INET6
                        ? (socklen_t)sizeof(struct sockaddr_in6)
                        : (socklen_t)sizeof(struct sockaddr_in),
                    t->key);
        atomic_init(&t->phase, PHASE_HEAD);
        atomic_init(&t->since_ms, mr_now_ms());
        atomic_init(&t->body_bytes, 0);
        pthread_mutex_lock(&h->conns_mu);
        t->next = h->conns;
        if (h->conns)
            h->conns->prev = t;
        h->conns = t;
        h->conn_count++;
        pthread_cond_signal(&h->reap_cv);
        pthread_mutex_unlock(&h->conns_mu);
        return;
    }
    conn_track *t = *socket_context;
    *socket_context = NULL;
    if (!t)
        return;
    pthread_mutex_lock(&h->conns_mu);
    if (t->prev)
        t->prev->next = t->next;
    else
        h->conns = t->next;
    if (t->next)
        t->next->prev = t->prev;
    h->conn_count--;
    pthread_mutex_unlock(&h->conns_mu);
    free(t);
}

conn_track *http_guard_of(struct MHD_Connection *c)
{
    const union MHD_ConnectionInfo *i = MHD_get_connection_info(c, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
    return i ? i->socket_context : NULL;
}

void http_guard_phase(conn_track *t, conn_phase phase)
{
    if (!t || atomic_load(&t->phase) == (int)phase)
        return;
    atomic_store(&t->body_bytes, 0);
    atomic_store(&t->since_ms, mr_now_ms());
    atomic_store(&t->phase, phase);
}

void http_guard_body(conn_track *t, size_t n)
{
    if (t)
        atomic_fetch_add(&t->body_bytes, n);
}

/* The deadline of t's phase in ms on the mr_now_ms clock; INT64_MAX for none. */
static int64_t deadline_ms(const mr_http *h, conn_track *t)
{
    int64_t since = atomic_load(&t->since_ms), grace = (int64_t)h->request_timeout_s * 1000;
    switch (atomic_load(&t->phase)) {
    case PHASE_HEAD:
        return since + grace;
    case PHASE_BODY:
        return since + grace + (int64_t)(atomic_load(&t->body_bytes) * 1000 / MIN_BODY_RATE);
    default:
        return INT64_MAX;
    }
}

static void *reaper_main(void *arg)
{
    mr_http *h = arg;
    pthread_mutex_lock(&h->conns_mu);
    while (!h->reap_stop) {
        if (!h->conns) {
            pthread_cond_wait(&h->reap_cv, &h->conns_mu);
            continue;
        }
        struct timespec ts;
        clock_gettime(CLOCK_MONOTONIC, &ts);
        ts.tv_nsec += REAP_INTERVAL_MS * 1000000L;
        if (ts.tv_nsec >= 1000000000L) {
            ts.tv_sec++;
            ts.tv_nsec -= 1000000000L;
        }
        pthread_cond_timedwait(&h->reap_cv, &h->conns_mu, &ts);
        int64_t now = mr_now_ms();
        for (conn_track *t = h->conns; t && !h->reap_stop; t = t->next) {
            if (t->reaped || t->fd < 0 || now < deadline_ms(h, t))
                continue;
            t->reaped = true;
            bool head = atomic_load(&t->phase) == PHASE_HEAD;
            shutdown(t->fd, SHUT_RDWR);
            atomic_fetch_add(&h->connections_reaped, 1);
            if (!h->quiet) {
                char who[64];
                describe(t, who, sizeof who);
                fprintf(stderr, "microrayd: http: closed a connection from %s: %s after %.1f s\n", who,
                        head ? "request head not complete" : "request body arriving too slowly",
                        (double)(now - atomic_load(&t->since_ms)) / 1e3);
            }
        }
    }
    pthread_mutex_unlock(&h->conns_mu);
    return NULL;
}

/* The budget needs descriptors: raise the soft limit towards the hard one,
 * or shrink the budget to what the limit allows. */
static void fit_fd_limit(mr_http *h)
{
    struct rlimit rl;
    if (getrlimit(RLIMIT_NOFILE, &rl) != 0)
        return;
    rlim_t need = (rlim_t)h->max_connections + SPARE_FDS;
    if (rl.rlim_cur != RLIM_INFINITY && rl.rlim_cur < need) {
        rlim_t want = rl.rlim_max == RLIM_INFINITY || rl.rlim_max > need ? need : rl.rlim_max;
        struct rlimit nl = {want, rl.rlim_max};
        if (setrlimit(RLIMIT_NOFILE, &nl) == 0)
            rl.rlim_cur = want;
    }
    if (rl.rlim_cur != RLIM_INFINITY && rl.rlim_cur < need) {
        unsigned fit = rl.rlim_cur > SPARE_FDS + 16 ? (unsigned)(rl.rlim_cur - SPARE_FDS) : 16;
        if (!h->quiet)
            fprintf(stderr,
                    "microrayd: warning: the open-file limit (%llu) allows %u connections, not %u\n",
                    (unsigned long long)rl.rlim_cur, fit, h->max_connections);
        h->max_connections = fit;
    }
}

int http_guard_start(mr_http *h, mr_error *err)
{
    fit_fd_limit(h);
    atomic_init(&h->connections_refused, 0);
    atomic_init(&h->connections_reaped, 0);
    pthread_condattr_t ca;
    bool mu_ok = false, cv_ok = false;
    if (pthread_mutex_init(&h->conns_mu, NULL) != 0)
        goto fail;
    mu_ok = true;
    if (pthread_condattr_init(&ca) != 0)
        goto fail;
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    cv_ok = pthread_cond_init(&h->reap_cv, &ca) == 0;
    pthread_condattr_destroy(&ca);
    if (!cv_ok)
        goto fail;
    if (pthread_create(&h->reaper, NULL, reaper_main, h) != 0)
        goto fail;
    h->reaper_running = true;
    return MR_OK;
fail:
    if (cv_ok)
        pthread_cond_destroy(&h->reap_cv);
    if (mu_ok)
        pthread_mutex_destroy(&h->conns_mu);
    return mr_error_set(err, MR_ERR_NOMEM, "cannot create the HTTP reaper thread");
}

void http_guard_stop(mr_http *h)
{
    if (!h->reaper_running)
        return;
    pthread_mutex_lock(&h->conns_mu);
    h->reap_stop = true;
    pthread_cond_signal(&h->reap_cv);
    pthread_mutex_unlock(&h->conns_mu);
    pthread_join(h->reaper, NULL);
    h->reaper_running = false;
}

void http_guard_free(mr_http *h)
{
    pthread_cond_destroy(&h->reap_cv);
    pthread_mutex_destroy(&h->conns_mu);
}
