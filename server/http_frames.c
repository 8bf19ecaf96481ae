/*
 * http_frames.c - a job's frames as a collection (http_internal.h):
 *   GET /v1/jobs/{id}/frames      every frame's state, retries, error,
 *                                 seconds, file size and links;
 *   GET /v1/jobs/{id}/frames.tar  every finished frame and stats.json as one
 *                                 POSIX tar (ustar) archive, streamed from
 *                                 the files (never held in memory).
 * One frame's file, preview and stats are http_handlers.c's.
 *
 * The archive's length is known before the first byte (a 512-byte header
 * per file, the file padded to 512 bytes, two zero blocks at the end), so
 * it is sent with a Content-Length and a client can show progress. Its
 * members are NNNN.exr and stats.json at the top level: `tar -x -C DIR`
 * gives what `microray fetch ID --out DIR` writes. A frame whose file
 * changes size while the archive is read (the job was deleted meanwhile)
 * ends the response with an error, so a cut archive never looks whole.
 */
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "http_internal.h"
#include "worker.h"

#define TAR_BLOCK 512u

/* ---- GET /v1/jobs/{id}/frames ----------------------------------------- */

/* A JSON string of s (quotes, backslashes and control characters escaped). */
static cJSON *text_or_null(const char *s)
{
    return s && *s ? cJSON_CreateString(s) : cJSON_CreateNull();
}

enum MHD_Result http_job_frames(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &job, &res))
        return res;
    const char *state_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "state");
    static const char *const states[] = {"pending", "running", "done", "failed"};
    int only = -1;
    for (int i = 0; state_arg && i < 4; i++)
        if (!strcmp(state_arg, states[i]))
            only = i;
    if (state_arg && only < 0)
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "unknown frame state '%.64s'; expected pending, running, done or failed",
                                 state_arg);
    mr_store *st = mr_daemon_store(r->h->d);
    mr_frame_record *frames = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_frames(st, job.id, &frames, &count, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    http_put(doc, "id", cJSON_CreateString(job.id), &ok);
    cJSON *list = http_put(doc, "frames", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < count && ok; i++) {
        const mr_frame_record *f = &frames[i];
        if (only >= 0 && (int)f->state != only)
            continue;
        cJSON *o = cJSON_CreateObject();
        http_put(o, "index", cJSON_CreateNumber((double)f->index), &ok);
        http_put(o, "state", cJSON_CreateString(mr_frame_state_name(f->state)), &ok);
        http_put(o, "retries", cJSON_CreateNumber(f->retries), &ok);
        http_put(o, "error", text_or_null(f->error), &ok);
        cJSON *seconds = cJSON_CreateNull(), *bytes = cJSON_CreateNull(), *links = cJSON_CreateNull();
        if (f->state == MR_FRAME_DONE) {
            cJSON *stats = f->stats_json ? cJSON_Parse(f->stats_json) : NULL;
            const cJSON *total =
                cJSON_GetObjectItemCaseSensitive(cJSON_GetObjectItemCaseSensitive(stats, "seconds"), "total");
            if (cJSON_IsNumber(total)) {
                cJSON_Delete(seconds);
                seconds = cJSON_CreateNumber(total->valuedouble);
            }
            cJSON_Delete(stats);
            char path[4096];
            struct stat sb;
            if (mr_store_frame_file(st, job.id, f->index, path, sizeof path, NULL) == MR_OK &&
                stat(path, &sb) == 0) {
                cJSON_Delete(bytes);
                bytes = cJSON_CreateNumber((double)sb.st_size);
            }
            char href[128];
            cJSON_Delete(links);
            links = cJSON_CreateObject();
            snprintf(href, sizeof href, "/v1/jobs/%s/frames/%zu", job.id, f->index);
            http_put(links, "exr", cJSON_CreateString(href), &ok);
            snprintf(href, sizeof href, "/v1/jobs/%s/frames/%zu.png", job.id, f->index);
            http_put(links, "png", cJSON_CreateString(href), &ok);
            snprintf(href, sizeof href, "/v1/jobs/%s/frames/%zu/stats", job.id, f->index);
            http_put(links, "stats", cJSON_CreateString(href), &ok);
        }
        http_put(o, "seconds", seconds, &ok);
        http_put(o, "bytes", bytes, &ok);
        http_put(o, "links", links, &ok);
        if (!o || !cJSON_AddItemToArray(list, o)) {
            cJSON_Delete(o);
            ok = false;
        }
    }
    mr_frame_records_free(frames, count);
    return http_send_built(r, c, MHD_HTTP_OK, doc, ok);
}

/* ---- GET /v1/jobs/{id}/frames.tar ------------------------------------- */

typedef struct tar_member {
    size_t index;     /* frame index; SIZE_MAX: stats.json */
    uint64_t size;
    long long mtime;
} tar_member;

typedef struct tar_stream {
    mr_store *st;
    char job[MR_JOB_ID_LEN + 1];
    tar_member *members;
    size_t count;
    char *stats;      /* stats.json, the last member */
    size_t at;        /* member being sent */
    int phase;        /* 0 header, 1 body, 2 padding, 3 the end blocks */
    uint64_t done;    /* bytes of the phase sent */
    int fd;
    uint8_t header[TAR_BLOCK];
} tar_stream;

static uint64_t padded(uint64_t n) { return (n + TAR_BLOCK - 1) / TAR_BLOCK * TAR_BLOCK; }

/* v as width - 1 octal digits and a NUL (v below 8^(width-1): frames are
 * far below the 8 GiB of a 12-byte field). */
static void tar_octal(uint8_t *field, size_t width, uint64_t v)
{
    field[width - 1] = '\0';
    for (size_t i = width - 1; i-- > 0; v >>= 3)
        field[i] = (uint8_t)('0' + (v & 7));
}

/* A ustar header: name, mode 0644, size and mtime in octal, the checksum
 * over the header with its own field as spaces. */
static void tar_header(uint8_t h[TAR_BLOCK], const char *name, uint64_t size, long long mtime)
{
    memset(h, 0, TAR_BLOCK);
    snprintf((char *)h, 100, "%s", name);
    memcpy(h + 100, "0000644", 8);
    memcpy(h + 108, "0000000", 8);
    memcpy(h + 116, "0000000", 8);
    tar_octal(h + 124, 12, size);
    tar_octal(h + 136, 12, (uint64_t)(mtime > 0 ? mtime : 0));
    memset(h + 148, ' ', 8);
    h[156] = '0';
    memcpy(h + 257, "ustar", 6);
    memcpy(h + 263, "00", 2);
    unsigned sum = 0;
    for (size_t i = 0; i < TAR_BLOCK; i++)
        sum += h[i];
    tar_octal(h + 148, 7, sum);
    h[155] = ' ';
}

static void tar_free(void *cls)
{
    tar_stream *t = cls;
    if (t->fd >= 0)
        close(t->fd);
    free(t->members);
    free(t->stats);
    free(t);
}

static ssize_t tar_read(void *cls, uint64_t pos, char *buf, size_t max)
{
    (void)pos;
    tar_stream *t = cls;
    for (;;) {
        if (t->at >= t->count) { /* two zero blocks end the archive */
            uint64_t left = 2 * TAR_BLOCK - t->done;
            if (left == 0)
                return MHD_CONTENT_READER_END_OF_STREAM;
            size_t n = left < max ? (size_t)left : max;
            memset(buf, 0, n);
            t->done += n;
            return (ssize_t)n;
        }
        tar_member *m = &t->members[t->at];
        if (t->phase == 0) {
            if (t->done == 0) {
                char name[MR_FRAME_NAME_MAX];
                if (m->index == SIZE_MAX)
                    snprintf(name, sizeof name, "stats.json");
                else
                    mr_frame_file_name(m->index, name);
                tar_header(t->header, name, m->size, m->mtime);
                if (m->index != SIZE_MAX) {
                    char path[4096];
                    t->fd = mr_store_frame_file(t->st, t->job, m->index, path, sizeof path, NULL) == MR_OK
                                ? open(path, O_RDONLY | O_CLOEXEC)
                                : -1;
                    if (t->fd < 0)
                        return MHD_CONTENT_READER_END_WITH_ERROR; /* gone meanwhile */
                }
            }
            size_t n = TAR_BLOCK - (size_t)t->done < max ? TAR_BLOCK - (size_t)t->done : max;
            memcpy(buf, t->header + t->done, n);
            t->done += n;
            if (t->done == TAR_BLOCK) {
                t->phase = 1;
                t->done = 0;
            }
            return (ssize_t)n;
        }
        if (t->phase == 1) {
            uint64_t left = m->size - t->done;
            if (left == 0) {
                t->phase = 2;
                t->done = 0;
                continue;
            }
            size_t n = left < max ? (size_t)left : max;
            ssize_t got;
            if (m->index == SIZE_MAX) {
                memcpy(buf, t->stats + t->done, n);
                got = (ssize_t)n;
            } else {
                got = pread(t->fd, buf, n, (off_t)t->done);
                if (got <= 0) /* shorter than it was: not a whole archive */
                    return MHD_CONTENT_READER_END_WITH_ERROR;
            }
            t->done += (uint64_t)got;
            return got;
        }
        /* padding to the block */
        uint64_t left = padded(m->size) - m->size - t->done;
        if (left == 0) {
            if (t->fd >= 0)
                close(t->fd);
            t->fd = -1;
            t->at++;
            t->phase = 0;
            t->done = 0;
            continue;
        }
        size_t n = left < max ? (size_t)left : max;
        memset(buf, 0, n);
        t->done += n;
        return (ssize_t)n;
    }
}

enum MHD_Result http_frames_tar(req *r, struct MHD_Connection *c)
{
    mr_job_record job;
    enum MHD_Result res = MHD_NO;
    if (!http_load_job(r, c, &job, &res))
        return res;
    mr_store *st = mr_daemon_store(r->h->d);
    mr_frame_record *frames = NULL;
    size_t count = 0;
    mr_error err = {0};
    int rc = mr_store_frames(st, job.id, &frames, &count, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    tar_stream *t = calloc(1, sizeof *t);
    cJSON *stats = NULL;
    if (!t || !(t->members = calloc(count + 1, sizeof *t->members))) {
        free(t);
        mr_frame_records_free(frames, count);
        return http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    t->st = st;
    t->fd = -1;
    memcpy(t->job, job.id, sizeof t->job);
    memcpy(r->job, job.id, sizeof r->job);
    uint64_t total = 2 * TAR_BLOCK;
    for (size_t i = 0; i < count; i++) {
        char path[4096];
        struct stat sb;
        if (frames[i].state != MR_FRAME_DONE ||
            mr_store_frame_file(st, job.id, frames[i].index, path, sizeof path, NULL) < 0 ||
            stat(path, &sb) != 0)
            continue;
        t->members[t->count++] = (tar_member){frames[i].index, (uint64_t)sb.st_size, (long long)sb.st_mtime};
        total += TAR_BLOCK + padded((uint64_t)sb.st_size);
    }
    mr_frame_records_free(frames, count);
    if ((rc = http_job_stats_doc(r->h, &job, &stats, &err)) < 0 ||
        !(t->stats = cJSON_Print(stats))) {
        cJSON_Delete(stats);
        tar_free(t);
        return rc < 0 ? http_send_error(r, c, rc, &err)
                      : http_send_problem(r, c, P_INTERNAL, NULL, "out of memory");
    }
    cJSON_Delete(stats);
    size_t slen = strlen(t->stats);
    t->members[t->count++] = (tar_member){SIZE_MAX, slen, (long long)time(NULL)};
    total += TAR_BLOCK + padded(slen);
    struct MHD_Response *resp = MHD_create_response_from_callback(total, 64 * 1024, tar_read, t, tar_free);
    if (!resp) {
        tar_free(t);
        return MHD_NO;
    }
    char disposition[96];
    snprintf(disposition, sizeof disposition, "attachment; filename=\"%s.tar\"", job.id);
    if (MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, "application/x-tar") != MHD_YES ||
        MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_DISPOSITION, disposition) != MHD_YES) {
        MHD_destroy_response(resp);
        return MHD_NO;
    }
    return http_send_response(r, c, MHD_HTTP_OK, resp, total);
}
