/*
 * store.c - the daemon's durable state (store.h): one sqlite connection in
 * WAL mode behind a mutex, with every statement prepared once at open and
 * reused, plus the frame and asset files under the data directory.
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
#include "store.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <pthread.h>
#include <stdarg.h>
#include <sqlite3.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "util/dup.h"
#include "util/hex.h"
#include "util/sha256.h"

/* Schema version kept in PRAGMA user_version; open() migrates older files
 * step by step and refuses newer ones. */
#define SCHEMA_VERSION 1
/* A guard against runaway frame counts, well above the job format's cap
 * (MR_MAX_FRAMES in core/job.h); the parser enforces the real limit. */
#define STORE_MAX_FRAMES 1000000u
#define STORE_BUSY_MS 5000 /* another process (sqlite3 shell, backup) holding the lock */
#define STORE_PATH_MAX 4096

enum stmt_id {
    S_BEGIN,
    S_COMMIT,
    S_ROLLBACK,
    S_JOB_INSERT,
    S_FRAME_INSERT,
    S_IDEM_GET,
    S_IDEM_INSERT,
    S_JOB_GET,
    S_JOB_LIST,
    S_JOB_LIST_STATE,
    S_JOB_JSON,
    S_JOB_STATE,
    S_JOB_SET_STATE,
    S_CLAIM_PICK,
    S_JOB_COUNTS,
    S_RECOVER_JOBS,
    S_RECOVER_FRAMES,
    S_RETRY_FRAMES,
    S_JOB_REQUEUE,
    S_DEL_IDEM,
    S_DEL_FRAMES,
    S_DEL_JOB,
    S_FRAMES_LIST,
    S_FRAME_ROW,
    S_FRAME_GET,
    S_FRAME_SET,
    S_FRAME_SET_RUNNING,
    S_FRAME_DONE,
    S_ASSET_INSERT,
    S_ASSET_GET,
    S_COUNT
};

/* Columns of a job record, in the order read_job() expects. Done and
 * failed counts come from the frames table (index frames_state makes them
 * index-only range counts) so they can never disagree with the frames. */
#define JOB_COLS                                                                          \
    "j.id, j.name, j.state, j.priority, j.max_retries, j.frame_count, j.created, "       \
    "j.started, j.finished, j.error, "                                                    \
    "(SELECT COUNT(*) FROM frames f WHERE f.job_id = j.id AND f.state = 2), "             \
    "(SELECT COUNT(*) FROM frames f WHERE f.job_id = j.id AND f.state = 3)"

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
    [S_JOB_LIST] = "SELECT " JOB_COLS " FROM jobs j ORDER BY j.seq DESC",
    [S_JOB_LIST_STATE] = "SELECT " JOB_COLS " FROM jobs j WHERE j.state = ?1 ORDER BY j.seq DESC",
    [S_JOB_JSON] = "SELECT json FROM jobs WHERE id = ?1",
    [S_JOB_STATE] = "SELECT state, frame_count FROM jobs WHERE id = ?1",
    /* ?2 state, ?3 error or NULL to keep it, ?4 now. started is set the
     * first time a job runs; finished on entering a final state and cleared
     * when it is queued or running again. */
    [S_JOB_SET_STATE] = "UPDATE jobs SET state = ?2, error = COALESCE(?3, error), "
                        "started = CASE WHEN ?2 = 1 AND started = 0 THEN ?4 ELSE started END, "
                        "finished = CASE WHEN ?2 >= 2 THEN ?4 ELSE 0 END WHERE id = ?1",
    [S_CLAIM_PICK] = "SELECT id FROM jobs WHERE state = 0 ORDER BY priority DESC, seq ASC LIMIT 1",
    [S_JOB_COUNTS] = "SELECT state, COUNT(*) FROM jobs GROUP BY state",
    [S_RECOVER_JOBS] = "UPDATE jobs SET state = 0 WHERE state = 1",
    [S_RECOVER_FRAMES] = "UPDATE frames SET state = 0 WHERE state = 1",
    /* Every frame that is not done gets rendered again with a fresh retry
     * budget: failed ones, pending ones a cancel left behind, and running
     * ones a stopped worker left behind. */
    [S_RETRY_FRAMES] = "UPDATE frames SET state = 0, retries = 0, error = '' "
                       "WHERE job_id = ?1 AND state <> 2",
    [S_JOB_REQUEUE] = "UPDATE jobs SET state = 0, error = '', finished = 0 WHERE id = ?1",
    [S_DEL_IDEM] = "DELETE FROM idempotency WHERE job_id = ?1",
    [S_DEL_FRAMES] = "DELETE FROM frames WHERE job_id = ?1",
    [S_DEL_JOB] = "DELETE FROM jobs WHERE id = ?1",
    [S_FRAMES_LIST] = "SELECT idx, state, retries, error, stats_json FROM frames "
                      "WHERE job_id = ?1 ORDER BY idx",
    [S_FRAME_ROW] = "SELECT idx, state, retries, error, stats_json FROM frames "
                    "WHERE job_id = ?1 AND idx = ?2",
    [S_FRAME_GET] = "SELECT f.state, f.retries, j.max_retries FROM frames f "
                    "JOIN jobs j ON j.id = f.job_id WHERE f.job_id = ?1 AND f.idx = ?2",
    [S_FRAME_SET] = "UPDATE frames SET state = ?3, retries = ?4, error = ?5 "
                    "WHERE job_id = ?1 AND idx = ?2",
    [S_FRAME_SET_RUNNING] = "UPDATE frames SET state = 1 WHERE job_id = ?1 AND idx = ?2",
    [S_FRAME_DONE] = "UPDATE frames SET state = 2, error = '', stats_json = ?3 "
                     "WHERE job_id = ?1 AND idx = ?2",
    [S_ASSET_INSERT] = "INSERT OR IGNORE INTO assets(id, size, created) VALUES(?1, ?2, ?3)",
    [S_ASSET_GET] = "SELECT size FROM assets WHERE id = ?1",
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

struct mr_store {
    pthread_mutex_t lock;
    sqlite3 *db;
    sqlite3_stmt *stmt[S_COUNT];
    char dir[STORE_PATH_MAX];
};

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

static double now_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* Ids reach the store straight from URLs; only well-formed ones are ever
 * looked up or turned into paths. */
static bool valid_job_id(const char *id) { return mr_hex_is_lower(id, MR_JOB_ID_LEN); }

/* A caller's string made safe for a message: printable ASCII, at most 64
 * characters. */
static const char *printable(const char *s, char out[72])
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

static int no_job(mr_error *err, const char *id)
{
    char buf[72];
    return mr_error_set(err, MR_ERR_NOT_FOUND, "no job '%s'", printable(id, buf));
}

static int io_error(mr_error *err, const char *what, const char *path, int e)
{
    return mr_error_set(err, MR_ERR_IO, "%s '%s': %s", what, path, strerror(e));
}

static int path_join(char *out, size_t size, mr_error *err, const char *fmt, ...)
    __attribute__((format(printf, 4, 5)));

static int path_join(char *out, size_t size, mr_error *err, const char *fmt, ...)
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
static void copy_col(char *dst, size_t size, sqlite3_stmt *s, int col)
{
    const unsigned char *t = sqlite3_column_text(s, col);
    size_t n = t ? (size_t)sqlite3_column_bytes(s, col) : 0;
    if (n >= size)
        n = size - 1;
    if (n)
        memcpy(dst, t, n);
    dst[n] = '\0';
}

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

/* ---- files ------------------------------------------------------------------ */

static int fsync_dir(const char *dir, mr_error *err)
{
    int fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        return io_error(err, "cannot open directory", dir, errno);
    if (fsync(fd) != 0) {
        int e = errno;
        close(fd);
        return io_error(err, "cannot fsync directory", dir, e);
    }
    close(fd);
    return MR_OK;
}

/* mkdir that accepts an existing directory; *created tells whether it is
 * new (its parent then needs an fsync for the entry to be durable). */
static int make_dir(const char *dir, bool *created, mr_error *err)
{
    if (created)
        *created = false;
    if (mkdir(dir, 0755) == 0) {
        if (created)
            *created = true;
        return MR_OK;
    }
    if (errno != EEXIST)
        return io_error(err, "cannot create directory", dir, errno);
    struct stat sb;
    if (stat(dir, &sb) != 0)
        return io_error(err, "cannot stat", dir, errno);
    if (!S_ISDIR(sb.st_mode))
        return mr_error_set(err, MR_ERR_IO, "'%s' exists and is not a directory", dir);
    return MR_OK;
}

static int make_dirs(const char *dir, mr_error *err)
{
    char p[STORE_PATH_MAX];
    int rc = path_join(p, sizeof p, err, "%s", dir);
    if (rc < 0)
        return rc;
    for (char *c = p + 1; *c; c++) {
        if (*c != '/')
            continue;
        *c = '\0';
        rc = make_dir(p, NULL, err);
        *c = '/';
        if (rc < 0)
            return rc;
    }
    return make_dir(p, NULL, err);
}

static int write_all(int fd, const void *data, size_t size)
{
    const unsigned char *p = data;
    while (size > 0) {
        ssize_t n = write(fd, p, size);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return -1;
        }
        p += n;
        size -= (size_t)n;
    }
    return 0;
}

/* Writes data through the already open fd of tmp, fsyncs, renames tmp to
 * path and fsyncs dir: after it returns, path holds the complete bytes
 * even across a crash. Closes fd; removes tmp on failure. */
static int commit_file(int fd, const char *tmp, const char *path, const char *dir,
                       const void *data, size_t size, mr_error *err)
{
    int rc = MR_OK;
    if (size > 0 && write_all(fd, data, size) != 0) {
        rc = io_error(err, "cannot write", tmp, errno);
        close(fd);
        goto fail;
    }
    if (fsync(fd) != 0) {
        rc = io_error(err, "cannot fsync", tmp, errno);
        close(fd);
        goto fail;
    }
    /* close can report a delayed write error (NFS); the data is not safe
     * then. */
    if (close(fd) != 0) {
        rc = io_error(err, "cannot close", tmp, errno);
        goto fail;
    }
    if (rename(tmp, path) != 0) {
        rc = io_error(err, "cannot rename to", path, errno);
        goto fail;
    }
    return fsync_dir(dir, err);
fail:
    unlink(tmp);
    return rc;
}

/* Removes the regular files in dir and dir itself; a missing dir is fine. */
static int remove_dir(const char *dir, mr_error *err)
{
    DIR *d = opendir(dir);
    if (!d)
        return errno == ENOENT ? MR_OK : io_error(err, "cannot open directory", dir, errno);
    int rc = MR_OK;
    struct dirent *e;
    errno = 0;
    while ((e = readdir(d)) != NULL) {
        if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0)
            continue;
        if (unlinkat(dirfd(d), e->d_name, 0) != 0 && errno != ENOENT && rc == MR_OK) {
            char p[STORE_PATH_MAX];
            int e2 = errno;
            if (path_join(p, sizeof p, NULL, "%s/%s", dir, e->d_name) < 0)
                snprintf(p, sizeof p, "%s/...", dir);
            rc = io_error(err, "cannot remove", p, e2);
        }
        errno = 0;
    }
    if (errno != 0 && rc == MR_OK)
        rc = io_error(err, "cannot read directory", dir, errno);
    closedir(d);
    if (rc < 0)
        return rc;
    /* ENOTEMPTY: a frame of the deleted job was being written at the same
     * time; that writer finds the rows gone and removes its file and the
     * directory itself. */
    if (rmdir(dir) != 0 && errno != ENOENT && errno != ENOTEMPTY)
        return io_error(err, "cannot remove directory", dir, errno);
    return MR_OK;
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
    default: return MR_ERR_IO;
    }
}

/* The message of the connection's last failure; read it before any other
 * call on the connection (the caller holds the mutex, so nobody else can
 * overwrite it). */
static int db_fail(mr_store *st, int sqlite_rc, const char *what, mr_error *err)
{
    /* sqlite's words first: a long data directory must not cut them off. */
    return mr_error_set(err, db_code(sqlite_rc), "sqlite: %s: %s (%s/microray.sqlite)", what,
                        sqlite3_errmsg(st->db), st->dir);
}

/* A statement ready for binding; released with stmt_release(). */
static sqlite3_stmt *stmt_use(mr_store *st, enum stmt_id id) { return st->stmt[id]; }

static void stmt_release(sqlite3_stmt *s)
{
    /* reset repeats the last step's error code, which was already checked. */
    sqlite3_reset(s);
    sqlite3_clear_bindings(s);
}

/* Steps a statement that returns no rows, then releases it. */
static int exec_stmt(mr_store *st, sqlite3_stmt *s, const char *what, mr_error *err)
{
    int rc = sqlite3_step(s);
    int out = rc == SQLITE_DONE ? MR_OK : db_fail(st, rc, what, err);
    stmt_release(s);
    return out;
}

/* Checks bind results: all of them are SQLITE_OK or the first failure. */
static int bind_check(mr_store *st, int rc, const char *what, mr_error *err)
{
    return rc == SQLITE_OK ? MR_OK : db_fail(st, rc, what, err);
}

static int bind_text(sqlite3_stmt *s, int i, const char *t)
{
    return t ? sqlite3_bind_text(s, i, t, -1, SQLITE_STATIC) : sqlite3_bind_null(s, i);
}

static int tx_begin(mr_store *st, mr_error *err)
{
    return exec_stmt(st, stmt_use(st, S_BEGIN), "begin transaction", err);
}

static int tx_commit(mr_store *st, mr_error *err)
{
    return exec_stmt(st, stmt_use(st, S_COMMIT), "commit", err);
}

/* After a failed statement sqlite may already have rolled back (disk
 * full, I/O error); only roll back what is still open. */
static void tx_rollback(mr_store *st)
{
    if (!sqlite3_get_autocommit(st->db)) {
        sqlite3_stmt *s = stmt_use(st, S_ROLLBACK);
        sqlite3_step(s);
        stmt_release(s);
    }
}

/* Looks a job's state (and frame count, if wanted) up; MR_ERR_NOT_FOUND if
 * it does not exist. */
static int job_lookup_locked(mr_store *st, const char *id, mr_job_state *state, size_t *frames,
                             mr_error *err)
{
    sqlite3_stmt *s = stmt_use(st, S_JOB_STATE);
    int rc = bind_check(st, bind_text(s, 1, id), "find job", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW) {
            *state = (mr_job_state)sqlite3_column_int(s, 0);
            if (frames)
                *frames = (size_t)sqlite3_column_int64(s, 1);
        } else if (step == SQLITE_DONE) {
            rc = no_job(err, id);
        } else {
            rc = db_fail(st, step, "find job", err);
        }
    }
    stmt_release(s);
    return rc;
}

static int job_state_locked(mr_store *st, const char *id, mr_job_state *state, mr_error *err)
{
    return job_lookup_locked(st, id, state, NULL, err);
}

/* For a frame lookup that found no row: an unknown job, or a job without
 * that frame. */
static int no_frame(mr_store *st, const char *id, size_t index, mr_error *err)
{
    mr_job_state state;
    int rc = job_state_locked(st, id, &state, err);
    if (rc < 0)
        return rc;
    return mr_error_set(err, MR_ERR_NOT_FOUND, "job '%s' has no frame %zu", id, index);
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
        return db_fail(st, rc, sql, err);
    rc = sqlite3_step(s);
    int out = MR_OK;
    if (rc == SQLITE_ROW) {
        if (num)
            *num = sqlite3_column_int64(s, 0);
        if (text)
            copy_col(text, size, s, 0);
    } else {
        out = db_fail(st, rc, sql, err);
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
    /* Later versions add "if (version < 2) ALTER ..." steps here. */
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
    /* Room for "/frames/<id>/NNNNNNN.exr.tmp" below the directory. */
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
    if ((rc = make_dirs(st->dir, err)) < 0)
        goto fail;
    if ((rc = path_join(path, sizeof path, err, "%s/assets", st->dir)) < 0 ||
        (rc = make_dir(path, NULL, err)) < 0)
        goto fail;
    if ((rc = path_join(path, sizeof path, err, "%s/frames", st->dir)) < 0 ||
        (rc = make_dir(path, NULL, err)) < 0)
        goto fail;

    if (pthread_mutex_init(&st->lock, NULL) != 0) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "cannot create the store mutex");
        goto fail;
    }
    mutex_ready = true;

    if ((rc = path_join(path, sizeof path, err, "%s/microray.sqlite", st->dir)) < 0)
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
            rc = db_fail(st, src, "prepare statement", err);
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

/* Best effort: frame directories of jobs whose rows are gone (a crash
 * between a delete's commit and its file removal) and asset temporaries
 * of interrupted uploads. Failures here must not stop a start-up. */
static void remove_orphans(mr_store *st)
{
    char path[STORE_PATH_MAX];
    if (path_join(path, sizeof path, NULL, "%s/frames", st->dir) == MR_OK) {
        DIR *d = opendir(path);
        struct dirent *e;
        while (d && (e = readdir(d)) != NULL) {
            if (!valid_job_id(e->d_name))
                continue;
            mr_job_state state;
            pthread_mutex_lock(&st->lock);
            int rc = job_state_locked(st, e->d_name, &state, NULL);
            pthread_mutex_unlock(&st->lock);
            char sub[STORE_PATH_MAX];
            if (rc == MR_ERR_NOT_FOUND &&
                path_join(sub, sizeof sub, NULL, "%s/%s", path, e->d_name) == MR_OK)
                remove_dir(sub, NULL);
        }
        if (d)
            closedir(d);
    }
    if (path_join(path, sizeof path, NULL, "%s/assets", st->dir) == MR_OK) {
        DIR *d = opendir(path);
        struct dirent *e;
        while (d && (e = readdir(d)) != NULL) {
            if (strncmp(e->d_name, ".upload-", 8) == 0) /* an upload cut off by a crash */
                unlinkat(dirfd(d), e->d_name, 0);
        }
        if (d)
            closedir(d);
    }
}

int mr_store_recover(mr_store *st, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_recover: no store");
    pthread_mutex_lock(&st->lock);
    int requeued = 0;
    int rc = tx_begin(st, err);
    if (rc < 0)
        goto done;
    if ((rc = exec_stmt(st, stmt_use(st, S_RECOVER_JOBS), "re-queue running jobs", err)) < 0)
        goto done;
    sqlite3_int64 n = sqlite3_changes64(st->db);
    requeued = n > INT_MAX ? INT_MAX : (int)n;
    if ((rc = exec_stmt(st, stmt_use(st, S_RECOVER_FRAMES), "reset running frames", err)) < 0)
        goto done;
    rc = tx_commit(st, err);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    remove_orphans(st);
    return requeued;
}

/* ---- jobs ------------------------------------------------------------------- */

int mr_store_job_create(mr_store *st, const char *json, size_t json_len, const char *name,
                        size_t frame_count, int priority, int max_retries,
                        const char *idempotency_key, const char *body_hash,
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
    double now = now_seconds();

    pthread_mutex_lock(&st->lock);
    if ((rc = tx_begin(st, err)) < 0)
        goto done;

    if (keyed) {
        sqlite3_stmt *s = stmt_use(st, S_IDEM_GET);
        rc = bind_check(st, bind_text(s, 1, idempotency_key), "look up idempotency key", err);
        if (rc == MR_OK) {
            int step = sqlite3_step(s);
            if (step == SQLITE_ROW) {
                const char *h = (const char *)sqlite3_column_text(s, 0);
                if (h && strcmp(h, body_hash) == 0) {
                    copy_col(id, MR_JOB_ID_LEN + 1, s, 1);
                    if (existing)
                        *existing = true;
                    rc = 1; /* found: nothing to insert */
                } else {
                    char kb[72];
                    rc = mr_error_set(err, MR_ERR_CONFLICT,
                                      "idempotency key '%s' was used before with a different "
                                      "request body",
                                      printable(idempotency_key, kb));
                }
            } else if (step != SQLITE_DONE) {
                rc = db_fail(st, step, "look up idempotency key", err);
            }
        }
        stmt_release(s);
        if (rc != MR_OK) {
            if (rc == 1)
                rc = tx_commit(st, err);
            goto done;
        }
    }

    sqlite3_stmt *s = stmt_use(st, S_JOB_INSERT);
    rc = bind_check(st,
                    sqlite3_bind_text(s, 1, new_id, -1, SQLITE_STATIC) |
                        sqlite3_bind_text(s, 2, name, name_len, SQLITE_STATIC) |
                        sqlite3_bind_int(s, 3, priority) | sqlite3_bind_int(s, 4, max_retries) |
                        sqlite3_bind_int64(s, 5, (sqlite3_int64)frame_count) |
                        sqlite3_bind_text(s, 6, json, (int)json_len, SQLITE_STATIC) |
                        sqlite3_bind_double(s, 7, now),
                    "insert job", err);
    if (rc < 0) {
        stmt_release(s);
        goto done;
    }
    if ((rc = exec_stmt(st, s, "insert job", err)) < 0)
        goto done;

    /* One prepared insert stepped per frame inside the open transaction:
     * 100,000 frames is one commit, not 100,000. */
    s = stmt_use(st, S_FRAME_INSERT);
    if ((rc = bind_check(st, sqlite3_bind_text(s, 1, new_id, -1, SQLITE_STATIC), "insert frames",
                         err)) < 0) {
        stmt_release(s);
        goto done;
    }
    for (size_t i = 0; i < frame_count; i++) {
        int brc = sqlite3_bind_int64(s, 2, (sqlite3_int64)i);
        int step = brc == SQLITE_OK ? sqlite3_step(s) : brc;
        if (step != SQLITE_DONE) {
            rc = db_fail(st, step, "insert frames", err);
            break;
        }
        sqlite3_reset(s);
    }
    stmt_release(s);
    if (rc < 0)
        goto done;

    if (keyed) {
        s = stmt_use(st, S_IDEM_INSERT);
        rc = bind_check(st,
                        bind_text(s, 1, idempotency_key) | bind_text(s, 2, body_hash) |
                            sqlite3_bind_text(s, 3, new_id, -1, SQLITE_STATIC),
                        "store idempotency key", err);
        if (rc < 0) {
            stmt_release(s);
            goto done;
        }
        if ((rc = exec_stmt(st, s, "store idempotency key", err)) < 0)
            goto done;
    }
    if ((rc = tx_commit(st, err)) < 0)
        goto done;
    memcpy(id, new_id, sizeof new_id);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    return rc < 0 ? rc : MR_OK;
}

static void read_job(sqlite3_stmt *s, mr_job_record *r)
{
    memset(r, 0, sizeof *r);
    copy_col(r->id, sizeof r->id, s, 0);
    copy_col(r->name, sizeof r->name, s, 1);
    r->state = (mr_job_state)sqlite3_column_int(s, 2);
    r->priority = sqlite3_column_int(s, 3);
    r->max_retries = sqlite3_column_int(s, 4);
    r->frame_count = (size_t)sqlite3_column_int64(s, 5);
    r->created = sqlite3_column_double(s, 6);
    r->started = sqlite3_column_double(s, 7);
    r->finished = sqlite3_column_double(s, 8);
    copy_col(r->error, sizeof r->error, s, 9);
    r->frames_done = (size_t)sqlite3_column_int64(s, 10);
    r->frames_failed = (size_t)sqlite3_column_int64(s, 11);
}

int mr_store_job_get(mr_store *st, const char *id, mr_job_record *out, mr_error *err)
{
    if (!st || !out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_get: missing argument");
    if (!valid_job_id(id))
        return no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_JOB_GET);
    int rc = bind_check(st, bind_text(s, 1, id), "read job", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW)
            read_job(s, out);
        else if (step == SQLITE_DONE)
            rc = no_job(err, id);
        else
            rc = db_fail(st, step, "read job", err);
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_json(mr_store *st, const char *id, char **json, mr_error *err)
{
    if (!st || !json)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_json: missing argument");
    *json = NULL;
    if (!valid_job_id(id))
        return no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_JOB_JSON);
    int rc = bind_check(st, bind_text(s, 1, id), "read job document", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW) {
            const unsigned char *t = sqlite3_column_text(s, 0);
            size_t n = t ? (size_t)sqlite3_column_bytes(s, 0) : 0;
            if (!(*json = mr_memdup_str(t, n)))
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory reading job '%s'", id);
        } else if (step == SQLITE_DONE) {
            rc = no_job(err, id);
        } else {
            rc = db_fail(st, step, "read job document", err);
        }
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_list(mr_store *st, bool filter, mr_job_state state, mr_job_record **out,
                      size_t *count, mr_error *err)
{
    if (!st || !out || !count)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_list: missing argument");
    *out = NULL;
    *count = 0;
    mr_job_record *list = NULL;
    size_t n = 0, cap = 0;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, filter ? S_JOB_LIST_STATE : S_JOB_LIST);
    int rc = MR_OK;
    if (filter)
        rc = bind_check(st, sqlite3_bind_int(s, 1, (int)state), "list jobs", err);
    while (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            break;
        if (step != SQLITE_ROW) {
            rc = db_fail(st, step, "list jobs", err);
            break;
        }
        if (n == cap) {
            size_t ncap = cap ? cap * 2 : 16;
            mr_job_record *grown = realloc(list, ncap * sizeof *grown);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory listing jobs");
                break;
            }
            list = grown;
            cap = ncap;
        }
        read_job(s, &list[n++]);
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        free(list);
        return rc;
    }
    *out = list;
    *count = n;
    return MR_OK;
}

int mr_store_job_set_state(mr_store *st, const char *id, mr_job_state state, const char *error,
                           mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_set_state: no store");
    if ((unsigned)state > MR_JOB_CANCELED)
        return mr_error_set(err, MR_ERR_INVALID, "invalid job state %d", (int)state);
    if (!valid_job_id(id))
        return no_job(err, id);
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_JOB_SET_STATE);
    int rc = bind_check(st,
                        bind_text(s, 1, id) | sqlite3_bind_int(s, 2, (int)state) |
                            bind_text(s, 3, error) | sqlite3_bind_double(s, 4, now_seconds()),
                        "set job state", err);
    if (rc == MR_OK)
        rc = exec_stmt(st, s, "set job state", err);
    else
        stmt_release(s);
    if (rc == MR_OK && sqlite3_changes(st->db) == 0)
        rc = no_job(err, id);
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
    int rc = tx_begin(st, err);
    if (rc < 0)
        goto done;
    sqlite3_stmt *s = stmt_use(st, S_CLAIM_PICK);
    int step = sqlite3_step(s);
    if (step == SQLITE_ROW)
        copy_col(found, sizeof found, s, 0);
    else if (step == SQLITE_DONE)
        rc = mr_error_set(err, MR_ERR_NOT_FOUND, "no queued job");
    else
        rc = db_fail(st, step, "pick queued job", err);
    stmt_release(s);
    if (rc < 0)
        goto done;
    s = stmt_use(st, S_JOB_SET_STATE);
    rc = bind_check(st,
                    sqlite3_bind_text(s, 1, found, -1, SQLITE_STATIC) |
                        sqlite3_bind_int(s, 2, MR_JOB_RUNNING) | sqlite3_bind_null(s, 3) |
                        sqlite3_bind_double(s, 4, now_seconds()),
                    "claim job", err);
    if (rc < 0) {
        stmt_release(s);
        goto done;
    }
    if ((rc = exec_stmt(st, s, "claim job", err)) < 0)
        goto done;
    if ((rc = tx_commit(st, err)) < 0)
        goto done;
    memcpy(id, found, sizeof found);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_job_retry(mr_store *st, const char *id, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_retry: no store");
    if (!valid_job_id(id))
        return no_job(err, id);
    int requeued = 0;
    pthread_mutex_lock(&st->lock);
    int rc = tx_begin(st, err);
    if (rc < 0)
        goto done;
    mr_job_state state;
    if ((rc = job_state_locked(st, id, &state, err)) < 0)
        goto done;
    if (state != MR_JOB_FAILED && state != MR_JOB_CANCELED) {
        rc = mr_error_set(err, MR_ERR_CONFLICT,
                          "job '%s' is %s; only failed or canceled jobs can be retried", id,
                          mr_job_state_name(state));
        goto done;
    }
    sqlite3_stmt *s = stmt_use(st, S_RETRY_FRAMES);
    if ((rc = bind_check(st, bind_text(s, 1, id), "re-queue frames", err)) < 0) {
        stmt_release(s);
        goto done;
    }
    if ((rc = exec_stmt(st, s, "re-queue frames", err)) < 0)
        goto done;
    sqlite3_int64 n = sqlite3_changes64(st->db);
    if (n == 0) {
        rc = mr_error_set(err, MR_ERR_CONFLICT, "job '%s' has no failed or unfinished frames to retry",
                          id);
        goto done;
    }
    requeued = n > INT_MAX ? INT_MAX : (int)n;
    s = stmt_use(st, S_JOB_REQUEUE);
    if ((rc = bind_check(st, bind_text(s, 1, id), "re-queue job", err)) < 0) {
        stmt_release(s);
        goto done;
    }
    if ((rc = exec_stmt(st, s, "re-queue job", err)) < 0)
        goto done;
    rc = tx_commit(st, err);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    return rc < 0 ? rc : requeued;
}

int mr_store_job_delete(mr_store *st, const char *id, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_delete: no store");
    if (!valid_job_id(id))
        return no_job(err, id);
    char dir[STORE_PATH_MAX];
    int rc = path_join(dir, sizeof dir, err, "%s/frames/%s", st->dir, id);
    if (rc < 0)
        return rc;
    static const enum stmt_id steps[] = {S_DEL_IDEM, S_DEL_FRAMES, S_DEL_JOB};
    pthread_mutex_lock(&st->lock);
    if ((rc = tx_begin(st, err)) < 0)
        goto done;
    for (size_t i = 0; i < sizeof steps / sizeof *steps; i++) {
        sqlite3_stmt *s = stmt_use(st, steps[i]);
        if ((rc = bind_check(st, bind_text(s, 1, id), "delete job", err)) < 0) {
            stmt_release(s);
            goto done;
        }
        if ((rc = exec_stmt(st, s, "delete job", err)) < 0)
            goto done;
    }
    if (sqlite3_changes(st->db) == 0) {
        rc = no_job(err, id);
        goto done;
    }
    rc = tx_commit(st, err);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    /* Rows first, files second: a crash in between leaves an orphan
     * directory (removed by the next mr_store_recover), never a row whose
     * files are gone. */
    return remove_dir(dir, err);
}

int mr_store_job_counts(mr_store *st, uint64_t counts[5], mr_error *err)
{
    if (!st || !counts)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_job_counts: missing argument");
    for (int i = 0; i < 5; i++)
        counts[i] = 0;
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_JOB_COUNTS);
    int rc = MR_OK;
    for (;;) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            break;
        if (step != SQLITE_ROW) {
            rc = db_fail(st, step, "count jobs", err);
            break;
        }
        int state = sqlite3_column_int(s, 0);
        if (state >= 0 && state < 5)
            counts[state] = (uint64_t)sqlite3_column_int64(s, 1);
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

/* ---- frames ----------------------------------------------------------------- */

/* One row of S_FRAMES_LIST / S_FRAME_ROW into f (stats_json malloc'ed). */
static int read_frame_row(sqlite3_stmt *s, mr_frame_record *f, mr_error *err)
{
    memset(f, 0, sizeof *f);
    f->index = (size_t)sqlite3_column_int64(s, 0);
    f->state = (mr_frame_state)sqlite3_column_int(s, 1);
    f->retries = sqlite3_column_int(s, 2);
    copy_col(f->error, sizeof f->error, s, 3);
    const unsigned char *t = sqlite3_column_text(s, 4);
    if (t && !(f->stats_json = mr_memdup_str(t, (size_t)sqlite3_column_bytes(s, 4))))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory reading frames");
    return MR_OK;
}

int mr_store_frames(mr_store *st, const char *id, mr_frame_record **out, size_t *count,
                    mr_error *err)
{
    if (!st || !out || !count)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frames: missing argument");
    *out = NULL;
    *count = 0;
    if (!valid_job_id(id))
        return no_job(err, id);
    mr_frame_record *list = NULL;
    size_t n = 0, cap = 0;
    pthread_mutex_lock(&st->lock);
    mr_job_state state;
    size_t expected = 0;
    /* An empty result must not hide an unknown id; the frame count sizes
     * the array once (a record is over 500 bytes, 100,000 of them are
     * 54 MB). */
    int rc = job_lookup_locked(st, id, &state, &expected, err);
    if (rc == MR_OK && expected > 0) {
        list = malloc(expected * sizeof *list);
        if (!list)
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory listing %zu frames", expected);
        cap = list ? expected : 0;
    }
    sqlite3_stmt *s = stmt_use(st, S_FRAMES_LIST);
    if (rc == MR_OK)
        rc = bind_check(st, bind_text(s, 1, id), "list frames", err);
    while (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            break;
        if (step != SQLITE_ROW) {
            rc = db_fail(st, step, "list frames", err);
            break;
        }
        if (n == cap) {
            size_t ncap = cap ? cap * 2 : 64;
            mr_frame_record *grown = realloc(list, ncap * sizeof *grown);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory listing frames");
                break;
            }
            list = grown;
            cap = ncap;
        }
        if ((rc = read_frame_row(s, &list[n], err)) < 0)
            break;
        n++;
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0) {
        mr_frame_records_free(list, n);
        return rc;
    }
    *out = list;
    *count = n;
    return MR_OK;
}

int mr_store_frame_get(mr_store *st, const char *id, size_t index, mr_frame_record *out, mr_error *err)
{
    memset(out, 0, sizeof *out);
    if (!valid_job_id(id))
        return no_job(err, id);
    pthread_mutex_lock(&st->lock);
    mr_job_state state;
    size_t frames = 0;
    int rc = job_lookup_locked(st, id, &state, &frames, err);
    if (rc == MR_OK && index >= frames)
        rc = mr_error_set(err, MR_ERR_NOT_FOUND, "job %s has no frame %zu", id, index);
    sqlite3_stmt *s = stmt_use(st, S_FRAME_ROW);
    if (rc == MR_OK)
        rc = bind_check(st, bind_text(s, 1, id), "read frame", err);
    if (rc == MR_OK)
        rc = bind_check(st, sqlite3_bind_int64(s, 2, (sqlite3_int64)index), "read frame", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW)
            rc = read_frame_row(s, out, err);
        else if (step == SQLITE_DONE)
            rc = mr_error_set(err, MR_ERR_NOT_FOUND, "job %s has no frame %zu", id, index);
        else
            rc = db_fail(st, step, "read frame", err);
    }
    stmt_release(s);
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
    sqlite3_stmt *s = stmt_use(st, S_FRAME_GET);
    int rc = bind_check(st, bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, (sqlite3_int64)index),
                        "read frame", err);
    bool missing = false;
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_ROW) {
            if (state)
                *state = (mr_frame_state)sqlite3_column_int(s, 0);
            if (retries)
                *retries = sqlite3_column_int(s, 1);
            if (max_retries)
                *max_retries = sqlite3_column_int(s, 2);
        } else if (step == SQLITE_DONE) {
            missing = true;
        } else {
            rc = db_fail(st, step, "read frame", err);
        }
    }
    stmt_release(s);
    if (missing)
        return no_frame(st, id, index, err);
    return rc;
}

/* Updates state, retries and error of an existing frame (lock held). */
static int frame_set_locked(mr_store *st, const char *id, size_t index, mr_frame_state state,
                            int retries, const char *error, mr_error *err)
{
    sqlite3_stmt *s = stmt_use(st, S_FRAME_SET);
    int rc = bind_check(st,
                        bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, (sqlite3_int64)index) |
                            sqlite3_bind_int(s, 3, (int)state) | sqlite3_bind_int(s, 4, retries) |
                            bind_text(s, 5, error ? error : ""),
                        "update frame", err);
    if (rc < 0) {
        stmt_release(s);
        return rc;
    }
    return exec_stmt(st, s, "update frame", err);
}

int mr_store_frame_set_running(mr_store *st, const char *id, size_t index, mr_error *err)
{
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_set_running: no store");
    if (!valid_job_id(id))
        return no_job(err, id);
    if (index > (size_t)INT64_MAX)
        return mr_error_set(err, MR_ERR_NOT_FOUND, "job '%s' has no frame %zu", id, index);
    pthread_mutex_lock(&st->lock);
    /* Only the state changes: the error of an earlier attempt stays
     * visible until this attempt ends. */
    sqlite3_stmt *s = stmt_use(st, S_FRAME_SET_RUNNING);
    int rc = bind_check(st, bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, (sqlite3_int64)index),
                        "mark frame running", err);
    if (rc == MR_OK)
        rc = exec_stmt(st, s, "mark frame running", err);
    else
        stmt_release(s);
    if (rc == MR_OK && sqlite3_changes(st->db) == 0)
        rc = no_frame(st, id, index, err);
    pthread_mutex_unlock(&st->lock);
    return rc;
}

int mr_store_frame_failed(mr_store *st, const char *id, size_t index, const char *error,
                          bool *gave_up, mr_error *err)
{
    if (gave_up)
        *gave_up = false;
    if (!st)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_failed: no store");
    if (!valid_job_id(id))
        return no_job(err, id);
    pthread_mutex_lock(&st->lock);
    int retries = 0, max_retries = 0;
    bool give_up = false;
    int rc = tx_begin(st, err);
    if (rc < 0)
        goto done;
    if ((rc = frame_get_locked(st, id, index, NULL, &retries, &max_retries, err)) < 0)
        goto done;
    if (retries < INT_MAX)
        retries++;
    give_up = retries > max_retries;
    if ((rc = frame_set_locked(st, id, index, give_up ? MR_FRAME_FAILED : MR_FRAME_PENDING,
                               retries, error, err)) < 0)
        goto done;
    rc = tx_commit(st, err);
done:
    if (rc < 0)
        tx_rollback(st);
    pthread_mutex_unlock(&st->lock);
    if (rc == MR_OK && gave_up)
        *gave_up = give_up;
    return rc;
}

static int frame_file(const mr_store *st, const char *id, size_t index, const char *suffix,
                      char *path, size_t size, mr_error *err)
{
    return path_join(path, size, err, "%s/frames/%s/%04zu.exr%s", st->dir, id, index, suffix);
}

int mr_store_frame_done(mr_store *st, const char *id, size_t index, const void *exr,
                        size_t exr_size, const char *stats_json, mr_error *err)
{
    if (!st || (!exr && exr_size > 0))
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_done: missing argument");
    if (!valid_job_id(id))
        return no_job(err, id);
    char dir[STORE_PATH_MAX], tmp[STORE_PATH_MAX], path[STORE_PATH_MAX];
    int rc;
    if ((rc = path_join(dir, sizeof dir, err, "%s/frames/%s", st->dir, id)) < 0 ||
        (rc = frame_file(st, id, index, ".tmp", tmp, sizeof tmp, err)) < 0 ||
        (rc = frame_file(st, id, index, "", path, sizeof path, err)) < 0)
        return rc;

    /* Refuse unknown frames before touching the disk. */
    pthread_mutex_lock(&st->lock);
    rc = frame_get_locked(st, id, index, NULL, NULL, NULL, err);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;

    bool created = false;
    if ((rc = make_dir(dir, &created, err)) < 0)
        return rc;
    if (created) {
        char parent[STORE_PATH_MAX];
        if ((rc = path_join(parent, sizeof parent, err, "%s/frames", st->dir)) < 0 ||
            (rc = fsync_dir(parent, err)) < 0)
            return rc;
    }
    int fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (fd < 0)
        return io_error(err, "cannot create", tmp, errno);
    if ((rc = commit_file(fd, tmp, path, dir, exr, exr_size, err)) < 0)
        return rc;

    /* The file is durable; only now may the row say so. */
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_FRAME_DONE);
    rc = bind_check(st,
                    bind_text(s, 1, id) | sqlite3_bind_int64(s, 2, (sqlite3_int64)index) |
                        bind_text(s, 3, stats_json),
                    "mark frame done", err);
    if (rc == MR_OK)
        rc = exec_stmt(st, s, "mark frame done", err);
    else
        stmt_release(s);
    bool gone = rc == MR_OK && sqlite3_changes(st->db) == 0;
    if (gone)
        rc = no_job(err, id);
    pthread_mutex_unlock(&st->lock);
    if (gone) {
        /* The job was deleted while this frame was written: its delete
         * may have missed the file, so clean up here. */
        unlink(path);
        rmdir(dir);
    }
    return rc;
}

int mr_store_frame_path(mr_store *st, const char *id, size_t index, char *path, size_t path_size,
                        mr_error *err)
{
    if (!st || !path || path_size == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_frame_path: missing argument");
    path[0] = '\0';
    if (!valid_job_id(id))
        return no_job(err, id);
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

/* ---- assets ----------------------------------------------------------------- */

struct mr_asset_upload {
    int fd;
    char tmp[STORE_PATH_MAX];
    uint64_t size;
    mr_sha256 hash;
};

int mr_store_asset_upload_begin(mr_store *st, mr_asset_upload **out, mr_error *err)
{
    *out = NULL;
    mr_asset_upload *up = calloc(1, sizeof *up);
    if (!up)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory starting an upload");
    int rc = path_join(up->tmp, sizeof up->tmp, err, "%s/assets/.upload-XXXXXX", st->dir);
    if (rc < 0) {
        free(up);
        return rc;
    }
    /* A unique temporary: two uploads of the same bytes at once must not
     * write into one file. */
    up->fd = mkstemp(up->tmp);
    if (up->fd < 0) {
        rc = io_error(err, "cannot create", up->tmp, errno);
        free(up);
        return rc;
    }
    if (fchmod(up->fd, 0644) != 0) {
        rc = io_error(err, "cannot chmod", up->tmp, errno);
        mr_store_asset_upload_abort(up);
        return rc;
    }
    mr_sha256_init(&up->hash);
    *out = up;
    return MR_OK;
}

int mr_store_asset_upload_write(mr_asset_upload *up, const void *data, size_t size, mr_error *err)
{
    if (size > 0 && write_all(up->fd, data, size) != 0)
        return io_error(err, "cannot write", up->tmp, errno);
    mr_sha256_update(&up->hash, data, size);
    up->size += size;
    return MR_OK;
}

void mr_store_asset_upload_abort(mr_asset_upload *up)
{
    if (!up)
        return;
    if (up->fd >= 0) {
        close(up->fd);
        unlink(up->tmp);
    }
    free(up);
}

int mr_store_asset_upload_finish(mr_store *st, mr_asset_upload *up, char id[MR_ASSET_ID_LEN + 1],
                                 bool *existed, mr_error *err)
{
    if (existed)
        *existed = false;
    id[0] = '\0';
    uint8_t digest[32];
    char hex[MR_ASSET_ID_LEN + 1];
    mr_sha256_final(&up->hash, digest);
    mr_hex_encode(digest, sizeof digest, hex);
    uint64_t size = up->size;

    char dir[STORE_PATH_MAX], path[STORE_PATH_MAX];
    int rc;
    if ((rc = path_join(dir, sizeof dir, err, "%s/assets", st->dir)) < 0 ||
        (rc = path_join(path, sizeof path, err, "%s/%s", dir, hex)) < 0) {
        mr_store_asset_upload_abort(up);
        return rc;
    }
    /* A file of the right size under its hash is taken as complete: it
     * only ever appears there by rename after an fsync. */
    struct stat sb;
    bool present = stat(path, &sb) == 0 && S_ISREG(sb.st_mode) && (uint64_t)sb.st_size == size;
    if (present) {
        mr_store_asset_upload_abort(up);
    } else {
        rc = commit_file(up->fd, up->tmp, path, dir, NULL, 0, err); /* closes the fd */
        up->fd = -1;
        free(up);
        if (rc < 0)
            return rc;
    }

    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_ASSET_INSERT);
    rc = bind_check(st,
                    sqlite3_bind_text(s, 1, hex, -1, SQLITE_STATIC) |
                        sqlite3_bind_int64(s, 2, (sqlite3_int64)size) |
                        sqlite3_bind_double(s, 3, now_seconds()),
                    "record asset", err);
    if (rc == MR_OK)
        rc = exec_stmt(st, s, "record asset", err);
    else
        stmt_release(s);
    bool known = rc == MR_OK && sqlite3_changes(st->db) == 0;
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    if (existed)
        *existed = known;
    memcpy(id, hex, sizeof hex);
    return MR_OK;
}

int mr_store_asset_put(mr_store *st, const void *data, size_t size, char id[MR_ASSET_ID_LEN + 1],
                       bool *existed, mr_error *err)
{
    if (existed)
        *existed = false;
    if (!st || !id || (!data && size > 0))
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_asset_put: missing argument");
    id[0] = '\0';
    mr_asset_upload *up = NULL;
    int rc = mr_store_asset_upload_begin(st, &up, err);
    if (rc == MR_OK && (rc = mr_store_asset_upload_write(up, data, size, err)) < 0)
        mr_store_asset_upload_abort(up);
    else if (rc == MR_OK)
        rc = mr_store_asset_upload_finish(st, up, id, existed, err);
    return rc;
}

int mr_store_asset_path(mr_store *st, const char *id, char *path, size_t path_size, mr_error *err)
{
    if (!st || !path || path_size == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mr_store_asset_path: missing argument");
    path[0] = '\0';
    char buf[72];
    /* Only exact hashes become paths: "../x", "a/b", uppercase, short or
     * long strings never reach the file system. */
    if (!mr_hex_is_lower(id, MR_ASSET_ID_LEN))
        return mr_error_set(err, MR_ERR_NOT_FOUND, "no asset '%s' (an asset id is 64 lowercase "
                            "hex digits)", printable(id, buf));
    pthread_mutex_lock(&st->lock);
    sqlite3_stmt *s = stmt_use(st, S_ASSET_GET);
    int rc = bind_check(st, bind_text(s, 1, id), "find asset", err);
    if (rc == MR_OK) {
        int step = sqlite3_step(s);
        if (step == SQLITE_DONE)
            rc = mr_error_set(err, MR_ERR_NOT_FOUND, "no asset '%s'", id);
        else if (step != SQLITE_ROW)
            rc = db_fail(st, step, "find asset", err);
    }
    stmt_release(s);
    pthread_mutex_unlock(&st->lock);
    if (rc < 0)
        return rc;
    if ((rc = path_join(path, path_size, err, "%s/assets/%s", st->dir, id)) < 0) {
        path[0] = '\0';
        return rc;
    }
    /* A row without its file (removed by hand) is as good as unknown; an
     * upload of the same bytes writes it again. */
    if (access(path, R_OK) != 0) {
        int e = errno;
        path[0] = '\0';
        return mr_error_set(err, MR_ERR_NOT_FOUND, "asset '%s' is recorded but its file is "
                            "unreadable: %s", id, strerror(e));
    }
    return MR_OK;
}
