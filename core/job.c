/*
 * job.c - lifetime of mr_job: the one place that knows what a job owns.
 *
 * The parser builds jobs from zeroed allocations and sets counts as soon as
 * arrays exist, so mr_job_free() must (and does) accept any partially built
 * job: NULL strings and arrays are skipped. A kind's parameters are released
 * through its parameter table (kinds/params.h), so no kind is named here.
 */
#include "job.h"

#include "kinds/kind.h"

#include <stdlib.h>

static void object_desc_clear(mr_object_desc *o)
{
    free(o->name);
    if (o->poses)
        for (size_t i = 0; i < o->pose_count; i++)
            mr_pose_desc_clear(&o->poses[i]);
    free(o->poses);
    if (o->params && o->kind && o->kind->params)
        mr_params_clear(o->kind->params, o->params);
    free(o->params);
}

void mr_job_free(mr_job *job)
{
    if (!job)
        return;
    free(job->name);
    free(job->notify);
    if (job->assets)
        for (size_t i = 0; i < job->asset_count; i++) {
            free(job->assets[i].name);
            free(job->assets[i].path);
            free(job->assets[i].id);
        }
    free(job->assets);
    if (job->objects)
        for (size_t i = 0; i < job->object_count; i++)
            object_desc_clear(&job->objects[i]);
    free(job->objects);
    free(job->lights);
    free(job->camera.path.keys);
    free(job->camera.node_name);
    free(job->frame_times);
    free(job);
}

int mr_output_crypto_ranks(const mr_output_desc *out)
{
    if (!(out->aovs & MR_AOV_CRYPTOMATTE))
        return 0;
    int ranks = out->spp < MR_CRYPTO_MAX_RANKS ? out->spp : MR_CRYPTO_MAX_RANKS;
    return ranks + (ranks & 1);
}

int mr_job_film_new(const mr_job *job, mr_film **out, mr_error *err)
{
    return mr_film_new_aovs(job->output.width, job->output.height,
                            job->output.aovs ? job->output.aovs : MR_AOV_DEFAULT,
                            mr_output_crypto_ranks(&job->output), out, err);
}

bool mr_job_has_reference(const mr_job *job)
{
    for (size_t i = 0; job && i < job->object_count; i++)
        if (job->objects[i].reference)
            return true;
    return false;
}
