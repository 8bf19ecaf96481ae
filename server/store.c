/*
 * store.c - the daemon's durable state (store.h): one sqlite connection in
 * WAL mode behind a mutex, with every statement prepared once at open and
 * reused, plus the frame and asset files under the data directory. This
 * file is the database itself (schema, statements, plumbing, the data
 * directory, recovery); jobs, frames and assets are store_jobs.c,
 * store_frames.c and store_assets.c (store_internal.h).
 *
 * Durability: WAL with synchronous=NORMAL, so a commit does not fsync; a
 * power cut may lose the last commits but never corrupts the database. That
 * is enough because the files a row points at are fsynced (file, then
 * rename, then directory) before the row is written: a frame row that
 * survived always has its complete EXR, and a lost "done" only means the
 * frame is rendered again.
 *
 * Locking: the mutex covers sqlite only. File writes (EXR frames, assets)
 * and directory removal happen outside it so an fsync never stalls status
 * requests; the row checks around them keep the files and rows consistent
 * when a job is deleted while its frame is being written (see
 * mr_store_frame_done and mr_store_job_delete).
 */
#include "store_internal.h"

#include <dirent.h>
#include <errno.h>
#include <limits.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "microray.h"

/* Schema version kept in PRAGMA user_version; open() migrates older files
 * step by step and refuses newer ones. */
#define SCHEMA_VERSION 4
#define STORE_BUSY_MS 5000 /* another process (sqlite3 shell, backup) holding the lock */

/* Columns of a job record, in the order read_job() expects. Done and
 * failed counts come from the frames table (index frames_state makes them
 * index-only range counts) so they can never disagree with the frames. */
#define JOB_COLS                                                                          \
    "j.id, j.name, j.state, j.priority, j.max_retries, j.frame_count, j.created, "       \
    "j.started, j.finished, j.error, "                                                    \
    "(SELECT COUNT(*) FROM frames f WHERE f.job_id = j.id AND f.state = 2), "             \
    "(SELECT COUNT(*) FROM frames f WHERE f.job_id = j.id AND f.state = 3), j.seq, j.done_seq"

/* Queued and running jobs that use asset a.id. */
#define ASSET_ACTIVE                                                                      \
    "(SELECT COUNT(*) FROM job_assets ja JOIN jobs j ON j.id = ja.job_id "                 \
    "WHERE ja.asset_id = a.id AND j.state IN (0, 1))"

static const char *const stmt_sql[S_COUNT] = {
    [S_BEGIN] = "BEGIN IMMEDIATE",
    [S_COMMIT] = "COMMIT",
    [S_ROLLBACK] = "ROLLBACK",
    [S_JOB_INSERT] = "INSERT INTO jobs(id, seq, name, state, priority, max_retries, frame_count, "
                     "json, error, created, started, finished) "
                     "VALUES(?1, (SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs), ?2, 0, ?3, ?4, ?5, "
                     "?6, '', ?7, 0, 0)",
    [S_FRAME_INSERT] = "INSERT INTO frames(job_id, idx, state, retries, error, stats_json) "
                       "VALUES(?1, ?2, 0, 0, '', NULL)",
    [S_IDEM_GET] = "SELECT body_hash, job_id FROM idempotency WHERE key = ?1",
    [S_IDEM_INSERT] = "INSERT INTO idempotency(key, body_hash, job_id) VALUES(?1, ?2, ?3)",
    [S_JOB_GET] = "SELECT " JOB_COLS " FROM jobs j WHERE j.id = ?1",
    /* ?1 state or -1, ?2 name or NULL, ?3 seq the page starts below or 0,
     * ?4 rows or -1 (sqlite: no limit); newest first */
    [S_JOB_QUERY] = "SELECT " JOB_COLS " FROM jobs j WHERE (?1 < 0 OR j.state = ?1) "
                    "AND (?2 IS NULL OR j.name = ?2) AND (?3 <= 0 OR j.seq < ?3) "
                    "ORDER BY j.seq DESC LIMIT ?4",
    [S_JOB_JSON] = "SELECT json FROM jobs WHERE id = ?1",
    [S_JOB_STATE] = "SELECT state, frame_count FROM jobs WHERE id = ?1",
    /* ?2 state, ?3 error or NULL to keep it, ?4 now. started is set the
     * first time a job runs; finished on entering a final state and cleared
     * when it is queued or running again. interrupted counts the job's
     * starts since a frame last finished (S_JOB_PROGRESS resets it): one
     * more for each start, one less when a start ends gracefully (running
     * back to queued: a stop); what is left at recovery are the starts the
     * process did not survive. */
    [S_JOB_SET_STATE] = "UPDATE jobs SET state = ?2, error = COALESCE(?3, error), "
                        "interrupted = CASE WHEN ?2 = 1 THEN interrupted + 1 "
                        "WHEN ?2 = 0 AND state = 1 AND interrupted > 0 THEN interrupted - 1 "
                        "ELSE interrupted END, "
                        "started = CASE WHEN ?2 = 1 AND started = 0 THEN ?4 ELSE started END, "
                        "finished = CASE WHEN ?2 >= 2 THEN ?4 ELSE 0 END WHERE id = ?1",
    [S_CLAIM_PICK] = "SELECT id FROM jobs WHERE state = 0 ORDER BY priority DESC, seq ASC LIMIT 1",
    [S_JOB_COUNTS] = "SELECT state, COUNT(*) FROM jobs GROUP BY state",
    /* frames still to render: pending or running, of queued or running jobs */
    [S_QUEUE_FRAMES] = "SELECT COUNT(*) FROM jobs j JOIN frames f ON f.job_id = j.id "
                       "WHERE j.state IN (0, 1) AND f.state IN (0, 1)",
    /* Recovery, in this order (crash-loop protection): a frame that was
     * running when the process died counts as a failed attempt (?1 the
     * message), and fails once its attempts exceed the job's max_retries;
     * a job whose starts were interrupted more than max_retries times in a
     * row (no frame finished in between; see S_JOB_SET_STATE) fails (?1
     * now) instead of being resumed again, which is what stops a job that
     * kills the daemon from killing every restart; the rest resume. */
    [S_RECOVER_FRAMES] = "UPDATE frames SET retries = retries + 1, error = ?1, "
                         "state = CASE WHEN retries + 1 > (SELECT max_retries FROM jobs j "
                         "WHERE j.id = frames.job_id) THEN 3 ELSE 0 END WHERE state = 1",
    [S_RECOVER_GIVE_UP] = "UPDATE jobs SET state = 3, finished = ?1, error = 'the daemon stopped "
                          "' || interrupted || ' times in a row while running this job (killed, "
                          "crashed or out of memory) before a frame finished; not resumed again' "
                          "WHERE state = 1 AND interrupted > max_retries",
    [S_RECOVER_JOBS] = "UPDATE jobs SET state = 0 WHERE state = 1",
    /* Every frame that is not done gets rendered again with a fresh retry
     * budget: failed ones, pending ones a cancel left behind, and running
     * ones a stopped worker left behind. */
    [S_RETRY_FRAMES] = "UPDATE frames SET state = 0, retries = 0, error = '' "
                       "WHERE job_id = ?1 AND state <> 2",
    [S_JOB_REQUEUE] = "UPDATE jobs SET state = 0, error = '', finished = 0, interrupted = 0 "
                      "WHERE id = ?1",
    [S_DEL_IDEM] = "DELETE FROM idempotency WHERE job_id = ?1",
    [S_DEL_FRAMES] = "DELETE FROM frames WHERE job_id = ?1",
    [S_DEL_JOB] = "DELETE FROM jobs WHERE id = ?1",
    [S_TOMBSTONE_ADD] = "INSERT OR IGNORE INTO deleted_jobs(id) VALUES (?1)",
    [S_TOMBSTONE_DROP] = "DELETE FROM deleted_jobs WHERE id = ?1",
    [S_TOMBSTONES] = "SELECT id FROM deleted_jobs",
    [S_FRAMES_LIST] = "SELECT idx, state, retries, error, stats_json FROM frames "
                      "WHERE job_id = ?1 ORDER BY idx",
    [S_FRAME_ROW] = "SELECT idx, state, retries, error, stats_json FROM frames "
                    "WHERE job_id = ?1 AND idx = ?2",
    [S_FRAME_GET] = "SELECT f.state, f.retries, j.max_retries FROM frames f "
                    "JOIN jobs j ON j.id = f.job_id WHERE f.job_id = ?1 AND f.idx = ?2",
    [S_FRAME_SET] = "UPDATE frames SET state = ?3, retries = ?4, error = ?5 "
                    "WHERE job_id = ?1 AND idx = ?2",
    [S_FRAME_SET_RUNNING] = "UPDATE frames SET state = 1 WHERE job_id = ?1 AND idx = ?2",
    /* a render that ended without finishing its frame (a cancel, a stop,
     * a worker gone): the frame is no longer running; no attempt counted */
    [S_FRAMES_RELEASE] = "UPDATE frames SET state = 0 WHERE job_id = ?1 AND state = 1",
    /* done_seq: the job's frames in the order they were done, for event
     * streams that resume (mr_store_frames_after); jobs.done_seq counts */
    [S_FRAME_DONE] = "UPDATE frames SET state = 2, error = '', stats_json = ?3, "
                     "done_seq = (SELECT done_seq + 1 FROM jobs WHERE id = ?1) "
                     "WHERE job_id = ?1 AND idx = ?2",
    [S_JOB_PROGRESS] = "UPDATE jobs SET interrupted = 0, done_seq = done_seq + 1 WHERE id = ?1",
    [S_ASSET_INSERT] = "INSERT OR IGNORE INTO assets(id, size, created) VALUES(?1, ?2, ?3)",
    [S_ASSET_GET] = "SELECT size FROM assets WHERE id = ?1",
    /* an asset with the number of queued and running jobs that use it */
    [S_ASSET_ROW] = "SELECT a.id, a.size, a.created, a.last_used, " ASSET_ACTIVE ", a.rowid "
                    "FROM assets a WHERE a.id = ?1",
    /* ?1 rowid the page starts below or 0, ?2 rows or -1; newest first */
    [S_ASSET_LIST] = "SELECT a.id, a.size, a.created, a.last_used, " ASSET_ACTIVE ", a.rowid "
                     "FROM assets a WHERE ?1 <= 0 OR a.rowid < ?1 ORDER BY a.rowid DESC LIMIT ?2",
    /* a job uses an uploaded asset: only if it is (still) stored */
    [S_ASSET_USE] = "INSERT OR IGNORE INTO job_assets(job_id, asset_id) "
                    "SELECT ?1, id FROM assets WHERE id = ?2",
    [S_ASSET_TOUCH] = "UPDATE assets SET last_used = ?2 WHERE id = ?1",
    [S_ASSET_ACTIVE] = "SELECT " ASSET_ACTIVE " FROM assets a WHERE a.id = ?1",
    [S_ASSET_DELETE] = "DELETE FROM assets WHERE id = ?1",
    /* a job's frames done after event sequence ?2, in the order they were */
    [S_FRAMES_AFTER] = "SELECT idx, stats_json, done_seq FROM frames "
                       "WHERE job_id = ?1 AND state = 2 AND done_seq > ?2 ORDER BY done_seq LIMIT ?3",
};

/* Version 1. frames.state/jobs.state hold mr_frame_state/mr_job_state.
 * frames is WITHOUT ROWID: its primary key is how every frame is found, and
 * one B-tree less per row cut a 100,000-frame insert by about a quarter. */
static const char schema_v1[] =
    "CREATE TABLE jobs("
    " id TEXT PRIMARY KEY NOT NULL,"
    " seq INTEGER NOT NULL UNIQUE,"
    " name TEXT NOT NULL DEFAULT '',"
    " state INTEGER NOT NULL,"
    " priority INTEGER NOT NULL DEFAULT 0,"
    " max_retries INTEGER NOT NULL DEFAULT 0,"
    " frame_count INTEGER NOT NULL,"
    " json TEXT NOT NULL,"
    " error TEXT NOT NULL DEFAULT '',"
    " created REAL NOT NULL,"
    " started REAL NOT NULL DEFAULT 0,"
    " finished REAL NOT NULL DEFAULT 0);"
    "CREATE INDEX jobs_queue ON jobs(state, priority DESC, seq);"
    "CREATE TABLE frames("
    " job_id TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,"
    " idx INTEGER NOT NULL,"
    " state INTEGER NOT NULL DEFAULT 0,"
    " retries INTEGER NOT NULL DEFAULT 0,"
    " error TEXT NOT NULL DEFAULT '',"
    " stats_json TEXT,"
    " PRIMARY KEY(job_id, idx)) WITHOUT ROWID;"
    "CREATE INDEX frames_state ON frames(job_id, state);"
    "CREATE TABLE idempotency("
    " key TEXT PRIMARY KEY NOT NULL,"
    " body_hash TEXT NOT NULL,"
    " job_id TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE);"
    "CREATE INDEX idempotency_job ON idempotency(job_id);"
    "CREATE TABLE assets("
    " id TEXT PRIMARY KEY NOT NULL,"
    " size INTEGER NOT NULL,"
    " created REAL NOT NULL);";

static const char schema_v2[] =
    "ALTER TABLE jobs ADD COLUMN interrupted INTEGER NOT NULL DEFAULT 0;";

/* Version 3 (issue 19): which jobs use which uploaded assets (an asset in
 * use by a queued or running job is not deleted) and when an asset was
 * last named by a job; the order frames were done in (event ids). */
static const char schema_v3[] =
    "CREATE TABLE job_assets("
    " job_id TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,"
    " asset_id TEXT NOT NULL,"
    " PRIMARY KEY(job_id, asset_id)) WITHOUT ROWID;"
    "CREATE INDEX job_assets_asset ON job_assets(asset_id);"
    "ALTER TABLE assets ADD COLUMN last_used REAL NOT NULL DEFAULT 0;"
    "ALTER TABLE jobs ADD COLUMN done_seq INTEGER NOT NULL DEFAULT 0;"
    "ALTER TABLE frames ADD COLUMN done_seq INTEGER NOT NULL DEFAULT 0;";

/* Version 4: the jobs deleted whose frame folders may still be on disk (a
 * crash between a delete's commit and its file removal). Start-up removes
 * the folders listed here and no others: a folder of no job that is not
 * listed (a database lost or replaced) is left alone and reported. */
static const char schema_v4[] = "CREATE TABLE deleted_jobs(id TEXT PRIMARY KEY NOT NULL) WITHOUT ROWID;";

/* ---- names ---------------------------------------------------------------- */

static const char *const job_state_names[] = {"queued", "running", "succeeded", "failed",
                                              "canceled"};
static const char *const frame_state_names[] = {"pending", "running", "done", "failed"};

const char *mr_job_state_name(mr_job_state s)
{
    if ((unsigned)s < sizeof job_state_names / sizeof *job_state_names)
        return job_state_names[s];
    return "unknown";
}

bool mr_job_state_parse(const char *name, mr_job_state *out)
{
    if (!name)
        return false;
    for (unsigned i = 0; i < sizeof job_state_names / sizeof *job_state_names; i++) {
        if (strcmp(name, job_state_names[i]) == 0) {
            if (out)
                *out = (mr_job_state)i;
            return true;
        }
    }
    return false;
}

const char *mr_frame_state_name(mr_frame_state s)
{
    if ((unsigned)s < sizeof frame_state_names / sizeof *frame_state_names)
        return frame_state_names[s];
    return "unknown";
}

/* ---- small helpers ---------------------------------------------------------- */

double store_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* Ids reach the store straight from URLs; only well-formed ones are ever
 * looked up or turned into paths. */
bool store_valid_job_id(const char *id) { return mr_hex_is_lower(id, MR_JOB_ID_LEN); }

/* A caller's string made safe for a message: printable ASCII, at most 64
 * characters. */
const char *store_printable(const char *s, char out[72])
{
    if (!s)
        return "(null)";
    size_t n = 0;
    for (; s[n] && n < 64; n++)
        out[n] = (s[n] >= 0x20 && s[n] < 0x7f) ? s[n] : '?';
    if (s[n]) {
        memcpy(out + n, "...", 3);
        n += 3;
    }
    out[n] = '\0';
    return out;
}

int store_no_job(mr_error *err, const char *id)
{
    char buf[72];
    return mr_error_set(err, MR_ERR_NOT_FOUND, "no job '%s'", store_printable(id, buf));
}

int store_io_error(mr_error *err, const char *what, const char *path, int e)
{
    return mr_error_set(err, MR_ERR_IO, "%s '%s': %s", what, path, strerror(e));
}

int store_path_join(char *out, size_t size, mr_error *err, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(out, size, fmt, ap);
    va_end(ap);
    if (n < 0 || (size_t)n >= size)
        return mr_error_set(err, MR_ERR_INVALID, "path too long (%d bytes, room for %zu)", n,
                            size ? size - 1 : 0);
    return MR_OK;
}

/* Copies a text column, cut to fit (names are capped when stored). */
void store_copy_col(char *dst, size_t size, sqlite3_stmt *s, int col)
{
    const unsigned char *t = sqlite3_column_text(s, col);
    size_t n = t ? (size_t)sqlite3_column_bytes(s, col) : 0;
    if (n >= size)
        n = size - 1;
    if (n)
        memcpy(dst, t, n);
    dst[n] = '\0';
}

/* ---- sqlite plumbing -------------------------------------------------------- */

static int db_code(int sqlite_rc)
{
    switch (sqlite_rc & 0xff) {
    case SQLITE_NOMEM: return MR_ERR_NOMEM;
    case SQLITE_NOTADB:
    case SQLITE_CORRUPT: return MR_ERR_FORMAT;
    case SQLITE_CONSTRAINT: return MR_ERR_CONFLICT;
    case SQLITE_TOOBIG: return MR_ERR_LIMIT;
    case SQLITE_FULL: return MR_ERR_NO_SPACE;
    default: return MR_ERR_IO;
    }
}

/* The message of the connection's last failure; read it before any other
 * call on the connection (the caller holds the mutex, so nobody else can
 * overwrite it). */
int store_db_fail(mr_store *st, int sqlite_rc, const char *what, mr_error *err)
{
    /* sqlite's words first: a long data directory must not cut them off. */
    return mr_error_set(err, db_code(sqlite_rc), "sqlite: %s: %s (%s/microray.sqlite)", what,
                        sqlite3_errmsg(st->db), st->dir);
}

/* A statement ready for binding; released with store_stmt_release(). */
sqlite3_stmt *store_stmt(mr_store *st, enum stmt_id id) { return st->stmt[id]; }

void store_stmt_release(sqlite3_stmt *s)
{
    /* reset repeats the last step's error code, which was already checked. */
    sqlite3_reset(s);
    sqlite3_clear_bindings(s);
}

/* Steps a statement that returns no rows, then releases it. */
int store_exec(mr_store *st, sqlite3_stmt *s, const char *what, mr_error *err)
{
    int rc = sqlite3_step(s);
    int out = rc == SQLITE_DONE ? MR_OK : store_db_fail(st, rc, what, err);
    store_stmt_release(s);
    return out;
}

/* Checks bind results: all of them are SQLITE_OK or the first failure. */
int store_bind_check(mr_store *st, int rc, const char *what, mr_error *err)
{
    return rc == SQLITE_OK ? MR_OK : store_db_fail(st, rc, what, err);
}

int store_exec_bound(mr_store *st, sqlite3_stmt *s, int bind_rc, const char *what, mr_error *err)
{
    int rc = store_bind_check(st, bind_rc, what, err);
    if (rc < 0) {
        store_stmt_release(s);
        return rc;
    }
    return store_exec(st, s, what, err);
}

int store_read_rows(mr_store *st, sqlite3_stmt *s, int bind_rc, store_rows *rows, const char *what,
                    mr_error *err)
{
    char doing[64];
    snprintf(doing, sizeof doing, "list %s", what);
    int rc = store_bind_check(st, bind_rc, doing, err);
    while (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            break;
        if (step != SQLITE_ROW) {
            rc = store_db_fail(st, step, doing, err);
            break;
        }
        if (rows->count == rows->cap) {
            size_t ncap = rows->cap ? rows->cap * 2 : rows->first_cap;
            void *grown = realloc(rows->items, ncap * rows->elem);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory listing %s", what);
                break;
            }
            rows->items = grown;
            rows->cap = ncap;
        }
        if ((rc = rows->read(s, (char *)rows->items + rows->count * rows->elem, err)) < 0)
            break;
        rows->count++;
    }
    store_stmt_release(s);
    return rc;
}

int store_step_row(mr_store *st, sqlite3_stmt *s, int bind_rc, const char *what, mr_error *err)
{
    int rc = store_bind_check(st, bind_rc, what, err);
    if (rc < 0)
        return rc;
    int step = sqlite3_step(s);
    if (step == SQLITE_ROW)
        return 1;
    return step == SQLITE_DONE ? 0 : store_db_fail(st, step, what, err);
}

int store_bind_text(sqlite3_stmt *s, int i, const char *t)
{
    return t ? sqlite3_bind_text(s, i, t, -1, SQLITE_STATIC) : sqlite3_bind_null(s, i);
}

int store_tx_begin(mr_store *st, mr_error *err)
{
    return store_exec(st, store_stmt(st, S_BEGIN), "begin transaction", err);
}

int store_tx_commit(mr_store *st, mr_error *err)
{
    return store_exec(st, store_stmt(st, S_COMMIT), "commit", err);
}

int store_tx_end(mr_store *st, int rc, mr_error *err)
{
    if (rc >= 0) {
        int c = store_tx_commit(st, err);
        if (c < 0)
            rc = c;
    }
    if (rc < 0)
        store_tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

/* After a failed statement sqlite may already have rolled back (disk
 * full, I/O error); only roll back what is still open. */
void store_tx_rollback(mr_store *st)
{
    if (!sqlite3_get_autocommit(st->db)) {
        sqlite3_stmt *s = store_stmt(st, S_ROLLBACK);
        sqlite3_step(s);
        store_stmt_release(s);
    }
}

static int exec_sql(mr_store *st, const char *sql, const char *what, mr_error *err)
{
    char *msg = NULL;
    int rc = sqlite3_exec(st->db, sql, NULL, NULL, &msg);
    if (rc != SQLITE_OK) {
        int out = mr_error_set(err, db_code(rc), "sqlite: %s: %s (%s/microray.sqlite)", what,
                               msg ? msg : sqlite3_errstr(rc), st->dir);
        sqlite3_free(msg);
        return out;
    }
    return MR_OK;
}

/* Runs a one-row pragma and returns its first column as an integer or
 * copies it as text. */
static int pragma_get(mr_store *st, const char *sql, sqlite3_int64 *num, char *text, size_t size,
                      mr_error *err)
{
    sqlite3_stmt *s = NULL;
    int rc = sqlite3_prepare_v2(st->db, sql, -1, &s, NULL);
    if (rc != SQLITE_OK)
        return store_db_fail(st, rc, sql, err);
    rc = sqlite3_step(s);
    int out = MR_OK;
    if (rc == SQLITE_ROW) {
        if (num)
            *num = sqlite3_column_int64(s, 0);
        if (text)
            store_copy_col(text, size, s, 0);
    } else {
        out = store_db_fail(st, rc, sql, err);
    }
    sqlite3_finalize(s);
    return out;
}

/* Creates or upgrades the schema inside one write transaction, so two
 * processes opening a new directory at once cannot both create it. */
static int migrate(mr_store *st, mr_error *err)
{
    int rc = exec_sql(st, "BEGIN IMMEDIATE", "begin schema transaction", err);
    if (rc < 0)
        return rc;
    sqlite3_int64 version = 0;
    rc = pragma_get(st, "PRAGMA user_version", &version, NULL, 0, err);
    if (rc < 0)
        goto fail;
    if (version > SCHEMA_VERSION) {
        rc = mr_error_set(err, MR_ERR_FORMAT,
                          "%s/microray.sqlite has schema version %lld; this microrayd knows "
                          "versions up to %d",
                          st->dir, (long long)version, SCHEMA_VERSION);
        goto fail;
    }
    if (version < 1) {
        rc = exec_sql(st, schema_v1, "create schema", err);
        if (rc < 0)
            goto fail;
    }
    if (version < 2) {
        /* v2: consecutive starts of a job that the process did not survive */
        rc = exec_sql(st, schema_v2, "upgrade schema to version 2", err);
        if (rc < 0)
            goto fail;
    }
    if (version < 3) {
        rc = exec_sql(st, schema_v3, "upgrade schema to version 3", err);
        if (rc < 0)
            goto fail;
    }
    if (version < 4) {
        rc = exec_sql(st, schema_v4, "upgrade schema to version 4", err);
        if (rc < 0)
            goto fail;
    }
    if (version != SCHEMA_VERSION) {
        char sql[64];
        snprintf(sql, sizeof sql, "PRAGMA user_version = %d", SCHEMA_VERSION);
        rc = exec_sql(st, sql, "set schema version", err);
        if (rc < 0)
            goto fail;
    }
    return exec_sql(st, "COMMIT", "commit schema", err);
fail:
    if (!sqlite3_get_autocommit(st->db))
        sqlite3_exec(st->db, "ROLLBACK", NULL, NULL, NULL);
    return rc;
}

/* ---- open / close ----------------------------------------------------------- */

int mr_store_open(const char *data_dir, mr_store **out, mr_error *err)
{
    mr_store *st = NULL;
    bool mutex_ready = false;
    int rc;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_open: no output handle");
    *out = NULL;
    if (!data_dir || !*data_dir)
        return mr_error_set(err, MR_ERR_INVALID, "no data directory given");
    /* Room for "/frames/<id>/NNNNNNN.exr.tmpXXXXXX" below the directory. */
    if (strlen(data_dir) > STORE_PATH_MAX - 128)
        return mr_error_set(err, MR_ERR_INVALID, "data directory path too long (%zu bytes)",
                            strlen(data_dir));
    if (!sqlite3_threadsafe())
        return mr_error_set(err, MR_ERR_INVALID, "sqlite was built without thread support");

    st = calloc(1, sizeof *st);
    if (!st)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory opening the store");
    size_t n = strlen(data_dir);
    while (n > 1 && data_dir[n - 1] == '/')
        n--;
    memcpy(st->dir, data_dir, n);
    st->dir[n] = '\0';

    char path[STORE_PATH_MAX];
    if ((rc = mr_fs_make_dirs(st->dir, "store", err)) < 0)
        goto fail;
    if ((rc = store_path_join(path, sizeof path, err, "%s/assets", st->dir)) < 0 ||
        (rc = mr_fs_make_dirs(path, "store", err)) < 0)
        goto fail;
    if ((rc = store_path_join(path, sizeof path, err, "%s/frames", st->dir)) < 0 ||
        (rc = mr_fs_make_dirs(path, "store", err)) < 0)
        goto fail;

    if (pthread_mutex_init(&st->lock, NULL) != 0) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "cannot create the store mutex");
        goto fail;
    }
    mutex_ready = true;

    if ((rc = store_path_join(path, sizeof path, err, "%s/microray.sqlite", st->dir)) < 0)
        goto fail;
    /* NOMUTEX: st->lock already serialises every use of the connection. */
    int src = sqlite3_open_v2(path, &st->db,
                              SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_NOMUTEX, NULL);
    if (src != SQLITE_OK) {
        rc = mr_error_set(err, db_code(src), "cannot open '%s': %s", path,
                          st->db ? sqlite3_errmsg(st->db) : sqlite3_errstr(src));
        goto fail;
    }
    sqlite3_busy_timeout(st->db, STORE_BUSY_MS);

    char mode[16] = "";
    if ((rc = pragma_get(st, "PRAGMA journal_mode = WAL", NULL, mode, sizeof mode, err)) < 0)
        goto fail;
    if (strcmp(mode, "wal") != 0) {
        rc = mr_error_set(err, MR_ERR_IO,
                          "%s: cannot use write-ahead logging (journal mode stays '%s')", path, mode);
        goto fail;
    }
    if ((rc = exec_sql(st, "PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = ON",
                       "set pragmas", err)) < 0)
        goto fail;
    if ((rc = migrate(st, err)) < 0)
        goto fail;

    for (int i = 0; i < S_COUNT; i++) {
        src = sqlite3_prepare_v3(st->db, stmt_sql[i], -1, SQLITE_PREPARE_PERSISTENT, &st->stmt[i],
                                 NULL);
        if (src != SQLITE_OK) {
            rc = store_db_fail(st, src, "prepare statement", err);
            goto fail;
        }
    }
    *out = st;
    return MR_OK;

fail:
    if (st) {
        for (int i = 0; i < S_COUNT; i++)
            sqlite3_finalize(st->stmt[i]);
        sqlite3_close(st->db);
        if (mutex_ready)
            pthread_mutex_destroy(&st->lock);
        free(st);
    }
    return rc;
}

void mr_store_close(mr_store *st)
{
    if (!st)
        return;
    for (int i = 0; i < S_COUNT; i++)
        sqlite3_finalize(st->stmt[i]);
    /* The last connection to close checkpoints the WAL into the database. */
    sqlite3_close(st->db);
    pthread_mutex_destroy(&st->lock);
    free(st);
}

const char *mr_store_dir(const mr_store *st) { return st ? st->dir : NULL; }

/* ---- recovery --------------------------------------------------------------- */

void store_forget_deleted(mr_store *st, const char *id, const char *dir)
{
    struct stat left;
    if (dir && stat(dir, &left) == 0)
        return;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_TOMBSTONE_DROP);
    store_exec_bound(st, s, store_bind_text(s, 1, id), "forget a deleted job", NULL);
    pthread_mutex_unlock(&st->lock);
}

/* Removes the temporaries a writer killed mid-write left in directory
 * path (mr_fs_atomic_abandoned). */
static void remove_temporaries(const char *path)
{
    DIR *d = opendir(path);
    struct dirent *e;
    while (d && (e = readdir(d)) != NULL)
        if (mr_fs_atomic_abandoned(dirfd(d), e->d_name, NULL, 0))
            unlinkat(dirfd(d), e->d_name, 0);
    if (d)
        closedir(d);
}

/* Best effort, failures must not stop a start-up: the frame folders of
 * deleted jobs (deleted_jobs: a crash between a delete's commit and its
 * file removal), temporaries of frames and uploads cut off by a crash.
 * A folder of no job that no delete listed is left alone and counted
 * (mr_store_unknown_frame_dirs): its rows are not in this database (one
 * lost, emptied or replaced), and removing it would lose frames for good. */
static void remove_orphans(mr_store *st)
{
    char path[STORE_PATH_MAX], sub[STORE_PATH_MAX];
    st->unknown_frame_dirs = 0;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = store_stmt(st, S_TOMBSTONES);
    char (*gone)[40] = NULL;
    size_t ngone = 0, cap = 0;
    while (sqlite3_step(s) == SQLITE_ROW) {
        const char *id = (const char *)sqlite3_column_text(s, 0);
        if (!id || !store_valid_job_id(id))
            continue;
        if (ngone == cap) {
            char(*more)[40] = realloc(gone, (cap = cap ? 2 * cap : 16) * sizeof *gone);
            if (!more)
                break;
            gone = more;
        }
        snprintf(gone[ngone++], sizeof *gone, "%s", id);
    }
    store_stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    for (size_t i = 0; i < ngone; i++) {
        mr_job_state state;
        pthread_mutex_lock(&st->lock);
        const bool has_row = store_job_state_locked(st, gone[i], &state, NULL) == MR_OK;
        pthread_mutex_unlock(&st->lock);
        const char *dir = NULL;
        if (!has_row && store_path_join(sub, sizeof sub, NULL, "%s/frames/%s", st->dir, gone[i]) == MR_OK) {
            if (mr_fs_remove_dir(sub, NULL) != MR_OK)
                continue; /* listed still: tried again at the next start */
            dir = sub;
        }
        store_forget_deleted(st, gone[i], dir);
    }
    free(gone);
    if (store_path_join(path, sizeof path, NULL, "%s/frames", st->dir) == MR_OK) {
        DIR *d = opendir(path);
        struct dirent *e;
        while (d && (e = readdir(d)) != NULL) {
            if (!store_valid_job_id(e->d_name) ||
                store_path_join(sub, sizeof sub, NULL, "%s/%s", path, e->d_name) != MR_OK)
                continue;
            mr_job_state state;
            pthread_mutex_lock(&st->lock);
            const int rc = store_job_state_locked(st, e->d_name, &state, NULL);
            pthread_mutex_unlock(&st->lock);
            if (rc == MR_ERR_NOT_FOUND)
                st->unknown_frame_dirs++;
            else
                remove_temporaries(sub);
        }
        if (d)
            closedir(d);
    }
    if (store_path_join(path, sizeof path, NULL, "%s/assets", st->dir) == MR_OK) {
        DIR *d = opendir(path);
        struct dirent *e;
        while (d && (e = readdir(d)) != NULL) {
            /* an upload cut off by a crash (".upload.tmpXXXXXX"; earlier
             * versions named it ".upload-XXXXXX"); assets are hex hashes */
            if (strncmp(e->d_name, ".upload", 7) == 0)
                unlinkat(dirfd(d), e->d_name, 0);
        }
        if (d)
            closedir(d);
    }
}

size_t mr_store_unknown_frame_dirs(const mr_store *st) { return st ? st->unknown_frame_dirs : 0; }

int mr_store_recover(mr_store *st, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_recover: no store");
    pthread_mutex_lock(&st->lock);
    int requeued = 0;
    int rc = store_tx_begin(st, err);
    if (rc < 0)
        goto done;
    sqlite3_stmt *s = store_stmt(st, S_RECOVER_FRAMES);
    if ((rc = store_exec_bound(st, s,
                               store_bind_text(s, 1, "the daemon stopped during this frame "
                                                     "(killed, crashed or out of memory)"),
                               "count interrupted frames", err)) < 0)
        goto done;
    s = store_stmt(st, S_RECOVER_GIVE_UP);
    if ((rc = store_exec_bound(st, s, sqlite3_bind_double(s, 1, store_now()),
                               "fail crash-looping jobs", err)) < 0)
        goto done;
    if ((rc = store_exec(st, store_stmt(st, S_RECOVER_JOBS), "re-queue running jobs", err)) < 0)
        goto done;
    sqlite3_int64 n = sqlite3_changes64(st->db);
    requeued = n > INT_MAX ? INT_MAX : (int)n;
done:
    rc = store_tx_end(st, rc, err);
    if (rc < 0)
        return rc;
    remove_orphans(st);
    return requeued;
}
