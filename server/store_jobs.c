/*
 * store_jobs.c - jobs in the store (store.h, store_internal.h): creation
 * with idempotency keys (one transaction: the job, all its frame rows and
 * the key), reads, listing, state changes, claiming the next queued job,
 * retry and deletion (rows first, files second: see store.c).
 */
#include <errno.h>
#include <limits.h>
#include <stdlib.h>
#include <string.h>
#include <sys/random.h>

#include "store_internal.h"
#include "microray.h"

/* A guard against runaway frame counts, well above the job format's cap
 * (MR_MAX_FRAMES in microray.h); the parser enforces the real limit. */
#define STORE_MAX_FRAMES 1000000u

/* Length of at most max bytes of s that does not end inside a UTF-8
 * sequence, so a cut name stays valid text. */
static size_t utf8_prefix(const char *s, size_t max)
{
    size_t n = strlen(s);
    if (n <= max)
        return n;
    n = max;
    while (n > 0 && ((unsigned char)s[n] & 0xC0) == 0x80)
        n--;
    return n;
}

static int random_job_id(char id[MR_JOB_ID_LEN + 1], mr_error *err)
{
    unsigned char b[MR_JOB_ID_LEN / 2];
    size_t got = 0;
    while (got < sizeof b) {
        ssize_t n = getrandom(b + got, sizeof b - got, 0);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return mr_error_set(err, MR_ERR_IO, "getrandom: %s", strerror(errno));
        }
        got += (size_t)n;
    }
    mr_hex_encode(b, sizeof b, id);
    return MR_OK;
}

/* Looks a job's state (and frame count, if wanted) up; MR_ERR_NOT_FOUND if
 * it does not exist. */
int store_job_lookup_locked(mr_store *st, const char *id, mr_job_state *state, size_t *frames,
                            mr_error *err)
{
    sqlite3_stmt *s = store_stmt(st, S_JOB_STATE);
    int rc = store_step_row(st, s, store_bind_text(s, 1, id), "find job", err);
    if (rc == 1) {
        *state = (mr_job_state)sqlite3_column_int(s, 0);
        if (frames)
            *frames = (size_t)sqlite3_column_int64(s, 1);
        rc = MR_OK;
    } else if (rc == 0) {
        rc = store_no_job(err, id);
    }
    store_stmt_release(s);
    return rc;
}

int store_job_state_locked(mr_store *st, const char *id, mr_job_state *state, mr_error *err)
{
    return store_job_lookup_locked(st, id, state, NULL, err);
}

/* ---- jobs ------------------------------------------------------------------- */

int mr_store_job_create(mr_store *st, const char *json, size_t json_len, const char *name,
                        size_t frame_count, int priority, int max_retries,
                        const char *idempotency_key, const char *body_hash,
                        char id[MR_JOB_ID_LEN + 1], bool *existing, mr_error *err)
{
    return mr_store_job_create_using(st, json, json_len, name, frame_count, priority, max_retries,
                                     idempotency_key, body_hash, NULL, 0, id, existing, err);
}

/* Records that job uses each of the assets, and their last use (lock and
 * transaction held). */
static int record_asset_uses(mr_store *st, const char *job, const char *const *ids, size_t n,
                             mr_error *err)
{
    double now = store_now();
    for (size_t i = 0; i < n; i++) {
        sqlite3_stmt *s = store_stmt(st, S_ASSET_USE);
        int rc = store_exec_bound(st, s,
                                  sqlite3_bind_text(s, 1, job, -1, SQLITE_STATIC) |
                                      store_bind_text(s, 2, ids[i]),
                                  "record asset use", err);
        if (rc < 0)
            return rc;
        if (sqlite3_changes(st->db) == 0) {
            /* none inserted: a second name for the same asset, or gone */
            s = store_stmt(st, S_ASSET_GET);
            rc = store_step_row(st, s, store_bind_text(s, 1, ids[i]), "find asset", err);
            store_stmt_release(s);
            if (rc < 0)
                return rc;
            if (rc == 0) {
                char b[72];
                return mr_error_set(err, MR_ERR_NOT_FOUND, "no uploaded asset '%s' (deleted meanwhile?)",
                                    store_printable(ids[i], b));
            }
        }
        s = store_stmt(st, S_ASSET_TOUCH);
        if ((rc = store_exec_bound(st, s, store_bind_text(s, 1, ids[i]) | sqlite3_bind_double(s, 2, now),
                                   "record asset use", err)) < 0)
            return rc;
    }
    return MR_OK;
}

int mr_store_job_create_using(mr_store *st, const char *json, size_t json_len, const char *name,
                              size_t frame_count, int priority, int max_retries,
                              const char *idempotency_key, const char *body_hash,
                              const char *const *asset_ids, size_t asset_count,
                              char id[MR_JOB_ID_LEN + 1], bool *existing, mr_error *err)
{
    if (existing)
        *existing = false;
    if (!st || !id || !json)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_create: missing argument");
    id[0] = '\0';
    if (frame_count > STORE_MAX_FRAMES)
        return mr_error_set(err, MR_ERR_LIMIT, "%zu frames; the store takes at most %u",
                            frame_count, STORE_MAX_FRAMES);
    if (max_retries < 0)
        return mr_error_set(err, MR_ERR_INVALID, "max_retries must not be negative, got %d",
                            max_retries);
    if (json_len > (size_t)INT_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "job document of %zu bytes is too large", json_len);
    bool keyed = idempotency_key && *idempotency_key;
    if (keyed && !body_hash)
        return mr_error_set(err, MR_ERR_INVALID, "idempotency key given without a body hash");

    char new_id[MR_JOB_ID_LEN + 1];
    int rc = random_job_id(new_id, err);
    if (rc < 0)
        return rc;
    if (!name)
        name = "";
    int name_len = (int)utf8_prefix(name, sizeof ((mr_job_record *)0)->name - 1);
    double now = store_now();

    pthread_mutex_lock(&st->lock);
    if ((rc = store_tx_begin(st, err)) < 0)
        goto done;

    if (keyed) {
        sqlite3_stmt *s = store_stmt(st, S_IDEM_GET);
        rc = store_bind_check(st, store_bind_text(s, 1, idempotency_key), "look up idempotency key",
                              err);
        if (rc == MR_OK) {
            int step = sqlite3_step(s);
            if (step == SQLITE_ROW) {
                const char *h = (const char *)sqlite3_column_text(s, 0);
                if (h && strcmp(h, body_hash) == 0) {
                    store_copy_col(id, MR_JOB_ID_LEN + 1, s, 1);
                    if (existing)
                        *existing = true;
                    rc = 1; /* found: nothing to insert */
                } else {
                    char kb[72];
                    rc = mr_error_set(err, MR_ERR_CONFLICT,
                                      "idempotency key '%s' was used before with a different "
                                      "request body",
                                      store_printable(idempotency_key, kb));
                }
            } else if (step != SQLITE_DONE) {
                rc = store_db_fail(st, step, "look up idempotency key", err);
            }
        }
        store_stmt_release(s);
        if (rc != MR_OK) /* 1: found, the transaction ends with nothing written */
            goto done;
    }

    sqlite3_stmt *s = store_stmt(st, S_JOB_INSERT);
    if ((rc = store_exec_bound(st, s,
                               sqlite3_bind_text(s, 1, new_id, -1, SQLITE_STATIC) |
                                   sqlite3_bind_text(s, 2, name, name_len, SQLITE_STATIC) |
                                   sqlite3_bind_int(s, 3, priority) |
                                   sqlite3_bind_int(s, 4, max_retries) |
                                   sqlite3_bind_int64(s, 5, (sqlite3_int64)frame_count) |
                                   sqlite3_bind_text(s, 6, json, (int)json_len, SQLITE_STATIC) |
                                   sqlite3_bind_double(s, 7, now),
                               "insert job", err)) < 0)
        goto done;

    /* One prepared insert stepped per frame inside the open transaction:
     * 100,000 frames is one commit, not 100,000. */
    s = store_stmt(st, S_FRAME_INSERT);
    if ((rc = store_bind_check(st, sqlite3_bind_text(s, 1, new_id, -1, SQLITE_STATIC), "insert frames",
                               err)) < 0) {
        store_stmt_release(s);
        goto done;
    }
    for (size_t i = 0; i < frame_count; i++) {
        int brc = sqlite3_bind_int64(s, 2, (sqlite3_int64)i);
        int step = brc == SQLITE_OK ? sqlite3_step(s) : brc;
        if (step != SQLITE_DONE) {
            rc = store_db_fail(st, step, "insert frames", err);
            break;
        }
        sqlite3_reset(s);
    }
    store_stmt_release(s);
    if (rc < 0)
        goto done;
    if ((rc = record_asset_uses(st, new_id, asset_ids, asset_count, err)) < 0)
        goto done;

    if (keyed) {
        s = store_stmt(st, S_IDEM_INSERT);
        if ((rc = store_exec_bound(st, s,
                                   store_bind_text(s, 1, idempotency_key) |
                                       store_bind_text(s, 2, body_hash) |
                                       sqlite3_bind_text(s, 3, new_id, -1, SQLITE_STATIC),
                                   "store idempotency key", err)) < 0)
            goto done;
    }
done:
    rc = store_tx_end(st, rc, err);
    if (rc == MR_OK) /* a new job (1: the key's job, already in id) */
        memcpy(id, new_id, sizeof new_id);
    return rc < 0 ? rc : MR_OK;
}

static void read_job(sqlite3_stmt *s, mr_job_record *r)
{
    memset(r, 0, sizeof *r);
    store_copy_col(r->id, sizeof r->id, s, 0);
    store_copy_col(r->name, sizeof r->name, s, 1);
    r->state = (mr_job_state)sqlite3_column_int(s, 2);
    r->priority = sqlite3_column_int(s, 3);
    r->max_retries = sqlite3_column_int(s, 4);
    r->frame_count = (size_t)sqlite3_column_int64(s, 5);
    r->created = sqlite3_column_double(s, 6);
    r->started = sqlite3_column_double(s, 7);
    r->finished = sqlite3_column_double(s, 8);
    store_copy_col(r->error, sizeof r->error, s, 9);
    r->frames_done = (size_t)sqlite3_column_int64(s, 10);
    r->frames_failed = (size_t)sqlite3_column_int64(s, 11);
    r->seq = sqlite3_column_int64(s, 12);
    r->done_seq = sqlite3_column_int64(s, 13);
}

static int job_row(sqlite3_stmt *s, void *row, mr_error *err)
{
    (void)err;
    read_job(s, row);
    return MR_OK;
}

int mr_store_job_get(mr_store *st, const char *id, mr_job_record *out, mr_error *err)
{
    if (!st || !out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_get: missing argument");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_JOB_GET);
    int rc = store_step_row(st, s, store_bind_text(s, 1, id), "read job", err);
    if (rc == 1)
        rc = job_row(s, out, err);
    else if (rc == 0)
        rc = store_no_job(err, id);
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_json(mr_store *st, const char *id, char **json, mr_error *err)
{
    if (!st || !json)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_json: missing argument");
    *json = NULL;
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_JOB_JSON);
    int rc = store_step_row(st, s, store_bind_text(s, 1, id), "read job document", err);
    if (rc == 1) {
        const unsigned char *t = sqlite3_column_text(s, 0);
        size_t n = t ? (size_t)sqlite3_column_bytes(s, 0) : 0;
        rc = (*json = mr_memdup_str(t, n))
                 ? MR_OK
                 : mr_error_set(err, MR_ERR_NOMEM, "out of memory reading job '%s'", id);
    } else if (rc == 0) {
        rc = store_no_job(err, id);
    }
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_list(mr_store *st, const mr_job_query *q, mr_job_record **out, size_t *count,
                      int64_t *next, mr_error *err)
{
    if (!st || !q || !out || !count)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_list: missing argument");
    *out = NULL;
    *count = 0;
    if (next)
        *next = 0;
    /* one row more than asked tells whether another page follows */
    sqlite3_int64 rows_wanted = q->limit && q->limit < (size_t)INT64_MAX ? (sqlite3_int64)q->limit + 1 : -1;
    store_rows rows = {.elem = sizeof **out, .first_cap = 16, .read = job_row};
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_JOB_QUERY);
    int rc = store_read_rows(st, s,
                             sqlite3_bind_int(s, 1, q->by_state ? (int)q->state : -1) |
                                 store_bind_text(s, 2, q->name) |
                                 sqlite3_bind_int64(s, 3, q->before > 0 ? q->before : 0) |
                                 sqlite3_bind_int64(s, 4, rows_wanted),
                             &rows, "jobs", err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        free(rows.items);
        return rc;
    }
    *out = rows.items;
    *count = rows.count;
    if (q->limit && rows.count > q->limit) {
        *count = q->limit;
        if (next)
            *next = (*out)[q->limit - 1].seq;
    }
    return MR_OK;
}

int mr_store_job_set_state(mr_store *st, const char *id, mr_job_state state, const char *error,
                           mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_set_state: no store");
    if ((unsigned)state > MR_JOB_CANCELED)
        return mr_error_set(err, MR_ERR_INVALID, "invalid job state %d", (int)state);
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_JOB_SET_STATE);
    int rc = store_exec_bound(st, s,
                              store_bind_text(s, 1, id) | sqlite3_bind_int(s, 2, (int)state) |
                                  store_bind_text(s, 3, error) |
                                  sqlite3_bind_double(s, 4, store_now()),
                              "set job state", err);
    if (rc == MR_OK && sqlite3_changes(st->db) == 0)
        rc = store_no_job(err, id);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_claim(mr_store *st, char id[MR_JOB_ID_LEN + 1], mr_error *err)
{
    if (!st || !id)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_claim: missing argument");
    id[0] = '\0';
    char found[MR_JOB_ID_LEN + 1] = "";
    pthread_mutex_lock(&st->lock);
    int rc = store_tx_begin(st, err);
    if (rc < 0)
        goto done;
    sqlite3_stmt *s = store_stmt(st, S_CLAIM_PICK);
    rc = store_step_row(st, s, SQLITE_OK, "pick queued job", err);
    if (rc == 1) {
        store_copy_col(found, sizeof found, s, 0);
        rc = MR_OK;
    } else if (rc == 0) {
        rc = mr_error_set(err, MR_ERR_NOT_FOUND, "no queued job");
    }
    store_stmt_release(s);
    if (rc < 0)
        goto done;
    s = store_stmt(st, S_JOB_SET_STATE);
    if ((rc = store_exec_bound(st, s,
                               sqlite3_bind_text(s, 1, found, -1, SQLITE_STATIC) |
                                   sqlite3_bind_int(s, 2, MR_JOB_RUNNING) |
                                   sqlite3_bind_null(s, 3) | sqlite3_bind_double(s, 4, store_now()),
                               "claim job", err)) < 0)
        goto done;
done:
    rc = store_tx_end(st, rc, err);
    if (rc == MR_OK)
        memcpy(id, found, sizeof found);
    return rc;
}

int mr_store_job_retry(mr_store *st, const char *id, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_retry: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    int requeued = 0;
    pthread_mutex_lock(&st->lock);
    int rc = store_tx_begin(st, err);
    if (rc < 0)
        goto done;
    mr_job_state state = MR_JOB_QUEUED; /* (set by the look-up; GCC 12 at -O3 cannot tell) */
    if ((rc = store_job_state_locked(st, id, &state, err)) < 0)
        goto done;
    if (state != MR_JOB_FAILED && state != MR_JOB_CANCELED) {
        rc = mr_error_set(err, MR_ERR_CONFLICT,
                          "job '%s' is %s; only failed or canceled jobs can be retried", id,
                          mr_job_state_name(state));
        goto done;
    }
    sqlite3_stmt *s = store_stmt(st, S_RETRY_FRAMES);
    if ((rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "re-queue frames", err)) < 0)
        goto done;
    sqlite3_int64 n = sqlite3_changes64(st->db);
    if (n == 0) {
        rc = mr_error_set(err, MR_ERR_CONFLICT, "job '%s' has no failed or unfinished frames to retry",
                          id);
        goto done;
    }
    requeued = n > INT_MAX ? INT_MAX : (int)n;
    s = store_stmt(st, S_JOB_REQUEUE);
    if ((rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "re-queue job", err)) < 0)
        goto done;
done:
    rc = store_tx_end(st, rc, err);
    return rc < 0 ? rc : requeued;
}

int mr_store_job_delete(mr_store *st, const char *id, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_delete: no store");
    if (!store_valid_job_id(id))
        return store_no_job(err, id);
    char dir[STORE_PATH_MAX];
    int rc = store_path_join(dir, sizeof dir, err, "%s/frames/%s", st->dir, id);
    if (rc < 0)
        return rc;
    static const enum stmt_id steps[] = {S_DEL_IDEM, S_DEL_FRAMES, S_DEL_JOB};
    pthread_mutex_lock(&st->lock);
    if ((rc = store_tx_begin(st, err)) < 0)
        goto done;
    for (size_t i = 0; i < sizeof steps / sizeof *steps; i++) {
        sqlite3_stmt *s = store_stmt(st, steps[i]);
        if ((rc = store_exec_bound(st, s, store_bind_text(s, 1, id), "delete job", err)) < 0)
            goto done;
    }
    if (sqlite3_changes(st->db) == 0) {
        rc = store_no_job(err, id);
        goto done;
    }
    sqlite3_stmt *listed = store_stmt(st, S_TOMBSTONE_ADD);
    rc = store_exec_bound(st, listed, store_bind_text(listed, 1, id), "delete job", err);
done:
    rc = store_tx_end(st, rc, err);
    if (rc < 0)
        return rc;
    /* Rows first (the job's listed in deleted_jobs in the same commit),
     * files second: a crash in between leaves a folder the next
     * mr_store_recover removes, never a row whose files are gone. */
    if ((rc = mr_fs_remove_dir(dir, err)) < 0)
        return rc;
    store_forget_deleted(st, id, dir); /* (a writer that raced the removal keeps it listed) */
    return MR_OK;
}

int mr_store_job_counts(mr_store *st, uint64_t counts[5], mr_error *err)
{
    if (!st || !counts)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_counts: missing argument");
    for (int i = 0; i < 5; i++)
        counts[i] = 0;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_JOB_COUNTS);
    int rc = MR_OK;
    for (;;) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            break;
        if (step != SQLITE_ROW) {
            rc = store_db_fail(st, step, "count jobs", err);
            break;
        }
        int state = sqlite3_column_int(s, 0);
        if (state >= 0 && state < 5)
            counts[state] = (uint64_t)sqlite3_column_int64(s, 1);
    }
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_queue_frames(mr_store *st, uint64_t *frames, mr_error *err)
{
    *frames = 0;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_QUEUE_FRAMES);
    int rc = store_step_row(st, s, SQLITE_OK, "count queued frames", err);
    if (rc == 1) {
        *frames = (uint64_t)sqlite3_column_int64(s, 0);
        rc = MR_OK;
    }
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc < 0 ? rc : MR_OK;
}
