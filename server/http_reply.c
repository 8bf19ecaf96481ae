/*
 * http_reply.c - the front end's responses (http_internal.h): JSON bodies
 * with a trailing newline, RFC 9457 application/problem+json for every
 * non-2xx answer (schemas/openapi.yaml lists the slugs) and the mapping of
 * daemon and store failures onto them. Every answer goes through
 * http_send_response, which counts status classes for /metrics.
 */
#define _GNU_SOURCE /* asprintf */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

#include "http_internal.h"

#define PROBLEM_BASE "/problems/"
#define CT_PROBLEM "application/problem+json"
/* Seconds a 503 asks the client to wait when its cause says nothing
 * better: a stopping daemon is usually restarted within that. */
#define RETRY_AFTER_DEFAULT "5"

/* Every problem type: its status, slug, title and what it means (the page
 * GET /problems/<slug> serves; `type` is that path, a URI reference the
 * client resolves against the daemon's own address, RFC 9457 3.1.1). The
 * rule for a job: 400 `malformed-json` when the body is not one JSON text
 * (RFC 8259), 422 `invalid-job` for every JSON document that is not a
 * valid job (wrong types, unknown or duplicate fields, out of range, over a
 * cap, a reference or asset that does not resolve, over the memory budget),
 * 413 for a body over the size cap. */
static const struct {
    unsigned status;
    const char *slug, *title, *about;
} PROBLEMS[] = {
    [P_BAD_REQUEST] = {400, "bad-request", "Bad request",
                       "A header, query parameter or the request's framing is wrong (an "
                       "Idempotency-Key, a list filter, conflicting Content-Length fields, an "
                       "empty upload). The detail says which."},
    [P_MALFORMED_JSON] = {400, "malformed-json", "Malformed JSON",
                          "The job body is not one JSON text by RFC 8259: a syntax error, invalid "
                          "UTF-8, a NUL byte, a number JSON does not allow (064, 1.e1, +1) or data "
                          "after the value. The detail gives the byte offset, line and column. "
                          "Nothing of the job was read."},
    [P_INVALID_JOB] = {422, "invalid-job", "Invalid job",
                       "The body is JSON but not a valid job: a wrong type, an unknown or duplicate "
                       "field, a value out of range, over a cap (frames, pixels, objects, ...), a "
                       "reference that does not resolve (an object naming a missing asset), an "
                       "asset the daemon cannot find or may not read, or objects over the job "
                       "memory budget. `pointer` is the JSON pointer of the first problem and "
                       "`errors` lists every problem found ({pointer, detail}), not only the first; "
                       "`errors_omitted` counts those beyond the list's 32."},
    [P_UNAUTHORIZED] = {401, "unauthorized", "Authentication required",
                        "The daemon was started with a token (--token-file) and the request lacks "
                        "Authorization: Bearer <token>, or carries another token."},
    [P_NOT_FOUND] = {404, "not-found", "Not found",
                     "No route at this path, or no such job, frame, asset or problem type; also a "
                     "frame that is not rendered yet."},
    [P_METHOD] = {405, "method-not-allowed", "Method not allowed",
                  "The path exists but not for this method; the Allow header lists the methods it "
                  "has (OPTIONS answers with the same header)."},
    [P_NOT_ACCEPTABLE] = {406, "not-acceptable", "Not acceptable",
                          "The Accept header allows none of the representations of the resource "
                          "(frames are image/x-exr or image/png)."},
    [P_CONFLICT] = {409, "conflict", "Conflict with the resource's state",
                    "The action does not fit the resource's state: cancel of a finished job, retry "
                    "of a job that is not failed or canceled, deletion of an asset a job still "
                    "uses."},
    [P_TOO_LARGE] = {413, "body-too-large", "Request body too large",
                     "The request body is over the route's cap (jobs 1 MiB, assets 512 MiB by "
                     "default, every other route 4096 bytes)."},
    [P_URI_TOO_LONG] = {414, "uri-too-long", "Request target too long",
                        "The request target (path and query) is over 8192 bytes."},
    [P_RANGE] = {416, "range-not-satisfiable", "Range not satisfiable",
                 "The Range header asks for bytes the file does not have; Content-Range gives "
                 "its size."},
    [P_UNPROCESSABLE] = {422, "unprocessable", "Request cannot be processed",
                         "The request is well formed but over one of the daemon's limits."},
    [P_IDEMPOTENCY] = {422, "idempotency-key-reused", "Idempotency key reused with another body",
                       "The Idempotency-Key was used before with a different request body; the "
                       "same key with the same body returns the job of the first request."},
    [P_HEADERS_TOO_LARGE] = {431, "headers-too-large", "Request header fields too large",
                             "The request head (request line and headers) is over 16384 bytes."},
    [P_INTERNAL] = {500, "internal", "Internal server error",
                    "A failure on the daemon's side (the store, the disk, memory); the detail "
                    "says which."},
    [P_UNAVAILABLE] = {503, "unavailable", "Service unavailable",
                       "The daemon cannot take this request now: it is stopping (the frames in "
                       "progress finish, reads are served), the disk is full, or a resource is "
                       "busy (previews being made, event streams open). Retry-After says when to "
                       "try again."},
    [P_NO_SPACE] = {507, "insufficient-storage", "Insufficient storage",
                    "The data directory's disk is full: the render queue is paused until space is "
                    "freed (deleting jobs frees their frames); reads and deletes go on."},
};
#define PROBLEM_COUNT (sizeof PROBLEMS / sizeof PROBLEMS[0])

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
    if (status >= 100 && status < 600)
        atomic_fetch_add(&r->h->responses[status / 100], 1);
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
                                      const char *extra_value, cJSON *ext, const char *fmt,
                                      va_list ap)
{
    char raw[1024], detail[1024], instance[1024];
    vsnprintf(raw, sizeof raw, fmt, ap);
    /* what the client sent, quoted, may be any bytes: JSON wants UTF-8 */
    json_utf8_text(raw, detail, sizeof detail);
    json_utf8_text(r->url ? r->url : r->path, instance, sizeof instance);
    char type[128];
    snprintf(type, sizeof type, PROBLEM_BASE "%s", PROBLEMS[kind].slug);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "type", cJSON_CreateString(type), &ok);
    http_put(doc, "title", cJSON_CreateString(PROBLEMS[kind].title), &ok);
    http_put(doc, "status", cJSON_CreateNumber(PROBLEMS[kind].status), &ok);
    http_put(doc, "detail", cJSON_CreateString(detail), &ok);
    http_put(doc, "instance", cJSON_CreateString(instance), &ok);
    if (pointer && *pointer)
        http_put(doc, "pointer", cJSON_CreateString(pointer), &ok);
    /* extension members (RFC 9457 3.2), moved over */
    for (const cJSON *m = ext ? ext->child : NULL; m && ok; m = m->next)
        http_put(doc, m->string, cJSON_Duplicate(m, true), &ok);
    cJSON_Delete(ext);
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
    enum MHD_Result res = send_problem_h(r, c, kind, pointer, NULL, NULL, NULL, fmt, ap);
    va_end(ap);
    return res;
}

enum MHD_Result http_send_problem_ext(req *r, struct MHD_Connection *c, problem_kind kind,
                                      const char *pointer, cJSON *ext, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    enum MHD_Result res = send_problem_h(r, c, kind, pointer, NULL, NULL, ext, fmt, ap);
    va_end(ap);
    return res;
}

enum MHD_Result http_send_problem_hdr(req *r, struct MHD_Connection *c, problem_kind kind,
                                      const char *header, const char *value, const char *fmt,
                                      ...)
{
    va_list ap;
    va_start(ap, fmt);
    enum MHD_Result res = send_problem_h(r, c, kind, NULL, header, value, NULL, fmt, ap);
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

/* GET /problems/{slug}: what a problem type means, as a small HTML page
 * (the `type` of every problem document points here). */
enum MHD_Result http_problem_page(req *r, struct MHD_Connection *c)
{
    const char *slug = r->params[0];
    for (size_t i = 0; i < PROBLEM_COUNT; i++) {
        if (!PROBLEMS[i].slug || strcmp(PROBLEMS[i].slug, slug) != 0)
            continue;
        char *page = NULL;
        int n = asprintf(&page,
                         "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                         "<title>%u %s</title></head>\n<body><h1>%s</h1>\n"
                         "<p>HTTP status %u, problem type <code>%s%s</code> (RFC 9457).</p>\n"
                         "<p>%s</p>\n<p>All problem types: schemas/openapi.yaml of microray.</p>"
                         "\n</body></html>\n",
                         PROBLEMS[i].status, PROBLEMS[i].title, PROBLEMS[i].title,
                         PROBLEMS[i].status, PROBLEM_BASE, PROBLEMS[i].slug, PROBLEMS[i].about);
        if (n < 0)
            return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
        struct MHD_Response *resp = http_buffer_response(page, (size_t)n, "text/html; charset=utf-8");
        if (resp && MHD_add_response_header(resp, MHD_HTTP_HEADER_CACHE_CONTROL, "max-age=86400") != MHD_YES) {
            MHD_destroy_response(resp);
            resp = NULL;
        }
        return http_send_response(r, c, MHD_HTTP_OK, resp, (uint64_t)n);
    }
    return http_send_problem(r, c, P_NOT_FOUND, NULL, "no problem type '%s'", slug);
}
