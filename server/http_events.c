/*
 * http_events.c - server-sent event streams, GET /v1/jobs/{id}/events
 * (http_internal.h).
 *
 * The body comes from a content reader that drains the subscriber's queue
 * and suspends the connection when it is empty (returning 0 without
 * suspending would busy-loop the polling thread); the daemon's notify
 * callback resumes it. The notify callback sets a flag that the reader
 * checks under the stream's mutex right before suspending, which closes the
 * window where an event arrives between "nothing pending" and the suspend.
 * A ticker thread resumes streams that sent nothing for 15 s so they write
 * a keepalive comment (proxies drop silent streams), and once a second
 * looks at the socket of every suspended stream: libmicrohttpd takes a
 * suspended connection out of its poll set, so without a look a client
 * that went away would hold its subscriber slot (MR_MAX_SUBSCRIBERS) until
 * the next keepalive fails. A hang-up (POLLRDHUP: the client closed or
 * shut down its side; an event-stream client sends nothing after its
 * request) ends the stream at once. The socket is valid while the
 * connection is suspended: libmicrohttpd cannot close a suspended one.
 */
#define _GNU_SOURCE /* POLLRDHUP */
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "http_internal.h"
#include "microray.h"

#define KEEPALIVE_MS 15000
/* Largest event block passed on to a client in one piece. */
#define EVENT_MAX (64u * 1024u)
#define SSE_BLOCK 16384

static const char KEEPALIVE[] = ": keepalive\n\n";

/* One event stream. Shared by the response (its content reader) and the
 * request (its log line): freed when both have let go. */
struct sse_stream {
    mr_http *h;
    struct MHD_Connection *conn;
    mr_event_sub *sub;
    atomic_int refs;
    pthread_mutex_t mu;
    bool suspended;     /* the connection is suspended waiting for an event */
    bool notified;      /* an event became pending since the reader last looked */
    bool keepalive_due; /* the ticker resumed us to send a keepalive */
    bool closed;        /* the request is over: never touch conn again */
    bool gone;          /* the client hung up: end the stream */
    int fd;             /* the connection's socket */
    bool registered;
    _Atomic int64_t last_send_ms;
    _Atomic uint64_t bytes;
    size_t out_len, out_off; /* the block being sent, in buf */
    char *buf;
    sse_stream *prev, *next;
};

static void sse_release(sse_stream *s)
{
    if (atomic_fetch_sub(&s->refs, 1) != 1)
        return;
    pthread_mutex_destroy(&s->mu);
    free(s->buf);
    free(s);
}

/* From the publishing thread: wake the stream if it sleeps. */
static void sse_notify(void *user)
{
    sse_stream *s = user;
    pthread_mutex_lock(&s->mu);
    if (!s->closed) {
        s->notified = true;
        if (s->suspended) {
            s->suspended = false;
            MHD_resume_connection(s->conn);
        }
    }
    pthread_mutex_unlock(&s->mu);
}

/* Ends the stream's ties to the connection and the daemon; idempotent. Runs
 * when the request completes (and, as a fallback, when the response is
 * freed), after which nothing may resume the connection. */
static void sse_close(sse_stream *s)
{
    pthread_mutex_lock(&s->mu);
    bool was_closed = s->closed;
    s->closed = true;
    pthread_mutex_unlock(&s->mu);
    if (was_closed)
        return;
    mr_http *h = s->h;
    pthread_mutex_lock(&h->streams_mu);
    if (s->registered) {
        if (s->prev)
            s->prev->next = s->next;
        else
            h->streams = s->next;
        if (s->next)
            s->next->prev = s->prev;
        s->registered = false;
    }
    pthread_mutex_unlock(&h->streams_mu);
    /* The daemon promises no notify call runs or starts after this returns. */
    mr_events_unsubscribe(s->sub);
    s->sub = NULL;
}

static void sse_response_free(void *cls)
{
    sse_stream *s = cls;
    sse_close(s);
    sse_release(s);
}

static ssize_t sse_read(void *cls, uint64_t pos, char *buf, size_t max)
{
    (void)pos;
    sse_stream *s = cls;
    mr_http *h = s->h;
    for (;;) {
        if (s->out_off < s->out_len) {
            size_t n = s->out_len - s->out_off;
            n = n < max ? n : max;
            memcpy(buf, s->buf + s->out_off, n);
            s->out_off += n;
            atomic_fetch_add(&s->bytes, n);
            atomic_store(&s->last_send_ms, mr_now_ms());
            return (ssize_t)n;
        }
        if (atomic_load(&h->stopping) || !s->sub)
            return MHD_CONTENT_READER_END_OF_STREAM;
        pthread_mutex_lock(&s->mu);
        bool gone = s->gone;
        s->notified = false;
        bool keepalive = s->keepalive_due;
        s->keepalive_due = false;
        pthread_mutex_unlock(&s->mu);
        if (gone)
            return MHD_CONTENT_READER_END_WITH_ERROR;

        int n = mr_events_next(s->sub, s->buf, EVENT_MAX);
        if (n < 0)
            return MHD_CONTENT_READER_END_OF_STREAM;
        if (n > 0) {
            /* A block that did not fit was cut at the buffer's end. */
            s->out_len = (size_t)n < EVENT_MAX ? (size_t)n : strlen(s->buf);
            s->out_off = 0;
            continue;
        }
        if (keepalive || mr_now_ms() - atomic_load(&s->last_send_ms) >= KEEPALIVE_MS) {
            memcpy(s->buf, KEEPALIVE, sizeof KEEPALIVE - 1);
            s->out_len = sizeof KEEPALIVE - 1;
            s->out_off = 0;
            continue;
        }
        pthread_mutex_lock(&s->mu);
        if (s->notified || s->keepalive_due || atomic_load(&h->stopping)) {
            /* An event (or a stop) came in since we looked: look again. */
            pthread_mutex_unlock(&s->mu);
            continue;
        }
        s->suspended = true;
        MHD_suspend_connection(s->conn);
        pthread_mutex_unlock(&s->mu);
        return 0;
    }
}

enum MHD_Result http_job_events(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &job, &res))
        return res;
    if (atomic_load(&h->stopping))
        return http_send_problem(r, c, P_UNAVAILABLE, NULL, "the daemon is stopping");
    /* a resumed stream: the id of the last event the client got (the
     * header EventSource sends, or the query parameter for clients that
     * cannot set headers) */
    const char *last = MHD_lookup_connection_value(c, MHD_HEADER_KIND, "Last-Event-ID");
    if (!last)
        last = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "last_event_id");
    int64_t last_event_id = -1;
    if (last) {
        size_t n = strspn(last, "0123456789");
        if (n == 0 || n > 18 || last[n])
            return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                     "Last-Event-ID '%.32s' is not an id of this job's events", last);
        last_event_id = atoll(last);
    }
    sse_stream *s = calloc(1, sizeof *s);
    char *buf = malloc(EVENT_MAX);
    if (!s || !buf || pthread_mutex_init(&s->mu, NULL) != 0) {
        free(s);
        free(buf);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    s->h = h;
    s->conn = c;
    s->buf = buf;
    const union MHD_ConnectionInfo *fd = MHD_get_connection_info(c, MHD_CONNECTION_INFO_CONNECTION_FD);
    s->fd = fd ? fd->connect_fd : -1;
    atomic_init(&s->refs, 1);
    atomic_init(&s->last_send_ms, mr_now_ms());
    atomic_init(&s->bytes, 0);
    s->sub = mr_events_subscribe(h->d, job.id, last_event_id);
    if (!s->sub) {
        s->closed = true;
        sse_release(s);
        return http_send_problem(r, c, P_UNAVAILABLE, NULL,
                                 "too many event streams are open; poll GET /v1/jobs/%s instead", job.id);
    }
    mr_events_set_notify(s->sub, sse_notify, s);

    pthread_mutex_lock(&h->streams_mu);
    s->next = h->streams;
    if (h->streams)
        h->streams->prev = s;
    h->streams = s;
    s->registered = true;
    pthread_cond_signal(&h->tick_cv);
    pthread_mutex_unlock(&h->streams_mu);

    /* The response owns one reference, the request (for its log line) one. */
    struct MHD_Response *resp =
        MHD_create_response_from_callback(MHD_SIZE_UNKNOWN, SSE_BLOCK, sse_read, s,
                                          sse_response_free);
    if (!resp) {
        sse_response_free(s);
        return MHD_NO;
    }
    atomic_fetch_add(&s->refs, 1);
    r->sse = s;
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, "text/event-stream") !=
            MHD_YES ||
        MHD_add_response_header(resp, MHD_HTTP_HEADER_CACHE_CONTROL, "no-cache") != MHD_YES) {
        MHD_destroy_response(resp);
        return MHD_NO;
    }
    return http_send_response(r, c, MHD_HTTP_OK, resp, 0);
}

/* Whether the client of a suspended stream hung up (s->mu held). */
static bool client_gone(const sse_stream *s)
{
    if (s->fd < 0)
        return false;
    struct pollfd p = {.fd = s->fd, .events = POLLRDHUP};
    return poll(&p, 1, 0) == 1 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR | POLLNVAL));
}

/* Resumes streams that have been silent for KEEPALIVE_MS, and those whose
 * client hung up (to end them). Sleeps without a timeout while there are
 * no streams. */
static void *ticker_main(void *arg)
{
    mr_http *h = arg;
    pthread_mutex_lock(&h->streams_mu);
    while (!h->tick_stop) {
        if (!h->streams) {
            pthread_cond_wait(&h->tick_cv, &h->streams_mu);
            continue;
        }
        struct timespec ts;
        clock_gettime(CLOCK_MONOTONIC, &ts);
        ts.tv_sec += 1;
        pthread_cond_timedwait(&h->tick_cv, &h->streams_mu, &ts);
        int64_t now = mr_now_ms();
        for (sse_stream *s = h->streams; s && !h->tick_stop; s = s->next) {
            pthread_mutex_lock(&s->mu);
            if (s->suspended && !s->closed && client_gone(s)) {
                s->gone = true;
                s->suspended = false;
                MHD_resume_connection(s->conn);
            } else if (s->suspended && !s->closed &&
                       now - atomic_load(&s->last_send_ms) >= KEEPALIVE_MS) {
                s->keepalive_due = true;
                s->suspended = false;
                MHD_resume_connection(s->conn);
            }
            pthread_mutex_unlock(&s->mu);
        }
    }
    pthread_mutex_unlock(&h->streams_mu);
    return NULL;
}


int http_events_start(mr_http *h, mr_error *err)
{
    pthread_condattr_t ca;
    bool mu_ok = false, cv_ok = false;
    if (pthread_mutex_init(&h->streams_mu, NULL) != 0)
        goto fail;
    mu_ok = true;
    if (pthread_condattr_init(&ca) != 0)
        goto fail;
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    cv_ok = pthread_cond_init(&h->tick_cv, &ca) == 0;
    pthread_condattr_destroy(&ca);
    if (!cv_ok)
        goto fail;
    if (pthread_create(&h->ticker, NULL, ticker_main, h) != 0)
        goto fail;
    h->ticker_running = true;
    return MR_OK;
fail:
    if (cv_ok)
        pthread_cond_destroy(&h->tick_cv);
    if (mu_ok)
        pthread_mutex_destroy(&h->streams_mu);
    return mr_error_set(err, MR_ERR_NOMEM, "cannot create the HTTP ticker thread");
}

void http_events_stop(mr_http *h)
{
    pthread_mutex_lock(&h->streams_mu);
    h->tick_stop = true;
    pthread_cond_signal(&h->tick_cv);
    for (sse_stream *s = h->streams; s; s = s->next) {
        pthread_mutex_lock(&s->mu);
        if (s->suspended && !s->closed) {
            s->suspended = false;
            MHD_resume_connection(s->conn);
        }
        pthread_mutex_unlock(&s->mu);
    }
    pthread_mutex_unlock(&h->streams_mu);
    if (h->ticker_running)
        pthread_join(h->ticker, NULL);
    h->ticker_running = false;
}

void http_events_free(mr_http *h)
{
    pthread_cond_destroy(&h->tick_cv);
    pthread_mutex_destroy(&h->streams_mu);
}

uint64_t http_events_request_done(sse_stream *s)
{
    sse_close(s);
    uint64_t bytes = atomic_load(&s->bytes);
    sse_release(s);
    return bytes;
}
