/*
 * store.h - the daemon's durable state: a sqlite database (WAL) of jobs,
 * frames and idempotency keys, plus content-addressed asset files and frame
 * EXR files under the data directory.
 *
 * Layout of a data directory:
 *   DIR/microray.sqlite        jobs, frames, assets (WAL mode)
 *   DIR/assets/<sha256>        uploaded model/image bytes, named by content hash
 *   DIR/frames/<job id>/NNNN.exr
 * Files are written to a temporary name, fsynced and renamed; a frame is
 * recorded as done in sqlite only after its file is complete, so after a
 * crash every frame marked done has its file and nothing half-written is
 * ever served.
 *
 * Thread safety: one connection guarded by a mutex; every function may be
 * called from any thread (HTTP threads and render workers).
 */
#ifndef MR_STORE_H
#define MR_STORE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "microray.h"

typedef struct mr_store mr_store;

typedef enum mr_job_state {
    MR_JOB_QUEUED = 0,
    MR_JOB_RUNNING,
    MR_JOB_SUCCEEDED,
    MR_JOB_FAILED,
    MR_JOB_CANCELED
} mr_job_state;

typedef enum mr_frame_state {
    MR_FRAME_PENDING = 0,
    MR_FRAME_RUNNING,
    MR_FRAME_DONE,
    MR_FRAME_FAILED
} mr_frame_state;

/* "queued", "running", ... and back; parse returns false for unknown names. */
const char *mr_job_state_name(mr_job_state s);
bool mr_job_state_parse(const char *name, mr_job_state *out);
const char *mr_frame_state_name(mr_frame_state s);

#define MR_JOB_ID_LEN 32 /* hex characters of a job id (128 random bits) */
#define MR_ASSET_ID_LEN 64 /* hex characters of a SHA-256 */

typedef struct mr_job_record {
    char id[MR_JOB_ID_LEN + 1];
    char name[257];
    mr_job_state state;
    int priority;          /* higher runs first; ties by submission order */
    int max_retries;       /* per frame */
    size_t frame_count;
    size_t frames_done, frames_failed;
    double created, started, finished; /* unix seconds; 0 = not yet */
    char error[512];       /* why it failed, or "" */
    int64_t seq;           /* submission order (1, 2, ...): list cursors */
    int64_t done_seq;      /* frames done so far, counting each once in the order they
                              were (the last frame event's id) */
} mr_job_record;

typedef struct mr_frame_record {
    size_t index;
    mr_frame_state state;
    int retries;           /* failed attempts so far */
    char error[512];
    char *stats_json;      /* per-frame stats object as JSON text, or NULL */
} mr_frame_record;

/* Opens (creating if needed) the store in data_dir. */
int mr_store_open(const char *data_dir, mr_store **out, mr_error *err);
void mr_store_close(mr_store *st);
const char *mr_store_dir(const mr_store *st);

/* Crash recovery, called once at startup. What was running when the last
 * process died was interrupted: a running frame counts a failed attempt
 * (back to pending, or failed once its attempts exceed max_retries), and a
 * running job counts an interrupted start; a job whose last max_retries + 1
 * starts were all interrupted before a frame finished fails (a poison job
 * that kills the daemon cannot kill every restart), the others go back to
 * queued and resume (done frames are kept). A graceful stop leaves nothing
 * running, so it counts nothing. Returns the number of jobs re-queued, or a
 * negative mr_err. */
int mr_store_recover(mr_store *st, mr_error *err);
/* The frames/<id> folders the last mr_store_recover found of no job in the
 * database and of no delete: left in place (the daemon says so). */
size_t mr_store_unknown_frame_dirs(const mr_store *st);

/* Creates a queued job holding the job document `json` (already validated)
 * with frame_count pending frames. With an idempotency key: if the key was
 * used before with the same body hash, *existing is set and id is that job's;
 * with a different body, MR_ERR_CONFLICT. body_hash is the SHA-256 hex of the
 * request body. */
int mr_store_job_create(mr_store *st, const char *json, size_t json_len, const char *name,
                        size_t frame_count, int priority, int max_retries,
                        const char *idempotency_key, const char *body_hash,
                        char id[MR_JOB_ID_LEN + 1], bool *existing, mr_error *err);
/* mr_store_job_create for a job that names uploaded assets by id: each is
 * recorded as used by the job (an asset in use by a queued or running job
 * is not deleted) and its last use set to now, in the same transaction;
 * MR_ERR_NOT_FOUND when one of them is not stored (any more). */
int mr_store_job_create_using(mr_store *st, const char *json, size_t json_len, const char *name,
                              size_t frame_count, int priority, int max_retries,
                              const char *idempotency_key, const char *body_hash,
                              const char *const *asset_ids, size_t asset_count,
                              char id[MR_JOB_ID_LEN + 1], bool *existing, mr_error *err);
/* MR_ERR_NOT_FOUND for unknown ids. */
int mr_store_job_get(mr_store *st, const char *id, mr_job_record *out, mr_error *err);
/* The stored job document (malloc'ed, NUL-terminated); caller frees. */
int mr_store_job_json(mr_store *st, const char *id, char **json, mr_error *err);
/* Which jobs mr_store_job_list returns. Zeroed: all of them. */
typedef struct mr_job_query {
    bool by_state;         /* only jobs in state */
    mr_job_state state;
    const char *name;      /* only jobs of this name (exactly); NULL: any */
    int64_t before;        /* only jobs submitted before the one of this seq (a
                              page's cursor); 0: from the newest */
    size_t limit;          /* at most this many; 0: no limit */
} mr_job_query;
/* The jobs q selects, newest first; *out is malloc'ed (caller frees).
 * next (may be NULL) receives the cursor of the following page (q->before
 * for it), 0 when there is none. */
int mr_store_job_list(mr_store *st, const mr_job_query *q, mr_job_record **out, size_t *count,
                      int64_t *next, mr_error *err);
/* Moves a job to a new state (sets started/finished times as fitting);
 * error may be NULL. */
int mr_store_job_set_state(mr_store *st, const char *id, mr_job_state state, const char *error,
                           mr_error *err);
/* Picks the queued job with the highest priority (oldest first among
 * equals), marks it running and returns its id; MR_ERR_NOT_FOUND if none. */
int mr_store_job_claim(mr_store *st, char id[MR_JOB_ID_LEN + 1], mr_error *err);
/* Failed frames back to pending with their retry counts reset, and the job
 * back to queued. MR_ERR_CONFLICT if the job is running or queued. Returns
 * the number of frames re-queued. */
int mr_store_job_retry(mr_store *st, const char *id, mr_error *err);
/* Removes the job's rows and its frames directory. */
int mr_store_job_delete(mr_store *st, const char *id, mr_error *err);

/* Frames of a job in index order; *out malloc'ed, free with mr_frame_records_free. */
int mr_store_frames(mr_store *st, const char *id, mr_frame_record **out, size_t *count,
                    mr_error *err);
void mr_frame_records_free(mr_frame_record *frames, size_t count);
/* One frame of a job (free out->stats_json); MR_ERR_NOT_FOUND for unknown
 * jobs and indices outside the job. */
int mr_store_frame_get(mr_store *st, const char *id, size_t index, mr_frame_record *out,
                       mr_error *err);
int mr_store_frame_set_running(mr_store *st, const char *id, size_t index, mr_error *err);
/* The job's render ended: frames still marked running (a cancel killed
 * the worker mid-frame, say) go back to pending without counting a failed
 * attempt. Returns how many, or a negative mr_err. */
int mr_store_frames_release(mr_store *st, const char *id, mr_error *err);
/* Records a finished frame: its EXR bytes are written to
 * DIR/frames/<id>/NNNN.exr (temporary name, fsync, rename) and only then is
 * the row marked done with stats_json. */
int mr_store_frame_done(mr_store *st, const char *id, size_t index, const void *exr,
                        size_t exr_size, const char *stats_json, mr_error *err);
/* A frame that could not be stored for want of space goes back to
 * pending without counting an attempt: the render was fine, the disk
 * was full (the queue pauses until space is back). */
int mr_store_frame_requeue(mr_store *st, const char *id, size_t index, const char *error, mr_error *err);
/* Records a failed attempt: retries + 1; the frame goes back to pending
 * while retries <= max_retries, else to failed. A final failure (one that
 * would repeat: a limit, an invalid input) fails the frame at once.
 * *gave_up tells which. */
int mr_store_frame_failed(mr_store *st, const char *id, size_t index, const char *error,
                          bool final, bool *gave_up, mr_error *err);
/* Where a frame's EXR file is when it is done, whatever its state (one
 * path, no query: for listing many frames at once). */
int mr_store_frame_file(const mr_store *st, const char *id, size_t index, char *path, size_t size,
                        mr_error *err);
/* A frame done, in the order frames were (for event streams that resume). */
typedef struct mr_frame_done_record {
    size_t index;
    int64_t done_seq;      /* the job's done_seq right after it */
    char *stats_json;      /* malloc'ed, may be NULL */
} mr_frame_done_record;
/* The job's frames done after sequence after (a Last-Event-ID), at most
 * limit, in the order they were done. Free with mr_frame_done_records_free. */
int mr_store_frames_after(mr_store *st, const char *id, int64_t after, size_t limit,
                          mr_frame_done_record **out, size_t *count, mr_error *err);
void mr_frame_done_records_free(mr_frame_done_record *f, size_t count);
/* Path of a done frame's EXR file; MR_ERR_NOT_FOUND unless the frame is done. */
int mr_store_frame_path(mr_store *st, const char *id, size_t index, char *path, size_t path_size,
                        mr_error *err);

/* Stores bytes as an asset named by their SHA-256 (deduplicated: storing the
 * same bytes again only reports *existed). */
int mr_store_asset_put(mr_store *st, const void *data, size_t size, char id[MR_ASSET_ID_LEN + 1],
                       bool *existed, mr_error *err);
/* The same, streamed: an upload is written to a temporary file in the
 * assets directory and hashed as it arrives, so its bytes are never held in
 * memory; finish renames it under its hash (or drops it when those bytes are
 * already stored) and records it. finish and abort free the upload. */
typedef struct mr_asset_upload mr_asset_upload;
int mr_store_asset_upload_begin(mr_store *st, mr_asset_upload **out, mr_error *err);
int mr_store_asset_upload_write(mr_asset_upload *up, const void *data, size_t size, mr_error *err);
int mr_store_asset_upload_finish(mr_store *st, mr_asset_upload *up, char id[MR_ASSET_ID_LEN + 1],
                                 bool *existed, mr_error *err);
void mr_store_asset_upload_abort(mr_asset_upload *up);

/* An uploaded asset as listed. */
typedef struct mr_asset_record {
    char id[MR_ASSET_ID_LEN + 1];
    uint64_t size;
    double created;        /* first stored, unix seconds */
    double last_used;      /* last named by a submitted job; 0: never */
    size_t jobs_active;    /* queued and running jobs that use it */
    int64_t seq;           /* list cursor */
} mr_asset_record;
/* MR_ERR_NOT_FOUND for unknown ids. */
int mr_store_asset_get(mr_store *st, const char *id, mr_asset_record *out, mr_error *err);
/* Assets newest first, at most limit (0: all) of those stored before the
 * one of seq before (0: from the newest); *next is the cursor of the
 * following page, 0 when there is none. *out is malloc'ed. */
int mr_store_asset_list(mr_store *st, int64_t before, size_t limit, mr_asset_record **out,
                        size_t *count, int64_t *next, mr_error *err);
/* Removes an asset's row and file; MR_ERR_CONFLICT while a queued or
 * running job uses it, MR_ERR_NOT_FOUND when unknown. */
int mr_store_asset_delete(mr_store *st, const char *id, mr_error *err);

/* Path of a stored asset; MR_ERR_NOT_FOUND for unknown ids (also for
 * strings that are not 64 lowercase hex digits). */
int mr_store_asset_path(mr_store *st, const char *id, char *path, size_t path_size,
                        mr_error *err);

/* Frames still to render (pending or running, of queued or running jobs):
 * the queue's depth in frames, for /metrics. */
int mr_store_queue_frames(mr_store *st, uint64_t *frames, mr_error *err);
/* Counts of jobs per state (for /metrics), indexed by mr_job_state. */
int mr_store_job_counts(mr_store *st, uint64_t counts[5], mr_error *err);

#endif
