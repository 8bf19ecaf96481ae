/*
 * http_handlers.c - the handlers of the job, frame, asset and service
 * routes (http_internal.h; the event stream's is in http_events.c), with
 * the frame route's content negotiation and the PNG preview routes (the
 * pictures and their disk cache are previews.c's). They run on
 * libmicrohttpd's thread pool and only parse, call the daemon or the store
 * and answer: rendering happens on the daemon's workers. The one heavier
 * thing done here, making a PNG preview from a stored EXR, is bounded (at
 * most previews_max at once, each made once and cached).
 */
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

#include "http_internal.h"
#include "job_json.h"
#include "previews.h"
#include "stats_json.h"
#include "microray.h"

#define CT_METRICS "text/plain; version=0.0.4; charset=utf-8"
#define CT_EXR "image/x-exr"
#define CT_PNG "image/png"

/* ---- job records as JSON ------------------------------------------------ */

static cJSON *str_or_null(const char *s)
{
    return s && *s ? cJSON_CreateString(s) : cJSON_CreateNull();
}

static cJSON *time_or_null(double t)
{
    return t > 0 ? cJSON_CreateNumber(t) : cJSON_CreateNull();
}

/* The same instant as an RFC 3339 string (UTC, milliseconds), or null. */
static cJSON *rfc3339_or_null(double t)
{
    char text[40];
    return t > 0 && mr_format_rfc3339(t, text, sizeof text) ? cJSON_CreateString(text) : cJSON_CreateNull();
}

static cJSON *job_json(const mr_job_record *j, bool *ok)
{
    cJSON *o = cJSON_CreateObject();
    http_put(o, "id", cJSON_CreateString(j->id), ok);
    http_put(o, "name", cJSON_CreateString(j->name), ok);
    http_put(o, "state", cJSON_CreateString(mr_job_state_name(j->state)), ok);
    http_put(o, "priority", cJSON_CreateNumber(j->priority), ok);
    http_put(o, "max_retries", cJSON_CreateNumber(j->max_retries), ok);
    cJSON *f = http_put(o, "frames", cJSON_CreateObject(), ok);
    http_put(f, "total", cJSON_CreateNumber((double)j->frame_count), ok);
    http_put(f, "done", cJSON_CreateNumber((double)j->frames_done), ok);
    http_put(f, "failed", cJSON_CreateNumber((double)j->frames_failed), ok);
    http_put(o, "created", time_or_null(j->created), ok);
    http_put(o, "started", time_or_null(j->started), ok);
    http_put(o, "finished", time_or_null(j->finished), ok);
    http_put(o, "created_at", rfc3339_or_null(j->created), ok);
    http_put(o, "started_at", rfc3339_or_null(j->started), ok);
    http_put(o, "finished_at", rfc3339_or_null(j->finished), ok);
    http_put(o, "error", str_or_null(j->error), ok);
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
bool http_load_job(req *r, struct MHD_Connection *c, mr_job_record *job, enum MHD_Result *res)
{
    const char *id = r->params[0];
    if (!mr_hex_is_lower(id, MR_JOB_ID_LEN)) {
        *res = http_send_problem(r, c, P_NOT_FOUND, NULL, "no job with id '%s'", id);
        return false;
    }
    memcpy(r->job, id, MR_JOB_ID_LEN + 1);
    mr_error err = {0};
    int rc = mr_store_job_get(mr_daemon_store(r->h->d), id, job, &err);
    if (rc < 0) {
        *res = rc == MR_ERR_NOT_FOUND
                   ? http_send_problem(r, c, P_NOT_FOUND, NULL, "no job with id '%s'", id)
                   : http_send_error(r, c, rc, &err);
        return false;
    }
    return true;
}

/* ---- handlers: jobs ----------------------------------------------------- */

/* A refused job: 413 over the size cap; 400 malformed-json when the body
 * is not JSON; 422 invalid-job with the first problem's pointer and every
 * problem in `errors`; else the daemon's error as usual. */
static enum MHD_Result job_refused(req *r, struct MHD_Connection *c, int rc,
                                   const mr_job_problems *problems, const mr_error *err)
{
    const mr_json_error *first = problems->count ? &problems->items[0] : NULL;
    if (rc == MR_ERR_LIMIT && r->len > MR_JOB_MAX_BYTES)
        return http_send_problem(r, c, P_TOO_LARGE, NULL, "%s", err->msg);
    if (rc == MR_ERR_CONFLICT)
        return http_send_problem(r, c, P_IDEMPOTENCY, NULL, "%s", err->msg);
    if (!first || (rc != MR_ERR_INVALID && rc != MR_ERR_LIMIT && rc != MR_ERR_NOT_FOUND))
        return http_send_error(r, c, rc, err);
    if (first->syntax)
        return http_send_problem(r, c, P_MALFORMED_JSON, NULL, "%s", first->message);
    bool ok = true;
    cJSON *ext = cJSON_CreateObject();
    cJSON *list = http_put(ext, "errors", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < problems->count && ok; i++) {
        char redacted[sizeof problems->items[i].message], shown[sizeof redacted];
        char pointer[sizeof problems->items[i].pointer];
        mr_daemon_redact(r->h->d, problems->items[i].message, redacted, sizeof redacted);
        /* UTF-8 text: a message cut to its size may end inside a character */
        json_utf8_text(redacted, shown, sizeof shown);
        json_utf8_text(problems->items[i].pointer, pointer, sizeof pointer);
        cJSON *e = cJSON_CreateObject();
        http_put(e, "pointer", cJSON_CreateString(pointer), &ok);
        http_put(e, "detail", cJSON_CreateString(shown), &ok);
        if (!e || !cJSON_AddItemToArray(list, e)) {
            cJSON_Delete(e);
            ok = false;
        }
    }
    if (problems->more)
        http_put(ext, "errors_omitted", cJSON_CreateNumber((double)problems->more), &ok);
    if (!ok) {
        cJSON_Delete(ext);
        ext = NULL;
    }
    char shown[sizeof first->message];
    mr_daemon_redact(r->h->d, first->message, shown, sizeof shown);
    return http_send_problem_ext(r, c, P_INVALID_JOB, first->pointer, ext, "%s", shown);
}

/* POST /v1/jobs?dry_run=1: what a submission would do, without queuing:
 * the job's size and work, the memory it surely needs, its assets' files,
 * which objects derive data (built on first use, then kept) and the
 * reference passes its frames get. */
static enum MHD_Result job_estimate(req *r, struct MHD_Connection *c, const mr_job *job)
{
    const mr_daemon_config *cfg = mr_daemon_config_of(r->h->d);
    const mr_output_desc *o = &job->output;
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "valid", cJSON_CreateTrue(), &ok);
    http_put(doc, "name", cJSON_CreateString(job->name ? job->name : ""), &ok);
    http_put(doc, "frames", cJSON_CreateNumber((double)job->frame_count), &ok);
    http_put(doc, "width", cJSON_CreateNumber(o->width), &ok);
    http_put(doc, "height", cJSON_CreateNumber(o->height), &ok);
    http_put(doc, "samples", cJSON_CreateNumber(o->spp), &ok);
    http_put(doc, "camera_rays", cJSON_CreateNumber((double)job->frame_count * o->width * o->height * o->spp),
             &ok);
    cJSON *mem = http_put(doc, "memory", cJSON_CreateObject(), &ok);
    size_t floor = mr_job_memory_floor(job);
    http_put(mem, "geometry_floor", cJSON_CreateNumber((double)floor), &ok);
    http_put(mem, "film", cJSON_CreateNumber((double)mr_film_bytes(o->width, o->height, o->aovs,
                                                                     mr_output_crypto_ranks(o))),
             &ok);
    http_put(mem, "budget", cJSON_CreateNumber((double)cfg->job_memory), &ok);
    cJSON *assets = http_put(doc, "assets", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < job->asset_count && ok; i++) {
        const mr_asset_desc *a = &job->assets[i];
        struct stat st;
        cJSON *e = cJSON_CreateObject();
        http_put(e, "name", cJSON_CreateString(a->name), &ok);
        http_put(e, "source", cJSON_CreateString(a->id ? "upload" : "path"), &ok);
        http_put(e, "bytes", stat(a->path, &st) == 0 ? cJSON_CreateNumber((double)st.st_size)
                                                     : cJSON_CreateNull(), &ok);
        if (!e || !cJSON_AddItemToArray(assets, e)) {
            cJSON_Delete(e);
            ok = false;
        }
    }
    cJSON *derived = http_put(doc, "derived", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < job->object_count && ok; i++) {
        const mr_kind *k = job->objects[i].kind;
        if (!mr_object_derives(&job->objects[i]))
            continue;
        char pointer[32];
        snprintf(pointer, sizeof pointer, "/objects/%zu", i);
        cJSON *e = cJSON_CreateObject();
        http_put(e, "pointer", cJSON_CreateString(pointer), &ok);
        http_put(e, "kind", cJSON_CreateString(mr_kind_name(k)), &ok);
        if (!e || !cJSON_AddItemToArray(derived, e)) {
            cJSON_Delete(e);
            ok = false;
        }
    }
    cJSON *refs = http_put(doc, "references", cJSON_CreateArray(), &ok);
    unsigned passes = 0;
    mr_error err = {0};
    if (mr_job_reference_passes(job, &passes, &err) < 0)
        ok = false;
    for (int t = 0; t < MR_REFERENCE_TYPES && ok; t++)
        if (passes & (1u << t))
            ok = cJSON_AddItemToArray(refs, cJSON_CreateString(mr_reference_name(t)));
    return http_send_built(r, c, MHD_HTTP_OK, doc, ok);
}

/* dry_run: absent, "0"/"false" (no), "1"/"true" (yes); anything else -1,
 * a bare `?dry_run` and an empty value included (libmicrohttpd gives the
 * bare key a NULL value, which MHD_lookup_connection_value cannot tell
 * from an absent one: read that way, `?dry_run` queued the job). */
static int dry_run_arg(struct MHD_Connection *c)
{
    static const char key[] = "dry_run";
    const char *v = NULL;
    size_t n = 0;
    if (MHD_lookup_connection_value_n(c, MHD_GET_ARGUMENT_KIND, key, sizeof key - 1, &v, &n) != MHD_YES)
        return 0;
    if (!v)
        return -1;
    if (!strcmp(v, "0") || !strcmp(v, "false"))
        return 0;
    if (!strcmp(v, "1") || !strcmp(v, "true"))
        return 1;
    return -1;
}

enum MHD_Result http_job_submit(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    int dry = dry_run_arg(c);
    if (dry < 0)
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "dry_run: expected 1, true, 0 or false");
    const char *key = MHD_lookup_connection_value(c, MHD_HEADER_KIND, "Idempotency-Key");
    char id[MR_JOB_ID_LEN + 1] = "";
    bool existing = false;
    mr_error err = {0};
    mr_job_problems *problems = calloc(1, sizeof *problems);
    if (!problems)
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    mr_job *job = NULL;
    int rc = dry ? mr_daemon_check_job(h->d, r->body ? r->body : "", r->len, &job, problems, &err)
                 : mr_daemon_submit(h->d, r->body ? r->body : "", r->len, key, id, &existing, problems,
                                    &err);
    if (rc < 0) {
        enum MHD_Result res = job_refused(r, c, rc, problems, &err);
        free(problems);
        return res;
    }
    free(problems);
    if (dry) {
        enum MHD_Result res = job_estimate(r, c, job);
        mr_job_free(job);
        return res;
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
    http_put(doc, "id", cJSON_CreateString(id), &ok);
    http_put(doc, "state", cJSON_CreateString(state), &ok);
    http_put(doc, "location", cJSON_CreateString(location), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return MHD_NO;
    }
    size_t n = 0;
    struct MHD_Response *resp = http_json_response(doc, CT_JSON, &n);
    if (resp && (MHD_add_response_header(resp, MHD_HTTP_HEADER_LOCATION, location) != MHD_YES ||
                 (existing &&
                  MHD_add_response_header(resp, "Idempotent-Replay", "true") != MHD_YES))) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return http_send_response(r, c, MHD_HTTP_ACCEPTED, resp, n);
}

/* GET /v1/jobs: pages of at most `limit` jobs (default LIST_LIMIT_DEFAULT),
 * newest first, filtered by `state` and `name`; `next` (and a Link header
 * with rel="next") carries the cursor of the following page, null on the
 * last. The cursor is opaque to clients: the submission number of the
 * page's last job, so pages stay put while new jobs arrive. */
#define LIST_LIMIT_DEFAULT 100
#define LIST_LIMIT_MAX 1000

enum MHD_Result http_job_list(req *r, struct MHD_Connection *c)
{
    const char *state_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "state");
    const char *limit_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "limit");
    const char *cursor_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "cursor");
    const char *name_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "name");
    mr_job_query q = {.limit = LIST_LIMIT_DEFAULT};
    if (state_arg && !mr_job_state_parse(state_arg, &q.state))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "unknown state '%.64s'; expected queued, running, succeeded, failed "
                                 "or canceled",
                                 state_arg);
    q.by_state = state_arg != NULL;
    size_t limit = 0;
    if (limit_arg && (!parse_index(limit_arg, &limit) || limit < 1 || limit > LIST_LIMIT_MAX))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "limit '%.32s': expected an integer in 1..%d", limit_arg,
                                 LIST_LIMIT_MAX);
    if (limit_arg)
        q.limit = limit;
    size_t cursor = 0;
    if (cursor_arg && (!parse_index(cursor_arg, &cursor) || cursor < 1))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "cursor '%.32s' is not one this daemon gave (the \"next\" of a page)",
                                 cursor_arg);
    q.before = (int64_t)cursor;
    if (name_arg && (!name_arg[0] || strlen(name_arg) > 256))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "name: expected 1..256 bytes");
    q.name = name_arg;
    mr_job_record *jobs = NULL;
    size_t count = 0;
    int64_t next = 0;
    mr_error err = {0};
    int rc = mr_store_job_list(mr_daemon_store(r->h->d), &q, &jobs, &count, &next, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    cJSON *arr = http_put(doc, "jobs", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < count && ok; i++) {
        cJSON *j = job_json(&jobs[i], &ok);
        if (!arr || !j || !cJSON_AddItemToArray(arr, j)) {
            cJSON_Delete(j);
            ok = false;
        }
    }
    free(jobs);
    char cursor_text[24] = "", link[1024] = "";
    if (next > 0) {
        snprintf(cursor_text, sizeof cursor_text, "%lld", (long long)next);
        char name_q[800] = "";
        if (q.name) {
            char enc[780];
            http_url_encode(q.name, enc, sizeof enc);
            snprintf(name_q, sizeof name_q, "&name=%s", enc);
        }
        snprintf(link, sizeof link, "</v1/jobs?limit=%zu&cursor=%s%s%s%s>; rel=\"next\"", q.limit,
                 cursor_text, q.by_state ? "&state=" : "", q.by_state ? mr_job_state_name(q.state) : "",
                 name_q);
    }
    http_put(doc, "next", next > 0 ? cJSON_CreateString(cursor_text) : cJSON_CreateNull(), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    size_t n = 0;
    struct MHD_Response *resp = http_json_response(doc, CT_JSON, &n);
    if (resp && link[0] && MHD_add_response_header(resp, "Link", link) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return http_send_response(r, c, MHD_HTTP_OK, resp, n);
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

enum MHD_Result http_job_get(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &job, &res))
        return res;
    mr_frame_record *frames = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_frames(mr_daemon_store(r->h->d), job.id, &frames, &count, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
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
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    return http_send_response(r, c, MHD_HTTP_OK, http_buffer_response(b.p, b.len, CT_JSON), b.len);
}

/* Runs the daemon's action (cancel, retry, delete) on the job of the path,
 * its result in *result; false when it answered itself (unknown job, or the
 * action failed). */
static bool job_action(req *r, struct MHD_Connection *c,
                       int (*action)(mr_daemon *d, const char *id, mr_error *err),
                       mr_job_record *job, int *result, enum MHD_Result *res)
{
    if (!http_load_job(r, c, job, res))
        return false;
    mr_error err = {0};
    *result = action(r->h->d, job->id, &err);
    if (*result < 0) {
        *res = http_send_error(r, c, *result, &err);
        return false;
    }
    return true;
}

/* POST .../cancel and .../retry: 202 with the job's id and state as they
 * are after the action (fallback when the store cannot say) and, for a
 * retry, how many frames it re-queued. */
static enum MHD_Result change_job(req *r, struct MHD_Connection *c,
                                  int (*action)(mr_daemon *d, const char *id, mr_error *err),
                                  mr_job_state fallback, bool report_requeued)
{
    mr_job_record job;
    int requeued = 0;
    enum MHD_Result res = MHD_NO;
    if (!job_action(r, c, action, &job, &requeued, &res))
        return res;
    mr_error err = {0};
    if (mr_store_job_get(mr_daemon_store(r->h->d), job.id, &job, &err) < 0)
        job.state = fallback;
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "id", cJSON_CreateString(job.id), &ok);
    http_put(doc, "state", cJSON_CreateString(mr_job_state_name(job.state)), &ok);
    if (report_requeued)
        http_put(doc, "frames_requeued", cJSON_CreateNumber(requeued), &ok);
    return http_send_built(r, c, MHD_HTTP_ACCEPTED, doc, ok);
}

enum MHD_Result http_job_cancel(req *r, struct MHD_Connection *c)
{
    return change_job(r, c, mr_daemon_cancel, MR_JOB_CANCELED, false);
}

enum MHD_Result http_job_retry(req *r, struct MHD_Connection *c)
{
    return change_job(r, c, mr_daemon_retry, MR_JOB_QUEUED, true);
}

enum MHD_Result http_job_delete(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    int rc = 0;
    enum MHD_Result res = MHD_NO;
    if (!job_action(r, c, mr_daemon_delete, &job, &rc, &res))
        return res;
    struct MHD_Response *empty = MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
    return http_send_response(r, c, MHD_HTTP_NO_CONTENT, empty, 0);
}

/* ---- handlers: frames and statistics ------------------------------------ */

/* The job and the frame index of a .../frames/{n} path; answers 404 itself. */
static bool load_frame(req *r, struct MHD_Connection *c, mr_job_record *job, size_t *index,
                       enum MHD_Result *res)
{
    if (!http_load_job(r, c, job, res))
        return false;
    if (!parse_index(r->params[1], index)) {
        *res = http_send_problem(r, c, P_NOT_FOUND, NULL, "'%s' is not a frame number", r->params[1]);
        return false;
    }
    if (*index >= job->frame_count) {
        *res = http_send_problem(r, c, P_NOT_FOUND, NULL, "job %s has %zu frames (0..%zu)", job->id,
                                 job->frame_count, job->frame_count ? job->frame_count - 1 : 0);
        return false;
    }
    return true;
}

/* ---- content negotiation (RFC 9110 12.5.1) --------------------------------
 * Accept lists media ranges (a type such as image/png, a type's family as
 * "image/" and an asterisk, or anything as an asterisk on both sides of the
 * slash) with optional weights (";q=0.5", three decimals at most). Each representation
 * takes the weight of the most specific range that matches it (several
 * equally specific ones: the highest), 0 when none matches; the highest
 * weight wins, ties go to the server's order of preference, and when every
 * weight is 0 the answer is 406. Elements that do not parse are ignored,
 * and a request without an Accept header (or without any element that
 * parses) accepts anything. Parameters other than q do not narrow a range. */

typedef struct accept_state {
    const char *const *types; /* "type/subtype", the server's preference first */
    size_t n;
    int spec[4];  /* specificity of the best range matching types[i]: 0 none, 1 any,
                     2 type/ *, 3 exact */
    int q[4];     /* its weight, in thousandths */
    bool parsed;  /* some element was understood */
} accept_state;

static const char *ows(const char *p)
{
    while (*p == ' ' || *p == '\t')
        p++;
    return p;
}

static bool is_tchar(char ch)
{
    return ch > 0x20 && ch < 0x7f && !strchr("\"(),/:;<=>?@[\\]{}", ch);
}

static const char *token_end(const char *p)
{
    while (is_tchar(*p))
        p++;
    return p;
}

/* Past the quoted string at p (on its opening quote); NULL if unterminated. */
static const char *quoted_end(const char *p)
{
    for (p++; *p; p++) {
        if (*p == '\\' && p[1])
            p++;
        else if (*p == '"')
            return p + 1;
    }
    return NULL;
}

/* The comma ending the element at p (outside quoted strings), or the NUL. */
static const char *element_end(const char *p)
{
    while (*p && *p != ',') {
        if (*p == '"') {
            const char *e = quoted_end(p);
            if (!e)
                return p + strlen(p);
            p = e;
        } else {
            p++;
        }
    }
    return p;
}

/* qvalue = ("0" ["." 0*3DIGIT]) / ("1" ["." 0*3"0"]), in thousandths; -1 if not one. */
static int parse_qvalue(const char *p, const char *end)
{
    if (p == end || (*p != '0' && *p != '1'))
        return -1;
    int whole = *p++ - '0', q = whole * 1000, scale = 100;
    if (p == end)
        return q;
    if (*p++ != '.')
        return -1;
    for (int k = 0; p < end; k++, p++) {
        if (k >= 3 || *p < '0' || *p > '9' || (whole && *p != '0'))
            return -1;
        q += (*p - '0') * scale;
        scale /= 10;
    }
    return q;
}

static void accept_element(accept_state *a, const char *p, const char *end)
{
    const char *t0 = ows(p), *t1 = token_end(t0);
    if (t1 == t0 || *t1 != '/')
        return;
    const char *s0 = t1 + 1, *s1 = token_end(s0);
    if (s1 == s0)
        return;
    int q = 1000;
    p = ows(s1);
    while (p < end && *p == ';') {
        const char *n0 = ows(p + 1), *n1 = token_end(n0);
        if (n1 == n0 || *n1 != '=')
            return;
        const char *v0 = n1 + 1, *v1 = *v0 == '"' ? quoted_end(v0) : token_end(v0);
        if (!v1 || v1 == v0 || v1 > end)
            return;
        if (n1 - n0 == 1 && (*n0 == 'q' || *n0 == 'Q')) {
            if ((q = parse_qvalue(v0, v1)) < 0)
                return;
            p = end; /* the weight ends the range (old accept-ext parameters may follow) */
            break;
        }
        p = ows(v1);
    }
    if (p != end)
        return;
    size_t tl = (size_t)(t1 - t0), sl = (size_t)(s1 - s0);
    bool any_type = tl == 1 && *t0 == '*', any_sub = sl == 1 && *s0 == '*';
    if (any_type && !any_sub)
        return; /* "* /png" is no media range */
    a->parsed = true;
    for (size_t i = 0; i < a->n; i++) {
        const char *type = a->types[i], *slash = strchr(type, '/');
        bool type_eq = (size_t)(slash - type) == tl && !strncasecmp(type, t0, tl);
        bool sub_eq = strlen(slash + 1) == sl && !strncasecmp(slash + 1, s0, sl);
        int spec = any_type ? 1 : !type_eq ? 0 : any_sub ? 2 : sub_eq ? 3 : 0;
        if (spec > a->spec[i] || (spec && spec == a->spec[i] && q > a->q[i])) {
            a->spec[i] = spec;
            a->q[i] = q;
        }
    }
}

static enum MHD_Result accept_header(void *cls, enum MHD_ValueKind kind, const char *key,
                                     const char *value)
{
    (void)kind;
    if (key && value && !strcasecmp(key, MHD_HTTP_HEADER_ACCEPT))
        for (const char *p = value;; p++) {
            const char *e = element_end(p);
            accept_element(cls, p, e);
            if (!*e)
                break;
            p = e;
        }
    return MHD_YES;
}

/* The index into types (n <= 4, the server's preference first) of the
 * representation to send, or -1 when the Accept headers allow none. */
static int negotiate(struct MHD_Connection *c, const char *const *types, size_t n)
{
    accept_state a = {.types = types, .n = n};
    MHD_get_connection_values(c, MHD_HEADER_KIND, accept_header, &a);
    if (!a.parsed)
        return 0;
    int best = -1, best_q = 0;
    for (size_t i = 0; i < n; i++)
        if (a.q[i] > best_q) {
            best = (int)i;
            best_q = a.q[i];
        }
    return best;
}

/* ---- PNG previews (previews.h) --------------------------------------------
 * Reading an EXR and encoding a PNG take a while (about 0.2 s for 1080p
 * here), so at most previews_max requests make one at once; beyond that
 * the answer is 503 with Retry-After: 1, and the other threads of the pool
 * stay free for everything else. Cached previews are served without a
 * slot. */

static bool preview_slot_take(mr_http *h)
{
    if (atomic_fetch_add(&h->previews_busy, 1) < h->previews_max)
        return true;
    atomic_fetch_sub(&h->previews_busy, 1);
    return false;
}

static void preview_slot_give(mr_http *h)
{
    atomic_fetch_sub(&h->previews_busy, 1);
}

static enum MHD_Result preview_busy(req *r, struct MHD_Connection *c)
{
    return http_send_problem_hdr(r, c, P_UNAVAILABLE, "Retry-After", "1",
                                 "%u previews are being made; try again in a second",
                                 r->h->previews_max);
}

/* Caching writes into the data directory: not while its disk is full. */
static bool may_cache(req *r)
{
    return !mr_daemon_disk_full(r->h->d, NULL, 0);
}

static enum MHD_Result preview_failed(req *r, struct MHD_Connection *c, const char *job,
                                      size_t index, int rc, const mr_error *err)
{
    if (rc == MR_ERR_NOT_FOUND)
        return http_send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is gone", index, job);
    char msg[sizeof err->msg];
    mr_daemon_redact(r->h->d, err->msg[0] ? err->msg : mr_err_name(rc), msg, sizeof msg);
    return http_send_problem(r, c, P_INTERNAL, NULL, "frame %zu of job %s cannot be previewed: %s",
                             index, job, msg);
}

/* Adds the NULL-terminated name, value pairs; false (resp destroyed) on failure. */
static bool add_headers(struct MHD_Response *resp, const char *const *kv)
{
    for (; kv[0]; kv += 2)
        if (kv[1] && MHD_add_response_header(resp, kv[0], kv[1]) != MHD_YES) {
            MHD_destroy_response(resp);
            return false;
        }
    return true;
}

/* 200 with the body as image/png (the response takes it over) and headers
 * (name, value pairs, NULL-terminated; a NULL value is skipped). */
static enum MHD_Result send_png(req *r, struct MHD_Connection *c, mr_preview_body *b,
                                const char *const *headers)
{
    struct MHD_Response *resp = NULL;
    size_t size = b->size;
    if (b->fd >= 0) {
        resp = MHD_create_response_from_fd(size, b->fd);
        if (resp)
            b->fd = -1;
        else
            mr_preview_body_free(b);
    } else {
        resp = MHD_create_response_from_buffer(size, b->data, MHD_RESPMEM_MUST_FREE);
        if (resp)
            b->data = NULL;
        else
            mr_preview_body_free(b);
    }
    const char *ctype[] = {MHD_HTTP_HEADER_CONTENT_TYPE, CT_PNG, NULL};
    if (!resp || !add_headers(resp, ctype) || !add_headers(resp, headers))
        return MHD_NO;
    return http_send_response(r, c, MHD_HTTP_OK, resp, size);
}

/* The EXR path of a done frame; answers 404 itself when it is not done. */
static bool frame_exr_path(req *r, struct MHD_Connection *c, const mr_job_record *job, size_t index,
                           char *path, size_t size, enum MHD_Result *res)
{
    mr_error err = {0};
    int rc = mr_store_frame_path(mr_daemon_store(r->h->d), job->id, index, path, size, &err);
    if (rc == MR_ERR_NOT_FOUND)
        *res = http_send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is not rendered", index,
                                 job->id);
    else if (rc < 0)
        *res = http_send_error(r, c, rc, &err);
    return rc == MR_OK;
}

/* ---- caching and ranges of frames -----------------------------------------
 * A frame's EXR never changes once it is done (a finished frame is never
 * rendered again; a deleted job takes it away), nor does its preview: both
 * are served with a strong ETag (the EXR file's size and modification
 * time, "-png" for the preview) and Cache-Control: immutable, and
 * If-None-Match answers 304. The EXR also takes a single byte range
 * (Range: bytes=a-b, a-, -n; RFC 9110 14): 206 with Content-Range, 416
 * when it lies outside the file; If-Range with another tag, several
 * ranges or a unit other than bytes get the whole file. */

#define FRAME_CACHE_CONTROL "max-age=31536000, immutable"

static void frame_etag(const struct stat *st, const char *suffix, char *out, size_t size)
{
    snprintf(out, size, "\"%llx-%llx.%lx%s\"", (unsigned long long)st->st_size,
             (unsigned long long)st->st_mtim.tv_sec, (unsigned long)st->st_mtim.tv_nsec, suffix);
}

/* Whether If-None-Match names etag (or is "*"). */
static bool etag_matches(struct MHD_Connection *c, const char *etag)
{
    const char *match = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_IF_NONE_MATCH);
    return match && (strstr(match, etag) || !strcmp(match, "*"));
}

static enum MHD_Result not_modified(req *r, struct MHD_Connection *c, const char *const *headers)
{
    struct MHD_Response *resp = MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
    if (!resp || !add_headers(resp, headers))
        return MHD_NO;
    return http_send_response(r, c, MHD_HTTP_NOT_MODIFIED, resp, 0);
}

/* The one byte range a Range header asks of a file of size bytes: 1 with
 * [*first, *last], 0 to send the whole file, -1 unsatisfiable. */
static int parse_range(const char *h, uint64_t size, uint64_t *first, uint64_t *last)
{
    if (!h || strncmp(h, "bytes=", 6) != 0 || strchr(h, ','))
        return 0;
    const char *p = h + 6;
    char *end = NULL;
    if (*p == '-') { /* the last n bytes */
        if (p[1] < '0' || p[1] > '9')
            return 0;
        unsigned long long n = strtoull(p + 1, &end, 10);
        if (*end || n == 0)
            return *end ? 0 : -1;
        if (size == 0)
            return -1;
        *first = n >= size ? 0 : size - n;
        *last = size - 1;
        return 1;
    }
    if (*p < '0' || *p > '9')
        return 0;
    unsigned long long a = strtoull(p, &end, 10);
    if (*end != '-')
        return 0;
    p = end + 1;
    unsigned long long b = size ? size - 1 : 0;
    if (*p) {
        if (*p < '0' || *p > '9')
            return 0;
        b = strtoull(p, &end, 10);
        if (*end || b < a)
            return 0;
    }
    if (a >= size)
        return -1;
    *first = a;
    *last = b >= size ? size - 1 : b;
    return 1;
}

/* The preview of a done frame (negotiated: with Vary: Accept). */
static enum MHD_Result send_frame_png(req *r, struct MHD_Connection *c, const mr_job_record *job,
                                      size_t index, const char *exr_path, bool negotiated)
{
    char etag[96] = "";
    struct stat st;
    if (stat(exr_path, &st) == 0)
        frame_etag(&st, "-png", etag, sizeof etag);
    const char *cache[] = {MHD_HTTP_HEADER_ETAG, etag[0] ? etag : NULL, MHD_HTTP_HEADER_CACHE_CONTROL,
                           FRAME_CACHE_CONTROL, MHD_HTTP_HEADER_VARY, negotiated ? "Accept" : NULL,
                           NULL};
    if (etag[0] && etag_matches(c, etag))
        return not_modified(r, c, cache);
    mr_preview_body body;
    if (!mr_preview_frame_cached(exr_path, &body)) {
        if (!preview_slot_take(r->h))
            return preview_busy(r, c);
        mr_error err = {0};
        int rc = mr_preview_frame_build(exr_path, may_cache(r), &body, &err);
        preview_slot_give(r->h);
        if (rc < 0)
            return preview_failed(r, c, job->id, index, rc, &err);
    }
    char name[MR_FRAME_NAME_MAX], disposition[MR_FRAME_NAME_MAX + 32];
    mr_frame_preview_name(index, name);
    snprintf(disposition, sizeof disposition, "inline; filename=\"%s\"", name);
    const char *headers[] = {MHD_HTTP_HEADER_CONTENT_DISPOSITION, disposition,
                             MHD_HTTP_HEADER_VARY, negotiated ? "Accept" : NULL,
                             MHD_HTTP_HEADER_ETAG, etag[0] ? etag : NULL,
                             MHD_HTTP_HEADER_CACHE_CONTROL, FRAME_CACHE_CONTROL, NULL};
    return send_png(r, c, &body, headers);
}

/* GET .../frames/{n}: the EXR, or its PNG preview for Accept: image/png. */
enum MHD_Result http_frame_get(req *r, struct MHD_Connection *c)
{
    static const char *const types[] = {CT_EXR, CT_PNG};
    mr_job_record job;
    size_t index = 0;
    enum MHD_Result res = MHD_NO;
    /* first: it needs no store, and an unacceptable request is one whatever the frame */
    int choice = negotiate(c, types, 2);
    if (choice < 0)
        return http_send_problem_hdr(r, c, P_NOT_ACCEPTABLE, MHD_HTTP_HEADER_VARY, "Accept",
                                     "frames are served as " CT_EXR " (the default) or " CT_PNG
                                     "; the Accept header allows neither");
    if (!load_frame(r, c, &job, &index, &res))
        return res;
    char path[4096];
    if (!frame_exr_path(r, c, &job, index, path, sizeof path, &res))
        return res;
    if (choice == 1)
        return send_frame_png(r, c, &job, index, path, true);
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        /* Deleted between the lookup and here. */
        return errno == ENOENT ? http_send_problem(r, c, P_NOT_FOUND, NULL,
                                                   "frame %zu of job %s is gone", index, job.id)
                               : http_send_problem(r, c, P_INTERNAL, NULL, "cannot open frame %zu: %s",
                                                   index, strerror(errno));
    struct stat st;
    if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
        close(fd);
        return http_send_problem(r, c, P_INTERNAL, NULL, "frame %zu of job %s is not a file", index,
                                 job.id);
    }
    char etag[96], name[MR_FRAME_NAME_MAX], disposition[MR_FRAME_NAME_MAX + 32];
    frame_etag(&st, "", etag, sizeof etag);
    mr_frame_file_name(index, name);
    snprintf(disposition, sizeof disposition, "attachment; filename=\"%s\"", name);
    const char *headers[] = {MHD_HTTP_HEADER_VARY, "Accept", MHD_HTTP_HEADER_ETAG, etag,
                             MHD_HTTP_HEADER_CACHE_CONTROL, FRAME_CACHE_CONTROL,
                             MHD_HTTP_HEADER_ACCEPT_RANGES, "bytes", NULL};
    if (etag_matches(c, etag)) {
        close(fd);
        return not_modified(r, c, headers);
    }
    uint64_t size = (uint64_t)st.st_size, first = 0, last = size ? size - 1 : 0;
    const char *range = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_RANGE);
    const char *if_range = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_IF_RANGE);
    int ranged = range && (!if_range || !strcmp(if_range, etag)) ? parse_range(range, size, &first, &last) : 0;
    char content_range[96];
    if (ranged < 0) {
        close(fd);
        snprintf(content_range, sizeof content_range, "bytes */%llu", (unsigned long long)size);
        return http_send_problem_hdr(r, c, P_RANGE, MHD_HTTP_HEADER_CONTENT_RANGE, content_range,
                                     "frame %zu of job %s has %llu bytes; the range '%.64s' lies "
                                     "outside them", index, job.id, (unsigned long long)size, range);
    }
    uint64_t length = ranged ? last - first + 1 : size;
    struct MHD_Response *resp = MHD_create_response_from_fd_at_offset64(length, fd, first);
    if (!resp) {
        close(fd);
        return MHD_NO;
    }
    snprintf(content_range, sizeof content_range, "bytes %llu-%llu/%llu", (unsigned long long)first,
             (unsigned long long)last, (unsigned long long)size);
    const char *more[] = {MHD_HTTP_HEADER_CONTENT_TYPE, CT_EXR,
                          MHD_HTTP_HEADER_CONTENT_DISPOSITION, disposition,
                          MHD_HTTP_HEADER_CONTENT_RANGE, ranged ? content_range : NULL, NULL};
    if (!add_headers(resp, headers) || !add_headers(resp, more))
        return MHD_NO;
    return http_send_response(r, c, ranged ? MHD_HTTP_PARTIAL_CONTENT : MHD_HTTP_OK, resp, length);
}

/* GET .../frames/{n}.png: the preview whatever Accept says (the path chose). */
enum MHD_Result http_frame_png(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    size_t index = 0;
    enum MHD_Result res = MHD_NO;
    char path[4096];
    if (!load_frame(r, c, &job, &index, &res) ||
        !frame_exr_path(r, c, &job, index, path, sizeof path, &res))
        return res;
    return send_frame_png(r, c, &job, index, path, false);
}

static void sheet_plan_free(mr_sheet_plan *plan)
{
    for (size_t i = 0; i < plan->count; i++)
        free(plan->exr[i]);
}

/* The job's output size, from its stored document. */
static int job_size(mr_store *st, const char *id, int *width, int *height, mr_error *err)
{
    char *doc = NULL;
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    int rc = mr_store_job_json(st, id, &doc, err);
    if (rc == MR_OK && (rc = mr_job_parse(doc, strlen(doc), &job, &jerr)) < 0)
        mr_error_set(err, rc, "the stored job does not parse: %s", jerr.message);
    if (rc == MR_OK) {
        *width = job->output.width;
        *height = job->output.height;
    }
    mr_job_free(job);
    free(doc);
    return rc;
}

/* GET .../contact-sheet.png: thumbnails of (up to 64 of) the job's frames. */
enum MHD_Result http_contact_sheet(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &job, &res))
        return res;
    mr_store *st = mr_daemon_store(r->h->d);
    mr_sheet_plan plan = {.frame_count = job.frame_count};
    plan.count = mr_contact_sheet_frames(job.frame_count, plan.index);
    mr_error err = {0};
    for (size_t i = 0; i < plan.count; i++) {
        char path[4096];
        int rc = mr_store_frame_path(st, job.id, plan.index[i], path, sizeof path, &err);
        if (rc == MR_OK && !(plan.exr[i] = mr_strdup(path)))
            rc = mr_error_set(&err, MR_ERR_NOMEM, "out of memory");
        if (rc < 0 && rc != MR_ERR_NOT_FOUND) {
            sheet_plan_free(&plan);
            return http_send_error(r, c, rc, &err);
        }
    }
    mr_sheet_plan_key(&plan);
    char etag[24];
    snprintf(etag, sizeof etag, "\"%s\"", plan.key);
    /* the sheet changes as frames finish: clients revalidate, cheaply */
    const char *headers[] = {MHD_HTTP_HEADER_ETAG, etag, MHD_HTTP_HEADER_CACHE_CONTROL, "no-cache",
                             MHD_HTTP_HEADER_CONTENT_DISPOSITION,
                             "inline; filename=\"contact-sheet.png\"", NULL};
    const char *match = MHD_lookup_connection_value(c, MHD_HEADER_KIND, MHD_HTTP_HEADER_IF_NONE_MATCH);
    if (match && (strstr(match, etag) || !strcmp(match, "*"))) {
        sheet_plan_free(&plan);
        struct MHD_Response *resp = MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
        if (!resp || !add_headers(resp, headers))
            return MHD_NO;
        return http_send_response(r, c, MHD_HTTP_NOT_MODIFIED, resp, 0);
    }
    mr_preview_body body;
    if (!mr_preview_sheet_cached(&plan, &body)) {
        int width = 0, height = 0;
        size_t bad = 0;
        int rc = job_size(st, job.id, &width, &height, &err);
        if (rc < 0) {
            sheet_plan_free(&plan);
            return http_send_error(r, c, rc, &err);
        }
        if (!preview_slot_take(r->h)) {
            sheet_plan_free(&plan);
            return preview_busy(r, c);
        }
        rc = mr_preview_sheet_build(&plan, width, height, may_cache(r), &body, &bad, &err);
        preview_slot_give(r->h);
        if (rc < 0) {
            sheet_plan_free(&plan);
            return preview_failed(r, c, job.id, bad, rc, &err);
        }
    }
    sheet_plan_free(&plan);
    return send_png(r, c, &body, headers);
}

enum MHD_Result http_frame_stats(req *r, struct MHD_Connection *c)
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
        return http_send_error(r, c, rc, &err);
    if (rc < 0 || f.state != MR_FRAME_DONE || !f.stats_json) {
        free(f.stats_json);
        return http_send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is not rendered", index,
                                 job.id);
    }
    size_t n = strlen(f.stats_json);
    /* the stored text as it is; the response frees it */
    return http_send_response(r, c, MHD_HTTP_OK, http_buffer_response(f.stats_json, n, CT_JSON), n);
}

int http_job_stats_doc(mr_http *h, const mr_job_record *rec, cJSON **out, mr_error *err)
{
    *out = NULL;
    mr_store *st = mr_daemon_store(h->d);
    mr_frame_record *frames = NULL;
    size_t count = 0, done = 0;
    cJSON **stored = NULL;
    char *doc_json = NULL;
    mr_job *job = NULL;
    int rc = mr_store_frames(st, rec->id, &frames, &count, err);
    if (rc < 0)
        goto cleanup;
    stored = calloc(count ? count : 1, sizeof *stored);
    if (!stored) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        goto cleanup;
    }
    double threads = 0;
    for (size_t i = 0; i < count; i++) {
        if (frames[i].state != MR_FRAME_DONE || !frames[i].stats_json)
            continue;
        cJSON *o = cJSON_Parse(frames[i].stats_json);
        if (!cJSON_IsObject(o)) {
            cJSON_Delete(o);
            continue;
        }
        threads = num_or(o, "threads", threads);
        stored[done++] = o;
    }

    /* Name, size and frame count as stats.json reports them; the stored
     * document is the validated job, so parsing it again cannot fail unless
     * the store is damaged, and then the record's figures stand in. */
    mr_job fallback = {0};
    fallback.name = (char *)rec->name;
    fallback.frame_count = rec->frame_count;
    mr_error ignored;
    if (mr_store_job_json(st, rec->id, &doc_json, &ignored) == MR_OK)
        mr_job_parse(doc_json, strlen(doc_json), &job, NULL);
    if (!(threads >= 1 && threads <= 65536)) {
        threads = h->render_threads;
        if (threads <= 0) {
            long n = sysconf(_SC_NPROCESSORS_ONLN);
            threads = n > 0 ? (double)n : 1;
        }
    }
    rc = mr_stats_from_frames(job ? job : &fallback, stored, done, (unsigned)threads, out, err);
cleanup:
    mr_job_free(job);
    free(doc_json);
    for (size_t k = 0; stored && k < done; k++)
        cJSON_Delete(stored[k]);
    free(stored);
    mr_frame_records_free(frames, count);
    return rc;
}

enum MHD_Result http_job_stats(req *r, struct MHD_Connection *c)
{
    mr_job_record rec;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &rec, &res))
        return res;
    cJSON *root = NULL;
    mr_error err = {0};
    int rc = http_job_stats_doc(r->h, &rec, &root, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    return http_send_json(r, c, MHD_HTTP_OK, root);
}

/* ---- handlers: assets and service --------------------------------------- */

enum MHD_Result http_asset_put(req *r, struct MHD_Connection *c)
{
    if (r->len == 0 || !r->upload)
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "empty body: send the asset's bytes");
    char id[MR_ASSET_ID_LEN + 1] = "";
    bool existed = false;
    mr_error err = {0};
    mr_asset_upload *up = r->upload;
    r->upload = NULL; /* finish frees it */
    int rc = mr_store_asset_upload_finish(mr_daemon_store(r->h->d), up, id, &existed, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "id", cJSON_CreateString(id), &ok);
    http_put(doc, "size", cJSON_CreateNumber((double)r->len), &ok);
    http_put(doc, "existed", cJSON_CreateBool(existed), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    /* where the asset is (GET/DELETE /v1/assets/{id}, http_assets.c) */
    char location[96];
    snprintf(location, sizeof location, "/v1/assets/%s", id);
    size_t n = 0;
    struct MHD_Response *resp = http_json_response(doc, CT_JSON, &n);
    if (resp && MHD_add_response_header(resp, MHD_HTTP_HEADER_LOCATION, location) != MHD_YES) {
        MHD_destroy_response(resp);
        resp = NULL;
    }
    return http_send_response(r, c, existed ? MHD_HTTP_OK : MHD_HTTP_CREATED, resp, n);
}

static enum MHD_Result h_status(req *r, struct MHD_Connection *c, const char *status)
{
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "status", cJSON_CreateString(status), &ok);
    if (!ok) {
        cJSON_Delete(doc);
        return MHD_NO;
    }
    return http_send_json(r, c, MHD_HTTP_OK, doc);
}

enum MHD_Result http_healthz(req *r, struct MHD_Connection *c)
{
    return h_status(r, c, "ok");
}

enum MHD_Result http_readyz(req *r, struct MHD_Connection *c)
{
    if (atomic_load(&r->h->stopping) || mr_daemon_stopping(r->h->d))
        return http_send_problem(r, c, P_UNAVAILABLE, NULL, "the daemon is stopping: the frames in "
                                 "progress finish, reads are served meanwhile");
    if (!mr_daemon_ready(r->h->d))
        return http_send_problem(r, c, P_UNAVAILABLE, NULL, "the daemon is not ready for jobs");
    char why[512];
    if (mr_daemon_disk_full(r->h->d, why, sizeof why))
        return http_send_problem(r, c, P_UNAVAILABLE, NULL, "disk full, the render queue is "
                                 "paused until space is freed: %s", why);
    return h_status(r, c, "ready");
}

enum MHD_Result http_metrics(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    char *daemon_text = mr_daemon_metrics(h->d);
    if (!daemon_text)
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    mr_http_counters k;
    mr_http_counters_get(h, &k);
    char own[1536];
    int n = snprintf(own, sizeof own,
                     "# HELP microray_http_requests_total HTTP requests received.\n"
                     "# TYPE microray_http_requests_total counter\n"
                     "microray_http_requests_total %llu\n"
                     "# HELP microray_http_responses_total HTTP responses sent, by status class.\n"
                     "# TYPE microray_http_responses_total counter\n",
                     (unsigned long long)k.requests);
    for (int cls = 1; cls <= 5 && n > 0 && (size_t)n < sizeof own; cls++)
        n += snprintf(own + n, sizeof own - (size_t)n, "microray_http_responses_total{class=\"%dxx\"} %llu\n",
                      cls, (unsigned long long)k.responses[cls]);
    if (n < 0 || (size_t)n >= sizeof own)
        n = 0;
    size_t dn = strlen(daemon_text);
    bool nl = dn > 0 && daemon_text[dn - 1] != '\n';
    char *body = malloc(dn + nl + (size_t)n + 1);
    if (!body) {
        free(daemon_text);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    memcpy(body, daemon_text, dn);
    if (nl)
        body[dn] = '\n';
    memcpy(body + dn + nl, own, (size_t)n + 1);
    free(daemon_text);
    size_t len = dn + nl + (size_t)n;
    return http_send_response(r, c, MHD_HTTP_OK, http_buffer_response(body, len, CT_METRICS), len);
}

