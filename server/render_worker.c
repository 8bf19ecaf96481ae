/*
 * render_worker.c - `microrayd render-worker`: the render worker process's
 * side (render_proc.h). It renders the jobs the daemon sends, one at a
 * time, with the same worker code as the one-shot renderer (worker.h):
 * assets come from its own scene cache, each miss imported in a child of
 * its own (import_worker.h); every finished frame is encoded here and sent
 * to the daemon, which stores it and answers with what to do next.
 */
#define _GNU_SOURCE
#include "render_proc.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "child.h"
#include "import_worker.h"
#include "job_json.h"
#include "render_msg.h"
#include "sandbox.h"
#include "stats_json.h"

/* The largest message the daemon sends: a job (capped by the daemon's
 * body limit), its asset paths and one byte per frame. */
#define MAX_JOB_MESSAGE ((size_t)1 << 30)

typedef struct worker_ctx {
    int fd;
    mr_device *dev;
    mr_cache *cache;
    const char *data_dir;
    size_t job_memory;
    mr_import_limits import;
    /* the job in hand */
    const char *job_id;
    const mr_job *job;
    const uint8_t *wanted;
    size_t frame_count;
    bool stop;                    /* the daemon asked to end the job */
    bool have_decision;           /* the daemon already decided on a frame it could not store */
    mr_frame_decision decision;
} worker_ctx;

/* The daemon is gone or out of step: nothing to do but end. */
static _Noreturn void channel_lost(const mr_error *e)
{
    fprintf(stderr, "microrayd render-worker: %s\n", e->msg);
    _exit(3);
}

static void send_or_die(worker_ctx *c, const mr_msg *m)
{
    mr_error e;
    if (mr_msg_send(c->fd, m, &e) < 0)
        channel_lost(&e);
}

/* The daemon's answer to a frame: ACK or DECISION. */
static void await_answer(worker_ctx *c, uint32_t type, int *code, char *msg, size_t msg_size)
{
    mr_msg m;
    mr_error e;
    if (mr_msg_recv(c->fd, MAX_JOB_MESSAGE, &m, &e) < 0)
        channel_lost(&e);
    if (m.type != type) {
        mr_error_set(&e, MR_ERR_FORMAT, "expected message %u from the daemon, got %u", type, m.type);
        channel_lost(&e);
    }
    c->stop |= (m.flags & MR_MSG_STOP) != 0;
    c->decision = (mr_frame_decision)(m.flags & MR_MSG_DECISION_MASK);
    if (code)
        *code = m.code;
    if (msg)
        snprintf(msg, msg_size, "%s", m.len[0] ? (const char *)m.part[0] : "");
    mr_msg_free(&m);
}

static bool w_wanted(void *user, size_t index)
{
    worker_ctx *c = user;
    return index < c->frame_count && c->wanted[index];
}

static void w_frame_started(void *user, size_t index)
{
    worker_ctx *c = user;
    mr_msg m = {.type = MR_MSG_STARTED, .index = (uint32_t)index};
    send_or_die(c, &m);
}

static int w_frame_done(void *user, size_t index, const mr_film *film, mr_frame_stats *st,
                        mr_error *err)
{
    worker_ctx *c = user;
    double t0 = mr_now();
    mr_exr_meta meta;
    mr_exr_meta_for_frame(&meta, c->job, st);
    snprintf(meta.job, sizeof meta.job, "%s", c->job_id); /* the daemon names jobs by id */
    uint8_t *data = NULL;
    size_t size = 0;
    char *json = NULL;
    mr_exr_options opt = c->job->output.exr; /* encoded on the worker's threads */
    opt.threads = mr_device_threads(c->dev);
    int rc = mr_exr_write_memory(&data, &size, film, &opt, &meta, err);
    st->encode_s = mr_now() - t0;
    if (rc == MR_OK) {
        /* the record carries the final totals (the worker adds encode after us) */
        mr_frame_stats rec = *st;
        rec.total_s += rec.encode_s;
        if (!(json = mr_frame_stats_json(&rec)))
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    if (rc < 0) {
        free(data);
        return rc; /* the worker reports it through w_frame_failed */
    }
    mr_msg m = {.type = MR_MSG_FRAME, .index = (uint32_t)index, .len = {strlen(json), size},
                .part = {(const uint8_t *)json, data}};
    send_or_die(c, &m);
    free(json);
    free(data);
    int code;
    char msg[sizeof err->msg];
    await_answer(c, MR_MSG_ACK, &code, msg, sizeof msg);
    if (code < 0) {
        /* not stored: the daemon has recorded it and decided */
        c->have_decision = code != MR_ERR_CANCELLED;
        return mr_error_set(err, code, "%s", msg);
    }
    return MR_OK;
}

static mr_frame_decision w_frame_failed(void *user, size_t index, const mr_error *err)
{
    worker_ctx *c = user;
    if (c->have_decision) {
        c->have_decision = false;
        return c->decision;
    }
    mr_msg m = {.type = MR_MSG_FAILED, .index = (uint32_t)index, .code = err->code,
                .len = {strlen(err->msg)}, .part = {(const uint8_t *)err->msg}};
    send_or_die(c, &m);
    await_answer(c, MR_MSG_DECISION, NULL, NULL, 0);
    return c->decision;
}

static bool w_stop_requested(void *user)
{
    return ((worker_ctx *)user)->stop;
}

/* The cache key of an asset's file: its content hash (uploaded assets are
 * named by it already; server-side files are hashed). The cache adds the
 * import parameters ("refine") to it. The path was checked to be a regular
 * file when the job was resolved, but the file may have been replaced
 * since: O_NONBLOCK, so a FIFO planted under an asset root cannot block the
 * worker forever waiting for a writer, and anything but a regular file is
 * refused (the worker names the asset's field). */
static int asset_key(const mr_asset_desc *a, char key[65], mr_error *err)
{
    if (a->id) {
        snprintf(key, 65, "%s", a->id);
        return MR_OK;
    }
    int fd = open(a->path, O_RDONLY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0)
        return mr_error_set(err, MR_ERR_IO, "%s: %s", a->path, strerror(errno));
    int rc = MR_OK;
    struct stat st;
    if (fstat(fd, &st) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: %s", a->path, strerror(errno));
        goto done;
    }
    if (!S_ISREG(st.st_mode)) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: not a regular file (a FIFO, device or directory "
                          "cannot be an asset)", a->path);
        goto done;
    }
    mr_sha256 h;
    mr_sha256_init(&h);
    char buf[1 << 16];
    for (;;) {
        ssize_t n = read(fd, buf, sizeof buf);
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0) {
            rc = mr_error_set(err, MR_ERR_IO, "%s: read error: %s", a->path, strerror(errno));
            goto done;
        }
        if (n == 0)
            break;
        mr_sha256_update(&h, buf, (size_t)n);
    }
    uint8_t digest[32];
    mr_sha256_final(&h, digest);
    mr_hex_encode(digest, sizeof digest, key);
done:
    close(fd);
    return rc;
}

/* A cache miss imports in a child process under the daemon's limits
 * (import_worker.h); the worker's own death (a cancel) takes it along. */
typedef struct isolated_import {
    worker_ctx *c;
    char label[96]; /* an upload by its id, not by its path in the data directory */
} isolated_import;

static int import_in_child(void *user, const char *path, const mr_refine_params *refine,
                           mr_asset **out, mr_asset_stage *stage, mr_error *err)
{
    isolated_import *ii = user;
    return mr_import_isolated(path, ii->label, refine, &ii->c->import, NULL, NULL, out, stage, err);
}

static int w_acquire(void *user, const mr_asset_desc *desc, mr_asset **out, bool *hit,
                     double *saved_s, mr_asset_stage *stage, mr_error *err)
{
    worker_ctx *c = user;
    char key[65];
    int rc = asset_key(desc, key, err);
    if (rc < 0)
        return rc;
    isolated_import ii = {.c = c};
    if (desc->id)
        snprintf(ii.label, sizeof ii.label, "asset %.64s", desc->id);
    else
        snprintf(ii.label, sizeof ii.label, "%s", desc->path);
    mr_cache_importer importer = {.import = import_in_child, .user = &ii};
    return mr_cache_acquire_refined(c->cache, key, desc->path,
                                    desc->refine ? &desc->refine_params : NULL, &importer, out, hit,
                                    saved_s, stage, err);
}

static void w_release(void *user, mr_asset *asset)
{
    mr_cache_release(((worker_ctx *)user)->cache, asset);
}

/* One JOB message: parse, point the assets at their resolved paths,
 * render, and end with END. */
static void run_job(worker_ctx *c, const mr_msg *in)
{
    mr_error err = {0};
    mr_job *job = NULL;
    mr_job_error jerr;
    mr_job_stats stats = {0};
    int rc = mr_job_parse((const char *)in->part[1], in->len[1], &job, &jerr);
    if (rc < 0) {
        mr_error_set(&err, rc, "%s: %s", jerr.pointer, jerr.message);
        goto end;
    }
    const char *path = (const char *)in->part[2], *paths_end = path + in->len[2];
    for (size_t i = 0; i < job->asset_count; i++) {
        size_t n = path < paths_end ? strnlen(path, (size_t)(paths_end - path)) : 0;
        char *copy = path + n < paths_end ? strdup(path) : NULL;
        if (!copy) {
            rc = mr_error_set(&err, path + n < paths_end ? MR_ERR_NOMEM : MR_ERR_INVALID,
                              "the daemon sent %s asset paths than the job has assets",
                              path + n < paths_end ? "no fewer" : "fewer");
            goto end;
        }
        free(job->assets[i].path);
        job->assets[i].path = copy;
        path += n + 1;
    }
    if (in->len[3] != job->frame_count) {
        rc = mr_error_set(&err, MR_ERR_INVALID, "the daemon sent %zu wanted flags for %zu frames",
                          in->len[3], job->frame_count);
        goto end;
    }
    c->job_id = (const char *)in->part[0];
    c->job = job;
    c->wanted = in->part[3];
    c->frame_count = in->len[3];
    c->stop = false;
    c->have_decision = false;
    mr_worker_io io = {
        .user = c,
        .frame_done = w_frame_done,
        .wanted = w_wanted,
        .frame_started = w_frame_started,
        .frame_failed = w_frame_failed,
        .stop_requested = w_stop_requested,
        .acquire_asset = w_acquire,
        .release_asset = w_release,
        .cache_dir = c->data_dir,
        .memory_budget = c->job_memory,
    };
    rc = mr_worker_run(c->dev, job, &io, &stats, &err);
end:;
    mr_cache_stats cs;
    mr_cache_stats_get(c->cache, &cs);
    const char *msg = rc < 0 ? err.msg : "";
    mr_msg m = {.type = MR_MSG_END, .code = rc, .len = {strlen(msg), sizeof cs},
                .part = {(const uint8_t *)msg, (const uint8_t *)&cs}};
    send_or_die(c, &m);
    mr_job_stats_free(&stats);
    mr_job_free(job);
    c->job = NULL;
    c->job_id = NULL;
    mr_heap_release(); /* the job's frames are done: the next may be small */
}

static bool parse_size(const char *s, size_t *out)
{
    char *end;
    errno = 0;
    unsigned long long v = strtoull(s, &end, 10);
    if (errno || *end || !s[0] || s[0] == '-')
        return false;
    *out = (size_t)v;
    return true;
}

int mr_cmd_render_worker(int argc, char **argv)
{
    mr_heap_keep_freed();
    worker_ctx c = {.fd = MR_CHILD_FD};
    size_t threads = 0, cache_bytes = 0;
    const char **roots = calloc((size_t)argc / 2 + 1, sizeof *roots);
    size_t root_count = 0;
    bool ok = argc % 2 == 0 && roots; /* --flag value pairs */
    for (int i = 0; i + 1 < argc && ok; i += 2) {
        const char *a = argv[i], *v = argv[i + 1];
        if (!strcmp(a, "--threads"))
            ok = parse_size(v, &threads) && threads <= MR_MAX_THREADS;
        else if (!strcmp(a, "--cache-bytes"))
            ok = parse_size(v, &cache_bytes);
        else if (!strcmp(a, "--data"))
            c.data_dir = v;
        else if (!strcmp(a, "--job-memory"))
            ok = parse_size(v, &c.job_memory);
        else if (!strcmp(a, "--import-memory"))
            ok = parse_size(v, &c.import.memory_bytes);
        else if (!strcmp(a, "--import-timeout"))
            c.import.timeout_s = strtod(v, NULL);
        else if (!strcmp(a, "--import-exe"))
            c.import.worker_exe = v;
        else if (!strcmp(a, "--asset-root"))
            roots[root_count++] = v;
        else
            ok = false;
    }
    struct stat st;
    if (!ok || !c.data_dir || fstat(MR_CHILD_FD, &st) != 0 || !S_ISSOCK(st.st_mode)) {
        fprintf(stderr, "microrayd render-worker: runs only as the daemon's render worker\n");
        free(roots);
        return 2;
    }
    mr_error err = {0};
    int status = 0;
    if (mr_device_new((unsigned)threads, &c.dev, &err) < 0 ||
        mr_cache_new(cache_bytes, &c.cache, &err) < 0) {
        fprintf(stderr, "microrayd render-worker: %s\n", err.msg);
        status = 1;
        goto done;
    }
    /* confined from here on (sandbox.h), its import children too */
    char *exe = realpath("/proc/self/exe", NULL);
    int sb = mr_sandbox_apply(c.data_dir, roots, root_count, exe, &err);
    free(exe);
    if (sb < 0 && sb != MR_ERR_NOT_FOUND) {
        fprintf(stderr, "microrayd render-worker: %s\n", err.msg);
        status = 1;
        goto done;
    }
    mr_msg hello = {.type = MR_MSG_HELLO, .index = MR_RENDER_PROTOCOL};
    send_or_die(&c, &hello);
    for (;;) {
        mr_msg m;
        if (mr_msg_recv(c.fd, MAX_JOB_MESSAGE, &m, &err) < 0)
            break; /* the daemon closed the channel: done */
        if (m.type != MR_MSG_JOB) {
            fprintf(stderr, "microrayd render-worker: message %u out of turn\n", m.type);
            mr_msg_free(&m);
            status = 3;
            break;
        }
        run_job(&c, &m);
        mr_msg_free(&m);
    }
done:
    mr_cache_free(c.cache);
    mr_device_free(c.dev);
    free(roots);
    return status;
}
