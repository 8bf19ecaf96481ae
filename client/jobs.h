/*
 * jobs.h - the client commands that follow a job and download its results:
 * `submit --wait [--out DIR]` and `fetch ID --out DIR`.
 *
 * Following prefers the job's event stream (GET /v1/jobs/{id}/events) and
 * falls back to polling GET /v1/jobs/{id} every 0.5 s when the stream
 * cannot be opened or breaks. Frames are downloaded as they finish (and
 * once more at the end for any that were missed) to DIR/NNNN.exr, each
 * written to a temporary name and renamed, then DIR/stats.json. With png,
 * DIR/NNNN.png (the daemon's previews) instead of the EXRs, and
 * DIR/contact-sheet.png at the end.
 */
#ifndef MRC_JOBS_H
#define MRC_JOBS_H

#include "api.h"

typedef struct mrc_follow_opts {
    const char *out_dir; /* NULL: do not download */
    bool quiet;          /* no progress output */
    bool tty;            /* draw a bar instead of lines */
    bool png;            /* PNG previews (NNNN.png, contact-sheet.png) instead of EXRs */
} mrc_follow_opts;

/* Follows job `id` until it succeeds (0), fails or is canceled
 * (-MRC_EXIT_JOB_FAILED), or following itself fails (other negatives). */
int mrc_job_wait(mrc_http *h, const char *id, const mrc_follow_opts *opts, mrc_error *err);

/* What a fetch did. */
typedef struct mrc_fetch_result {
    char state[16];      /* the job's, as seen */
    int fetched;         /* frames downloaded */
    int64_t bytes;
    int done, total;     /* the job's frames done and in all */
} mrc_fetch_result;

/* Downloads every frame that is done, and stats.json when there is one,
 * into opts->out_dir, whatever the job's state. out (may be NULL) says
 * what came. */
int mrc_job_fetch(mrc_http *h, const char *id, const mrc_follow_opts *opts, mrc_fetch_result *out,
                  mrc_error *err);

#endif
