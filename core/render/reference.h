/*
 * reference.h - the jobs a job's reference passes render (the job's
 * "reference"; microray.h "reference passes").
 *
 * A reference pass of type T draws the job's scene with every object that
 * asks for references ("reference": true, its own or the job's) replaced
 * by what its kind draws for T (kinds/kind.h `reference`): its exact
 * tessellation, or the ground truth its kind approximates. An object whose
 * kind has no T reference is drawn as its tessellation instead (for
 * ground truth) or as it is; a pass no asking object has a reference for
 * is not run. Objects that do not ask are drawn as they are. Everything
 * else (camera, lights, frames, output size) is the job's; the pass keeps
 * only the passes the comparison reads (MR_AOV_REFERENCE) and asks for no
 * reference passes of its own.
 *
 * The renderer (renderer.c) renders each pass's job through a renderer of
 * its own, with the frame's camera, and compares (mr_film_compare).
 */
#ifndef MR_REFERENCE_H
#define MR_REFERENCE_H

#include "kinds/kind.h"

typedef struct mr_reference_pass {
    mr_reference_type type;
    mr_job job;                  /* the source job's, borrowed, but for objects */
    mr_reference_objects objects; /* job.objects */
} mr_reference_pass;

/* The job pass `type` renders into *out (*present false, nothing held:
 * no asking object has a reference of that type). Free with
 * mr_reference_pass_clear. */
int mr_reference_pass_init(const mr_job *job, mr_reference_type type, mr_reference_pass *out,
                           bool *present, mr_error *err);
void mr_reference_pass_clear(mr_reference_pass *p);

#endif
