/*
 * svo_kind.h - the sparse voxel octree kind ("kind": "svo", paper 004): its
 * job parameters (the "svo" block) and its descriptor. svo_kind.c says how
 * it works.
 */
#ifndef MR_SVO_KIND_H
#define MR_SVO_KIND_H

#include <stdint.h>

#include "kinds/kind.h"
#include "kinds/svo/deform.h"
#include "kinds/svo/svo_trace.h"
#include "kinds/svo/voxelize.h"

#define MR_SVO_DEFAULT_DEPTH 8u
#define MR_SVO_JOB_MAX_DEPTH 12u        /* 4096^3; surface voxels of a character: ~15 M */
#define MR_SVO_MAX_INSTANCES 100000u    /* per object */
#define MR_SVO_DEFAULT_DELTA 1.0f       /* pixels */

/* One instance: placed by its transform (then the object's), posed by its
 * own pose or, without one, the object's (or rest). */
typedef struct mr_svo_instance {
    mr_mat4 transform;
    bool has_pose;
    mr_pose_desc pose;
} mr_svo_instance;

/* The "svo" block of a job object (its table is mr_kind_svo.params): the
 * asset voxelised once (shared by all instances). */
typedef struct mr_svo_params {
    uint32_t depth;              /* voxelisation depth 1..MR_SVO_JOB_MAX_DEPTH */
    mr_svo_voxelize_mode voxelize;
    mr_svo_method method;
    float delta;                 /* screen-space refinement threshold, pixels, > 0 */
    bool cull;                   /* frustum culling of deformed voxels */
    bool skeleton;               /* extract a skeleton (chapter 5) and skin to it */
    float omega;                 /* skeleton feature size (fraction of the cube), 0 = default */
    size_t instance_count;       /* 0 = one instance at the object's transform */
    mr_svo_instance *instances;
} mr_svo_params;

extern const mr_kind mr_kind_svo;

/* For tests: what the last update made instance k trace: its octree
 * (resize, emit: the instance's world octree; rigid: the shared one) and
 * in *pieces how many Embree primitives it is traced as (its subtrees, or
 * 1 whole); NULL for direct or k out of range. */
const mr_svo *mr_svo_kind_octree(const mr_geom *g, size_t k, uint32_t *pieces);

/* For tests: a rigid object's cast of one ray (object space, t from 0)
 * at instance k as the last update left it (with its level of detail):
 * every piece walked in turn, without Embree's tree and its culling, the
 * nearest hit kept (a tie: the piece the whole walk meets first). What
 * Embree's calls must give in any order. False: no hit, or not rigid. */
bool mr_svo_kind_cast(const mr_geom *g, size_t k, mr_vec3 org, mr_vec3 dir, mr_svo_hit *hit);

#endif
