/*
 * dmm_kind.h - the displaced micro-mesh kind ("kind": "dmm", paper 000):
 * its job parameters (the "dmm" block: bake and trace settings) and its
 * descriptor. dmm_kind.c says how it works.
 */
#ifndef MR_DMM_KIND_H
#define MR_DMM_KIND_H

#include <stdint.h>

#include "kinds/dmm/dmm_lod.h"
#include "kinds/kind.h"

/* How a dmm object is traced (issue 4). */
typedef enum mr_dmm_mode {
    MR_DMM_TESSELLATED = 0, /* micro-triangles expanded into Embree triangles (reference) */
    MR_DMM_BASE,            /* skinned base mesh, prism traversal (paper 000, Alg. 2/4) */
    MR_DMM_INTERPOLATED     /* interpolated matrices, Bezier bounds (paper 000, Alg. 1/3) */
} mr_dmm_mode;

/* How micro-vertices follow the skeleton: along the skinned base mesh
 * (eq. 5) or under interpolated accumulated matrices (eq. 6-8). Mode BASE
 * implies DEFORM_BASE, INTERPOLATED implies DEFORM_INTERPOLATED; TESSELLATED
 * expands either. */
typedef enum mr_dmm_deform { MR_DMM_DEFORM_BASE = 0, MR_DMM_DEFORM_INTERPOLATED } mr_dmm_deform;

/* Shading normal of a dmm hit: the micro-triangle's geometric normal, or
 * the rest-pose micro-triangle normal moved by the interpolated matrix at
 * the hit (the paper's Fig. 1c "interpolated-matrix normals"), or smooth
 * normals at the detailed mesh's scale moved the same way (dmm_kind.c). */
typedef enum mr_dmm_normals {
    MR_DMM_NORMALS_GEOMETRIC = 0,
    MR_DMM_NORMALS_MATRIX,
    MR_DMM_NORMALS_SMOOTH
} mr_dmm_normals;

/* One level for every base triangle, or per-triangle levels from the
 * detail (dmm_bake.h). */
typedef enum mr_dmm_levels { MR_DMM_LEVELS_UNIFORM = 0, MR_DMM_LEVELS_ADAPTIVE } mr_dmm_levels;

/* What mode TESSELLATED intersects its micro-triangles with: Embree's own
 * triangle intersector over Embree triangles (the pre-tessellated
 * baseline), or the tessellation-free modes' own watertight test, triangle
 * by triangle inside each base triangle's box (dmm_kind.c: the exact
 * reference, frames bit-identical to theirs). */
typedef enum mr_dmm_intersector {
    MR_DMM_INTERSECT_EMBREE = 0,
    MR_DMM_INTERSECT_WATERTIGHT
} mr_dmm_intersector;

#define MR_DMM_DEFAULT_LEVEL 3u
#define MR_DMM_DEFAULT_BASE_RATIO 0.25f

/* The "dmm" block of a job object (its table is mr_kind_dmm.params). */
typedef struct mr_dmm_params {
    uint32_t level;          /* subdivision level 0..5 (MR_UMESH_MAX_LEVEL); the largest
                                when adaptive */
    float base_ratio;        /* base / detailed triangles, (0, 1]; used when base_triangles is 0 */
    uint32_t base_triangles; /* target base triangle count per mesh, or 0 */
    mr_dmm_mode mode;
    mr_dmm_deform deform;
    mr_dmm_normals normals;
    mr_dmm_levels levels;
    mr_dmm_intersector intersector; /* mode TESSELLATED only */
} mr_dmm_params;

extern const mr_kind mr_kind_dmm;

/* A dmm object's levels of detail ("tolerance_px"; dmm_kind.c, per base
 * triangle), for tests and tools. mr_dmm_lod_bounds: false without a
 * tolerance; else *out points at its bounds (dmm_lod.h's table: per base
 * triangle its fine bound and, for each level up to its baked one, how far
 * its level-l surface strays from the baked one under any decimation and
 * without). mr_dmm_frame_tri_info: what the last frame traced, per base
 * triangle its level and decimation (dmm_encode.h's byte; the bake's
 * without a tolerance). */
bool mr_dmm_lod_bounds(const mr_geom *g, mr_dmm_lod_table *out);
const uint8_t *mr_dmm_frame_tri_info(const mr_geom *g);
/* The baked micro-triangles in the rest pose (what the fine bounds are measured
 * on), into out (mr_trimesh_free). */
int mr_dmm_rest_triangles(const mr_geom *g, mr_trimesh *out, mr_error *err);

#endif
