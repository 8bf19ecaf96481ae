/*
 * store_internal.h - what the parts of the store share, and only they
 * (server/store*.c):
 *   store.c         the database: schema and migration, every statement
 *                   (prepared once at open), sqlite plumbing, the data
 *                   directory and its file writes, recovery after a crash;
 *   store_jobs.c    jobs: create (with idempotency keys), read, list, state
 *                   changes, claim, retry, delete, counts;
 *   store_frames.c  frames: rows, their EXR files, retries;
 *   store_assets.c  content-addressed assets and streamed uploads.
 * Durability and locking rules are written at the head of store.c. Every
 * *_locked function expects st->lock held.
 */
#ifndef MR_STORE_INTERNAL_H
#define MR_STORE_INTERNAL_H

#include <pthread.h>
#include <sqlite3.h>

#include "store.h"

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
    S_JOB_QUERY,
    S_JOB_JSON,
    S_JOB_STATE,
    S_JOB_SET_STATE,
    S_CLAIM_PICK,
    S_JOB_COUNTS,
    S_QUEUE_FRAMES,
    S_RECOVER_FRAMES,
    S_RECOVER_GIVE_UP,
    S_RECOVER_JOBS,
    S_RETRY_FRAMES,
    S_JOB_REQUEUE,
    S_DEL_IDEM,
    S_DEL_FRAMES,
    S_DEL_JOB,
    S_TOMBSTONE_ADD,
    S_TOMBSTONE_DROP,
    S_TOMBSTONES,
    S_FRAMES_LIST,
    S_FRAME_ROW,
    S_FRAME_GET,
    S_FRAME_SET,
    S_FRAME_SET_RUNNING,
    S_FRAMES_RELEASE,
    S_FRAME_DONE,
    S_JOB_PROGRESS,
    S_ASSET_INSERT,
    S_ASSET_GET,
    S_ASSET_ROW,
    S_ASSET_LIST,
    S_ASSET_USE,
    S_ASSET_TOUCH,
    S_ASSET_ACTIVE,
    S_ASSET_DELETE,
    S_FRAMES_AFTER,
    S_COUNT
};

struct mr_store {
    pthread_mutex_t lock;
    sqlite3 *db;
    sqlite3_stmt *stmt[S_COUNT];
    char dir[STORE_PATH_MAX];
    size_t unknown_frame_dirs; /* frames/<id> folders of no job and no delete (mr_store_recover) */
};


/* ---- small helpers (store.c) ------------------------------------------ */

/* Wall-clock time, unix seconds (a job's created/started/finished). */
double store_now(void);
/* Ids reach the store straight from URLs; only well-formed ones are ever
 * looked up or turned into paths. */
bool store_valid_job_id(const char *id);
/* A caller's string made safe for a message: printable ASCII, at most 64
 * characters (out has 72 bytes). */
const char *store_printable(const char *s, char out[72]);
/* MR_ERR_NOT_FOUND "no job '<id>'". */
int store_no_job(mr_error *err, const char *id);
/* Takes deleted job id off deleted_jobs once its frame folder dir is gone
 * (NULL: at once); while the folder is there it stays listed, and the next
 * start removes it. Takes the lock: the caller does not hold it. */
void store_forget_deleted(mr_store *st, const char *id, const char *dir);
/* MR_ERR_IO "<what> '<path>': <strerror(e)>". */
int store_io_error(mr_error *err, const char *what, const char *path, int e);
/* printf into a path buffer; MR_ERR_INVALID when it does not fit. */
int store_path_join(char *out, size_t size, mr_error *err, const char *fmt, ...)
    __attribute__((format(printf, 4, 5)));
/* Copies a text column, cut to fit (names are capped when stored). */
void store_copy_col(char *dst, size_t size, sqlite3_stmt *s, int col);

/* ---- sqlite plumbing (store.c) ---------------------------------------- */

/* The message of the connection's last failure, with the mr_err that fits
 * the sqlite code; read it before any other call on the connection. */
int store_db_fail(mr_store *st, int sqlite_rc, const char *what, mr_error *err);
/* A statement ready for binding; released with store_stmt_release(). */
sqlite3_stmt *store_stmt(mr_store *st, enum stmt_id id);
void store_stmt_release(sqlite3_stmt *s);
/* Steps a statement that returns no rows, then releases it. */
int store_exec(mr_store *st, sqlite3_stmt *s, const char *what, mr_error *err);
/* Checks bind results: all of them are SQLITE_OK or the first failure. */
int store_bind_check(mr_store *st, int rc, const char *what, mr_error *err);
/* store_exec of a statement just bound: bind_rc is the OR of the bind
 * calls' results (SQLITE_OK is 0); a failed bind releases the statement
 * and names what. */
int store_exec_bound(mr_store *st, sqlite3_stmt *s, int bind_rc, const char *what, mr_error *err);
/* Steps s, just bound (bind_rc as for store_exec_bound), for a single
 * row: 1 when s stands on it (read the columns, then release s), 0 when
 * there is none, or a negative mr_err naming what. */
int store_step_row(mr_store *st, sqlite3_stmt *s, int bind_rc, const char *what, mr_error *err);
/* A growing array of rows read from a statement. */
typedef struct store_rows {
    void *items;           /* count rows of elem bytes, room for cap */
    size_t count, cap;
    size_t elem;
    size_t first_cap;      /* rows of the first allocation when cap is 0 */
    int (*read)(sqlite3_stmt *s, void *row, mr_error *err); /* fills one row */
} store_rows;
/* Steps s, just bound (bind_rc: the OR of the bind results), through all
 * its rows into rows (doubling its room as needed), then releases s. Rows
 * read before a failure stay counted for the caller to free. Messages say
 * "list <what>". */
int store_read_rows(mr_store *st, sqlite3_stmt *s, int bind_rc, store_rows *rows, const char *what,
                    mr_error *err);
/* Binds text, or NULL for a NULL t. */
int store_bind_text(sqlite3_stmt *s, int i, const char *t);
int store_tx_begin(mr_store *st, mr_error *err);
int store_tx_commit(mr_store *st, mr_error *err);
/* Rolls back what is still open (sqlite may have rolled back already). */
void store_tx_rollback(mr_store *st);
/* Ends the transaction of a function that took st->lock and began one:
 * commits when rc >= 0 (then returns rc, or the commit's failure), rolls
 * back when rc < 0 or the commit failed, and unlocks. */
int store_tx_end(mr_store *st, int rc, mr_error *err);

/* ---- job lookups (store_jobs.c) --------------------------------------- */

/* A job's state (and frame count, if frames is not NULL); MR_ERR_NOT_FOUND
 * if it does not exist. */
int store_job_lookup_locked(mr_store *st, const char *id, mr_job_state *state, size_t *frames,
                            mr_error *err);
int store_job_state_locked(mr_store *st, const char *id, mr_job_state *state, mr_error *err);

#endif
