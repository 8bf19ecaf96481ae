/*
 * render_proc.h - renders in worker processes, so that no job can take the
 * daemon down with it (issue 12).
 *
 * Each of the daemon's render slots (--workers) keeps one render worker
 * process: a fresh `microrayd render-worker` image (child.h) with its own
 * Embree device and its own scene cache (--cache-mb each), which lives
 * from job to job so that a warm cache stays warm. The worker imports (each
 * import in a child of its own, import_worker.h), derives data (bakes,
 * voxelisations, into DATA/<kind>/) and renders and encodes every frame;
 * the daemon keeps everything durable: it stores each frame the worker
 * sends, records failures, decides retries and publishes events. Only the
 * daemon touches the sqlite store and the frames folder.
 *
 * A worker that dies (a crash, the kernel's OOM killer, its memory limit)
 * ends only its current attempt: a frame in progress counts one failed
 * attempt with an error that says how the worker ended ("the render worker
 * was killed by SIGSEGV while rendering frame 7"), and the job goes on in
 * a new worker from the frames still wanted (a kind whose frames depend on
 * earlier ones is replayed by the renderer, so the frames are those of an
 * uninterrupted run). A death while the job is being prepared (import,
 * derived data, scene set-up) fails the job. A cancel kills the worker at
 * once; a stop (SIGTERM, a full disk) lets the frame in progress finish.
 */
#ifndef MR_RENDER_PROC_H
#define MR_RENDER_PROC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "cache.h"
#include "microray.h"
#include "worker.h"

typedef struct mr_render_proc_config {
    const char *exe;          /* the microrayd binary run as `render-worker` */
    unsigned threads;         /* render threads (0: all cores) */
    size_t cache_bytes;       /* the worker's scene cache */
    const char *data_dir;     /* derived data is kept in data_dir/<kind>/ */
    const char *const *asset_roots; /* what the worker may read besides DATA/assets (sandbox.h) */
    size_t root_count;
    size_t job_memory;        /* mr_renderer_options.memory_budget */
    size_t import_memory;     /* mr_import_limits of the worker's imports */
    double import_timeout_s;
    size_t memory_limit;      /* the worker's resident memory at which it is killed; 0: none */
    double frame_timeout_s;   /* a frame, or the preparation of a job, that takes longer is
                                 killed and fails as over a limit; 0: none */
    int nice;                 /* CPU niceness of the worker */
} mr_render_proc_config;

/* The resident memory a worker may reach: the job's geometry, the scene
 * cache, and 1 GiB for everything else (libraries, Embree's scene, films,
 * encoded frames). */
size_t mr_render_proc_memory_limit(size_t job_memory, size_t cache_bytes);

typedef struct mr_render_proc mr_render_proc;

/* A render slot, without a worker yet. cfg's strings are borrowed. */
int mr_render_proc_new(const mr_render_proc_config *cfg, mr_render_proc **out, mr_error *err);
/* Starts the slot's worker process if it has none, and waits for it to say
 * hello (mr_render_proc_run does the same when it needs one). */
int mr_render_proc_start(mr_render_proc *p, mr_error *err);
/* Ends the worker (its channel closes; killed if it has not exited after
 * a few seconds) and frees the slot. */
void mr_render_proc_free(mr_render_proc *p);

/* One job's conversation, from the daemon's side. */
typedef struct mr_render_session {
    void *user;
    const char *job_id;
    const char *job_json;       /* the job as submitted */
    size_t job_json_len;
    const char *const *paths;   /* resolved path of each of the job's assets */
    size_t path_count;
    uint8_t *wanted;            /* per frame: 1 = render; frames finished or given up
                                   are set to 0 here as the job goes on */
    size_t frame_count;
    /* A frame is being rendered. */
    void (*frame_started)(void *user, size_t index);
    /* A frame arrived: store it (its stats JSON and EXR file). A failure is
     * handed to frame_failed by the caller of this function, not here. */
    int (*frame_done)(void *user, size_t index, const char *stats_json, const uint8_t *exr,
                      size_t exr_size, mr_error *err);
    /* A frame failed (or could not be stored): retry, skip or abort. */
    mr_frame_decision (*frame_failed)(void *user, size_t index, const mr_error *err);
    /* Polled: end the job after the frame in progress (and at once while
     * it is being prepared). */
    bool (*stop_requested)(void *user);
    /* Polled every 50 ms: kill the worker at once. */
    bool (*cancelled)(void *user);
} mr_render_session;

/* Renders the session's wanted frames in p's worker (started if there is
 * none). Returns MR_OK when every wanted frame was stored or given up,
 * MR_ERR_CANCELLED when cancelled or stopped, or the error that ended the
 * job (the worker's, or how it died while preparing the job). */
int mr_render_proc_run(mr_render_proc *p, const mr_render_session *s, mr_error *err);

/* The scene-cache figures of the slot's workers: hits, misses, evictions
 * and saved seconds summed over every worker it had, bytes and entries of
 * the current one (as of its last job). */
void mr_render_proc_cache_stats(mr_render_proc *p, mr_cache_stats *out);
/* The current worker's pid, 0 if none (tests kill it). */
int mr_render_proc_pid(mr_render_proc *p);

/* The worker's side: `microrayd render-worker --threads N --cache-bytes N
 * --data DIR --job-memory N --import-memory N --import-timeout S
 * --import-exe PATH [--asset-root DIR]...`, run only by mr_render_proc on
 * descriptor 3. Once started it confines itself (sandbox.h). */
int mr_cmd_render_worker(int argc, char **argv);

#endif
