/*
 * store_frames.c - frames in the store (store.h, store_internal.h): their
 * rows, their EXR files under DIR/frames/<job>/ and their retries. A frame
 * is marked done only after its file is durable (store.c).
 */
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "store_internal.h"
#include "microray.h"

/* For a frame lookup that found no row: an unknown job, or a job without
 * that frame. */
static int no_frame(mr_store *st, const char *id, size_t index, mr_error *err)
{
    mr_job_state state;
    int rc = store_job_state_locked(st, id, &state, err);
    if (rc < 0)
        return rc;
    return mr_error_set(err, MR_ERR_NOT_FOUND, "job '%s' has no frame %zu", id, index);
}

/* ---- frames ----------------------------------------------------------------- */

/* One row of S_FRAMES_LIST / S_FRAME_ROW into f (stats_json malloc'ed). */
static int read_frame_row(sqlite3_stmt *s, mr_frame_record *f, mr_error *err)
{
    memset(f, 0, sizeof *f);
    f->index = (size_t)sqlite3_column_int64(s, 0);
    f->state = (mr_frame_state)sqlite3_column_int(s, 1);
    f->retries = sqlite3_column_int(s, 2);
    store_copy_col(f->error, sizeof f->error, s, 3);
    const unsigned char *t = sqlite3_column_text(s, 4);
    if (t && !(f->stats_json = mr_memdup_str(t, (size_t)sqlite3_column_bytes(s, 4))))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory reading frames");
    return MR_OK;
}

static int frame_row(sqlite3_stmt *s, void *row, mr_error *err)
{
    return read_frame_row(s, row, err);
}

int mr_store_frames(mr_store *st, const char *id, mr_frame_record **out, size_t *count,
                    mr_error *err)
{
    if (!st || !out || !count)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frames: missing argument");
    *out = NULL;
    *count = 0;
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    store_rows rows = {.elem = sizeof **out, .first_cap = 64, .read = frame_row};
    pthread_mutex_lock(&st->lock);
    mr_job_state state;
    size_t expected = 0;
    /* An empty result must not hide an unknown id; the frame count sizes
     * the array once (a record is over 500 bytes, 100,000 of them are
     * 54 MB). */
    int rc = store_job_lookup_locked(st, id, &state, &expected, err);
    if (rc == MR_OK && expected > 0) {
        rows.items = malloc(expected * rows.elem);
        if (!rows.items)
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory listing %zu frames", expected);
        rows.cap = rows.items ? expected : 0;
    }
    sqlite3_stmt *s = store_stmt(st, S_FRAMES_LIST);
    if (rc == MR_OK)
        rc = store_read_rows(st, s, store_bind_text(s, 1, id), &rows, "frames", err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        mr_frame_records_free(rows.items, rows.count);
        return rc;
    }
    *out = rows.items;
    *count = rows.count;
    return MR_OK;
}

int mr_store_frame_get(mr_store *st, const char *id, size_t index, mr_frame_record *out, mr_error *err)
{
    memset(out, 0, sizeof *out);
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    mr_job_state state;
    size_t frames = 0;
    int rc = store_job_lookup_locked(st, id, &state, &frames, err);
    if (rc == MR_OK && index >= frames)
        rc = mr_error_set(err, MR_ERR_NOT_FOUND, "job %s has no frame %zu", id, index);
    sqlite3_stmt *s = store_stmt(st, S_FRAME_ROW);
    if (rc == MR_OK)
        rc = store_bind_check(st, store_bind_text(s, 1, id), "read frame", err);
    if (rc == MR_OK)
        rc = store_bind_check(st, sqlite3_bind_int64(s, 2, (sqlite3_int64)index), "read frame", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW)
            rc = read_frame_row(s, out, err);
        else if (step == SQLITE_DONE)
            rc = mr_error_set(err, MR_ERR_NOT_FOUND, "job %s has no frame %zu", id, index);
        else
            rc = store_db_fail(st, step, "read frame", err);
    }
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

void mr_frame_records_free(mr_frame_record *frames, size_t count)
{
    if (!frames)
        return;
    for (size_t i = 0; i < count; i++)
        free(frames[i].stats_json);
    free(frames);
}

/* Reads a frame's state, retries and its job's max_retries (caller holds
 * the lock); MR_ERR_NOT_FOUND naming the job or the frame. */
static int frame_get_locked(mr_store *st, const char *id, size_t index, mr_frame_state *state,
                            int *retries, int *max_retries, mr_error *err)
{
    if (index > (size_t)INT64_MAX)
        return no_frame(st, id, index, err);
    sqlite3_stmt *s = store_stmt(st, S_FRAME_GET);
    int rc = store_step_row(st, s,
                            store_bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, (sqlite3_int64)index),
                            "read frame", err);
    if (rc == 1) {
        if (state)
            *state = (mr_frame_state)sqlite3_column_int(s, 0);
        if (retries)
            *retries = sqlite3_column_int(s, 1);
        if (max_retries)
            *max_retries = sqlite3_column_int(s, 2);
    }
    store_stmt_release(s);
    if (rc == 0)
        return no_frame(st, id, index, err);
    return rc < 0 ? rc : MR_OK;
}

/* Updates state, retries and error of an existing frame (lock held). */
static int frame_set_locked(mr_store *st, const char *id, size_t index, mr_frame_state state,
                            int retries, const char *error, mr_error *err)
{
    sqlite3_stmt *s = store_stmt(st, S_FRAME_SET);
    return store_exec_bound(st, s,
                            store_bind_text(s, 1, id) |
                                sqlite3_bind_int64(s, 2, (sqlite3_int64)index) |
                                sqlite3_bind_int(s, 3, (int)state) |
                                sqlite3_bind_int(s, 4, retries) |
                                store_bind_text(s, 5, error ? error : ""),
                            "update frame", err);
}

int mr_store_frame_set_running(mr_store *st, const char *id, size_t index, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_set_running: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    if (index > (size_t)INT64_MAX)
        return mr_error_set(err, MR_ERR_NOT_FOUND, "job '%s' has no frame %zu", id, index);
    pthread_mutex_lock(&st->lock);
    /* Only the state changes: the error of an earlier attempt stays
     * visible until this attempt ends. */
    sqlite3_stmt *s = store_stmt(st, S_FRAME_SET_RUNNING);
    int rc = store_exec_bound(st, s,
                              store_bind_text(s, 1, id) |
                                  sqlite3_bind_int64(s, 2, (sqlite3_int64)index),
                              "mark frame running", err);
    if (rc == MR_OK && sqlite3_changes(st->db) == 0)
        rc = no_frame(st, id, index, err);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_frames_release(mr_store *st, const char *id, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frames_release: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_FRAMES_RELEASE);
    int rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "release running frames", err);
    if (rc == MR_OK) {
        int n = sqlite3_changes(st->db);
        rc = n;
    }
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_frame_requeue(mr_store *st, const char *id, size_t index, const char *error, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_requeue: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    int retries = 0;
    int rc = store_tx_begin(st, err);
    if (rc == MR_OK && (rc = frame_get_locked(st, id, index, NULL, &retries, NULL, err)) == MR_OK)
        rc = frame_set_locked(st, id, index, MR_FRAME_PENDING, retries, error, err);
    return store_tx_end(st, rc, err);
}

int mr_store_frame_failed(mr_store *st, const char *id, size_t index, const char *error,
                          bool final, bool *gave_up, mr_error *err)
{
    if (gave_up)
        *gave_up = false;
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_failed: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    int retries = 0, max_retries = 0;
    bool give_up = false;
    int rc = store_tx_begin(st, err);
    if (rc < 0)
        goto done;
    if ((rc = frame_get_locked(st, id, index, NULL, &retries, &max_retries, err)) < 0)
        goto done;
    if (retries < INT_MAX)
        retries++;
    give_up = final || retries > max_retries;
    if ((rc = frame_set_locked(st, id, index, give_up ? MR_FRAME_FAILED : MR_FRAME_PENDING,
                               retries, error, err)) < 0)
        goto done;
done:
    rc = store_tx_end(st, rc, err);
    if (rc == MR_OK && gave_up)
        *gave_up = give_up;
    return rc;
}

static int frame_file(const mr_store *st, const char *id, size_t index, const char *suffix,
                      char *path, size_t size, mr_error *err)
{
    return store_path_join(path, size, err, "%s/frames/%s/%04zu.exr%s", st->dir, id, index, suffix);
}

int mr_store_frame_file(const mr_store *st, const char *id, size_t index, char *path, size_t size,
                        mr_error *err)
{
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    return frame_file(st, id, index, "", path, size, err);
}

int mr_store_frame_done(mr_store *st, const char *id, size_t index, const void *exr,
                        size_t exr_size, const char *stats_json, mr_error *err)
{
    if (!st || (!exr && exr_size > 0))
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_done: missing argument");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    char dir[STORE_PATH_MAX], path[STORE_PATH_MAX];
    int rc;
    if ((rc = store_path_join(dir, sizeof dir, err, "%s/frames/%s", st->dir, id)) < 0 ||
        (rc = frame_file(st, id, index, "", path, sizeof path, err)) < 0)
        return rc;

    /* Refuse unknown frames before touching the disk. */
    pthread_mutex_lock(&st->lock);
    rc = frame_get_locked(st, id, index, NULL, NULL, NULL, err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;

    /* a new frame directory is durable (its parent synced) before the
     * frame is renamed into it */
    if ((rc = mr_fs_make_dirs(dir, "frame", err)) < 0 ||
        (rc = mr_fs_write_atomic(path, exr, exr_size, "frame", err)) < 0)
        return rc;

    /* The file is durable; only now may the row say so. A finished frame
     * is progress too: the job's interrupted starts count from zero again
     * (crash-loop protection, mr_store_recover). */
    pthread_mutex_lock(&st->lock);
    bool gone = false;
    rc = store_tx_begin(st, err);
    if (rc == MR_OK) {
        sqlite3_stmt *s = store_stmt(st, S_FRAME_DONE);
        rc = store_exec_bound(st, s,
                              store_bind_text(s, 1, id) |
                                  sqlite3_bind_int64(s, 2, (sqlite3_int64)index) |
                                  store_bind_text(s, 3, stats_json),
                              "mark frame done", err);
        gone = rc == MR_OK && sqlite3_changes(st->db) == 0;
        if (gone) { /* listed, so a crash before the clean-up below leaves no unknown folder */
            s = store_stmt(st, S_TOMBSTONE_ADD);
            rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "list a deleted job's folder", err);
        }
    }
    if (rc == MR_OK && !gone) {
        sqlite3_stmt *s = store_stmt(st, S_JOB_PROGRESS);
        rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "record progress", err);
    }
    rc = store_tx_end(st, rc, err); /* and unlocks */
    if (gone) {
        /* The job was deleted while this frame was written: its delete
         * may have missed the file, so clean up here. */
        unlink(path);
        rmdir(dir);
        if (rc == MR_OK) {
            store_forget_deleted(st, id, dir);
            rc = store_no_job(err, id);
        }
    }
    return rc;
}

int mr_store_frame_path(mr_store *st, const char *id, size_t index, char *path, size_t path_size,
                        mr_error *err)
{
    if (!st || !path || path_size == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_path: missing argument");
    path[0] = '\0';
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    mr_frame_state state = MR_FRAME_PENDING;
    pthread_mutex_lock(&st->lock);
    int rc = frame_get_locked(st, id, index, &state, NULL, NULL, err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    if (state != MR_FRAME_DONE)
        return mr_error_set(err, MR_ERR_NOT_FOUND, "frame %zu of job '%s' is %s, not done", index,
                            id, mr_frame_state_name(state));
    rc = frame_file(st, id, index, "", path, path_size, err);
    if (rc < 0)
        path[0] = '\0';
    return rc;
}

/* ---- frames in the order they were done ---------------------------------- */

static int done_row(sqlite3_stmt *s, void *row, mr_error *err)
{
    mr_frame_done_record *f = row;
    memset(f, 0, sizeof *f);
    f->index = (size_t)sqlite3_column_int64(s, 0);
    const unsigned char *t = sqlite3_column_text(s, 1);
    if (t && !(f->stats_json = mr_memdup_str(t, (size_t)sqlite3_column_bytes(s, 1))))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory reading frames");
    f->done_seq = sqlite3_column_int64(s, 2);
    return MR_OK;
}

int mr_store_frames_after(mr_store *st, const char *id, int64_t after, size_t limit,
                          mr_frame_done_record **out, size_t *count, mr_error *err)
{
    *out = NULL;
    *count = 0;
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    store_rows rows = {.elem = sizeof **out, .first_cap = 16, .read = done_row};
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_FRAMES_AFTER);
    int rc = store_read_rows(st, s,
                             store_bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, after) |
                                 sqlite3_bind_int64(s, 3, limit ? (sqlite3_int64)limit : -1),
                             &rows, "frames done", err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        mr_frame_done_records_free(rows.items, rows.count);
        return rc;
    }
    *out = rows.items;
    *count = rows.count;
    return MR_OK;
}

void mr_frame_done_records_free(mr_frame_done_record *f, size_t count)
{
    for (size_t i = 0; f && i < count; i++)
        free(f[i].stats_json);
    free(f);
}
