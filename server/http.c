/*
 * http.c - microrayd's HTTP front end on libmicrohttpd 0.9.75 (http.h).
 *
 * One route table maps (method, path pattern) to a handler. A path that no
 * pattern matches answers 404; a path whose patterns exist only for other
 * methods answers 405 with an Allow header. Handlers run on libmicrohttpd's
 * thread pool and only parse, call the daemon or the store and answer:
 * rendering happens on the daemon's workers. Every non-2xx answer is an
 * RFC 9457 application/problem+json body (schemas/openapi.yaml lists them).
 *
 * libmicrohttpd calls the access handler several times per request (once
 * with the headers, once per body chunk, a last time with
 * *upload_data_size == 0), so everything a request needs lives in a struct
 * req hung on *con_cls; the NOTIFY_COMPLETED callback writes the request's
 * log line and frees it. Bodies are counted as they arrive and never kept
 * past their route's cap: a Content-Length over the cap is answered 413
 * before anything is read; a chunked body that passes the cap is answered
 * 413 once it ends (libmicrohttpd 0.9.75 queues responses only on the first
 * and the last call), its excess read and dropped up to DRAIN_MAX, beyond
 * which the connection is closed.
 *
 * Server-sent events: the body comes from a content reader that drains the
 * subscriber's queue and suspends the connection when it is empty (returning
 * 0 without suspending would busy-loop the polling thread); the daemon's
 * notify callback resumes it. The notify callback sets a flag that the
 * reader checks under the stream's mutex right before suspending, which
 * closes the window where an event arrives between "nothing pending" and
 * the suspend. A ticker thread resumes streams that sent nothing for 15 s so
 * they write a keepalive comment: a suspended connection never notices a
 * client that went away, and proxies drop silent streams.
 */
#include "http.h"

#include <arpa/inet.h>
#include <cJSON.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <microhttpd.h>
#include <netinet/in.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "job_json.h"
#include "stats_json.h"
#include "util/clock.h"
#include "util/hex.h"
#include "worker.h"

#define PROBLEM_BASE "https://microray.invalid/problems/"
#define CT_JSON "application/json"
#define CT_PROBLEM "application/problem+json"
#define CT_METRICS "text/plain; version=0.0.4; charset=utf-8"

#define DEFAULT_HOST "127.0.0.1"
#define DEFAULT_JOB_BYTES (1u << 20)
#define DEFAULT_ASSET_BYTES ((size_t)512 << 20)
#define DEFAULT_TIMEOUT_S 30
#define DEFAULT_PER_IP 128
/* Headers plus one read buffer per connection. libmicrohttpd clears this
 * pool on every keep-alive request, so it is a per-request cost: 128 KiB
 * made memset the top of the profile of status requests under load (14 %),
 * 32 KiB (the library's default) keeps uploads at a few handler calls per
 * 100 KiB. */
#define CONNECTION_MEMORY (32u * 1024u)
/* Requests whose route takes no body may still carry a small one (some
 * clients send "{}" with POST .../cancel); it is read and dropped. */
#define SMALL_BODY_CAP 4096
/* How much of a chunked body past its cap is read (and dropped) so that the
 * client still gets its 413; beyond it the connection is simply closed. */
#define DRAIN_MAX (1u << 20)
#define IDEMPOTENCY_KEY_MAX 200
#define KEEPALIVE_MS 15000
/* Largest event block passed on to a client in one piece. */
#define EVENT_MAX (64u * 1024u)
#define SSE_BLOCK 16384
#define PARAM_MAX 80
#define MAX_PARAMS 2
#define LOG_PATH_MAX 256

static const char KEEPALIVE[] = ": keepalive\n\n";

/* ---- types -------------------------------------------------------------- */

typedef struct sse_stream sse_stream;

struct mr_http {
    mr_daemon *d;
    struct MHD_Daemon *mhd;
    unsigned port;
    size_t max_job_bytes, max_asset_bytes;
    unsigned render_threads;
    bool quiet;
    atomic_bool stopping;
    _Atomic uint64_t requests, responses_4xx, responses_5xx;

    /* Event streams, for the keepalive ticker and for ending them at stop.
     * Lock order: streams_mu, then a stream's mu, then libmicrohttpd's own. */
    pthread_mutex_t streams_mu;
    pthread_cond_t tick_cv;
    sse_stream *streams;
    bool tick_stop;
    bool ticker_running;
    pthread_t ticker;
};

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
    bool registered;
    _Atomic int64_t last_send_ms;
    _Atomic uint64_t bytes;
    size_t out_len, out_off; /* the block being sent, in buf */
    char *buf;
    sse_stream *prev, *next;
};

typedef struct req req;
typedef enum MHD_Result (*handler_fn)(req *r, struct MHD_Connection *c);

typedef enum body_kind { BODY_NONE = 0, BODY_JOB, BODY_ASSET } body_kind;

typedef struct route {
    const char *method;
    const char *pattern; /* "/v1/jobs/{id}": {name} matches one non-empty segment */
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
    bool keep_body;
    bool answered;
    unsigned status;
    uint64_t bytes;
    char job[MR_JOB_ID_LEN + 1];
    char allow[64]; /* methods of the path when none matched this one */
    sse_stream *sse;
};

/* ---- responses ---------------------------------------------------------- */

typedef enum problem_kind {
    P_BAD_REQUEST,
    P_INVALID_JOB,
    P_NOT_FOUND,
    P_METHOD,
    P_CONFLICT,
    P_TOO_LARGE,
    P_UNPROCESSABLE,
    P_IDEMPOTENCY,
    P_INTERNAL,
    P_UNAVAILABLE
} problem_kind;

static const struct {
    unsigned status;
    const char *slug, *title;
} PROBLEMS[] = {
    [P_BAD_REQUEST] = {400, "bad-request", "Bad request"},
    [P_INVALID_JOB] = {400, "invalid-job", "Invalid job"},
    [P_NOT_FOUND] = {404, "not-found", "Not found"},
    [P_METHOD] = {405, "method-not-allowed", "Method not allowed"},
    [P_CONFLICT] = {409, "conflict", "Conflict with the job's state"},
    [P_TOO_LARGE] = {413, "body-too-large", "Request body too large"},
    [P_UNPROCESSABLE] = {422, "unprocessable-job", "Job cannot be processed"},
    [P_IDEMPOTENCY] = {422, "idempotency-key-reused", "Idempotency key reused with another body"},
    [P_INTERNAL] = {500, "internal", "Internal server error"},
    [P_UNAVAILABLE] = {503, "unavailable", "Service unavailable"},
};

/* Queues resp (which may be NULL after a failed allocation: the connection
 * is then closed) and drops our reference. */
static enum MHD_Result send_response(req *r, struct MHD_Connection *c, unsigned status,
                                     struct MHD_Response *resp, uint64_t bytes)
{
    if (!resp)
        return MHD_NO;
    r->answered = true;
    r->status = status;
    r->bytes = bytes;
    if (status >= 500)
        atomic_fetch_add(&r->h->responses_5xx, 1);
    else if (status >= 400)
        atomic_fetch_add(&r->h->responses_4xx, 1);
    enum MHD_Result ok = MHD_queue_response(c, status, resp);
    MHD_destroy_response(resp);
    return ok;
}

/* A response owning the printed document plus a trailing newline (friendlier
 * for curl users); NULL when out of memory. Frees doc. */
static struct MHD_Response *json_response(cJSON *doc, const char *ctype, size_t *len)
{
    char *text = doc ? cJSON_PrintUnformatted(doc) : NULL;
    cJSON_Delete(doc);
    if (!text)
        return NULL;
    size_t n = strlen(text);
    char *t = realloc(text, n + 2);
    if (!t) {
        free(text);
        return NULL;
    }
    t[n++] = '\n';
    t[n] = '\0';
    struct MHD_Response *resp = MHD_create_response_from_buffer(n, t, MHD_RESPMEM_MUST_FREE);
    if (!resp) {
        free(t);
        return NULL;
    }
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, ctype) != MHD_YES) {
        MHD_destroy_response(resp);
        return NULL;
    }
    *len = n;
    return resp;
}

static enum MHD_Result send_json(req *r, struct MHD_Connection *c, unsigned status, cJSON *doc)
{
    size_t n = 0;
    struct MHD_Response *resp = json_response(doc, CT_JSON, &n);
    return send_response(r, c, status, resp, n);
}

/* Adds v to o under key k; on any failure frees v and clears *ok, so a
 * document built from many adds is checked once at the end. */
static cJSON *put(cJSON *o, const char *k, cJSON *v, bool *ok)
{
    if (!o || !v || !cJSON_AddItemToObject(o, k, v)) {
        cJSON_Delete(v);
        *ok = false;
        return NULL;
    }
    return v;
}

static cJSON *str_or_null(const char *s)
{
    return s && *s ? cJSON_CreateString(s) : cJSON_CreateNull();
}

/* RFC 9457 problem; pointer (may be NULL or "") names the offending job field.
 * extra_header/extra_value (may be NULL) add one header, e.g. Allow. */
static enum MHD_Result send_problem_h(req *r, struct MHD_Connection *c, problem_kind kind,
                                      const char *pointer, const char *extra_header,
                                      const char *extra_value, const char *fmt, va_list ap)
{
    char detail[1024];
    vsnprintf(detail, sizeof detail, fmt, ap);
    char type[128];
    snprintf(type, sizeof type, PROBLEM_BASE "%s", PROBLEMS[kind].slug);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "type", cJSON_CreateString(type), &ok);
    put(doc, "title", cJSON_CreateString(PROBLEMS[kind].title), &ok);
    put(doc, "status", cJSON_CreateNumber(PROBLEMS[kind].status), &ok);
    put(doc, "detail", cJSON_CreateString(detail), &ok);
    put(doc, "instance", cJSON_CreateString(r->url ? r->url : r->path), &ok);
    if (pointer && *pointer)
        put(doc, "pointer", cJSON_CreateString(pointer), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        doc = NULL;
    }
    size_t n = 0;
    struct MHD_Response *resp = json_response(doc, CT_PROBLEM, &n);
    if (resp && extra_header && MHD_add_response_header(resp, extra_header, extra_value) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return send_response(r, c, PROBLEMS[kind].status, resp, n);
}

#if defined(__GNUC__)
__attribute__((format(printf, 5, 6)))
#endif
static enum MHD_Result send_problem(req *r, struct MHD_Connection *c, problem_kind kind,
                                    const char *pointer, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    enum MHD_Result res = send_problem_h(r, c, kind, pointer, NULL, NULL, fmt, ap);
    va_end(ap);
    return res;
}

#if defined(__GNUC__)
__attribute__((format(printf, 6, 7)))
#endif
static enum MHD_Result send_problem_hdr(req *r, struct MHD_Connection *c, problem_kind kind,
                                        const char *header, const char *value, const char *fmt,
                                        ...)
{
    va_list ap;
    va_start(ap, fmt);
    enum MHD_Result res = send_problem_h(r, c, kind, NULL, header, value, fmt, ap);
    va_end(ap);
    return res;
}

/* The usual mapping of a daemon or store failure. */
static enum MHD_Result send_error(req *r, struct MHD_Connection *c, int code, const mr_error *e)
{
    const char *msg = e && e->msg[0] ? e->msg : mr_err_name(code);
    switch (code) {
    case MR_ERR_NOT_FOUND:
        return send_problem(r, c, P_NOT_FOUND, NULL, "%s", msg);
    case MR_ERR_CONFLICT:
        return send_problem(r, c, P_CONFLICT, NULL, "%s", msg);
    case MR_ERR_INVALID:
        return send_problem(r, c, P_BAD_REQUEST, NULL, "%s", msg);
    case MR_ERR_LIMIT:
        return send_problem(r, c, P_UNPROCESSABLE, NULL, "%s", msg);
    default:
        return send_problem(r, c, P_INTERNAL, NULL, "%s", msg);
    }
}

/* ---- job records as JSON ------------------------------------------------ */

static cJSON *time_or_null(double t)
{
    return t > 0 ? cJSON_CreateNumber(t) : cJSON_CreateNull();
}

static cJSON *job_json(const mr_job_record *j, bool *ok)
{
    cJSON *o = cJSON_CreateObject();
    put(o, "id", cJSON_CreateString(j->id), ok);
    put(o, "name", cJSON_CreateString(j->name), ok);
    put(o, "state", cJSON_CreateString(mr_job_state_name(j->state)), ok);
    put(o, "priority", cJSON_CreateNumber(j->priority), ok);
    put(o, "max_retries", cJSON_CreateNumber(j->max_retries), ok);
    cJSON *f = put(o, "frames", cJSON_CreateObject(), ok);
    put(f, "total", cJSON_CreateNumber((double)j->frame_count), ok);
    put(f, "done", cJSON_CreateNumber((double)j->frames_done), ok);
    put(f, "failed", cJSON_CreateNumber((double)j->frames_failed), ok);
    put(o, "created", time_or_null(j->created), ok);
    put(o, "started", time_or_null(j->started), ok);
    put(o, "finished", time_or_null(j->finished), ok);
    put(o, "error", str_or_null(j->error), ok);
    if (!o)
        *ok = false;
    return o;
}

static double num_or(const cJSON *o, const char *k, double fallback)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(o, k);
    return cJSON_IsNumber(v) ? v->valuedouble : fallback;
}

/* ---- request parsing helpers ------------------------------------------- */

/* Frame numbers are plain decimals (leading zeros allowed, as in 0007). */
static bool parse_index(const char *s, size_t *out)
{
    size_t v = 0, n = 0;
    for (; s[n]; n++) {
        if (s[n] < '0' || s[n] > '9' || n >= 12)
            return false;
        v = v * 10 + (size_t)(s[n] - '0');
    }
    *out = v;
    return n > 0;
}

/* The job named by the {id} parameter; answers 404 itself when unknown. */
static bool load_job(req *r, struct MHD_Connection *c, mr_job_record *job, enum MHD_Result *res)
{
    const char *id = r->params[0];
    if (!mr_hex_is_lower(id, MR_JOB_ID_LEN)) {
        *res = send_problem(r, c, P_NOT_FOUND, NULL, "no job with id '%s'", id);
        return false;
    }
    memcpy(r->job, id, MR_JOB_ID_LEN + 1);
    mr_error err = {0};
    int rc = mr_store_job_get(mr_daemon_store(r->h->d), id, job, &err);
    if (rc < 0) {
        *res = rc == MR_ERR_NOT_FOUND
                   ? send_problem(r, c, P_NOT_FOUND, NULL, "no job with id '%s'", id)
                   : send_error(r, c, rc, &err);
        return false;
    }
    return true;
}

/* ---- handlers: jobs ----------------------------------------------------- */

static bool idempotency_key_ok(const char *key)
{
    size_t n = strlen(key);
    if (n == 0 || n > IDEMPOTENCY_KEY_MAX)
        return false;
    for (size_t i = 0; i < n; i++)
        if ((unsigned char)key[i] < 0x20 || (unsigned char)key[i] > 0x7e)
            return false;
    return true;
}

static enum MHD_Result h_job_submit(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    const char *key = MHD_lookup_connection_value(c, MHD_HEADER_KIND, "Idempotency-Key");
    char id[MR_JOB_ID_LEN + 1] = "";
    char pointer[512] = "";
    bool existing = false;
    mr_error err = {0};
    int rc = mr_daemon_submit(h->d, r->body ? r->body : "", r->len, key, id, &existing, pointer,
                              &err);
    if (rc < 0) {
        const char *msg = err.msg[0] ? err.msg : mr_err_name(rc);
        switch (rc) {
        case MR_ERR_INVALID:
            return send_problem(r, c, P_INVALID_JOB, pointer, "%s", msg);
        case MR_ERR_LIMIT:
            /* The job parser's own size cap, when configured above it. */
            if (r->len > MR_JOB_MAX_BYTES)
                return send_problem(r, c, P_TOO_LARGE, NULL, "%s", msg);
            return send_problem(r, c, P_UNPROCESSABLE, pointer, "%s", msg);
        case MR_ERR_NOT_FOUND:
            return send_problem(r, c, P_UNPROCESSABLE, pointer, "%s", msg);
        case MR_ERR_CONFLICT:
            return send_problem(r, c, P_IDEMPOTENCY, NULL, "%s", msg);
        default:
            return send_problem(r, c, P_INTERNAL, NULL, "%s", msg);
        }
    }
    memcpy(r->job, id, sizeof r->job);
    char location[64];
    snprintf(location, sizeof location, "/v1/jobs/%s", id);
    /* A replay reports the job as it is now; a new job is queued by definition. */
    const char *state = mr_job_state_name(MR_JOB_QUEUED);
    mr_job_record rec;
    if (existing && mr_store_job_get(mr_daemon_store(h->d), id, &rec, NULL) == MR_OK)
        state = mr_job_state_name(rec.state);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "id", cJSON_CreateString(id), &ok);
    put(doc, "state", cJSON_CreateString(state), &ok);
    put(doc, "location", cJSON_CreateString(location), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return MHD_NO;
    }
    size_t n = 0;
    struct MHD_Response *resp = json_response(doc, CT_JSON, &n);
    if (resp && (MHD_add_response_header(resp, MHD_HTTP_HEADER_LOCATION, location) != MHD_YES ||
                 (existing &&
                  MHD_add_response_header(resp, "Idempotent-Replay", "true") != MHD_YES))) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return send_response(r, c, MHD_HTTP_ACCEPTED, resp, n);
}

static enum MHD_Result h_job_list(req *r, struct MHD_Connection *c)
{
    const char *state_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "state");
    mr_job_state state = MR_JOB_QUEUED;
    if (state_arg && !mr_job_state_parse(state_arg, &state))
        return send_problem(r, c, P_BAD_REQUEST, NULL,
                            "unknown state '%.64s'; expected queued, running, succeeded, failed "
                            "or canceled",
                            state_arg);
    mr_job_record *jobs = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_job_list(mr_daemon_store(r->h->d), state_arg != NULL, state, &jobs, &count,
                               &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    cJSON *arr = put(doc, "jobs", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < count && ok; i++) {
        cJSON *j = job_json(&jobs[i], &ok);
        if (!arr || !j || !cJSON_AddItemToArray(arr, j)) {
            cJSON_Delete(j);
            ok = false;
        }
    }
    free(jobs);
    if (!ok) {
        cJSON_Delete(doc);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return send_json(r, c, MHD_HTTP_OK, doc);
}

/* ---- the job detail, written by hand -------------------------------------
 * GET /v1/jobs/{id} is what clients poll, and a job may have up to 100,000
 * frames: building and printing a cJSON tree (and parsing every frame's
 * stats to find one number) cost about 8 us per frame, several times what
 * writing the text directly costs. */

typedef struct sbuf {
    char *p;
    size_t len, cap;
    bool oom;
} sbuf;

static void sb_reserve(sbuf *b, size_t more)
{
    if (b->oom || b->len + more + 1 <= b->cap)
        return;
    size_t cap = b->cap ? b->cap : 4096;
    while (cap < b->len + more + 1)
        cap *= 2;
    char *p = realloc(b->p, cap);
    if (!p) {
        b->oom = true;
        return;
    }
    b->p = p;
    b->cap = cap;
}

static void sb_put(sbuf *b, const char *s, size_t n)
{
    sb_reserve(b, n);
    if (b->oom)
        return;
    memcpy(b->p + b->len, s, n);
    b->len += n;
    b->p[b->len] = '\0';
}

#if defined(__GNUC__)
__attribute__((format(printf, 2, 3)))
#endif
static void sb_printf(sbuf *b, const char *fmt, ...)
{
    char tmp[256];
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(tmp, sizeof tmp, fmt, ap);
    va_end(ap);
    if (n > 0)
        sb_put(b, tmp, (size_t)n < sizeof tmp ? (size_t)n : sizeof tmp - 1);
}

/* A JSON string literal: quotes, backslashes and control characters escaped,
 * other bytes (UTF-8) as they are. */
static void sb_json_string(sbuf *b, const char *s)
{
    sb_put(b, "\"", 1);
    for (const char *run = s;; s++) {
        unsigned char ch = (unsigned char)*s;
        if (ch != 0 && ch >= 0x20 && ch != '"' && ch != '\\')
            continue;
        sb_put(b, run, (size_t)(s - run));
        if (ch == 0)
            break;
        if (ch == '"' || ch == '\\') {
            char esc[2] = {'\\', (char)ch};
            sb_put(b, esc, 2);
        } else {
            sb_printf(b, "\\u%04x", ch);
        }
        run = s + 1;
    }
    sb_put(b, "\"", 1);
}

static const char *skip_ws(const char *p)
{
    while (*p == ' ' || *p == '\t' || *p == '\n' || *p == '\r')
        p++;
    return p;
}

/* Past the JSON string starting at p (on its opening quote); NULL if unterminated. */
static const char *skip_string(const char *p)
{
    for (p++; *p; p++) {
        if (*p == '\\' && p[1])
            p++;
        else if (*p == '"')
            return p + 1;
    }
    return NULL;
}

/* Past the JSON value starting at p; NULL if the text ends first. */
static const char *skip_value(const char *p)
{
    int depth = 0;
    do {
        p = skip_ws(p);
        if (*p == '"') {
            p = skip_string(p);
            if (!p)
                return NULL;
        } else if (*p == '{' || *p == '[') {
            depth++;
            p++;
        } else if (*p == '}' || *p == ']') {
            if (--depth < 0)
                return NULL;
            p++;
        } else if (*p == ',' || *p == ':') {
            if (depth == 0)
                return p;
            p++;
        } else if (*p) {
            while (*p && !strchr(" \t\r\n,:{}[]\"", *p))
                p++;
        } else {
            return NULL;
        }
    } while (depth > 0);
    return p;
}

/* The value of member `key` of the object at p, or NULL. Keys with escapes
 * never match (none of the stats keys has one). */
static const char *json_member(const char *p, const char *key)
{
    p = p ? skip_ws(p) : NULL;
    if (!p || *p != '{')
        return NULL;
    p = skip_ws(p + 1);
    size_t kl = strlen(key);
    while (*p == '"') {
        const char *k = p + 1, *ke = skip_string(p);
        if (!ke)
            return NULL;
        bool match = (size_t)(ke - 1 - k) == kl && !memcmp(k, key, kl);
        p = skip_ws(ke);
        if (*p != ':')
            return NULL;
        p = skip_ws(p + 1);
        if (match)
            return p;
        p = skip_value(p);
        if (!p)
            return NULL;
        p = skip_ws(p);
        if (*p != ',')
            return NULL;
        p = skip_ws(p + 1);
    }
    return NULL;
}

/* Appends the number at p as it is written (it came from our own stats
 * JSON), or null when p holds no finite number. */
static void sb_json_number_at(sbuf *b, const char *p)
{
    char *end = NULL;
    double v = p ? strtod(p, &end) : 0;
    bool plain = p && end != p && strspn(p, "-.0123456789eE+") >= (size_t)(end - p);
    if (!plain || v != v || v > 1e300 || v < -1e300 || *p == '+' ||
        !strchr(" \t\r\n,}]", *end ? *end : ' ')) {
        sb_put(b, "null", 4);
        return;
    }
    sb_put(b, p, (size_t)(end - p));
}

static enum MHD_Result h_job_get(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &job, &res))
        return res;
    mr_frame_record *frames = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_frames(mr_daemon_store(r->h->d), job.id, &frames, &count, &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = job_json(&job, &ok);
    char *head = ok ? cJSON_PrintUnformatted(doc) : NULL;
    cJSON_Delete(doc);
    sbuf b = {0};
    size_t hl = head ? strlen(head) : 0;
    if (hl < 2 || head[hl - 1] != '}') {
        b.oom = true;
    } else {
        sb_reserve(&b, hl + count * 96 + 64);
        sb_put(&b, head, hl - 1); /* reopened to add frame_states */
    }
    free(head);
    sb_put(&b, ",\"frame_states\":[", 17);
    for (size_t i = 0; i < count && !b.oom; i++) {
        const mr_frame_record *f = &frames[i];
        sb_printf(&b, "%s{\"index\":%zu,\"state\":\"%s\",\"retries\":%d,\"error\":", i ? "," : "",
                  f->index, mr_frame_state_name(f->state), f->retries);
        if (f->error[0])
            sb_json_string(&b, f->error);
        else
            sb_put(&b, "null", 4);
        sb_put(&b, ",\"seconds\":", 11);
        sb_json_number_at(&b, json_member(json_member(f->stats_json, "seconds"), "total"));
        sb_put(&b, "}", 1);
    }
    sb_put(&b, "]}\n", 3);
    mr_frame_records_free(frames, count);
    if (b.oom) {
        free(b.p);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    struct MHD_Response *resp = MHD_create_response_from_buffer(b.len, b.p, MHD_RESPMEM_MUST_FREE);
    if (!resp) {
        free(b.p);
        return MHD_NO;
    }
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, CT_JSON) != MHD_YES) {
        MHD_destroy_response(resp);
        return MHD_NO;
    }
    return send_response(r, c, MHD_HTTP_OK, resp, b.len);
}

static enum MHD_Result h_job_cancel(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &job, &res))
        return res;
    mr_error err = {0};
    int rc = mr_daemon_cancel(r->h->d, job.id, &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    if (mr_store_job_get(mr_daemon_store(r->h->d), job.id, &job, &err) < 0)
        job.state = MR_JOB_CANCELED;
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "id", cJSON_CreateString(job.id), &ok);
    put(doc, "state", cJSON_CreateString(mr_job_state_name(job.state)), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return send_json(r, c, MHD_HTTP_ACCEPTED, doc);
}

static enum MHD_Result h_job_retry(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &job, &res))
        return res;
    mr_error err = {0};
    int rc = mr_daemon_retry(r->h->d, job.id, &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    if (mr_store_job_get(mr_daemon_store(r->h->d), job.id, &job, &err) < 0)
        job.state = MR_JOB_QUEUED;
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "id", cJSON_CreateString(job.id), &ok);
    put(doc, "state", cJSON_CreateString(mr_job_state_name(job.state)), &ok);
    put(doc, "frames_requeued", cJSON_CreateNumber(rc), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return send_json(r, c, MHD_HTTP_ACCEPTED, doc);
}

static enum MHD_Result h_job_delete(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &job, &res))
        return res;
    mr_error err = {0};
    int rc = mr_daemon_delete(r->h->d, job.id, &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    struct MHD_Response *resp =
        MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
    return send_response(r, c, MHD_HTTP_NO_CONTENT, resp, 0);
}

/* ---- handlers: frames and statistics ------------------------------------ */

/* The job and the frame index of a .../frames/{n} path; answers 404 itself. */
static bool load_frame(req *r, struct MHD_Connection *c, mr_job_record *job, size_t *index,
                       enum MHD_Result *res)
{
    if (!load_job(r, c, job, res))
        return false;
    if (!parse_index(r->params[1], index)) {
        *res = send_problem(r, c, P_NOT_FOUND, NULL, "'%s' is not a frame number", r->params[1]);
        return false;
    }
    if (*index >= job->frame_count) {
        *res = send_problem(r, c, P_NOT_FOUND, NULL, "job %s has %zu frames (0..%zu)", job->id,
                            job->frame_count, job->frame_count ? job->frame_count - 1 : 0);
        return false;
    }
    return true;
}

static enum MHD_Result h_frame_get(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    size_t index = 0;
    enum MHD_Result res = MHD_NO;
    if (!load_frame(r, c, &job, &index, &res))
        return res;
    char path[4096];
    mr_error err = {0};
    int rc = mr_store_frame_path(mr_daemon_store(r->h->d), job.id, index, path, sizeof path, &err);
    if (rc == MR_ERR_NOT_FOUND)
        return send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is not rendered", index,
                            job.id);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        /* Deleted between the lookup and here. */
        return errno == ENOENT ? send_problem(r, c, P_NOT_FOUND, NULL,
                                              "frame %zu of job %s is gone", index, job.id)
                               : send_problem(r, c, P_INTERNAL, NULL, "cannot open frame %zu: %s",
                                              index, strerror(errno));
    struct stat st;
    if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
        close(fd);
        return send_problem(r, c, P_INTERNAL, NULL, "frame %zu of job %s is not a file", index,
                            job.id);
    }
    struct MHD_Response *resp = MHD_create_response_from_fd((size_t)st.st_size, fd);
    if (!resp) {
        close(fd);
        return MHD_NO;
    }
    char name[MR_FRAME_NAME_MAX], disposition[MR_FRAME_NAME_MAX + 32];
    mr_frame_file_name(index, name);
    snprintf(disposition, sizeof disposition, "attachment; filename=\"%s\"", name);
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, "image/x-exr") != MHD_YES ||
        MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_DISPOSITION, disposition) !=
            MHD_YES) {
        MHD_destroy_response(resp);
        return MHD_NO;
    }
    return send_response(r, c, MHD_HTTP_OK, resp, (uint64_t)st.st_size);
}

static enum MHD_Result h_frame_stats(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    size_t index = 0;
    enum MHD_Result res = MHD_NO;
    if (!load_frame(r, c, &job, &index, &res))
        return res;
    mr_frame_record f;
    mr_error err = {0};
    int rc = mr_store_frame_get(mr_daemon_store(r->h->d), job.id, index, &f, &err);
    if (rc < 0 && rc != MR_ERR_NOT_FOUND)
        return send_error(r, c, rc, &err);
    if (rc < 0 || f.state != MR_FRAME_DONE || !f.stats_json) {
        free(f.stats_json);
        return send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is not rendered", index,
                            job.id);
    }
    size_t n = strlen(f.stats_json);
    struct MHD_Response *resp =
        MHD_create_response_from_buffer(n, f.stats_json, MHD_RESPMEM_MUST_COPY);
    free(f.stats_json);
    if (resp && MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, CT_JSON) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return send_response(r, c, MHD_HTTP_OK, resp, n);
}

static enum MHD_Result h_job_stats(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    mr_job_record rec;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &rec, &res))
        return res;
    mr_store *st = mr_daemon_store(h->d);
    mr_frame_record *frames = NULL;
    size_t count = 0, done = 0;
    mr_frame_stats *fs = NULL;
    cJSON **stored = NULL;
    char *doc_json = NULL, *text = NULL;
    mr_job *job = NULL;
    cJSON *root = NULL;
    mr_error err = {0};
    int rc = mr_store_frames(st, rec.id, &frames, &count, &err);
    if (rc < 0) {
        res = send_error(r, c, rc, &err);
        goto cleanup;
    }
    fs = calloc(count ? count : 1, sizeof *fs);
    stored = calloc(count ? count : 1, sizeof *stored);
    if (!fs || !stored)
        goto oom;
    double threads = 0;
    for (size_t i = 0; i < count; i++) {
        if (frames[i].state != MR_FRAME_DONE || !frames[i].stats_json)
            continue;
        cJSON *o = cJSON_Parse(frames[i].stats_json);
        if (!cJSON_IsObject(o)) {
            cJSON_Delete(o);
            continue;
        }
        /* job totals and medians come from the one writer (stats_json.c) */
        mr_frame_stats_from_json(o, frames[i].index, &fs[done]);
        threads = num_or(o, "threads", threads);
        stored[done++] = o;
    }

    /* Name, size and frame count as stats.json reports them; the stored
     * document is the validated job, so parsing it again cannot fail unless
     * the store is damaged, and then the record's figures stand in. */
    mr_job fallback = {0};
    fallback.name = rec.name;
    fallback.frame_count = rec.frame_count;
    if (mr_store_job_json(st, rec.id, &doc_json, &err) == MR_OK)
        mr_job_parse(doc_json, strlen(doc_json), &job, NULL);
    if (!(threads >= 1 && threads <= 65536)) {
        threads = h->render_threads;
        if (threads <= 0) {
            long n = sysconf(_SC_NPROCESSORS_ONLN);
            threads = n > 0 ? (double)n : 1;
        }
    }
    mr_job_stats stats = {.frame_count = done, .frames = fs, .threads = (unsigned)threads};
    text = mr_stats_to_json(job ? job : &fallback, &stats, 0);
    root = text ? cJSON_Parse(text) : NULL;
    if (!root)
        goto oom;

    /* The frames list shows what the store recorded, exactly (and with the
     * fields the daemon adds beyond stats.json's, such as cache hits); the
     * regenerated entries only fill in what it lacks. */
    cJSON *arr = cJSON_GetObjectItemCaseSensitive(root, "frames");
    size_t i = 0;
    for (cJSON *gen = arr ? arr->child : NULL; gen && i < done; gen = gen->next, i++)
        for (const cJSON *kv = stored[i]->child; kv; kv = kv->next) {
            if (!kv->string)
                continue;
            cJSON *dup = cJSON_Duplicate(kv, true);
            bool added = dup && (cJSON_HasObjectItem(gen, kv->string)
                                     ? cJSON_ReplaceItemInObjectCaseSensitive(gen, kv->string, dup)
                                     : cJSON_AddItemToObject(gen, kv->string, dup));
            if (!added) {
                cJSON_Delete(dup);
                goto oom;
            }
        }
    res = send_json(r, c, MHD_HTTP_OK, root);
    root = NULL;
    goto cleanup;
oom:
    res = send_problem(r, c, P_INTERNAL, NULL, "out of memory");
cleanup:
    cJSON_Delete(root);
    free(text);
    mr_job_free(job);
    free(doc_json);
    for (size_t k = 0; stored && k < done; k++)
        cJSON_Delete(stored[k]);
    free(stored);
    free(fs);
    mr_frame_records_free(frames, count);
    return res;
}

/* ---- handlers: assets and service --------------------------------------- */

static enum MHD_Result h_asset_put(req *r, struct MHD_Connection *c)
{
    if (r->len == 0 || !r->upload)
        return send_problem(r, c, P_BAD_REQUEST, NULL, "empty body: send the asset's bytes");
    char id[MR_ASSET_ID_LEN + 1] = "";
    bool existed = false;
    mr_error err = {0};
    mr_asset_upload *up = r->upload;
    r->upload = NULL; /* finish frees it */
    int rc = mr_store_asset_upload_finish(mr_daemon_store(r->h->d), up, id, &existed, &err);
    if (rc < 0)
        return send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "id", cJSON_CreateString(id), &ok);
    put(doc, "size", cJSON_CreateNumber((double)r->len), &ok);
    put(doc, "existed", cJSON_CreateBool(existed), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return send_json(r, c, existed ? MHD_HTTP_OK : MHD_HTTP_CREATED, doc);
}

static enum MHD_Result h_status(req *r, struct MHD_Connection *c, const char *status)
{
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    put(doc, "status", cJSON_CreateString(status), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return MHD_NO;
    }
    return send_json(r, c, MHD_HTTP_OK, doc);
}

static enum MHD_Result h_healthz(req *r, struct MHD_Connection *c)
{
    return h_status(r, c, "ok");
}

static enum MHD_Result h_readyz(req *r, struct MHD_Connection *c)
{
    if (atomic_load(&r->h->stopping) || !mr_daemon_ready(r->h->d))
        return send_problem(r, c, P_UNAVAILABLE, NULL, "the daemon is not ready for jobs");
    return h_status(r, c, "ready");
}

static enum MHD_Result h_metrics(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    char *daemon_text = mr_daemon_metrics(h->d);
    if (!daemon_text)
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    mr_http_counters k;
    mr_http_counters_get(h, &k);
    char own[1024];
    int n = snprintf(own, sizeof own,
                     "# HELP microray_http_requests_total HTTP requests received.\n"
                     "# TYPE microray_http_requests_total counter\n"
                     "microray_http_requests_total %llu\n"
                     "# HELP microray_http_responses_total HTTP error responses by status class.\n"
                     "# TYPE microray_http_responses_total counter\n"
                     "microray_http_responses_total{class=\"4xx\"} %llu\n"
                     "microray_http_responses_total{class=\"5xx\"} %llu\n",
                     (unsigned long long)k.requests, (unsigned long long)k.responses_4xx,
                     (unsigned long long)k.responses_5xx);
    size_t dn = strlen(daemon_text);
    bool nl = dn > 0 && daemon_text[dn - 1] != '\n';
    char *body = malloc(dn + nl + (size_t)n + 1);
    if (!body) {
        free(daemon_text);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    memcpy(body, daemon_text, dn);
    if (nl)
        body[dn] = '\n';
    memcpy(body + dn + nl, own, (size_t)n + 1);
    free(daemon_text);
    size_t len = dn + nl + (size_t)n;
    struct MHD_Response *resp = MHD_create_response_from_buffer(len, body, MHD_RESPMEM_MUST_FREE);
    if (!resp) {
        free(body);
        return MHD_NO;
    }
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, CT_METRICS) != MHD_YES) {
        MHD_destroy_response(resp);
        return MHD_NO;
    }
    return send_response(r, c, MHD_HTTP_OK, resp, len);
}

/* ---- server-sent events ------------------------------------------------- */

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
        s->notified = false;
        bool keepalive = s->keepalive_due;
        s->keepalive_due = false;
        pthread_mutex_unlock(&s->mu);

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

static enum MHD_Result h_job_events(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!load_job(r, c, &job, &res))
        return res;
    if (atomic_load(&h->stopping))
        return send_problem(r, c, P_UNAVAILABLE, NULL, "the daemon is stopping");
    sse_stream *s = calloc(1, sizeof *s);
    char *buf = malloc(EVENT_MAX);
    if (!s || !buf || pthread_mutex_init(&s->mu, NULL) != 0) {
        free(s);
        free(buf);
        return send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    s->h = h;
    s->conn = c;
    s->buf = buf;
    atomic_init(&s->refs, 1);
    atomic_init(&s->last_send_ms, mr_now_ms());
    atomic_init(&s->bytes, 0);
    s->sub = mr_events_subscribe(h->d, job.id);
    if (!s->sub) {
        s->closed = true;
        sse_release(s);
        return send_problem(r, c, P_UNAVAILABLE, NULL,
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
    return send_response(r, c, MHD_HTTP_OK, resp, 0);
}

/* Resumes streams that have been silent for KEEPALIVE_MS. Sleeps without a
 * timeout while there are no streams. */
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
            if (s->suspended && !s->closed &&
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

/* ---- routing ------------------------------------------------------------ */

static const route ROUTES[] = {
    {"POST", "/v1/assets", h_asset_put, BODY_ASSET},
    {"POST", "/v1/jobs", h_job_submit, BODY_JOB},
    {"GET", "/v1/jobs", h_job_list, BODY_NONE},
    {"GET", "/v1/jobs/{id}", h_job_get, BODY_NONE},
    {"DELETE", "/v1/jobs/{id}", h_job_delete, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames/{n}", h_frame_get, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames/{n}/stats", h_frame_stats, BODY_NONE},
    {"GET", "/v1/jobs/{id}/stats", h_job_stats, BODY_NONE},
    {"GET", "/v1/jobs/{id}/events", h_job_events, BODY_NONE},
    {"POST", "/v1/jobs/{id}/cancel", h_job_cancel, BODY_NONE},
    {"POST", "/v1/jobs/{id}/retry", h_job_retry, BODY_NONE},
    {"GET", "/healthz", h_healthz, BODY_NONE},
    {"GET", "/readyz", h_readyz, BODY_NONE},
    {"GET", "/metrics", h_metrics, BODY_NONE},
};
#define ROUTE_COUNT (sizeof ROUTES / sizeof ROUTES[0])

static const char *segment_end(const char *s)
{
    while (*s && *s != '/')
        s++;
    return s;
}

/* Matches path against pattern segment by segment, capturing {params}. */
static bool route_match(const char *pattern, const char *path, char params[][PARAM_MAX])
{
    size_t np = 0;
    const char *p = pattern, *u = path;
    while (*p && *u) {
        if (*p != '/' || *u != '/')
            return false;
        p++;
        u++;
        const char *pe = segment_end(p), *ue = segment_end(u);
        size_t pl = (size_t)(pe - p), ul = (size_t)(ue - u);
        if (pl > 2 && p[0] == '{') {
            if (ul == 0 || ul >= PARAM_MAX || np >= MAX_PARAMS)
                return false;
            if (params) {
                memcpy(params[np], u, ul);
                params[np][ul] = '\0';
            }
            np++;
        } else if (pl != ul || memcmp(p, u, pl) != 0) {
            return false;
        }
        p = pe;
        u = ue;
    }
    return *p == '\0' && *u == '\0';
}

/* HEAD is answered by the GET handler (libmicrohttpd drops the body). */
static bool method_is(const char *method, const char *route_method)
{
    return !strcmp(method, route_method) || (!strcmp(method, "HEAD") && !strcmp(route_method, "GET"));
}

static void add_allowed(char *allow, size_t size, const char *m)
{
    if (strstr(allow, m))
        return;
    size_t n = strlen(allow);
    snprintf(allow + n, size - n, "%s%s", n ? ", " : "", m);
}

static size_t body_cap(const mr_http *h, body_kind kind)
{
    switch (kind) {
    case BODY_JOB:
        return h->max_job_bytes;
    case BODY_ASSET:
        return h->max_asset_bytes;
    default:
        return SMALL_BODY_CAP;
    }
}

static enum MHD_Result too_large(req *r, struct MHD_Connection *c)
{
    return send_problem(r, c, P_TOO_LARGE, NULL, "the request body is over %zu bytes", r->limit);
}

/* 404 or 405 for a request that matched no route. */
static enum MHD_Result answer_unrouted(req *r, struct MHD_Connection *c)
{
    if (!r->allow[0])
        return send_problem(r, c, P_NOT_FOUND, NULL, "no resource at %s", r->path);
    return send_problem_hdr(r, c, P_METHOD, MHD_HTTP_HEADER_ALLOW, r->allow,
                            "%s is not allowed on %s; allowed: %s", r->method, r->path, r->allow);
}

/* First call for a request: route it and refuse what can be refused before
 * the body is read. A response queued now makes libmicrohttpd close the
 * connection afterwards (the body is left unread), so requests without a
 * body learn about a wrong route on the last call and keep their connection. */
static enum MHD_Result begin_request(req *r, struct MHD_Connection *c, const char *url,
                                     const char *method)
{
    mr_http *h = r->h;
    const char *cl = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_CONTENT_LENGTH);
    const char *te =
        MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_TRANSFER_ENCODING);
    unsigned long long length = 0;
    bool length_ok = false;
    if (cl) {
        char *end = NULL;
        errno = 0;
        length = strtoull(cl, &end, 10);
        length_ok = end != cl && errno != ERANGE;
        if (!length_ok)
            length = ULLONG_MAX;
    }
    bool has_body = te || (cl && length > 0);

    for (size_t i = 0; i < ROUTE_COUNT && !r->rt; i++) {
        if (!route_match(ROUTES[i].pattern, url, NULL))
            continue;
        if (method_is(method, ROUTES[i].method)) {
            r->rt = &ROUTES[i];
            route_match(ROUTES[i].pattern, url, r->params);
        }
    }
    if (!r->rt) {
        for (size_t i = 0; i < ROUTE_COUNT; i++)
            if (route_match(ROUTES[i].pattern, url, NULL)) {
                add_allowed(r->allow, sizeof r->allow, ROUTES[i].method);
                if (!strcmp(ROUTES[i].method, "GET"))
                    add_allowed(r->allow, sizeof r->allow, "HEAD");
            }
        return has_body ? answer_unrouted(r, c) : MHD_YES;
    }
    r->limit = body_cap(h, r->rt->body);
    r->keep_body = r->rt->body == BODY_JOB; /* assets stream to a file */
    if (cl && length > r->limit)
        return too_large(r, c);
    if (length_ok && r->keep_body && length > 0)
        r->cap = (size_t)length + 1; /* exact first allocation, with the NUL */
    if (r->rt->body == BODY_JOB) {
        const char *key = MHD_lookup_connection_value(c, MHD_HEADER_KIND, "Idempotency-Key");
        if (key && !idempotency_key_ok(key))
            return send_problem(r, c, P_BAD_REQUEST, NULL,
                                "Idempotency-Key must be 1 to %d printable ASCII characters",
                                IDEMPOTENCY_KEY_MAX);
    }
    return MHD_YES;
}

/* A body chunk: counted, and kept when the route wants it. Past the cap
 * nothing more is kept. A Content-Length over the cap was refused before
 * reading anything; a chunked body only shows its size as it arrives, and
 * libmicrohttpd 0.9.75 cannot queue a response in the middle of a body
 * (only on the first and the last call), so the excess is read and dropped
 * up to DRAIN_MAX to answer 413 at the end, and beyond that the connection
 * is closed without an answer. */
static enum MHD_Result take_body(req *r, struct MHD_Connection *c, const char *data, size_t *size)
{
    (void)c;
    size_t n = *size;
    *size = 0;
    if (r->over || n > r->limit - r->len) {
        if (!r->over) {
            r->over = true;
            free(r->body);
            r->body = NULL;
            r->cap = 0;
            mr_store_asset_upload_abort(r->upload);
            r->upload = NULL;
        }
        r->drained += n;
        if (r->drained <= DRAIN_MAX)
            return MHD_YES;
        r->status = MHD_HTTP_CONTENT_TOO_LARGE;
        atomic_fetch_add(&r->h->responses_4xx, 1);
        return MHD_NO;
    }
    if (r->rt->body == BODY_ASSET) {
        mr_error err = {0};
        if ((!r->upload && mr_store_asset_upload_begin(mr_daemon_store(r->h->d), &r->upload, &err) < 0) ||
            mr_store_asset_upload_write(r->upload, data, n, &err) < 0) {
            /* No answer can be queued mid-body: log and close the connection. */
            if (!r->h->quiet)
                fprintf(stderr, "microrayd: upload failed: %s\n", err.msg);
            r->status = MHD_HTTP_INTERNAL_SERVER_ERROR;
            atomic_fetch_add(&r->h->responses_5xx, 1);
            return MHD_NO;
        }
    } else if (r->keep_body) {
        size_t need = r->len + n + 1; /* + NUL: handlers get a C string */
        if (!r->body || need > r->cap) {
            /* First allocation: Content-Length exactly when known, else 64 KiB;
             * then doubling, never beyond the cap. */
            size_t cap = r->body ? 2 * r->cap : r->cap;
            if (!r->body && cap == 0)
                cap = 64 * 1024;
            if (cap < need)
                cap = need;
            if (cap > r->limit + 1)
                cap = r->limit + 1;
            char *b = realloc(r->body, cap);
            if (!b) {
                /* No answer can be queued mid-body: close the connection. */
                r->status = MHD_HTTP_INTERNAL_SERVER_ERROR;
                atomic_fetch_add(&r->h->responses_5xx, 1);
                return MHD_NO;
            }
            r->body = b;
            r->cap = cap;
        }
        memcpy(r->body + r->len, data, n);
        r->body[r->len + n] = '\0';
    }
    r->len += n;
    return MHD_YES;
}

static enum MHD_Result on_request(void *cls, struct MHD_Connection *c, const char *url,
                                  const char *method, const char *version,
                                  const char *upload_data, size_t *upload_data_size,
                                  void **con_cls)
{
    (void)version;
    mr_http *h = cls;
    req *r = *con_cls;
    if (!r) {
        r = calloc(1, sizeof *r);
        if (!r)
            return MHD_NO;
        *con_cls = r;
        r->h = h;
        r->t0 = mr_now();
        r->url = url;
        atomic_fetch_add(&h->requests, 1);
        snprintf(r->method, sizeof r->method, "%s", method);
        /* Log-safe copy: no spaces or control characters in the log line. */
        size_t i = 0;
        for (; url[i] && i + 1 < sizeof r->path; i++)
            r->path[i] = (unsigned char)url[i] > 0x20 && (unsigned char)url[i] < 0x7f ? url[i] : '?';
        r->path[i] = '\0';
        enum MHD_Result res = begin_request(r, c, url, method);
        r->url = NULL;
        return res;
    }
    if (r->answered) {
        /* libmicrohttpd does not call again after a response was queued, but
         * should it, the rest of the body is not ours to read. */
        *upload_data_size = 0;
        return MHD_YES;
    }
    r->url = url;
    enum MHD_Result res;
    if (!r->rt) {
        *upload_data_size = 0;
        res = answer_unrouted(r, c);
    } else if (*upload_data_size) {
        res = take_body(r, c, upload_data, upload_data_size);
    } else if (r->over) {
        res = too_large(r, c);
    } else {
        res = r->rt->fn(r, c);
    }
    r->url = NULL;
    return res;
}

static void on_completed(void *cls, struct MHD_Connection *c, void **con_cls,
                         enum MHD_RequestTerminationCode toe)
{
    (void)c;
    (void)toe;
    mr_http *h = cls;
    req *r = *con_cls;
    if (!r)
        return;
    *con_cls = NULL;
    mr_store_asset_upload_abort(r->upload); /* a body cut off or refused */
    if (r->sse) {
        sse_close(r->sse);
        r->bytes = atomic_load(&r->sse->bytes);
        sse_release(r->sse);
    }
    if (!h->quiet) {
        char status[16] = "-";
        if (r->answered || r->status)
            snprintf(status, sizeof status, "%u", r->status);
        double ms = (mr_now() - r->t0) * 1e3;
        fprintf(stderr, "microrayd: %s %s %s %llu %.1fms%s%s\n", r->method, r->path, status,
                (unsigned long long)r->bytes, ms, r->job[0] ? " job=" : "", r->job);
    }
    free(r->body);
    free(r);
}

static void on_mhd_log(void *cls, const char *fmt, va_list ap)
{
    mr_http *h = cls;
    if (h->quiet)
        return;
    char msg[512];
    vsnprintf(msg, sizeof msg, fmt, ap);
    size_t n = strlen(msg);
    while (n && (msg[n - 1] == '\n' || msg[n - 1] == '\r'))
        msg[--n] = '\0';
    fprintf(stderr, "microrayd: http: %s\n", msg);
}

/* ---- lifecycle ---------------------------------------------------------- */

/* Numeric IPv4 or IPv6 (brackets allowed), or "localhost". */
static int parse_host(const char *host, unsigned port, struct sockaddr_storage *ss, bool *v6,
                      mr_error *err)
{
    memset(ss, 0, sizeof *ss);
    char buf[INET6_ADDRSTRLEN + 2];
    size_t n = strlen(host);
    if (n >= 2 && host[0] == '[' && host[n - 1] == ']' && n - 2 < sizeof buf) {
        memcpy(buf, host + 1, n - 2);
        buf[n - 2] = '\0';
    } else {
        snprintf(buf, sizeof buf, "%s", host);
    }
    if (!strcmp(host, "localhost"))
        snprintf(buf, sizeof buf, "%s", DEFAULT_HOST);
    struct sockaddr_in *a4 = (struct sockaddr_in *)ss;
    struct sockaddr_in6 *a6 = (struct sockaddr_in6 *)ss;
    if (n < sizeof buf && inet_pton(AF_INET, buf, &a4->sin_addr) == 1) {
        a4->sin_family = AF_INET;
        a4->sin_port = htons((uint16_t)port);
        *v6 = false;
        return MR_OK;
    }
    if (n < sizeof buf && inet_pton(AF_INET6, buf, &a6->sin6_addr) == 1) {
        a6->sin6_family = AF_INET6;
        a6->sin6_port = htons((uint16_t)port);
        *v6 = true;
        return MR_OK;
    }
    return mr_error_set(err, MR_ERR_INVALID,
                        "listen address '%.200s' is not a numeric IPv4 or IPv6 address", host);
}

int mr_http_start(mr_daemon *d, const mr_daemon_config *cfg, mr_http **out, mr_error *err)
{
    *out = NULL;
    const char *host = cfg->listen_host && *cfg->listen_host ? cfg->listen_host : DEFAULT_HOST;
    if (cfg->port > 65535)
        return mr_error_set(err, MR_ERR_INVALID, "port %u is out of range", cfg->port);
    struct sockaddr_storage ss;
    bool v6 = false;
    int rc = parse_host(host, cfg->port, &ss, &v6, err);
    if (rc < 0)
        return rc;

    mr_http *h = calloc(1, sizeof *h);
    if (!h)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    h->d = d;
    h->quiet = cfg->quiet;
    h->max_job_bytes = cfg->max_job_bytes ? cfg->max_job_bytes : DEFAULT_JOB_BYTES;
    h->max_asset_bytes = cfg->max_asset_bytes ? cfg->max_asset_bytes : DEFAULT_ASSET_BYTES;
    h->render_threads = cfg->render_threads;
    atomic_init(&h->stopping, false);
    atomic_init(&h->requests, 0);
    atomic_init(&h->responses_4xx, 0);
    atomic_init(&h->responses_5xx, 0);
    pthread_condattr_t ca;
    bool mu_ok = false, cv_ok = false;
    if (pthread_mutex_init(&h->streams_mu, NULL) != 0)
        goto fail_sync;
    mu_ok = true;
    if (pthread_condattr_init(&ca) != 0)
        goto fail_sync;
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    cv_ok = pthread_cond_init(&h->tick_cv, &ca) == 0;
    pthread_condattr_destroy(&ca);
    if (!cv_ok)
        goto fail_sync;
    if (pthread_create(&h->ticker, NULL, ticker_main, h) != 0)
        goto fail_sync;
    h->ticker_running = true;

    long cores = sysconf(_SC_NPROCESSORS_ONLN);
    unsigned threads = cfg->http_threads ? cfg->http_threads : cores > 0 ? (unsigned)cores : 1;
    unsigned timeout = cfg->connection_timeout_s ? cfg->connection_timeout_s : DEFAULT_TIMEOUT_S;
    unsigned per_ip = cfg->per_ip_connections ? cfg->per_ip_connections : DEFAULT_PER_IP;
    unsigned flags = MHD_USE_INTERNAL_POLLING_THREAD | MHD_ALLOW_SUSPEND_RESUME | MHD_USE_ERROR_LOG;
    if (MHD_is_feature_supported(MHD_FEATURE_EPOLL) == MHD_YES)
        flags |= MHD_USE_EPOLL;
    if (v6)
        flags |= MHD_USE_IPv6;
    errno = 0;
    h->mhd = MHD_start_daemon(
        flags, (uint16_t)cfg->port, NULL, NULL, on_request, h,
        /* first, or libmicrohttpd logs its option parsing its own way */
        MHD_OPTION_EXTERNAL_LOGGER, on_mhd_log, h, MHD_OPTION_SOCK_ADDR,
        (const struct sockaddr *)&ss, MHD_OPTION_THREAD_POOL_SIZE, threads,
        MHD_OPTION_CONNECTION_TIMEOUT, timeout, MHD_OPTION_PER_IP_CONNECTION_LIMIT, per_ip,
        MHD_OPTION_CONNECTION_MEMORY_LIMIT, (size_t)CONNECTION_MEMORY, MHD_OPTION_NOTIFY_COMPLETED,
        on_completed, h, MHD_OPTION_END);
    if (!h->mhd) {
        int e = errno;
        rc = mr_error_set(err, MR_ERR_IO, "cannot listen on %s%s%s:%u: %s", v6 ? "[" : "", host,
                          v6 ? "]" : "", cfg->port,
                          e ? strerror(e) : "libmicrohttpd refused to start");
        mr_http_stop(h);
        return rc;
    }
    const union MHD_DaemonInfo *info = MHD_get_daemon_info(h->mhd, MHD_DAEMON_INFO_BIND_PORT);
    h->port = info && info->port ? info->port : cfg->port;
    *out = h;
    return MR_OK;

fail_sync:
    if (cv_ok)
        pthread_cond_destroy(&h->tick_cv);
    if (mu_ok)
        pthread_mutex_destroy(&h->streams_mu);
    free(h);
    return mr_error_set(err, MR_ERR_NOMEM, "cannot create the HTTP ticker thread");
}

unsigned mr_http_port(const mr_http *h)
{
    return h ? h->port : 0;
}

void mr_http_stop(mr_http *h)
{
    if (!h)
        return;
    /* Streams must not stay suspended: libmicrohttpd cannot stop with
     * suspended connections. Readers see `stopping` and end their streams. */
    atomic_store(&h->stopping, true);
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
    if (h->mhd)
        MHD_stop_daemon(h->mhd);
    pthread_cond_destroy(&h->tick_cv);
    pthread_mutex_destroy(&h->streams_mu);
    free(h);
}

void mr_http_counters_get(const mr_http *h, mr_http_counters *out)
{
    memset(out, 0, sizeof *out);
    if (!h)
        return;
    /* atomic_load needs a non-const object in C11's generic form. */
    mr_http *m = (mr_http *)h;
    out->requests = atomic_load(&m->requests);
    out->responses_4xx = atomic_load(&m->responses_4xx);
    out->responses_5xx = atomic_load(&m->responses_5xx);
}
