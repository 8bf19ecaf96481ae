/* reference.c - the jobs of a job's reference passes (reference.h). */
#include "render/reference.h"

#include <string.h>

/* Appends what pass `type` draws for object o: its kind's reference of
 * that type; *declared: the kind has one. A kind without the op is its own
 * tessellation and has no ground truth. */
static int kind_reference(const mr_object_desc *o, mr_reference_type type,
                          mr_reference_objects *out, bool *declared, mr_error *err)
{
    size_t before = out->count;
    int rc = MR_OK;
    if (o->kind->reference)
        rc = o->kind->reference(o, type, out, err);
    else if (type == MR_REFERENCE_TESSELLATED)
        rc = mr_reference_objects_add(out, o, err);
    *declared = out->count > before;
    return rc;
}

int mr_reference_pass_init(const mr_job *job, mr_reference_type type, mr_reference_pass *out,
                           bool *present, mr_error *err)
{
    memset(out, 0, sizeof *out);
    *present = false;
    out->type = type;
    int rc = MR_OK;
    for (size_t i = 0; i < job->object_count && rc == MR_OK; i++) {
        const mr_object_desc *o = &job->objects[i];
        size_t first = out->objects.count;
        bool declared = false;
        if (o->reference) {
            rc = kind_reference(o, type, &out->objects, &declared, err);
            *present |= declared;
            /* no ground truth: its tessellation; no tessellation: as it is */
            if (rc == MR_OK && !declared && type == MR_REFERENCE_GROUND_TRUTH)
                rc = kind_reference(o, MR_REFERENCE_TESSELLATED, &out->objects, &declared, err);
        }
        if (rc == MR_OK && !declared)
            rc = mr_reference_objects_add(&out->objects, o, err);
        if (rc < 0)
            mr_error_prefix(err, "/objects/%zu: %s reference: ", i, mr_reference_name(type));
        /* a reference is drawn at full detail, but the tessellated pass
         * draws an object at the level it chose itself */
        for (size_t k = first; k < out->objects.count; k++) {
            out->objects.objects[k].reference = false;
            if (type == MR_REFERENCE_GROUND_TRUTH)
                out->objects.objects[k].tolerance_px = 0;
        }
    }
    if (rc < 0 || !*present) {
        mr_reference_pass_clear(out);
        *present = false;
        return rc;
    }
    out->job = *job;
    out->job.objects = out->objects.objects;
    out->job.object_count = out->objects.count;
    out->job.reference = false;
    out->job.output.aovs = MR_AOV_REFERENCE;
    return MR_OK;
}

void mr_reference_pass_clear(mr_reference_pass *p)
{
    mr_reference_objects_clear(&p->objects);
    memset(p, 0, sizeof *p);
}

int mr_job_reference_passes(const mr_job *job, unsigned *passes, mr_error *err)
{
    *passes = 0;
    if (!mr_job_has_reference(job))
        return MR_OK;
    for (int t = 0; t < MR_REFERENCE_TYPES; t++) {
        mr_reference_pass p;
        bool present;
        int rc = mr_reference_pass_init(job, (mr_reference_type)t, &p, &present, err);
        if (rc < 0)
            return rc;
        if (present)
            *passes |= 1u << t;
        mr_reference_pass_clear(&p);
    }
    return MR_OK;
}
