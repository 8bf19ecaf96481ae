/* worker.c - one job, its wanted frames (worker.h). */
#include "worker.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "microray.h"
#include "cache.h"

/* Without a cache, the import the cache would do on a miss (refinement
 * included). */
static int acquire(const mr_worker_io *io, const mr_asset_desc *d, mr_asset **out, bool *hit,
                   double *saved_s, mr_asset_stage *stage, mr_error *err)
{
    *stage = MR_ASSET_STAGE_LOAD;
    if (io->acquire_asset)
        return io->acquire_asset(io->user, d, out, hit, saved_s, stage, err);
    *hit = false;
    *saved_s = 0;
    return mr_cache_import(d->path, d->refine ? &d->refine_params : NULL, out, stage, err);
}

static void release(const mr_worker_io *io, mr_asset *a)
{
    if (io->release_asset)
        io->release_asset(io->user, a);
    else
        mr_asset_free(a);
}

int mr_worker_run(mr_device *dev, const mr_job *job, const mr_worker_io *io, mr_job_stats *stats,
                  mr_error *err)
{
    int rc = MR_OK;
    mr_asset **assets = NULL;
    mr_renderer *renderer = NULL;
    mr_film *film = NULL;

    memset(stats, 0, sizeof *stats);
    stats->threads = mr_device_threads(dev);
    stats->frames = calloc(job->frame_count, sizeof *stats->frames);
    assets = calloc(job->asset_count, sizeof *assets);
    if (!stats->frames || !assets) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory starting the job");
        goto done;
    }

    double t0 = mr_now();
    for (size_t i = 0; i < job->asset_count; i++) {
        bool hit;
        double saved;
        mr_asset_stage stage;
        /* Refinement runs on the job's threads, like its frames. */
        mr_asset_desc d = job->assets[i];
        d.refine_params.threads = stats->threads;
        if ((rc = acquire(io, &d, &assets[i], &hit, &saved, &stage, err)) < 0) {
            mr_error_prefix(err, "/assets/%s/%s: ", d.name,
                            stage == MR_ASSET_STAGE_REFINE ? "refine" : d.id ? "id" : "path");
            goto done;
        }
        stats->assets_cached += hit;
        stats->assets_loaded += !hit;
        stats->load_saved_s += saved;
    }
    stats->load_s = mr_now() - t0;

    mr_renderer_options opt = {.cancel = io->cancel, .cache_dir = io->cache_dir,
                               .memory_budget = io->memory_budget};
    t0 = mr_now();
    if ((rc = mr_renderer_new(dev, job, assets, &opt, &renderer, err)) < 0)
        goto done;
    stats->derive_s = mr_now() - t0;
    if ((rc = mr_job_film_new(job, &film, err)) < 0)
        goto done;

    bool first = true;
    for (size_t f = 0; f < job->frame_count; f++) {
        if (io->wanted && !io->wanted(io->user, f))
            continue;
        if (io->stop_requested && io->stop_requested(io->user)) {
            rc = mr_error_set(err, MR_ERR_CANCELLED, "stopped before frame %zu", f);
            goto done;
        }
        if (io->frame_started)
            io->frame_started(io->user, f);
        mr_frame_stats *st = &stats->frames[f];
        rc = mr_renderer_render(renderer, f, film, st, err);
        if (rc == MR_OK) {
            if (first) {
                st->load_s = stats->load_s;
                st->assets_cached = stats->assets_cached;
                st->assets_loaded = stats->assets_loaded;
                st->load_saved_s = stats->load_saved_s;
                st->derive_s = stats->derive_s;
                st->total_s += stats->load_s + stats->derive_s;
            }
            rc = io->frame_done(io->user, f, film, st, err);
        }
        if (rc == MR_ERR_CANCELLED)
            goto done;
        if (rc < 0) {
            mr_frame_decision d = io->frame_failed ? io->frame_failed(io->user, f, err) : MR_FRAME_ABORT;
            if (d == MR_FRAME_ABORT)
                goto done;
            rc = MR_OK;
            if (d == MR_FRAME_RETRY)
                f--; /* the loop's f++ brings us back to this frame */
            continue;
        }
        first = false;
        st->total_s += st->encode_s;
        stats->frame_count = f + 1;
        if (io->progress)
            io->progress(io->user, f, stats);
    }
done:
    mr_film_free(film);
    mr_renderer_free(renderer);
    if (assets)
        for (size_t i = 0; i < job->asset_count; i++)
            if (assets[i])
                release(io, assets[i]);
    free(assets);
    return rc;
}

void mr_frame_file_name(size_t index, char name[MR_FRAME_NAME_MAX])
{
    snprintf(name, MR_FRAME_NAME_MAX, "%04zu.exr", index);
}

void mr_frame_preview_name(size_t index, char name[MR_FRAME_NAME_MAX])
{
    snprintf(name, MR_FRAME_NAME_MAX, "%04zu.png", index);
}

void mr_job_stats_free(mr_job_stats *stats)
{
    if (!stats)
        return;
    free(stats->frames);
    memset(stats, 0, sizeof *stats);
}
