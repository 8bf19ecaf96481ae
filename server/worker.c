/* worker.c - one job, all frames (worker.h). */
#include "worker.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"

int mr_worker_run(mr_device *dev, const mr_job *job, size_t first, const mr_frame_sink *sink,
                  mr_job_stats *stats, mr_error *err)
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
        if ((rc = mr_asset_load(job->assets[i].path, &assets[i], err)) < 0) {
            mr_error_prefix(err, "/assets/%s/path: ", job->assets[i].name);
            goto done;
        }
    }
    stats->load_s = mr_now() - t0;

    if ((rc = mr_renderer_new(dev, job, assets, NULL, &renderer, err)) < 0)
        goto done;
    if ((rc = mr_film_new(job->output.width, job->output.height, &film, err)) < 0)
        goto done;

    for (size_t f = first; f < job->frame_count; f++) {
        if (sink->cancelled && sink->cancelled(sink->user)) {
            rc = mr_error_set(err, MR_ERR_CANCELLED, "cancelled before frame %zu", f);
            goto done;
        }
        mr_frame_stats *st = &stats->frames[f];
        if ((rc = mr_renderer_render(renderer, f, film, st, err)) < 0)
            goto done;
        if (f == first) {
            st->load_s = stats->load_s;
            st->total_s += stats->load_s;
        }
        if ((rc = sink->frame_done(sink->user, f, film, st, err)) < 0)
            goto done;
        st->total_s += st->encode_s;
        stats->frame_count = f + 1;
        if (sink->progress)
            sink->progress(sink->user, f, stats);
    }
done:
    mr_film_free(film);
    mr_renderer_free(renderer);
    if (assets)
        for (size_t i = 0; i < job->asset_count; i++)
            mr_asset_free(assets[i]);
    free(assets);
    return rc;
}

void mr_frame_file_name(size_t index, char name[MR_FRAME_NAME_MAX])
{
    snprintf(name, MR_FRAME_NAME_MAX, "%04zu.exr", index);
}

void mr_job_stats_free(mr_job_stats *stats)
{
    if (!stats)
        return;
    free(stats->frames);
    memset(stats, 0, sizeof *stats);
}
