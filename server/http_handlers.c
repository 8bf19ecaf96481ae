/*
 * http_handlers.c - the handlers of the job, frame, asset and service
 * routes (http_internal.h; the event stream's is in http_events.c). They
 * run on libmicrohttpd's thread pool and only parse, call the daemon or the
 * store and answer: rendering happens on the daemon's workers.
 */
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "http_internal.h"
#include "job_json.h"
#include "stats_json.h"
#include "microray.h"

#define CT_METRICS "text/plain; version=0.0.4; charset=utf-8"

/* ---- job records as JSON ------------------------------------------------ */

static cJSON *str_or_null(const char *s)
{
    return s && *s ? cJSON_CreateString(s) : cJSON_CreateNull();
}

static cJSON *time_or_null(double t)
{
    return t > 0 ? cJSON_CreateNumber(t) : cJSON_CreateNull();
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

enum MHD_Result http_job_submit(req *r, struct MHD_Connection *c)
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
            return http_send_problem(r, c, P_INVALID_JOB, pointer, "%s", msg);
        case MR_ERR_LIMIT:
            /* The job parser's own size cap, when configured above it. */
            if (r->len > MR_JOB_MAX_BYTES)
                return http_send_problem(r, c, P_TOO_LARGE, NULL, "%s", msg);
            return http_send_problem(r, c, P_UNPROCESSABLE, pointer, "%s", msg);
        case MR_ERR_NOT_FOUND:
            return http_send_problem(r, c, P_UNPROCESSABLE, pointer, "%s", msg);
        case MR_ERR_CONFLICT:
            return http_send_problem(r, c, P_IDEMPOTENCY, NULL, "%s", msg);
        default:
            return http_send_problem(r, c, P_INTERNAL, NULL, "%s", msg);
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

enum MHD_Result http_job_list(req *r, struct MHD_Connection *c)
{
    const char *state_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "state");
    mr_job_state state = MR_JOB_QUEUED;
    if (state_arg && !mr_job_state_parse(state_arg, &state))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "unknown state '%.64s'; expected queued, running, succeeded, failed "
                                 "or canceled",
                                 state_arg);
    mr_job_record *jobs = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_job_list(mr_daemon_store(r->h->d), state_arg != NULL, state, &jobs, &count,
                               &err);
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
    return http_send_built(r, c, MHD_HTTP_OK, doc, ok);
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

enum MHD_Result http_frame_get(req *r, struct MHD_Connection *c)
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
        return http_send_problem(r, c, P_NOT_FOUND, NULL, "frame %zu of job %s is not rendered", index,
                                 job.id);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
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
    return http_send_response(r, c, MHD_HTTP_OK, resp, (uint64_t)st.st_size);
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

enum MHD_Result http_job_stats(req *r, struct MHD_Connection *c)
{
    mr_http *h = r->h;
    mr_job_record rec;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &rec, &res))
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
        res = http_send_error(r, c, rc, &err);
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
    if ((rc = mr_stats_to_json(job ? job : &fallback, &stats, 0, &text, &err)) < 0) {
        res = http_send_error(r, c, rc, &err);
        goto cleanup;
    }
    if (!(root = cJSON_Parse(text)))
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
    res = http_send_json(r, c, MHD_HTTP_OK, root);
    root = NULL;
    goto cleanup;
oom:
    res = http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
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
    return http_send_built(r, c, existed ? MHD_HTTP_OK : MHD_HTTP_CREATED, doc, ok);
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
    if (atomic_load(&r->h->stopping) || !mr_daemon_ready(r->h->d))
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

