/*
 * daemon.c - microrayd serve: store, workers, scene cache, events and the
 * HTTP front end wired together (daemon.h).
 *
 * Workers claim queued jobs from the store by priority and render them with
 * the same worker code as the one-shot command. Frames already done (before
 * a crash or a stop) are skipped, so a resumed job renders only what is
 * missing. A user cancel stops the frame in progress within one tile; a
 * daemon stop (SIGTERM) lets it finish and leaves the job to resume.
 */
#include "daemon.h"

#include <cJSON.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdarg.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <time.h>

#include <curl/curl.h>

#include "cache.h"
#include "http.h"
#include "notify.h"
#include "proc_stats.h"
#include "import_worker.h"
#include "render_proc.h"
#include "space_guard.h"
#include "job_json.h"
#include "microray.h"
#include "stats_json.h"
#include "worker.h"

/* Events buffered per subscriber before its stream is ended, and streams
 * open at once (each holds an HTTP connection). */
#define MR_EVENT_QUEUE_MAX 1024
#define MR_MAX_SUBSCRIBERS 64

/* Nice value of render worker processes (HTTP threads keep 0). */
#define MR_WORKER_NICE 10

/* Upper bounds (seconds) of the frame time histogram buckets in /metrics. */
static const double FRAME_BUCKETS[] = {0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30};
#define N_BUCKETS (sizeof FRAME_BUCKETS / sizeof FRAME_BUCKETS[0])

typedef struct running_job {
    char id[MR_JOB_ID_LEN + 1];
    atomic_bool cancel;
    struct running_job *next;
} running_job;

typedef struct event_msg {
    char *text;
    struct event_msg *next;
} event_msg;

struct mr_event_sub {
    mr_daemon *d;
    char id[MR_JOB_ID_LEN + 1];
    event_msg *head, *tail;
    size_t queued;
    int64_t frames_sent;  /* highest frame event id queued: a frame replayed at subscription
                             is not sent again when its live event follows */
    bool ended;
    void (*notify)(void *user);
    void *notify_user;
    struct mr_event_sub *next;
};

struct mr_daemon {
    mr_daemon_config cfg;
    char *data_dir;
    char *data_real;              /* its realpath (NULL if none), for mr_daemon_redact */
    char **roots; /* realpath of each asset root */
    size_t root_count;
    mr_store *store;
    mr_http *http;
    pthread_t *workers;
    mr_render_proc **procs; /* one render slot (worker process) per worker thread */
    unsigned worker_count;
    mr_space_guard *space;        /* disk full: the queue pauses (space_guard.h) */
    pthread_t space_thread;
    bool space_thread_started;

    pthread_mutex_t lock; /* stopping, running, metrics */
    pthread_cond_t wake;     /* a job was queued, or stop */
    pthread_cond_t released; /* a worker let go of a job */
    bool stopping;
    atomic_bool ready;
    running_job *running;
    uint64_t frames_rendered, frames_failed, rays;
    uint64_t buckets[N_BUCKETS + 1];
    double frame_seconds_sum;

    pthread_mutex_t ev_lock;
    mr_event_sub *subs;

    mr_notifier *notifier; /* completion notifications (notify.h) */
    bool curl_ready;
};

static void log_line(const mr_daemon *d, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void log_line(const mr_daemon *d, const char *fmt, ...)
{
    if (d->cfg.quiet)
        return;
    char buf[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    fprintf(stderr, "microrayd: %s\n", buf);
}

/* ---- events -------------------------------------------------------------- */

static bool state_is_terminal(mr_job_state s)
{
    return s == MR_JOB_SUCCEEDED || s == MR_JOB_FAILED || s == MR_JOB_CANCELED;
}

/* Event ids (the SSE `id:` field, what a client sends back as
 * Last-Event-ID): the job's done_seq (store.h), the number of frames done
 * so far in the order they were. A frame event carries its own number;
 * other events the number of the last frame done before them. A stream
 * resumed after id N first gets the frame events after N from the store
 * (mr_events_subscribe), so a dropped client misses no frame. Negative
 * event_id: no id (a deletion). */
static void sub_push(mr_event_sub *s, const char *type, const char *json, int64_t event_id,
                     bool end)
{
    if (s->ended)
        return;
    bool is_frame = !strcmp(type, "frame");
    if (is_frame && event_id <= s->frames_sent)
        return; /* replayed already */
    if (is_frame)
        s->frames_sent = event_id;
    if (s->queued >= MR_EVENT_QUEUE_MAX) {
        /* a subscriber that does not read: end its stream instead of
         * buffering without bound (clients fall back to polling) */
        s->ended = true;
        if (s->notify)
            s->notify(s->notify_user);
        return;
    }
    size_t n = strlen(type) + strlen(json) + 64;
    event_msg *m = malloc(sizeof *m);
    char *text = malloc(n);
    if (!m || !text) {
        free(m);
        free(text);
        s->ended = true; /* out of memory: end the stream rather than lose events silently */
    } else {
        if (event_id >= 0)
            snprintf(text, n, "id: %lld\nevent: %s\ndata: %s\n\n", (long long)event_id, type, json);
        else
            snprintf(text, n, "event: %s\ndata: %s\n\n", type, json);
        *m = (event_msg){text, NULL};
        if (s->tail)
            s->tail->next = m;
        else
            s->head = m;
        s->tail = m;
        s->queued++;
        s->ended = end;
    }
    if (s->notify)
        s->notify(s->notify_user);
}

static void publish(mr_daemon *d, const char *id, const char *type, const char *json,
                    int64_t event_id, bool end)
{
    pthread_mutex_lock(&d->ev_lock);
    for (mr_event_sub *s = d->subs; s; s = s->next)
        if (strcmp(s->id, id) == 0)
            sub_push(s, type, json, event_id, end);
    pthread_mutex_unlock(&d->ev_lock);
}

static void state_json(const mr_job_record *r, char *json, size_t size)
{
    snprintf(json, size,
             "{\"id\":\"%s\",\"state\":\"%s\",\"frames\":{\"total\":%zu,\"done\":%zu,\"failed\":%zu}}",
             r->id, mr_job_state_name(r->state), r->frame_count, r->frames_done, r->frames_failed);
}

/* Publishes the job's current state (from the store). */
static void publish_state(mr_daemon *d, const char *id)
{
    mr_job_record r;
    mr_error err;
    if (mr_store_job_get(d->store, id, &r, &err) < 0)
        return;
    char json[1024];
    state_json(&r, json, sizeof json);
    publish(d, id, "state", json, r.done_seq, state_is_terminal(r.state));
}

static void notify_log(void *user, const char *line)
{
    log_line(user, "%s", line);
}

/* A job reached its final state: POST it to the job's notify URL, if it
 * names one (notify.h). */
static void notify_final(mr_daemon *d, const char *id)
{
    mr_job_record r;
    mr_error err;
    char *json = NULL;
    if (!d->notifier || mr_store_job_get(d->store, id, &r, &err) < 0 || !state_is_terminal(r.state) ||
        mr_store_job_json(d->store, id, &json, &err) < 0)
        return;
    cJSON *doc = cJSON_Parse(json);
    free(json);
    const cJSON *url = cJSON_GetObjectItemCaseSensitive(doc, "notify");
    if (cJSON_IsString(url)) {
        char when[40], location[64], shown[sizeof r.error];
        mr_daemon_redact(d, r.error, shown, sizeof shown);
        snprintf(location, sizeof location, "/v1/jobs/%s", r.id);
        cJSON *body = cJSON_CreateObject(), *frames = cJSON_CreateObject();
        cJSON_AddStringToObject(body, "id", r.id);
        cJSON_AddStringToObject(body, "name", r.name);
        cJSON_AddStringToObject(body, "state", mr_job_state_name(r.state));
        cJSON_AddNumberToObject(frames, "total", (double)r.frame_count);
        cJSON_AddNumberToObject(frames, "done", (double)r.frames_done);
        cJSON_AddNumberToObject(frames, "failed", (double)r.frames_failed);
        cJSON_AddItemToObject(body, "frames", frames);
        cJSON_AddNumberToObject(body, "finished", r.finished);
        if (mr_format_rfc3339(r.finished, when, sizeof when))
            cJSON_AddStringToObject(body, "finished_at", when);
        else
            cJSON_AddNullToObject(body, "finished_at");
        if (shown[0])
            cJSON_AddStringToObject(body, "error", shown);
        else
            cJSON_AddNullToObject(body, "error");
        cJSON_AddStringToObject(body, "location", location);
        char *text = cJSON_PrintUnformatted(body);
        if (text)
            mr_notifier_send(d->notifier, url->valuestring, text);
        else
            log_line(d, "job=%s: out of memory, its notification is not sent", id);
        free(text);
        cJSON_Delete(body);
    }
    cJSON_Delete(doc);
}

mr_event_sub *mr_events_subscribe(mr_daemon *d, const char *job_id, int64_t last_event_id)
{
    mr_job_record r;
    mr_error err;
    if (mr_store_job_get(d->store, job_id, &r, &err) < 0)
        return NULL;
    mr_event_sub *s = calloc(1, sizeof *s);
    if (!s)
        return NULL;
    s->d = d;
    s->frames_sent = last_event_id >= 0 ? last_event_id : 0;
    snprintf(s->id, sizeof s->id, "%s", job_id);
    pthread_mutex_lock(&d->ev_lock);
    size_t open = 0;
    for (mr_event_sub *o = d->subs; o; o = o->next)
        open++;
    if (open >= MR_MAX_SUBSCRIBERS) {
        pthread_mutex_unlock(&d->ev_lock);
        free(s);
        return NULL;
    }
    /* Under ev_lock no event is published meanwhile: the store's word and
     * the live events that follow it join without a gap (a frame stored
     * but not yet published is replayed here and skipped when its live
     * event comes: frames_sent). */
    bool more = false;
    if (last_event_id >= 0) {
        mr_frame_done_record *done = NULL;
        size_t n = 0, room = MR_EVENT_QUEUE_MAX - 8;
        if (mr_store_frames_after(d->store, job_id, last_event_id, room + 1, &done, &n, &err) == MR_OK) {
            more = n > room; /* the rest after a reconnection from the last one sent */
            for (size_t i = 0; i < n && i < room; i++)
                sub_push(s, "frame", done[i].stats_json ? done[i].stats_json : "{}", done[i].done_seq,
                         false);
        }
        mr_frame_done_records_free(done, n);
    }
    /* the state as it is now (re-read: frames may have finished since;
     * those still to be published come as live events, their numbers
     * being above frames_sent) */
    if (mr_store_job_get(d->store, job_id, &r, &err) == MR_OK) {
        if (last_event_id < 0)
            s->frames_sent = r.done_seq; /* a fresh stream starts from now */
        char json[1024];
        state_json(&r, json, sizeof json);
        /* its id: the last frame this stream has sent, so resuming from it
         * misses none; a replay cut short ends here (the client resumes) */
        sub_push(s, "state", json, s->frames_sent, more || state_is_terminal(r.state));
    }
    s->next = d->subs;
    d->subs = s;
    pthread_mutex_unlock(&d->ev_lock);
    return s;
}

int mr_events_next(mr_event_sub *s, char *buf, size_t size)
{
    int n = 0;
    pthread_mutex_lock(&s->d->ev_lock);
    event_msg *m = s->head;
    if (m) {
        size_t len = strlen(m->text);
        if (len >= size)
            len = size - 1; /* events are small; a tiny buffer only truncates */
        memcpy(buf, m->text, len);
        buf[len] = '\0';
        s->head = m->next;
        if (!s->head)
            s->tail = NULL;
        s->queued--;
        free(m->text);
        free(m);
        n = (int)len;
    } else if (s->ended) {
        n = -1;
    }
    pthread_mutex_unlock(&s->d->ev_lock);
    return n;
}

void mr_events_set_notify(mr_event_sub *s, void (*fn)(void *user), void *user)
{
    pthread_mutex_lock(&s->d->ev_lock);
    s->notify = fn;
    s->notify_user = user;
    bool pending = s->head || s->ended;
    pthread_mutex_unlock(&s->d->ev_lock);
    if (pending && fn)
        fn(user);
}

void mr_events_unsubscribe(mr_event_sub *s)
{
    if (!s)
        return;
    mr_daemon *d = s->d;
    pthread_mutex_lock(&d->ev_lock);
    for (mr_event_sub **p = &d->subs; *p; p = &(*p)->next)
        if (*p == s) {
            *p = s->next;
            break;
        }
    pthread_mutex_unlock(&d->ev_lock);
    for (event_msg *m = s->head, *next; m; m = next) {
        next = m->next;
        free(m->text);
        free(m);
    }
    free(s);
}

/* ---- asset resolution -------------------------------------------------- */

static bool path_has_dotdot(const char *p)
{
    for (const char *s = p; (s = strstr(s, "..")); s += 2) {
        bool start = s == p || s[-1] == '/';
        bool end = s[2] == '\0' || s[2] == '/';
        if (start && end)
            return true;
    }
    return false;
}

/* A server-side path, allowed only when it resolves (symlinks followed)
 * to a regular file below one of the asset roots. */
static int resolve_server_path(mr_daemon *d, const char *name, const char *path, char **out,
                               char pointer[512], mr_error *err)
{
    snprintf(pointer, 512, "/assets/%s/path", name);
    if (d->root_count == 0)
        return mr_error_set(err, MR_ERR_INVALID,
                            "server-side paths are disabled on this daemon (no --asset-root); upload the "
                            "asset with POST /v1/assets and name it by \"id\"");
    if (path_has_dotdot(path))
        return mr_error_set(err, MR_ERR_INVALID, "'..' is not allowed in asset paths");
    for (size_t i = 0; i < d->root_count; i++) {
        char candidate[PATH_MAX + 8];
        if (path[0] == '/')
            snprintf(candidate, sizeof candidate, "%s", path);
        else
            snprintf(candidate, sizeof candidate, "%s/%s", d->roots[i], path);
        char real[PATH_MAX];
        if (!realpath(candidate, real))
            continue;
        size_t rl = strlen(d->roots[i]);
        bool inside = strncmp(real, d->roots[i], rl) == 0 && (real[rl] == '/' || (rl == 1 && real[0] == '/'));
        if (!inside)
            continue;
        struct stat st;
        if (stat(real, &st) != 0 || !S_ISREG(st.st_mode))
            return mr_error_set(err, MR_ERR_INVALID, "'%s' is not a regular file", path);
        *out = strdup(real);
        return *out ? MR_OK : mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    return mr_error_set(err, MR_ERR_NOT_FOUND, "no file '%s' below the asset roots", path);
}

/* Fills in job->assets[i].path for every asset: uploaded ids become stored
 * files, server-side paths real paths below a root. With problems, every
 * asset that does not resolve is recorded there and the rest are still
 * tried (the first failure's code is returned); without, the first one
 * ends it (pointer names it). */
static int resolve_assets_all(mr_daemon *d, mr_job *job, char pointer[512], mr_job_problems *problems,
                              mr_error *err)
{
    int first = MR_OK;
    for (size_t i = 0; i < job->asset_count; i++) {
        mr_asset_desc *a = &job->assets[i];
        char *resolved = NULL;
        int rc;
        if (a->id) {
            char path[PATH_MAX];
            snprintf(pointer, 512, "/assets/%s/id", a->name);
            if ((rc = mr_store_asset_path(d->store, a->id, path, sizeof path, err)) < 0)
                mr_error_set(err, rc, "no uploaded asset with id %s", a->id);
            else if (!(resolved = strdup(path)))
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        } else {
            rc = resolve_server_path(d, a->name, a->path, &resolved, pointer, err);
        }
        if (rc < 0) {
            if (!problems || rc == MR_ERR_NOMEM)
                return rc;
            json_errors_add(problems, pointer, err->msg);
            if (first == MR_OK)
                first = rc;
            continue;
        }
        free(a->path);
        a->path = resolved;
    }
    pointer[0] = '\0';
    return first;
}

static int resolve_assets(mr_daemon *d, mr_job *job, char pointer[512], mr_error *err)
{
    return resolve_assets_all(d, job, pointer, NULL, err);
}

/* The files objects name as models (the asset of an object) over the
 * model file cap, each a problem at its path, found at submission rather
 * than when the worker imports it (a 3 GiB file failed after 17 s). */
static int check_model_sizes(const mr_job *job, mr_job_problems *problems, mr_error *err)
{
    int rc = MR_OK;
    for (size_t i = 0; i < job->asset_count; i++) {
        const mr_asset_desc *a = &job->assets[i];
        bool model = false;
        for (size_t o = 0; o < job->object_count && !model; o++)
            model = job->objects[o].asset == i;
        struct stat st;
        if (!model || a->id || stat(a->path, &st) != 0 ||
            (unsigned long long)st.st_size <= MR_MAX_ASSET_FILE_BYTES)
            continue;
        char pointer[512];
        snprintf(pointer, sizeof pointer, "/assets/%s/path", a->name);
        rc = mr_error_set(err, MR_ERR_LIMIT, "expected a model file of at most %llu bytes, got %lld",
                          (unsigned long long)MR_MAX_ASSET_FILE_BYTES, (long long)st.st_size);
        json_errors_add(problems, pointer, err->msg);
    }
    return rc;
}

/* ---- submission and control ---------------------------------------------- */

int mr_daemon_check_job(mr_daemon *d, const char *body, size_t len, mr_job **job_out,
                        mr_job_problems *problems, mr_error *err)
{
    mr_job *job = NULL;
    if (job_out)
        *job_out = NULL;
    int rc = mr_job_check(body, len, &job, problems);
    if (rc < 0) {
        mr_error_set(err, rc, "%s", problems->count ? problems->items[0].message : mr_err_name(rc));
        return rc;
    }
    char pointer[512];
    mr_error e = {0};
    int first = MR_OK;
    if ((rc = mr_job_check_memory(job, d->cfg.job_memory, pointer, &e)) < 0) {
        json_errors_add(problems, pointer, e.msg);
        first = rc;
    }
    rc = resolve_assets_all(d, job, pointer, problems, &e);
    if (first == MR_OK)
        first = rc;
    if (rc == MR_OK && (rc = check_model_sizes(job, problems, &e)) < 0 && first == MR_OK)
        first = rc;
    if (first < 0) {
        mr_job_free(job);
        return mr_error_set(err, first, "%s", problems->count ? problems->items[0].message : e.msg);
    }
    if (job_out)
        *job_out = job;
    else
        mr_job_free(job);
    return MR_OK;
}

int mr_daemon_submit(mr_daemon *d, const char *body, size_t len, const char *idempotency_key,
                     char id[MR_JOB_ID_LEN + 1], bool *existing, mr_job_problems *problems,
                     mr_error *err)
{
    mr_job *job = NULL;
    *existing = false;
    int rc = mr_daemon_check_job(d, body, len, &job, problems, err);
    const char **ids = NULL;
    size_t n_ids = 0;
    if (rc == MR_OK && !(ids = calloc(job->asset_count ? job->asset_count : 1, sizeof *ids)))
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    if (rc == MR_OK) {
        for (size_t i = 0; i < job->asset_count; i++)
            if (job->assets[i].id)
                ids[n_ids++] = job->assets[i].id;
        char hash[65];
        mr_sha256_hex(body, len, hash);
        rc = mr_store_job_create_using(d->store, body, len, job->name, job->frame_count,
                                       job->priority, job->max_retries, idempotency_key, hash, ids,
                                       n_ids, id, existing, err);
        if (rc == MR_ERR_NO_SPACE)
            mr_daemon_no_space(d, err->msg);
        if (rc == MR_ERR_NOT_FOUND) /* an asset deleted since it was resolved */
            json_errors_add(problems, "/assets", err->msg);
    }
    free(ids);
    mr_job_free(job);
    if (rc == MR_OK && !*existing) {
        log_line(d, "job=%s queued", id);
        pthread_mutex_lock(&d->lock);
        pthread_cond_broadcast(&d->wake);
        pthread_mutex_unlock(&d->lock);
    }
    return rc;
}

static running_job *find_running(mr_daemon *d, const char *id)
{
    for (running_job *r = d->running; r; r = r->next)
        if (strcmp(r->id, id) == 0)
            return r;
    return NULL;
}

int mr_daemon_cancel(mr_daemon *d, const char *id, mr_error *err)
{
    mr_job_record r;
    pthread_mutex_lock(&d->lock);
    int rc = mr_store_job_get(d->store, id, &r, err);
    if (rc == MR_OK && state_is_terminal(r.state))
        rc = mr_error_set(err, MR_ERR_CONFLICT, "job %s already %s", id, mr_job_state_name(r.state));
    if (rc == MR_OK)
        rc = mr_store_job_set_state(d->store, id, MR_JOB_CANCELED, "canceled by request", err);
    if (rc == MR_OK) {
        running_job *run = find_running(d, id);
        if (run)
            atomic_store(&run->cancel, true);
    }
    pthread_mutex_unlock(&d->lock);
    if (rc == MR_OK) {
        log_line(d, "job=%s canceled", id);
        publish_state(d, id);
        notify_final(d, id);
    }
    return rc;
}

int mr_daemon_retry(mr_daemon *d, const char *id, mr_error *err)
{
    /* Under d->lock, so no worker can claim or release the job meanwhile: a
     * canceled job whose worker is still finishing its frame must not be
     * queued again, or two workers would render it. */
    pthread_mutex_lock(&d->lock);
    int rc = find_running(d, id)
                 ? mr_error_set(err, MR_ERR_CONFLICT, "job %s is still stopping; retry in a moment", id)
                 : mr_store_job_retry(d->store, id, err);
    if (rc >= 0)
        pthread_cond_broadcast(&d->wake);
    pthread_mutex_unlock(&d->lock);
    if (rc >= 0) {
        log_line(d, "job=%s retrying %d frames", id, rc);
        publish_state(d, id);
    }
    return rc;
}

int mr_daemon_delete(mr_daemon *d, const char *id, mr_error *err)
{
    mr_error ignored;
    mr_job_record r;
    int rc = mr_store_job_get(d->store, id, &r, err);
    if (rc < 0)
        return rc;
    if (!state_is_terminal(r.state))
        mr_daemon_cancel(d, id, &ignored);
    pthread_mutex_lock(&d->lock);
    while (find_running(d, id))
        pthread_cond_wait(&d->released, &d->lock);
    rc = mr_store_job_delete(d->store, id, err);
    pthread_mutex_unlock(&d->lock);
    if (rc == MR_OK) {
        log_line(d, "job=%s deleted", id);
        publish(d, id, "deleted", "{}", -1, true);
    }
    return rc;
}

/* ---- rendering ----------------------------------------------------------- */

typedef struct job_run {
    mr_daemon *d;
    const char *id;
    const mr_job *job;
    running_job *entry;
    size_t failed;
    bool write_had_room; /* the last frame not stored for want of space had room by statvfs */
} job_run;

static void run_frame_started(void *user, size_t index)
{
    job_run *r = user;
    mr_error err;
    mr_store_frame_set_running(r->d->store, r->id, index, &err);
}

static bool run_stop_requested(void *user)
{
    job_run *r = user;
    pthread_mutex_lock(&r->d->lock);
    bool stop = r->d->stopping;
    pthread_mutex_unlock(&r->d->lock);
    return stop || mr_space_guard_full(r->d->space, NULL, 0);
}

static bool run_cancelled(void *user)
{
    job_run *r = user;
    return atomic_load(&r->entry->cancel);
}

void mr_daemon_no_space(mr_daemon *d, const char *why)
{
    if (mr_space_guard_report(d->space, why))
        log_line(d, "disk full: %s; the queue is paused (reads and deletes go on) until space "
                    "is freed", why);
}

bool mr_daemon_disk_full(mr_daemon *d, char *why, size_t size)
{
    return mr_space_guard_full(d->space, why, size);
}

/* Polls for space while the disk is full; resumes the queue when it is back. */
static void *space_main(void *p)
{
    mr_daemon *d = p;
    pthread_mutex_lock(&d->lock);
    while (!d->stopping) {
        struct timespec until;
        clock_gettime(CLOCK_REALTIME, &until);
        until.tv_sec += 1;
        pthread_cond_timedwait(&d->wake, &d->lock, &until);
        if (d->stopping)
            break;
        pthread_mutex_unlock(&d->lock);
        bool resumed = mr_space_guard_poll(d->space);
        pthread_mutex_lock(&d->lock);
        if (resumed) {
            log_line(d, "disk space is back: the queue resumes");
            pthread_cond_broadcast(&d->wake);
        }
    }
    pthread_mutex_unlock(&d->lock);
    return NULL;
}

/* A frame the render worker finished (its stats as JSON and its EXR
 * file): stored, published and counted. */
static int run_frame_done(void *user, size_t index, const char *stats_json, const uint8_t *exr,
                          size_t exr_size, mr_error *err)
{
    job_run *r = user;
    mr_daemon *d = r->d;
    mr_frame_stats st = {0};
    cJSON *parsed = cJSON_Parse(stats_json);
    if (!parsed)
        return mr_error_set(err, MR_ERR_FORMAT, "frame %zu: the render worker sent stats that "
                            "are not JSON", index);
    mr_frame_stats_from_json(parsed, index, &st);
    cJSON_Delete(parsed);
    /* Checked and stored under d->lock, which a cancel takes too: once a
     * cancel has answered, no frame of the job is recorded any more. */
    int rc;
    pthread_mutex_lock(&d->lock);
    if (atomic_load(&r->entry->cancel))
        rc = mr_error_set(err, MR_ERR_CANCELLED, "frame %zu cancelled", index);
    else
        rc = mr_store_frame_done(d->store, r->id, index, exr, exr_size, stats_json, err);
    /* the frame's event id: the job's frames done, this one the last (one
     * worker stores a job's frames, one at a time) */
    mr_job_record rec = {0};
    mr_error ignored;
    if (rc == MR_OK && mr_store_job_get(d->store, r->id, &rec, &ignored) < 0)
        rec.done_seq = 0;
    pthread_mutex_unlock(&d->lock);
    if (rc == MR_ERR_NO_SPACE) {
        /* A write refused with room on the file system (a quota: EDQUOT
         * reads as no space too) is no full disk: run_frame_failed then
         * counts the attempt, or the frame would render again forever.
         * Asked before the guard frees its reserve. */
        r->write_had_room = mr_space_guard_has_room(d->space, 2 * exr_size);
        char shown[sizeof err->msg];
        mr_daemon_redact(d, err->msg, shown, sizeof shown);
        mr_daemon_no_space(d, shown);
        mr_space_guard_need(d->space, exr_size);
    }
    if (rc < 0)
        return rc;
    publish(d, r->id, "frame", stats_json, rec.done_seq, false);
    pthread_mutex_lock(&d->lock);
    d->frames_rendered++;
    d->rays += st.rays;
    d->frame_seconds_sum += st.total_s;
    size_t b = 0;
    while (b < N_BUCKETS && st.total_s > FRAME_BUCKETS[b])
        b++;
    d->buckets[b]++;
    pthread_mutex_unlock(&d->lock);
    log_line(d, "job=%s frame %zu/%zu %.3fs (trace %.3f encode %.3f) %.1f Mrays/s%s", r->id,
             index + 1, r->job->frame_count, st.total_s, st.trace_s, st.encode_s, st.mrays_per_s,
             st.assets_cached && !st.assets_loaded ? " cache hit" : "");
    return MR_OK;
}

/* What a client reads of an error (a job's or a frame's) names files of
 * the data directory relative to it: "assets/<sha256>: ...", not the
 * server's absolute paths (issue 12 item 11). The log keeps them whole. */
void mr_daemon_redact(const mr_daemon *d, const char *in, char *out, size_t size)
{
    const char *prefixes[2] = {d->data_dir, d->data_real};
    size_t o = 0;
    while (*in && o + 1 < size) {
        size_t skip = 0;
        for (int k = 0; k < 2 && !skip; k++) {
            size_t n = prefixes[k] ? strlen(prefixes[k]) : 0;
            if (n > 0 && strncmp(in, prefixes[k], n) == 0 && in[n] == '/')
                skip = n + 1;
        }
        if (skip) {
            in += skip;
            continue;
        }
        out[o++] = *in++;
    }
    out[o] = '\0';
}

static mr_frame_decision run_frame_failed(void *user, size_t index, const mr_error *e)
{
    job_run *r = user;
    mr_error err;
    bool gave_up = true;
    /* A frame over a limit or with invalid input fails the same way every
     * time: retrying only repeats the work (and the memory) */
    bool final = e->code == MR_ERR_LIMIT || e->code == MR_ERR_INVALID;
    char shown[sizeof e->msg];
    mr_daemon_redact(r->d, e->msg, shown, sizeof shown);
    if (e->code == MR_ERR_NO_SPACE && !r->write_had_room) {
        /* the frame rendered and could not be stored: no attempt lost,
         * it waits (pending) while the queue pauses for space; first the
         * guard, whose reserve makes room for the record */
        mr_daemon_no_space(r->d, shown);
        mr_store_frame_requeue(r->d->store, r->id, index, shown, &err);
        log_line(r->d, "job=%s frame %zu not stored, it waits for disk space: %s", r->id, index, e->msg);
        return MR_FRAME_RETRY;
    }
    if (e->code == MR_ERR_NO_SPACE) /* (with room: a quota) the queue pauses all the same */
        mr_daemon_no_space(r->d, shown);
    r->write_had_room = false;
    mr_store_frame_failed(r->d->store, r->id, index, shown, final, &gave_up, &err);
    pthread_mutex_lock(&r->d->lock);
    r->d->frames_failed++;
    pthread_mutex_unlock(&r->d->lock);
    log_line(r->d, "job=%s frame %zu failed%s: %s", r->id, index, gave_up ? " (giving up)" : "", e->msg);
    char json[768];
    cJSON *o = cJSON_CreateObject();
    cJSON_AddNumberToObject(o, "index", (double)index);
    cJSON_AddStringToObject(o, "error", shown);
    cJSON_AddBoolToObject(o, "gave_up", gave_up);
    char *s = cJSON_PrintUnformatted(o);
    snprintf(json, sizeof json, "%s", s ? s : "{}");
    free(s);
    cJSON_Delete(o);
    mr_job_record rec;
    publish(r->d, r->id, "frame_failed", json,
            mr_store_job_get(r->d->store, r->id, &rec, &err) == MR_OK ? rec.done_seq : -1, false);
    if (gave_up) {
        r->failed++;
        return MR_FRAME_SKIP;
    }
    return MR_FRAME_RETRY;
}

/* Moves a running job to its final state, unless a cancel (or anything
 * else) changed it meanwhile: under d->lock, like every state change a
 * request makes, so the last word is the user's. */
static bool finish_job(mr_daemon *d, const char *id, mr_job_state state, const char *why)
{
    mr_error err;
    mr_job_record rec;
    char shown[sizeof err.msg];
    if (why)
        mr_daemon_redact(d, why, shown, sizeof shown);
    pthread_mutex_lock(&d->lock);
    int rc = mr_store_job_get(d->store, id, &rec, &err);
    bool changed = rc == MR_OK && rec.state == MR_JOB_RUNNING;
    if (changed)
        rc = mr_store_job_set_state(d->store, id, state, why ? shown : NULL, &err);
    pthread_mutex_unlock(&d->lock);
    if (rc < 0)
        log_line(d, "job=%s: could not record state %s: %s", id, mr_job_state_name(state), err.msg);
    return changed && rc == MR_OK;
}

/* Renders one claimed job to the end (or until cancelled or stopped) in
 * the render worker process of slot proc (render_proc.h). */
static void run_job(mr_daemon *d, mr_render_proc *proc, const char *id, running_job *entry)
{
    mr_error err = {0};
    char *json = NULL;
    mr_job *job = NULL;
    mr_frame_record *frames = NULL;
    size_t frame_count = 0;
    uint8_t *wanted = NULL;
    const char **paths = NULL;
    mr_job_error jerr;
    char pointer[512];
    int rc;

    log_line(d, "job=%s running", id);
    publish_state(d, id);
    if ((rc = mr_store_job_json(d->store, id, &json, &err)) < 0)
        goto fail;
    if ((rc = mr_job_parse(json, strlen(json), &job, &jerr)) < 0) {
        mr_error_set(&err, rc, "%s: %s", jerr.pointer, jerr.message);
        goto fail;
    }
    if ((rc = resolve_assets(d, job, pointer, &err)) < 0) {
        mr_error_prefix(&err, "%s: ", pointer);
        goto fail;
    }
    if ((rc = mr_store_frames(d->store, id, &frames, &frame_count, &err)) < 0)
        goto fail;
    wanted = calloc(job->frame_count, 1);
    paths = calloc(job->asset_count ? job->asset_count : 1, sizeof *paths);
    if (!wanted || !paths) {
        rc = mr_error_set(&err, MR_ERR_NOMEM, "out of memory");
        goto fail;
    }
    job_run run = {.d = d, .id = id, .job = job, .entry = entry};
    memset(wanted, 1, job->frame_count);
    for (size_t i = 0; i < frame_count; i++) {
        size_t f = frames[i].index;
        if (f < job->frame_count && (frames[i].state == MR_FRAME_DONE || frames[i].state == MR_FRAME_FAILED)) {
            wanted[f] = 0; /* done before a restart, or given up */
            run.failed += frames[i].state == MR_FRAME_FAILED;
        }
    }
    for (size_t i = 0; i < job->asset_count; i++)
        paths[i] = job->assets[i].path;
    mr_render_session session = {
        .user = &run,
        .job_id = id,
        .job_json = json,
        .job_json_len = strlen(json),
        .paths = paths,
        .path_count = job->asset_count,
        .wanted = wanted,
        .frame_count = job->frame_count,
        .frame_started = run_frame_started,
        .frame_done = run_frame_done,
        .frame_failed = run_frame_failed,
        .stop_requested = run_stop_requested,
        .cancelled = run_cancelled,
    };
    rc = mr_render_proc_run(proc, &session, &err);
    if (rc == MR_ERR_CANCELLED) {
        if (!atomic_load(&entry->cancel)) {
            /* the daemon is stopping or the disk is full: leave the job to
             * resume (at the next start, or once space is back) */
            char why[512];
            bool full = mr_daemon_disk_full(d, why, sizeof why);
            finish_job(d, id, MR_JOB_QUEUED, NULL);
            log_line(d, "job=%s paused for %s", id, full ? "disk space" : "shutdown");
        }
        goto done;
    }
    if (rc < 0)
        goto fail;
    bool ended;
    if (run.failed > 0) {
        char why[128];
        snprintf(why, sizeof why, "%zu frame%s failed after all retries", run.failed, run.failed == 1 ? "" : "s");
        ended = finish_job(d, id, MR_JOB_FAILED, why);
        log_line(d, "job=%s failed: %s", id, why);
    } else {
        ended = finish_job(d, id, MR_JOB_SUCCEEDED, NULL);
        log_line(d, "job=%s succeeded", id);
    }
    publish_state(d, id);
    if (ended)
        notify_final(d, id);
    goto done;
fail:
    /* a job canceled meanwhile stays canceled (and was notified as such) */
    ended = finish_job(d, id, MR_JOB_FAILED, err.msg);
    log_line(d, "job=%s failed: %s", id, err.msg);
    publish_state(d, id);
    if (ended)
        notify_final(d, id);
done:
    /* a frame the render did not finish (a cancel killed the worker in it)
     * is not running any more */
    if (mr_store_frames_release(d->store, id, &err) < 0)
        log_line(d, "job=%s: could not release its running frames: %s", id, err.msg);
    free(paths);
    free(wanted);
    mr_frame_records_free(frames, frame_count);
    mr_job_free(job);
    free(json);
}

typedef struct worker_slot {
    mr_daemon *d;
    mr_render_proc *proc;
} worker_slot;

static void *worker_main(void *p)
{
    mr_daemon *d = ((worker_slot *)p)->d;
    mr_render_proc *proc = ((worker_slot *)p)->proc;
    free(p);
    /* the worker process starts now, so the first job does not wait for it */
    mr_error err;
    if (mr_render_proc_start(proc, &err) < 0)
        log_line(d, "worker: %s (tried again at the next job)", err.msg);
    for (;;) {
        pthread_mutex_lock(&d->lock);
        if (d->stopping) {
            pthread_mutex_unlock(&d->lock);
            return NULL;
        }
        char id[MR_JOB_ID_LEN + 1];
        /* a full disk pauses the queue (space_main resumes it) */
        int rc = mr_space_guard_full(d->space, NULL, 0) ? MR_ERR_NOT_FOUND
                                                        : mr_store_job_claim(d->store, id, &err);
        if (rc == MR_ERR_NOT_FOUND || rc < 0) {
            if (rc != MR_ERR_NOT_FOUND)
                log_line(d, "worker: claiming a job failed: %s", err.msg);
            struct timespec until;
            clock_gettime(CLOCK_REALTIME, &until);
            until.tv_sec += 1;
            pthread_cond_timedwait(&d->wake, &d->lock, &until);
            pthread_mutex_unlock(&d->lock);
            continue;
        }
        running_job *entry = calloc(1, sizeof *entry);
        if (!entry) {
            mr_store_job_set_state(d->store, id, MR_JOB_QUEUED, NULL, &err);
            pthread_mutex_unlock(&d->lock);
            continue;
        }
        snprintf(entry->id, sizeof entry->id, "%s", id);
        atomic_init(&entry->cancel, false);
        entry->next = d->running;
        d->running = entry;
        pthread_mutex_unlock(&d->lock);

        run_job(d, proc, id, entry);

        pthread_mutex_lock(&d->lock);
        for (running_job **r = &d->running; *r; r = &(*r)->next)
            if (*r == entry) {
                *r = entry->next;
                break;
            }
        pthread_cond_broadcast(&d->released);
        pthread_mutex_unlock(&d->lock);
        free(entry);
    }
}

/* ---- metrics ------------------------------------------------------------- */

char *mr_daemon_metrics(mr_daemon *d)
{
    uint64_t counts[5] = {0};
    mr_error err;
    mr_store_job_counts(d->store, counts, &err);
    mr_cache_stats cs = {0};
    for (unsigned i = 0; i < d->worker_count; i++) {
        mr_cache_stats one;
        mr_render_proc_cache_stats(d->procs[i], &one);
        cs.hits += one.hits;
        cs.misses += one.misses;
        cs.bytes += one.bytes;
        cs.entries += one.entries;
        cs.saved_s += one.saved_s;
    }
    size_t cap = 16384 + (size_t)d->worker_count * 256, len = 0;
    char *out = malloc(cap);
    if (!out)
        return NULL;
#define EMIT(...)                                                                                  \
    do {                                                                                           \
        int n_ = snprintf(out + len, cap - len, __VA_ARGS__);                                     \
        if (n_ > 0)                                                                                \
            len += (size_t)n_ < cap - len ? (size_t)n_ : cap - len - 1;                            \
    } while (0)
    EMIT("# HELP microray_jobs Jobs by state.\n# TYPE microray_jobs gauge\n");
    for (int s = 0; s < 5; s++)
        EMIT("microray_jobs{state=\"%s\"} %llu\n", mr_job_state_name((mr_job_state)s),
             (unsigned long long)counts[s]);
    pthread_mutex_lock(&d->lock);
    EMIT("# HELP microray_frames_rendered_total Frames rendered and stored.\n"
         "# TYPE microray_frames_rendered_total counter\nmicroray_frames_rendered_total %llu\n",
         (unsigned long long)d->frames_rendered);
    EMIT("# HELP microray_frames_failed_total Failed frame attempts.\n"
         "# TYPE microray_frames_failed_total counter\nmicroray_frames_failed_total %llu\n",
         (unsigned long long)d->frames_failed);
    EMIT("# HELP microray_rays_traced_total Rays traced (primary and shadow).\n"
         "# TYPE microray_rays_traced_total counter\nmicroray_rays_traced_total %llu\n",
         (unsigned long long)d->rays);
    EMIT("# HELP microray_frame_seconds Wall time per frame, encode included.\n"
         "# TYPE microray_frame_seconds histogram\n");
    uint64_t cum = 0;
    for (size_t b = 0; b < N_BUCKETS; b++) {
        cum += d->buckets[b];
        EMIT("microray_frame_seconds_bucket{le=\"%g\"} %llu\n", FRAME_BUCKETS[b], (unsigned long long)cum);
    }
    cum += d->buckets[N_BUCKETS];
    EMIT("microray_frame_seconds_bucket{le=\"+Inf\"} %llu\n", (unsigned long long)cum);
    EMIT("microray_frame_seconds_sum %.6f\nmicroray_frame_seconds_count %llu\n", d->frame_seconds_sum,
         (unsigned long long)cum);
    pthread_mutex_unlock(&d->lock);
    EMIT("# HELP microray_cache_hits_total Scene cache hits.\n# TYPE microray_cache_hits_total counter\n"
         "microray_cache_hits_total %llu\n", (unsigned long long)cs.hits);
    EMIT("# HELP microray_cache_misses_total Scene cache misses.\n# TYPE microray_cache_misses_total counter\n"
         "microray_cache_misses_total %llu\n", (unsigned long long)cs.misses);
    EMIT("# HELP microray_cache_bytes Bytes held by the scene cache.\n# TYPE microray_cache_bytes gauge\n"
         "microray_cache_bytes %zu\n", cs.bytes);
    EMIT("# HELP microray_disk_full 1 while the queue is paused for disk space.\n"
         "# TYPE microray_disk_full gauge\nmicroray_disk_full %d\n",
         mr_space_guard_full(d->space, NULL, 0) ? 1 : 0);
    EMIT("# HELP microray_cache_entries Assets in the scene cache.\n# TYPE microray_cache_entries gauge\n"
         "microray_cache_entries %zu\n", cs.entries);
    EMIT("# HELP microray_cache_saved_seconds_total Import time saved by cache hits.\n"
         "# TYPE microray_cache_saved_seconds_total counter\nmicroray_cache_saved_seconds_total %.6f\n",
         cs.saved_s);
    /* the queue and the workers */
    uint64_t queued_frames = 0;
    mr_store_queue_frames(d->store, &queued_frames, &err);
    unsigned busy = 0;
    pthread_mutex_lock(&d->lock);
    for (running_job *r = d->running; r; r = r->next)
        busy++;
    pthread_mutex_unlock(&d->lock);
    EMIT("# HELP microray_queue_jobs Jobs waiting for a worker.\n# TYPE microray_queue_jobs gauge\n"
         "microray_queue_jobs %llu\n", (unsigned long long)counts[MR_JOB_QUEUED]);
    EMIT("# HELP microray_queue_frames Frames still to render, of queued and running jobs.\n"
         "# TYPE microray_queue_frames gauge\nmicroray_queue_frames %llu\n",
         (unsigned long long)queued_frames);
    EMIT("# HELP microray_workers Render worker slots (--workers).\n# TYPE microray_workers gauge\n"
         "microray_workers %u\n", d->worker_count);
    EMIT("# HELP microray_workers_busy Worker slots rendering a job now.\n"
         "# TYPE microray_workers_busy gauge\nmicroray_workers_busy %u\n", busy);
    EMIT("# HELP microray_build_info The daemon's version.\n# TYPE microray_build_info gauge\n"
         "microray_build_info{version=\"%s\"} 1\n", MR_VERSION_STRING);
    /* the daemon's process (the client libraries' standard names) */
    mr_proc_stats ps;
    if (mr_proc_stats_read(0, &ps)) {
        EMIT("# HELP process_cpu_seconds_total User and system CPU time of the daemon.\n"
             "# TYPE process_cpu_seconds_total counter\nprocess_cpu_seconds_total %.2f\n",
             ps.cpu_seconds);
        EMIT("# HELP process_resident_memory_bytes Resident memory of the daemon.\n"
             "# TYPE process_resident_memory_bytes gauge\nprocess_resident_memory_bytes %llu\n",
             (unsigned long long)ps.resident_bytes);
        EMIT("# HELP process_virtual_memory_bytes Virtual memory of the daemon.\n"
             "# TYPE process_virtual_memory_bytes gauge\nprocess_virtual_memory_bytes %llu\n",
             (unsigned long long)ps.virtual_bytes);
        EMIT("# HELP process_open_fds Open file descriptors of the daemon.\n"
             "# TYPE process_open_fds gauge\nprocess_open_fds %u\n", ps.open_fds);
        EMIT("# HELP process_max_fds The daemon's descriptor limit.\n"
             "# TYPE process_max_fds gauge\nprocess_max_fds %llu\n", (unsigned long long)ps.max_fds);
        EMIT("# HELP process_start_time_seconds When the daemon started, unix seconds.\n"
             "# TYPE process_start_time_seconds gauge\nprocess_start_time_seconds %.2f\n",
             ps.start_time);
    }
    /* each render worker's process (slot = --workers index) */
    EMIT("# HELP microray_worker_resident_memory_bytes Resident memory of a render worker process.\n"
         "# TYPE microray_worker_resident_memory_bytes gauge\n");
    for (unsigned i = 0; i < d->worker_count; i++) {
        int pid = mr_render_proc_pid(d->procs[i]);
        if (pid > 0 && mr_proc_stats_read(pid, &ps))
            EMIT("microray_worker_resident_memory_bytes{slot=\"%u\"} %llu\n", i,
                 (unsigned long long)ps.resident_bytes);
    }
    EMIT("# HELP microray_worker_cpu_seconds_total CPU time of the current render worker process of a slot.\n"
         "# TYPE microray_worker_cpu_seconds_total counter\n");
    for (unsigned i = 0; i < d->worker_count; i++) {
        int pid = mr_render_proc_pid(d->procs[i]);
        if (pid > 0 && mr_proc_stats_read(pid, &ps))
            EMIT("microray_worker_cpu_seconds_total{slot=\"%u\"} %.2f\n", i, ps.cpu_seconds);
    }
#undef EMIT
    return out;
}

/* ---- lifecycle ------------------------------------------------------------ */

mr_store *mr_daemon_store(mr_daemon *d) { return d->store; }
const mr_daemon_config *mr_daemon_config_of(const mr_daemon *d) { return &d->cfg; }
bool mr_daemon_ready(const mr_daemon *d) { return atomic_load(&((mr_daemon *)d)->ready); }

bool mr_daemon_stopping(mr_daemon *d)
{
    pthread_mutex_lock(&d->lock);
    bool stopping = d->stopping;
    pthread_mutex_unlock(&d->lock);
    return stopping;
}
unsigned mr_daemon_port(const mr_daemon *d) { return d->http ? mr_http_port(d->http) : 0; }

static void apply_defaults(mr_daemon_config *c)
{
    if (!c->listen_host)
        c->listen_host = "127.0.0.1";
    if (!c->workers)
        c->workers = 1;
    if (!c->cache_bytes)
        c->cache_bytes = (size_t)1 << 30;
    if (!c->max_job_bytes)
        c->max_job_bytes = (size_t)1 << 20;
    if (!c->max_asset_bytes)
        c->max_asset_bytes = (size_t)512 << 20;
    if (!c->http_threads) /* one per core: more only adds scheduling jitter (make bench) */
        c->http_threads = mr_cpu_count();
    if (!c->connection_timeout_s)
        c->connection_timeout_s = 30;
    if (!c->per_ip_connections)
        c->per_ip_connections = 128;
    mr_import_limits lim;
    mr_import_limits_default(&lim);
    if (!c->import_memory)
        c->import_memory = lim.memory_bytes;
    if (!(c->import_timeout_s > 0))
        c->import_timeout_s = lim.timeout_s;
    if (!c->job_memory)
        c->job_memory = mr_job_memory_default();
    if (!c->worker_memory)
        c->worker_memory = mr_render_proc_memory_limit(c->job_memory, c->cache_bytes);
    if (!c->worker_exe)
        c->worker_exe = "/proc/self/exe";
    if (!c->disk_reserve)
        c->disk_reserve = (size_t)64 << 20;
    if (!c->max_connections)
        c->max_connections = 1024;
    if (!c->request_timeout_s)
        c->request_timeout_s = 10;
}

int mr_daemon_start(const mr_daemon_config *cfg, mr_daemon **out, mr_error *err)
{
    *out = NULL;
    if (!cfg->data_dir || !cfg->data_dir[0])
        return mr_error_set(err, MR_ERR_INVALID, "no data directory given (--data DIR)");
    mr_daemon *d = calloc(1, sizeof *d);
    if (!d)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    int rc;
    pthread_mutex_init(&d->lock, NULL);
    pthread_mutex_init(&d->ev_lock, NULL);
    atomic_init(&d->ready, false);
    pthread_cond_init(&d->wake, NULL);
    pthread_cond_init(&d->released, NULL);
    d->cfg = *cfg;
    apply_defaults(&d->cfg);
    d->data_dir = strdup(cfg->data_dir);
    d->roots = calloc(cfg->asset_root_count ? cfg->asset_root_count : 1, sizeof *d->roots);
    if (!d->data_dir || !d->roots) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        goto fail;
    }
    d->cfg.data_dir = d->data_dir;
    d->cfg.asset_roots = NULL; /* the resolved copies below are what counts */
    for (size_t i = 0; i < cfg->asset_root_count; i++) {
        char real[PATH_MAX];
        if (!realpath(cfg->asset_roots[i], real)) {
            rc = mr_error_set(err, MR_ERR_IO, "asset root '%s': %s", cfg->asset_roots[i], strerror(errno));
            goto fail;
        }
        if (!(d->roots[d->root_count++] = strdup(real))) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
            goto fail;
        }
    }
    d->cfg.asset_root_count = d->root_count;
    /* the space guard before the store: on a full disk it releases the
     * reserve, which lets the store open and recover */
    if ((rc = mr_fs_make_dirs(d->data_dir, "data directory", err)) < 0 ||
        (rc = mr_space_guard_open(d->data_dir, d->cfg.disk_reserve, &d->space, err)) < 0 ||
        (rc = mr_store_open(d->data_dir, &d->store, err)) < 0)
        goto fail;
    char why[512];
    if (mr_space_guard_full(d->space, why, sizeof why))
        log_line(d, "disk full: %s; the queue is paused until space is freed", why);
    d->data_real = realpath(d->data_dir, NULL);
    if ((rc = mr_store_recover(d->store, err)) < 0)
        goto fail;
    if (rc > 0)
        log_line(d, "resuming %d job%s interrupted by a stop or crash", rc, rc == 1 ? "" : "s");
    const size_t unknown = mr_store_unknown_frame_dirs(d->store);
    if (unknown)
        log_line(d, "%s/frames holds the frames of %zu job%s this database does not know (a database "
                 "lost, emptied or replaced?): left in place, not served",
                 d->data_dir, unknown, unknown == 1 ? "" : "s");
    d->workers = calloc(d->cfg.workers, sizeof *d->workers);
    d->procs = calloc(d->cfg.workers, sizeof *d->procs);
    if (!d->workers || !d->procs) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        goto fail;
    }
    mr_render_proc_config pc = {
        .exe = d->cfg.worker_exe,
        .threads = d->cfg.render_threads,
        .cache_bytes = d->cfg.cache_bytes,
        /* derived data (bakes, voxelisations) is kept in DATA/<kind>/
         * (created on the first store), so a job after a restart, or
         * another job on the same asset, skips deriving it again */
        .data_dir = d->data_dir,
        .asset_roots = (const char *const *)d->roots,
        .root_count = d->root_count,
        .job_memory = d->cfg.job_memory,
        .import_memory = d->cfg.import_memory,
        .import_timeout_s = d->cfg.import_timeout_s,
        .memory_limit = d->cfg.worker_memory,
        .frame_timeout_s = d->cfg.frame_timeout_s,
        /* renders run at a lower CPU priority than the HTTP threads, so
         * status requests get a core within a scheduler tick even while
         * every core renders */
        .nice = MR_WORKER_NICE,
    };
    for (unsigned i = 0; i < d->cfg.workers; i++) {
        worker_slot *slot = malloc(sizeof *slot);
        if (!slot || (rc = mr_render_proc_new(&pc, &d->procs[i], err)) < 0) {
            free(slot);
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
            goto fail;
        }
        *slot = (worker_slot){.d = d, .proc = d->procs[i]};
        if (pthread_create(&d->workers[i], NULL, worker_main, slot) != 0) {
            free(slot);
            rc = mr_error_set(err, MR_ERR_NOMEM, "cannot start render worker %u", i);
            goto fail;
        }
        d->worker_count++;
    }
    if (pthread_create(&d->space_thread, NULL, space_main, d) != 0) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "cannot start the disk-space watch");
        goto fail;
    }
    d->space_thread_started = true;
    if (curl_global_init(CURL_GLOBAL_DEFAULT) != CURLE_OK) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "cannot initialise libcurl (notifications)");
        goto fail;
    }
    d->curl_ready = true;
    if ((rc = mr_notifier_start(notify_log, d, &d->notifier, err)) < 0)
        goto fail;
    if ((rc = mr_http_start(d, &d->cfg, &d->http, err)) < 0)
        goto fail;
    atomic_store(&d->ready, true);
    log_line(d, "listening on %s://%s:%u/ (data %s, %u worker%s)", d->cfg.tls_cert_pem ? "https" : "http",
             d->cfg.listen_host,
             mr_http_port(d->http), d->data_dir, d->worker_count, d->worker_count == 1 ? "" : "s");
    *out = d;
    return MR_OK;
fail:
    mr_daemon_stop(d);
    return rc;
}

void mr_daemon_stop(mr_daemon *d)
{
    if (!d)
        return;
    /* Draining: /readyz answers 503 (load balancers take the daemon out),
     * submissions and uploads are refused with 503, reads, cancels and
     * deletes are served while each frame in progress finishes; only then
     * does the port close. */
    atomic_store(&d->ready, false);
    pthread_mutex_lock(&d->lock);
    d->stopping = true;
    pthread_cond_broadcast(&d->wake);
    pthread_mutex_unlock(&d->lock);
    for (unsigned i = 0; i < d->worker_count; i++)
        pthread_join(d->workers[i], NULL);
    if (d->space_thread_started)
        pthread_join(d->space_thread, NULL);
    if (d->http)
        mr_http_stop(d->http); /* the port closes; event streams end */
    d->http = NULL;
    mr_notifier_stop(d->notifier); /* after the last job could end */
    d->notifier = NULL;
    if (d->curl_ready)
        curl_global_cleanup();
    free(d->workers);
    if (d->procs)
        for (unsigned i = 0; i < d->cfg.workers; i++)
            mr_render_proc_free(d->procs[i]);
    free(d->procs);
    mr_store_close(d->store);
    mr_space_guard_close(d->space);
    for (mr_event_sub *s = d->subs, *next; s; s = next) {
        next = s->next;
        for (event_msg *m = s->head, *mn; m; m = mn) {
            mn = m->next;
            free(m->text);
            free(m);
        }
        free(s);
    }
    for (size_t i = 0; i < d->root_count; i++)
        free(d->roots[i]);
    free(d->roots);
    free(d->data_dir);
    free(d->data_real);
    pthread_cond_destroy(&d->wake);
    pthread_cond_destroy(&d->released);
    pthread_mutex_destroy(&d->lock);
    pthread_mutex_destroy(&d->ev_lock);
    free(d);
}
