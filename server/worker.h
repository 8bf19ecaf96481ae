/*
 * worker.h - renders one job: import (or borrow from a cache) its assets,
 * build a renderer, render the wanted frames and hand each finished frame to
 * a sink.
 *
 * The one-shot command and the daemon share this code; only where jobs come
 * from, where assets come from and where frames go differ (mr_worker_io).
 */
#ifndef MR_WORKER_H
#define MR_WORKER_H

#include <stdatomic.h>

#include "cache.h"
#include "microray.h"

struct mr_job_stats;

/* What a frame failure should lead to (mr_worker_io.frame_failed). */
typedef enum mr_frame_decision { MR_FRAME_RETRY, MR_FRAME_SKIP, MR_FRAME_ABORT } mr_frame_decision;

typedef struct mr_worker_io {
    void *user;
    /* Called once per finished frame, in frame order. Encodes/stores the
     * frame and fills stats->encode_s (the worker adds it to total_s). */
    int (*frame_done)(void *user, size_t index, const mr_film *film, mr_frame_stats *stats,
                      mr_error *err);
    /* After frame_done, with the job's statistics so far; may be NULL. */
    void (*progress)(void *user, size_t index, const struct mr_job_stats *stats);
    /* Whether to render frame `index` (NULL: all); the daemon skips frames
     * already done before a restart. */
    bool (*wanted)(void *user, size_t index);
    /* Called before a frame is rendered; may be NULL. */
    void (*frame_started)(void *user, size_t index);
    /* A frame failed (err says why): retry it, skip it, or abort the job.
     * NULL: abort (the one-shot renderer's behaviour). */
    mr_frame_decision (*frame_failed)(void *user, size_t index, const mr_error *err);
    /* Polled between frames: stop after the frame in progress; may be NULL. */
    bool (*stop_requested)(void *user);
    /* Stops a frame in progress within one tile; may be NULL. */
    const atomic_bool *cancel;
    /* Where assets come from. NULL: mr_cache_import / mr_asset_free. With a
     * cache, *hit and *saved_s report whether the import was avoided. On
     * failure *stage says which step failed (cache.h): the worker points
     * the error at the asset's "path" or "id", or at its "refine". */
    int (*acquire_asset)(void *user, const mr_asset_desc *desc, mr_asset **out, bool *hit,
                         double *saved_s, mr_asset_stage *stage, mr_error *err);
    void (*release_asset)(void *user, mr_asset *asset);
    /* Root of the derived-data cache (mr_renderer_options.cache_dir), or NULL. */
    const char *cache_dir;
    /* mr_renderer_options.memory_budget (0: none). */
    size_t memory_budget;
} mr_worker_io;

/* File name of frame `index` within a job's output ("0007.exr"), and of
 * its PNG preview ("0007.png"). */
#define MR_FRAME_NAME_MAX 32
void mr_frame_file_name(size_t index, char name[MR_FRAME_NAME_MAX]);
void mr_frame_preview_name(size_t index, char name[MR_FRAME_NAME_MAX]);

typedef struct mr_job_stats {
    size_t frame_count;      /* one past the last frame finished */
    mr_frame_stats *frames;  /* job->frame_count entries */
    double load_s;           /* asset import (or cache lookup) */
    unsigned assets_cached;  /* assets that came from the cache */
    unsigned assets_loaded;  /* assets imported for this job */
    double load_saved_s;     /* import seconds the cache saved */
    double derive_s;         /* the renderer's set-up: derived data built or read */
    unsigned threads;
} mr_job_stats;

/* Renders the wanted frames of job (asset paths must already be resolved).
 * Returns MR_ERR_CANCELLED when cancelled or stopped. stats->frames is
 * allocated here; free with mr_job_stats_free. */
int mr_worker_run(mr_device *dev, const mr_job *job, const mr_worker_io *io, mr_job_stats *stats,
                  mr_error *err);
void mr_job_stats_free(mr_job_stats *stats);

#endif
