/*
 * http.c - microrayd's HTTP front end on libmicrohttpd 0.9.75 (http.h):
 * its lifecycle and the request cycle. The routes are one table
 * (http_routes.c), answers are made by http_reply.c, handlers live in
 * http_handlers.c and event streams in http_events.c (http_internal.h).
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
 * The request's struct is made when libmicrohttpd has the request line
 * (its URI log callback), so the raw target's length is known for 414 and
 * every request gets its log line, also one libmicrohttpd answers itself.
 * Our limits on the head (URI_MAX, HEAD_MAX) are below what libmicrohttpd
 * can hold in CONNECTION_MEMORY, so our handler answers 414 and 431 as
 * problem+json; a head past libmicrohttpd's own limit (about 30 KiB, less
 * with many small headers) gets its text/html 414 or 431. The connection
 * guard (http_guard.c) learns each request's phase from here.
 */
#include "http.h"

#include <arpa/inet.h>
#include <errno.h>
#include <limits.h>
#include <netinet/in.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/socket.h>
#include <unistd.h>

#include "http_internal.h"
#include "microray.h"

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
/* Longest request target (path and query, as sent) and request head
 * (request line and headers) we answer; both well below what fits in
 * CONNECTION_MEMORY, so that libmicrohttpd hands such requests to us
 * rather than answering its own text/html 414 or 431. */
#define URI_MAX 8192
#define HEAD_MAX 16384

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
    return http_send_problem(r, c, P_TOO_LARGE, NULL, "the request body is over %zu bytes", r->limit);
}

/* 404 or 405 for a request that matched no route; OPTIONS on a path that
 * exists: 204 with the methods it has in Allow. */
static enum MHD_Result answer_unrouted(req *r, struct MHD_Connection *c)
{
    if (!r->allow[0])
        return http_send_problem(r, c, P_NOT_FOUND, NULL, "no resource at %s", r->path);
    if (!strcmp(r->method, "OPTIONS")) {
        struct MHD_Response *resp = MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
        if (resp && MHD_add_response_header(resp, MHD_HTTP_HEADER_ALLOW, r->allow) != MHD_YES) {
            MHD_destroy_response(resp);
            resp = NULL;
        }
        return http_send_response(r, c, MHD_HTTP_NO_CONTENT, resp, 0);
    }
    return http_send_problem_hdr(r, c, P_METHOD, MHD_HTTP_HEADER_ALLOW, r->allow,
                                 "%s is not allowed on %s; allowed: %s", r->method, r->path, r->allow);
}

/* First call for a request: route it and refuse what can be refused before
 * the body is read. A response queued now makes libmicrohttpd close the
 * connection afterwards (the body is left unread), so requests without a
 * body learn about a wrong route on the last call and keep their connection. */
/* libmicrohttpd's %HH decoding, except that a decoded NUL becomes DEL:
 * handlers see URLs and arguments as C strings, and "/v1/jobs/ID%00/frames/0"
 * must not turn into "/v1/jobs/ID" (it answered the job). DEL matches no
 * route, id or argument, so such a request gets the 404 or 400 its text
 * deserves. */
static size_t unescape_no_nul(void *cls, struct MHD_Connection *c, char *s)
{
    (void)cls, (void)c;
    size_t n = MHD_http_unescape(s);
    for (size_t i = 0; i < n; i++)
        if (s[i] == '\0')
            s[i] = 0x7F;
    return n;
}

/* Every Content-Length field of the request must say the same: a second,
 * different one means the request's framing is ambiguous (request
 * smuggling through a proxy that reads the other one). libmicrohttpd frames
 * the body by the first and does not look at the others. */
typedef struct length_fields {
    const char *first;
    bool conflict;
} length_fields;

static enum MHD_Result collect_length(void *cls, enum MHD_ValueKind kind, const char *key,
                                      const char *value)
{
    (void)kind;
    length_fields *f = cls;
    if (strcasecmp(key, MHD_HTTP_HEADER_CONTENT_LENGTH) != 0)
        return MHD_YES;
    if (!f->first)
        f->first = value ? value : "";
    else if (strcmp(f->first, value ? value : "") != 0)
        f->conflict = true;
    return MHD_YES;
}

/* Whether the request carries the daemon's bearer token. Compared as
 * SHA-256 digests, byte by byte without an early exit, so the time taken
 * tells nothing about the token (not even its length). */
static bool authorized(const mr_http *h, struct MHD_Connection *c, bool *presented)
{
    const char *auth = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_AUTHORIZATION);
    *presented = auth && strncasecmp(auth, "Bearer ", 7) == 0;
    if (!*presented)
        return false;
    const char *token = auth + 7;
    while (*token == ' ')
        token++;
    uint8_t digest[32];
    mr_sha256 sha;
    mr_sha256_init(&sha);
    mr_sha256_update(&sha, token, strlen(token));
    mr_sha256_final(&sha, digest);
    unsigned diff = 0;
    for (size_t i = 0; i < sizeof digest; i++)
        diff |= (unsigned)(digest[i] ^ h->token_digest[i]);
    return diff == 0;
}

static enum MHD_Result begin_request(req *r, struct MHD_Connection *c, const char *url,
                                     const char *method)
{
    mr_http *h = r->h;
    /* Before routing, so that without the token nothing (not even which
     * paths exist) is learned; the probes stay open for load balancers. */
    bool presented = false;
    if (h->has_token && strcmp(url, "/healthz") != 0 && strcmp(url, "/readyz") != 0 &&
        !authorized(h, c, &presented))
        return http_send_problem_hdr(r, c, P_UNAUTHORIZED, MHD_HTTP_HEADER_WWW_AUTHENTICATE,
                                     presented ? "Bearer realm=\"microrayd\", error=\"invalid_token\""
                                               : "Bearer realm=\"microrayd\"",
                                     presented ? "the bearer token is not this daemon's"
                                               : "this daemon needs Authorization: Bearer <token>");
    if (r->uri_len > URI_MAX) {
        r->url = NULL; /* the instance is the (cut) log copy, not 8 KiB echoed back */
        return http_send_problem(r, c, P_URI_TOO_LONG, NULL,
                                 "the request target is %zu bytes, over %d", r->uri_len, URI_MAX);
    }
    const union MHD_ConnectionInfo *head = MHD_get_connection_info(c, MHD_CONNECTION_INFO_REQUEST_HEADER_SIZE);
    if (head && head->header_size > HEAD_MAX)
        return http_send_problem(r, c, P_HEADERS_TOO_LARGE, NULL,
                                 "the request head is %zu bytes, over %d", head->header_size, HEAD_MAX);
    const char *cl = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_CONTENT_LENGTH);
    const char *te =
        MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_TRANSFER_ENCODING);
    length_fields fields = {0};
    MHD_get_connection_values(c, MHD_HEADER_KIND, collect_length, &fields);
    if (fields.conflict)
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "conflicting Content-Length headers");
    if (cl && te)
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "Content-Length and Transfer-Encoding together");
    /* libmicrohttpd refused (itself) a Content-Length that is not all digits
     * or does not fit 64 bits before calling us; what reaches us is one. */
    unsigned long long length = 0;
    bool length_ok = false;
    if (cl) {
        char *end = NULL;
        errno = 0;
        length = strtoull(cl, &end, 10);
        length_ok = end != cl && !*end && errno != ERANGE && cl[0] >= '0' && cl[0] <= '9';
        if (!length_ok)
            return http_send_problem(r, c, P_BAD_REQUEST, NULL, "malformed Content-Length");
    }
    bool has_body = te || (cl && length > 0);

    r->rt = http_route_find(method, url, r->params);
    if (!r->rt) {
        http_route_methods(url, r->allow, sizeof r->allow);
        return has_body ? answer_unrouted(r, c) : MHD_YES;
    }
    /* New work is refused while a stop drains (before the body is read);
     * reads, cancels and deletes go on. */
    if (r->rt->body != BODY_NONE && mr_daemon_stopping(h->d))
        return http_send_problem(r, c, P_UNAVAILABLE, NULL,
                                 "the daemon is stopping and takes no new work; try again once it "
                                 "is back");
    r->limit = body_cap(h, r->rt->body);
    r->keep_body = r->rt->body == BODY_JOB; /* assets stream to a file */
    if (cl && length > r->limit)
        return too_large(r, c);
    if (length_ok && r->keep_body && length > 0)
        r->cap = (size_t)length + 1; /* exact first allocation, with the NUL */
    if (r->rt->body == BODY_JOB) {
        const char *key = MHD_lookup_connection_value(c, MHD_HEADER_KIND, "Idempotency-Key");
        if (key && !idempotency_key_ok(key))
            return http_send_problem(r, c, P_BAD_REQUEST, NULL,
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
        atomic_fetch_add(&r->h->responses[4], 1);
        return MHD_NO;
    }
    if (r->rt->body == BODY_ASSET) {
        if (r->body_err.code < 0) { /* failed already: the rest is read and dropped */
            r->len += n;
            return MHD_YES;
        }
        if ((!r->upload && mr_store_asset_upload_begin(mr_daemon_store(r->h->d), &r->upload,
                                                       &r->body_err) < 0) ||
            mr_store_asset_upload_write(r->upload, data, n, &r->body_err) < 0) {
            /* No answer can be queued mid-body: the rest of the body (at
             * most the cap) is read and dropped, and the end answers why
             * (507 for a full disk). */
            mr_store_asset_upload_abort(r->upload);
            r->upload = NULL;
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
                atomic_fetch_add(&r->h->responses[5], 1);
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

/* A new request's struct; NULL when out of memory. */
static req *new_request(mr_http *h, struct MHD_Connection *c)
{
    req *r = calloc(1, sizeof *r);
    if (!r)
        return NULL;
    r->h = h;
    r->t0 = mr_now();
    r->conn = http_guard_of(c);
    snprintf(r->method, sizeof r->method, "-");
    snprintf(r->path, sizeof r->path, "-");
    atomic_fetch_add(&h->requests, 1);
    return r;
}

/* Log-safe copy: no spaces or control characters in the log line. */
static void set_log_path(req *r, const char *url)
{
    size_t i = 0;
    for (; url[i] && i + 1 < sizeof r->path; i++)
        r->path[i] = (unsigned char)url[i] > 0x20 && (unsigned char)url[i] < 0x7f ? url[i] : '?';
    r->path[i] = '\0';
}

/* libmicrohttpd's URI log callback: the request line is in, the headers
 * are not. What it returns becomes the request's *con_cls. */
static void *on_uri(void *cls, const char *uri, struct MHD_Connection *c)
{
    req *r = new_request(cls, c);
    if (r) {
        r->uri_len = strlen(uri);
        set_log_path(r, uri);
    }
    return r;
}

static enum MHD_Result on_request(void *cls, struct MHD_Connection *c, const char *url,
                                  const char *method, const char *version,
                                  const char *upload_data, size_t *upload_data_size,
                                  void **con_cls)
{
    (void)version;
    mr_http *h = cls;
    req *r = *con_cls;
    if (!r && !(r = *con_cls = new_request(h, c)))
        return MHD_NO;
    if (!r->begun) {
        r->begun = true;
        r->url = url;
        snprintf(r->method, sizeof r->method, "%s", method);
        set_log_path(r, url);
        enum MHD_Result res = begin_request(r, c, url, method);
        r->url = NULL;
        http_guard_phase(r->conn, r->answered ? PHASE_ANSWER : PHASE_BODY);
        return res;
    }
    if (r->answered) {
        /* libmicrohttpd does not call again after a response was queued, but
         * should it, the rest of the body is not ours to read. */
        *upload_data_size = 0;
        return MHD_YES;
    }
    if (!*upload_data_size) /* the body is in: what remains is ours to do */
        http_guard_phase(r->conn, PHASE_ANSWER);
    else
        http_guard_body(r->conn, *upload_data_size);
    r->url = url;
    enum MHD_Result res;
    if (!r->rt) {
        *upload_data_size = 0;
        res = answer_unrouted(r, c);
    } else if (*upload_data_size) {
        res = take_body(r, c, upload_data, upload_data_size);
    } else if (r->over) {
        res = too_large(r, c);
    } else if (r->body_err.code < 0) {
        res = http_send_error(r, c, r->body_err.code, &r->body_err);
    } else {
        res = r->rt->fn(r, c);
    }
    r->url = NULL;
    return res;
}

static void on_completed(void *cls, struct MHD_Connection *c, void **con_cls,
                         enum MHD_RequestTerminationCode toe)
{
    (void)toe;
    mr_http *h = cls;
    req *r = *con_cls;
    if (!r)
        return;
    *con_cls = NULL;
    /* A keep-alive connection now waits for its next request head. */
    http_guard_phase(r->conn, PHASE_HEAD);
    mr_store_asset_upload_abort(r->upload); /* a body cut off or refused */
    if (r->sse)
        r->bytes = http_events_request_done(r->sse);
    if (!h->quiet) {
        char status[16] = "-";
        if (r->answered || r->status) {
            snprintf(status, sizeof status, "%u", r->status);
        } else {
            /* answered by libmicrohttpd itself (a malformed head) */
            const union MHD_ConnectionInfo *i = MHD_get_connection_info(c, MHD_CONNECTION_INFO_HTTP_STATUS);
            if (i)
                snprintf(status, sizeof status, "%u", i->http_status);
        }
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

/* 127.0.0.0/8, ::1 and IPv4-mapped 127/8: only this machine can connect. */
static bool is_loopback(const struct sockaddr_storage *ss)
{
    if (ss->ss_family == AF_INET)
        return (ntohl(((const struct sockaddr_in *)ss)->sin_addr.s_addr) >> 24) == 127;
    const struct in6_addr *a = &((const struct sockaddr_in6 *)ss)->sin6_addr;
    return IN6_IS_ADDR_LOOPBACK(a) || (IN6_IS_ADDR_V4MAPPED(a) && a->s6_addr[12] == 127);
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
    if (!is_loopback(&ss) && !(cfg->token && *cfg->token) && !cfg->insecure)
        return mr_error_set(err, MR_ERR_INVALID,
                            "%.200s is not a loopback address: anyone who reaches it could submit, "
                            "read and delete jobs; give --token-file FILE (clients send "
                            "Authorization: Bearer <token>) or, on a trusted network, --insecure",
                            host);
    bool tls = cfg->tls_cert_pem || cfg->tls_key_pem;
    if (tls && !(cfg->tls_cert_pem && cfg->tls_key_pem))
        return mr_error_set(err, MR_ERR_INVALID, "TLS needs both --tls-cert and --tls-key");
    if (tls && MHD_is_feature_supported(MHD_FEATURE_TLS) != MHD_YES)
        return mr_error_set(err, MR_ERR_INVALID, "this libmicrohttpd is built without TLS");

    mr_http *h = calloc(1, sizeof *h);
    if (!h)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    h->d = d;
    h->quiet = cfg->quiet;
    h->max_job_bytes = cfg->max_job_bytes ? cfg->max_job_bytes : DEFAULT_JOB_BYTES;
    h->max_asset_bytes = cfg->max_asset_bytes ? cfg->max_asset_bytes : DEFAULT_ASSET_BYTES;
    h->render_threads = cfg->render_threads;
    if (cfg->token && *cfg->token) {
        mr_sha256 sha;
        mr_sha256_init(&sha);
        mr_sha256_update(&sha, cfg->token, strlen(cfg->token));
        mr_sha256_final(&sha, h->token_digest);
        h->has_token = true;
    }
    atomic_init(&h->stopping, false);
    atomic_init(&h->requests, 0);
    for (int i = 0; i < 6; i++)
        atomic_init(&h->responses[i], 0);
    /* Defaults of the budget and deadline: daemon.c (apply_defaults). */
    h->max_connections = cfg->max_connections;
    h->request_timeout_s = cfg->request_timeout_s;
    if ((rc = http_events_start(h, err)) < 0) {
        free(h);
        return rc;
    }
    if ((rc = http_guard_start(h, err)) < 0) {
        http_events_stop(h);
        http_events_free(h);
        free(h);
        return rc;
    }

    long cores = sysconf(_SC_NPROCESSORS_ONLN);
    unsigned threads = cfg->http_threads ? cfg->http_threads : cores > 0 ? (unsigned)cores : 1;
    h->previews_max = threads / 2 ? threads / 2 : 1;
    atomic_init(&h->previews_busy, 0);
    unsigned timeout = cfg->connection_timeout_s ? cfg->connection_timeout_s : DEFAULT_TIMEOUT_S;
    unsigned per_ip = cfg->per_ip_connections ? cfg->per_ip_connections : DEFAULT_PER_IP;
    /* libmicrohttpd splits its limit over its threads; per thread the whole
     * budget, so it is only the backstop of the guard's global count. */
    unsigned backstop = h->max_connections * threads;
    unsigned flags = MHD_USE_INTERNAL_POLLING_THREAD | MHD_ALLOW_SUSPEND_RESUME | MHD_USE_ERROR_LOG;
    if (MHD_is_feature_supported(MHD_FEATURE_EPOLL) == MHD_YES)
        flags |= MHD_USE_EPOLL;
    if (v6)
        flags |= MHD_USE_IPv6;
    if (tls)
        flags |= MHD_USE_TLS;
    /* libmicrohttpd copies neither: the PEM text lives in cfg, which
     * outlives the daemon. */
    struct MHD_OptionItem tls_opts[] = {
        {tls ? MHD_OPTION_HTTPS_MEM_KEY : MHD_OPTION_END, 0, (void *)cfg->tls_key_pem},
        {MHD_OPTION_HTTPS_MEM_CERT, 0, (void *)cfg->tls_cert_pem},
        {MHD_OPTION_END, 0, NULL},
    };
    errno = 0;
    h->mhd = MHD_start_daemon(
        flags, (uint16_t)cfg->port, http_guard_accept, h, on_request, h,
        /* first, or libmicrohttpd logs its option parsing its own way */
        MHD_OPTION_EXTERNAL_LOGGER, on_mhd_log, h, MHD_OPTION_SOCK_ADDR,
        (const struct sockaddr *)&ss, MHD_OPTION_THREAD_POOL_SIZE, threads,
        MHD_OPTION_CONNECTION_TIMEOUT, timeout, MHD_OPTION_PER_IP_CONNECTION_LIMIT, per_ip,
        MHD_OPTION_CONNECTION_LIMIT, backstop, MHD_OPTION_NOTIFY_CONNECTION, http_guard_notify, h,
        MHD_OPTION_URI_LOG_CALLBACK, on_uri, h,
        MHD_OPTION_CONNECTION_MEMORY_LIMIT, (size_t)CONNECTION_MEMORY, MHD_OPTION_NOTIFY_COMPLETED,
        on_completed, h, MHD_OPTION_UNESCAPE_CALLBACK, unescape_no_nul, NULL, MHD_OPTION_ARRAY,
        tls_opts, MHD_OPTION_END);
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
    http_events_stop(h);
    http_guard_stop(h);
    if (h->mhd)
        MHD_stop_daemon(h->mhd);
    http_events_free(h);
    http_guard_free(h);
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
    for (int i = 0; i < 6; i++)
        out->responses[i] = atomic_load(&m->responses[i]);
}
