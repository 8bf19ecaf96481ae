/*
 * http_internal.h - what the parts of the HTTP front end share, and only
 * they (nothing outside server/http*.c includes it):
 *   http.c          lifecycle and the request cycle: body caps and reading,
 *                   log lines, start and stop;
 *   http_routes.c   the one route table and path matching;
 *   http_reply.c    responses: JSON bodies, RFC 9457 problems, error mapping;
 *   http_handlers.c the handlers of the job, frame, asset and service routes,
 *                   content negotiation (Accept) and the PNG preview routes
 *                   (their pictures and cache: previews.c);
 *   http_assets.c   uploaded assets as resources: list, one, delete;
 *   http_frames.c   a job's frames as a collection: the list, and every
 *                   finished frame streamed as one tar archive;
 *   http_events.c   server-sent event streams (GET /v1/jobs/{id}/events) and
 *                   their keepalive ticker;
 *   http_guard.c    the connection budget and the request head and body
 *                   deadlines (their reaper thread).
 * Cross-file names start with http_; handlers are named after their route.
 */
#ifndef MR_HTTP_INTERNAL_H
#define MR_HTTP_INTERNAL_H

#include <cJSON.h>
#include <microhttpd.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdatomic.h>

#include "http.h"

#define CT_JSON "application/json"
#define PARAM_MAX 80
#define MAX_PARAMS 2
#define LOG_PATH_MAX 256

typedef struct sse_stream sse_stream;
typedef struct conn_track conn_track;

struct mr_http {
    mr_daemon *d;
    struct MHD_Daemon *mhd;
    unsigned port;
    size_t max_job_bytes, max_asset_bytes;
    unsigned render_threads;
    bool quiet;
    bool has_token;
    uint8_t token_digest[32]; /* SHA-256 of the bearer token (compared, never the token) */
    atomic_bool stopping;
    _Atomic uint64_t requests;
    _Atomic uint64_t responses[6]; /* by status class: [2] counts 2xx, ... */

    /* Event streams, for the keepalive ticker and for ending them at stop.
     * Lock order: streams_mu, then a stream's mu, then libmicrohttpd's own. */
    pthread_mutex_t streams_mu;
    pthread_cond_t tick_cv;
    sse_stream *streams;
    bool tick_stop;
    bool ticker_running;
    pthread_t ticker;

    /* Connections, for the budget and the deadlines (http_guard.c). */
    unsigned max_connections, request_timeout_s;
    pthread_mutex_t conns_mu;
    pthread_cond_t reap_cv;
    conn_track *conns;
    unsigned conn_count;
    bool reap_stop;
    bool reaper_running;
    pthread_t reaper;
    _Atomic uint64_t connections_refused, connections_reaped;

    /* PNG previews being made (EXR reads, encoding) right now, and how many
     * may be: half the thread pool, at least 1, so the others keep
     * answering (http_handlers.c). */
    atomic_uint previews_busy;
    unsigned previews_max;
};

typedef struct req req;
typedef enum MHD_Result (*handler_fn)(req *r, struct MHD_Connection *c);

typedef enum body_kind { BODY_NONE = 0, BODY_JOB, BODY_ASSET } body_kind;

typedef struct route {
    const char *method;
    /* "/v1/jobs/{id}": {name} matches one non-empty segment; "{n}.png"
     * one that ends in ".png", capturing what comes before it */
    const char *pattern;
    handler_fn fn;
    body_kind body;
} route;

struct req {
    mr_http *h;
    const route *rt;
    const char *url; /* valid only during a handler call */
    char params[MAX_PARAMS][PARAM_MAX];
    double t0;
    char method[16];
    char path[LOG_PATH_MAX];
    char *body;
    mr_asset_upload *upload; /* POST /v1/assets: streamed to a file, never buffered */
    size_t len, cap, limit;
    size_t drained; /* bytes read and dropped after the cap was passed */
    bool over;      /* the body passed its cap */
    mr_error body_err; /* storing the body failed (an upload): answered when it ends */
    bool keep_body;
    bool answered;
    bool begun;     /* the access handler had its first call */
    size_t uri_len; /* the request target as sent (path and query) */
    unsigned status;
    uint64_t bytes;
    char job[MR_JOB_ID_LEN + 1];
    char allow[96]; /* methods of the path when none matched this one */
    sse_stream *sse;
    conn_track *conn; /* the connection's guard record (NULL if untracked) */
};

/* ---- routes (http_routes.c) ------------------------------------------- */

/* The route for method and path, its {params} captured into params; NULL
 * when none has both (HEAD is served by GET routes). */
const route *http_route_find(const char *method, const char *path, char params[][PARAM_MAX]);
/* The methods the routes of path have ("GET, HEAD, DELETE"), for 405's
 * Allow header; "" when no route has the path (404). */
void http_route_methods(const char *path, char *allow, size_t size);

/* ---- replies (http_reply.c) ------------------------------------------- */

typedef enum problem_kind {
    P_BAD_REQUEST,
    P_MALFORMED_JSON,
    P_INVALID_JOB,
    P_UNAUTHORIZED,
    P_NOT_FOUND,
    P_METHOD,
    P_NOT_ACCEPTABLE,
    P_CONFLICT,
    P_TOO_LARGE,
    P_URI_TOO_LONG,
    P_RANGE,
    P_UNPROCESSABLE,
    P_IDEMPOTENCY,
    P_HEADERS_TOO_LARGE,
    P_INTERNAL,
    P_UNAVAILABLE,
    P_NO_SPACE
} problem_kind;

/* Queues resp (which may be NULL after a failed allocation: the connection
 * is then closed), counts its status class and drops our reference. */
enum MHD_Result http_send_response(req *r, struct MHD_Connection *c, unsigned status,
                                   struct MHD_Response *resp, uint64_t bytes);
/* A response of len bytes at body (malloc'ed; the response owns it from
 * here on, also when this fails) with a Content-Type; NULL when out of
 * memory. */
struct MHD_Response *http_buffer_response(char *body, size_t len, const char *ctype);
/* A response owning the printed document plus a trailing newline (friendlier
 * for curl users); NULL when out of memory. Frees doc. */
struct MHD_Response *http_json_response(cJSON *doc, const char *ctype, size_t *len);
enum MHD_Result http_send_json(req *r, struct MHD_Connection *c, unsigned status, cJSON *doc);
/* Adds v to o under key k; on any failure frees v and clears *ok, so a
 * document built from many adds is checked once at the end. */
cJSON *http_put(cJSON *o, const char *k, cJSON *v, bool *ok);
/* http_send_json of a document built with http_put, or a 500 "out of
 * memory" problem (doc freed) when one of the puts failed (!ok). */
enum MHD_Result http_send_built(req *r, struct MHD_Connection *c, unsigned status, cJSON *doc, bool ok);
/* RFC 9457 problem; pointer (may be NULL or "") names the offending job field. */
enum MHD_Result http_send_problem(req *r, struct MHD_Connection *c, problem_kind kind,
                                  const char *pointer, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 5, 6)))
#endif
    ;
/* The same with extension members (RFC 9457 3.2): the members of the
 * object ext (may be NULL; consumed) join the document. */
enum MHD_Result http_send_problem_ext(req *r, struct MHD_Connection *c, problem_kind kind,
                                      const char *pointer, cJSON *ext, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 6, 7)))
#endif
    ;
/* The same with one extra header, e.g. Allow. */
enum MHD_Result http_send_problem_hdr(req *r, struct MHD_Connection *c, problem_kind kind,
                                      const char *header, const char *value, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 6, 7)))
#endif
    ;
/* s percent-encoded for a query value (RFC 3986 unreserved bytes kept),
 * cut to fit out. */
void http_url_encode(const char *s, char *out, size_t size);
/* The usual mapping of a daemon or store failure. */
enum MHD_Result http_send_error(req *r, struct MHD_Connection *c, int code, const mr_error *e);

/* ---- handlers (http_handlers.c, http_events.c) ------------------------- */

/* The job's stats.json document over its frames done so far (what GET
 * /v1/jobs/{id}/stats answers and frames.tar holds). */
int http_job_stats_doc(mr_http *h, const mr_job_record *rec, cJSON **out, mr_error *err);

/* The job named by the {id} parameter; answers 404 itself when unknown. */
bool http_load_job(req *r, struct MHD_Connection *c, mr_job_record *job, enum MHD_Result *res);

enum MHD_Result http_asset_put(req *r, struct MHD_Connection *c);
enum MHD_Result http_asset_list(req *r, struct MHD_Connection *c);
enum MHD_Result http_asset_get(req *r, struct MHD_Connection *c);
enum MHD_Result http_asset_delete(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_submit(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_list(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_get(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_delete(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_cancel(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_retry(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_frames(req *r, struct MHD_Connection *c);
enum MHD_Result http_frames_tar(req *r, struct MHD_Connection *c);
enum MHD_Result http_frame_get(req *r, struct MHD_Connection *c);
enum MHD_Result http_frame_png(req *r, struct MHD_Connection *c);
enum MHD_Result http_contact_sheet(req *r, struct MHD_Connection *c);
enum MHD_Result http_frame_stats(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_stats(req *r, struct MHD_Connection *c);
enum MHD_Result http_job_events(req *r, struct MHD_Connection *c);
enum MHD_Result http_healthz(req *r, struct MHD_Connection *c);
enum MHD_Result http_readyz(req *r, struct MHD_Connection *c);
enum MHD_Result http_metrics(req *r, struct MHD_Connection *c);
enum MHD_Result http_problem_page(req *r, struct MHD_Connection *c);

/* ---- event streams (http_events.c) ------------------------------------ */

/* The streams' lock, condition and keepalive ticker; MR_ERR_NOMEM. */
int http_events_start(mr_http *h, mr_error *err);
/* Ends the ticker and resumes every suspended stream (their readers see
 * h->stopping and end): libmicrohttpd cannot stop with suspended
 * connections. Before MHD_stop_daemon. */
void http_events_stop(mr_http *h);
/* Frees what http_events_start made; after MHD_stop_daemon. */
void http_events_free(mr_http *h);
/* The request of a stream is over: unties it from the connection and the
 * daemon, drops the request's reference; returns the bytes it sent. */
uint64_t http_events_request_done(sse_stream *s);

/* ---- the connection guard (http_guard.c) ------------------------------ */

/* Where a connection is in its request cycle, for the deadlines. */
typedef enum conn_phase {
    PHASE_HEAD,  /* waiting for (the rest of) a request line and headers */
    PHASE_BODY,  /* the head is in, the body is arriving */
    PHASE_ANSWER /* handled or being answered: no deadline */
} conn_phase;

/* The reaper thread; sizes the descriptor limit for h->max_connections
 * (which it may lower). MR_ERR_NOMEM. */
int http_guard_start(mr_http *h, mr_error *err);
/* Ends the reaper; before MHD_stop_daemon. */
void http_guard_stop(mr_http *h);
/* After MHD_stop_daemon. */
void http_guard_free(mr_http *h);
/* libmicrohttpd's accept policy and NOTIFY_CONNECTION callbacks (cls: h). */
enum MHD_Result http_guard_accept(void *cls, const struct sockaddr *addr, socklen_t len);
void http_guard_notify(void *cls, struct MHD_Connection *c, void **socket_context,
                       enum MHD_ConnectionNotificationCode code);
/* The record of c (NULL if untracked); valid until its CLOSED notification,
 * so for the whole of every request on it. */
conn_track *http_guard_of(struct MHD_Connection *c);
/* Enters a phase (its clock starts now); t may be NULL. */
void http_guard_phase(conn_track *t, conn_phase phase);
/* n more body bytes arrived; t may be NULL. */
void http_guard_body(conn_track *t, size_t n);

#endif
