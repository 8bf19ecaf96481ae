/*
 * job.c - lifetime of mr_job: the one place that knows what a job owns.
 *
 * The parser builds jobs from zeroed allocations and sets counts as soon as
 * arrays exist, so mr_job_free() must (and does) accept any partially built
 * job: NULL strings and arrays are skipped.
 */
#include "job.h"

#include <stdlib.h>

static void pose_desc_clear(mr_pose_desc *p)
{
    free(p->clip_name);
    if (p->joints)
        for (size_t i = 0; i < p->joint_count; i++)
            free(p->joints[i].joint);
    free(p->joints);
}

static void object_desc_clear(mr_object_desc *o)
{
    free(o->name);
    if (o->poses)
        for (size_t i = 0; i < o->pose_count; i++)
            pose_desc_clear(&o->poses[i]);
    free(o->poses);
    if (o->svo.instances)
        for (size_t i = 0; i < o->svo.instance_count; i++)
            pose_desc_clear(&o->svo.instances[i].pose);
    free(o->svo.instances);
}

void mr_job_free(mr_job *job)
{
    if (!job)
        return;
    free(job->name);
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
