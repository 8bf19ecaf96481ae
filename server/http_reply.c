/*
 * http_reply.c - the front end's responses (http_internal.h): JSON bodies
 * with a trailing newline, RFC 9457 application/problem+json for every
 * non-2xx answer (schemas/openapi.yaml lists the slugs) and the mapping of
 * daemon and store failures onto them. Every answer goes through
 * http_send_response, which counts status classes for /metrics.
 */
#include <stdio.h>
#include <stdlib.h>
#include <math.h>
#include <string.h>
#include <strings.h>
#include <time.h>

#include "http_internal.h"

#define PROBLEM_BASE "https://microray.invalid/problems/"
#define CT_PROBLEM "application/problem+json"
/* Seconds a 503 asks the client to wait when its cause says nothing
 * better: a stopping daemon is usually restarted within that. */
#define RETRY_AFTER_DEFAULT "5"

static const struct {
    unsigned status;
    const char *slug, *title;
} PROBLEMS[] = {
    [P_BAD_REQUEST] = {400, "bad-request", "Bad request"},
    [P_INVALID_JOB] = {400, "invalid-job", "Invalid job"},
    [P_UNAUTHORIZED] = {401, "unauthorized", "Authentication required"},
    [P_NOT_FOUND] = {404, "not-found", "Not found"},
    [P_METHOD] = {405, "method-not-allowed", "Method not allowed"},
    [P_NOT_ACCEPTABLE] = {406, "not-acceptable", "Not acceptable"},
    [P_CONFLICT] = {409, "conflict", "Conflict with the job's state"},
    [P_TOO_LARGE] = {413, "body-too-large", "Request body too large"},
    [P_URI_TOO_LONG] = {414, "uri-too-long", "Request target too long"},
    [P_UNPROCESSABLE] = {422, "unprocessable-job", "Job cannot be processed"},
    [P_IDEMPOTENCY] = {422, "idempotency-key-reused", "Idempotency key reused with another body"},
    [P_HEADERS_TOO_LARGE] = {431, "headers-too-large", "Request header fields too large"},
    [P_INTERNAL] = {500, "internal", "Internal server error"},
    [P_UNAVAILABLE] = {503, "unavailable", "Service unavailable"},
    [P_NO_SPACE] = {507, "insufficient-storage", "Insufficient storage"},
};

struct MHD_Response *http_buffer_response(char *body, size_t len, const char *ctype)
{
    struct MHD_Response *resp = MHD_create_response_from_buffer(len, body, MHD_RESPMEM_MUST_FREE);
    if (!resp) {
        free(body);
        return NULL;
    }
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, ctype) != MHD_YES) {
        MHD_destroy_response(resp);
        return NULL;
    }
    return resp;
}

/* Queues resp (which may be NULL after a failed allocation: the connection
 * is then closed) and drops our reference. */
enum MHD_Result http_send_response(req *r, struct MHD_Connection *c, unsigned status,
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
struct MHD_Response *http_json_response(cJSON *doc, const char *ctype, size_t *len)
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
    struct MHD_Response *resp = http_buffer_response(t, n, ctype);
    if (resp)
        *len = n;
    return resp;
}

enum MHD_Result http_send_json(req *r, struct MHD_Connection *c, unsigned status, cJSON *doc)
{
    size_t n = 0;
    struct MHD_Response *resp = http_json_response(doc, CT_JSON, &n);
    return http_send_response(r, c, status, resp, n);
}

/* Adds v to o under key k; on any failure frees v and clears *ok, so a
 * document built from many adds is checked once at the end. */
cJSON *http_put(cJSON *o, const char *k, cJSON *v, bool *ok)
{
    if (!o || !v || !cJSON_AddItemToObject(o, k, v)) {
        cJSON_Delete(v);
        *ok = false;
        return NULL;
    }
    return v;
}

enum MHD_Result http_send_built(req *r, struct MHD_Connection *c, unsigned status, cJSON *doc, bool ok)
{
    if (!ok) {
        cJSON_Delete(doc);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return http_send_json(r, c, status, doc);
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
    http_put(doc, "type", cJSON_CreateString(type), &ok);
    http_put(doc, "title", cJSON_CreateString(PROBLEMS[kind].title), &ok);
    http_put(doc, "status", cJSON_CreateNumber(PROBLEMS[kind].status), &ok);
    http_put(doc, "detail", cJSON_CreateString(detail), &ok);
    http_put(doc, "instance", cJSON_CreateString(r->url ? r->url : r->path), &ok);
    if (pointer && *pointer)
        http_put(doc, "pointer", cJSON_CreateString(pointer), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        doc = NULL;
    }
    size_t n = 0;
    struct MHD_Response *resp = http_json_response(doc, CT_PROBLEM, &n);
    if (resp && extra_header && MHD_add_response_header(resp, extra_header, extra_value) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    /* every 503 says when to come back (RFC 9110 10.2.3); callers that
     * know better pass their own */
    bool own_retry = extra_header && !strcasecmp(extra_header, "Retry-After");
    if (resp && PROBLEMS[kind].status == 503 && !own_retry &&
        MHD_add_response_header(resp, "Retry-After", RETRY_AFTER_DEFAULT) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return http_send_response(r, c, PROBLEMS[kind].status, resp, n);
}

enum MHD_Result http_send_problem(req *r, struct MHD_Connection *c, problem_kind kind,
                                  const char *pointer, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    enum MHD_Result res = send_problem_h(r, c, kind, pointer, NULL, NULL, fmt, ap);
    va_end(ap);
    return res;
}

enum MHD_Result http_send_problem_hdr(req *r, struct MHD_Connection *c, problem_kind kind,
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
enum MHD_Result http_send_error(req *r, struct MHD_Connection *c, int code, const mr_error *e)
{
    char msg[sizeof e->msg];
    mr_daemon_redact(r->h->d, e && e->msg[0] ? e->msg : mr_err_name(code), msg, sizeof msg);
    switch (code) {
    case MR_ERR_NOT_FOUND:
        return http_send_problem(r, c, P_NOT_FOUND, NULL, "%s", msg);
    case MR_ERR_CONFLICT:
        return http_send_problem(r, c, P_CONFLICT, NULL, "%s", msg);
    case MR_ERR_INVALID:
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "%s", msg);
    case MR_ERR_LIMIT:
        return http_send_problem(r, c, P_UNPROCESSABLE, NULL, "%s", msg);
    case MR_ERR_NO_SPACE:
        mr_daemon_no_space(r->h->d, msg);
        return http_send_problem(r, c, P_NO_SPACE, NULL, "%s (the render queue is paused until "
                                 "space is freed; reads and deletes still work)", msg);
    default:
        return http_send_problem(r, c, P_INTERNAL, NULL, "%s", msg);
    }
}


bool http_rfc3339(double t, char *out, size_t size)
{
    if (!(t >= 0 && t < 253402300800.0)) /* years 1970..9999 */
        return false;
    time_t whole = (time_t)floor(t);
    int ms = (int)((t - (double)whole) * 1000.0);
    if (ms > 999)
        ms = 999;
    struct tm tm;
    char date[32];
    if (!gmtime_r(&whole, &tm) || strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%S", &tm) == 0)
        return false;
    int n = snprintf(out, size, "%s.%03dZ", date, ms);
    return n > 0 && (size_t)n < size;
}

void http_url_encode(const char *s, char *out, size_t size)
{
    static const char hex[] = "0123456789ABCDEF";
    size_t o = 0;
    for (; *s && o + 4 <= size; s++) {
        unsigned char ch = (unsigned char)*s;
        if ((ch >= 'A' && ch <= 'Z') || (ch >= 'a' && ch <= 'z') || (ch >= '0' && ch <= '9') ||
            strchr("-._~", ch)) {
            out[o++] = (char)ch;
        } else {
            out[o++] = '%';
            out[o++] = hex[ch >> 4];
            out[o++] = hex[ch & 15];
        }
    }
    if (size)
        out[o < size ? o : size - 1] = '\0';
}
