/*
 * worker.h - renders one job from start to finish: import its assets, build a
 * renderer, render every frame and hand each finished frame to a sink.
 *
 * The one-shot command and the daemon share this code; only where jobs come
 * from and where frames go differ (the sink).
 */
#ifndef MR_WORKER_H
#define MR_WORKER_H

#include "job.h"
#include "render/device.h"
#include "render/renderer.h"

struct mr_job_stats;

typedef struct mr_frame_sink {
    void *user;
    /* Called once per finished frame, in frame order. Encodes/stores the
     * frame and fills stats->encode_s (the worker adds it to total_s). */
    int (*frame_done)(void *user, size_t index, const mr_film *film, mr_frame_stats *stats,
                      mr_error *err);
    /* Called after frame_done with the job's statistics so far (the frame's
     * totals now include encoding); may be NULL. Progress lines, stats.json. */
    void (*progress)(void *user, size_t index, const struct mr_job_stats *stats);
    /* Polled between frames; may be NULL. */
    bool (*cancelled)(void *user);
} mr_frame_sink;

/* File name of frame `index` within a job's output ("0007.exr"). */
#define MR_FRAME_NAME_MAX 32
void mr_frame_file_name(size_t index, char name[MR_FRAME_NAME_MAX]);

typedef struct mr_job_stats {
    size_t frame_count;      /* one past the last frame finished */
    mr_frame_stats *frames;  /* job->frame_count entries */
    double load_s;           /* asset import */
    unsigned threads;
} mr_job_stats;

/* Loads job->assets[i].path for every asset (paths must already be resolved
 * by the caller), renders frames [first, job->frame_count) and calls the sink
 * for each. stats->frames is allocated here; free with mr_job_stats_free. */
int mr_worker_run(mr_device *dev, const mr_job *job, size_t first, const mr_frame_sink *sink,
                  mr_job_stats *stats, mr_error *err);
void mr_job_stats_free(mr_job_stats *stats);

#endif
