/*
 * dmm_bake.h - first stage of the displaced micro-mesh (DMM) baker (paper
 * 000, issue 4 part 1): detailed triangle mesh -> base mesh + one float
 * displacement per micro-vertex. Hierarchical encoding, quantisation and the
 * min/max pyramid come later and consume this result.
 *
 * Steps:
 *  1. Weld the detailed mesh by position (importers split vertices at UV and
 *     normal seams; an unwelded base mesh would not share edges, and shared
 *     edges are what makes the DMM watertight, see micromesh.h).
 *  2. Simplify with meshoptimizer (meshopt_simplify: half-edge collapses onto
 *     existing vertices), so every base vertex IS a detailed vertex and keeps
 *     its position bits and its bone joints/weights (base_source names it).
 *  3. Base directions: area-weighted vertex normals of the base mesh, unit at
 *     the vertices. They are interpolated across a triangle without
 *     normalisation (eq. 5), by micromesh.h.
 *  4. Levels (params.adaptive): every base triangle gets the level whose
 *     micro-triangles are closest in area to the detailed mesh's mean
 *     triangle, log4(base area / mean detail area) rounded, within 0..L;
 *     then levels are raised until no shared edge joins levels more than one
 *     apart (raising keeps detail; at most L passes), and the finer side of
 *     an edge between levels l and l + 1 is decimated (micromesh.h). Without
 *     adaptive every triangle is at level L.
 *  5. For every micro-vertex of a triangle's subdivision, the signed distance
 *     along the interpolated direction d to the detailed surface: rays from
 *     the undisplaced point along +d and -d, each taking the first crossing
 *     where the detailed surface faces the way d points (its outward normal
 *     . d > 0: a ray that leaves the body through the detailed surface, or
 *     enters it from outside going inward). A crossing facing the other way
 *     is the inside of another part of the body (arm seen from the torso,
 *     one leg from the other) and is passed through. The nearer of the two
 *     wins (ties go to +d). Distances are in units of the unnormalised
 *     direction, i.e. exactly the d of eq. 5.
 *     The search is bounded, as production bakers bound theirs (a cage or a
 *     "max frontal / rear distance"), by a reach derived from the base mesh:
 *     MR_DMM_BAKE_REACH (a quarter) of the longest base edge at the corners
 *     the micro-vertex interpolates (its nonzero barycentric weights; the
 *     max of theirs, so both triangles of a shared edge use the same bound),
 *     and by max_displacement when that is given. Why a quarter: the detail
 *     a base edge of length L stands for lies within its sagitta of it; a
 *     sagitta of L/4 is a circular arc of 106 degrees over the edge, more
 *     bending than one base edge of a simplified surface represents. A
 *     surface farther away along d is another part of the body: before the
 *     bound, the bench dancer's rays found surfaces up to 36 % of its
 *     diagonal away, and the micro-triangles spanning those vertices stood
 *     up to 5.9 % of the diagonal off the detailed surface at every level.
 *     Unmatched micro-vertices (no facing crossing within the bound: the
 *     base surface passes a rim of an open mesh, or the detail folds away
 *     from d) take the height along d of the nearest point of the detailed
 *     surface (an Embree closest-point query), clamped to the bound, and
 *     are counted in fallback_count: continuous with their matched
 *     neighbours, where a displacement of 0 left steps that the encoder's
 *     corrections then had to climb.
 *     Micro-vertices on a shared base edge get bit-identical rays, bounds
 *     and closest-point queries from both triangles (micromesh.h's edge
 *     rule; each query is a pure function of its input), so both sides get
 *     the same displacement.
 *  6. Error report: distance from the DMM surface to the detailed mesh,
 *     sampled at every displaced micro-vertex and every (surviving)
 *     micro-triangle centroid, by an exact closest-point query (Embree rtcPointQuery with a
 *     point-triangle distance). RMS and max over all samples.
 *
 * Deterministic for any thread count: every base triangle is baked
 * independently and per-triangle counts are summed in triangle order.
 */
#ifndef MR_DMM_BAKE_H
#define MR_DMM_BAKE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "asset/asset.h"
#include "microray.h"

/* The displacement search reaches this fraction of the longest base edge
 * at the corners a micro-vertex interpolates (step 5). */
#define MR_DMM_BAKE_REACH 0.25f

typedef struct mr_dmm_bake_params {
    /* Target base triangle count; 0 means use target_ratio. */
    uint32_t target_triangles;
    /* Fraction of the detailed (welded) triangle count, in (0, 1]; used when
     * target_triangles is 0. */
    float target_ratio;
    /* meshopt_simplify's error bound, relative to the mesh extent; 0 means
     * no bound (simplify until the target count is reached or nothing can
     * collapse any more). */
    float max_error;
    /* Subdivision level 0..MR_UMESH_MAX_LEVEL: of every triangle, or the
     * largest with adaptive. */
    unsigned level;
    /* Per-triangle levels from the detail's density (step 4). */
    bool adaptive;
    /* Longest displacement searched, in direction-length units, on top of
     * the reach bound of step 5; 0 means the reach bound alone. */
    float max_displacement;
    /* Worker threads (0 = all cores). The result does not depend on it. */
    unsigned threads;
} mr_dmm_bake_params;

typedef struct mr_dmm_bake {
    unsigned level;                /* the largest triangle level */
    uint32_t micro_vertex_count;   /* floats per base triangle in displacements:
                                      mr_umesh_vertex_count(level) */
    uint32_t base_vertex_count;
    uint32_t base_triangle_count;
    float *base_positions;         /* 3 per base vertex, bit-identical to the source vertex */
    float *base_directions;        /* 3 per base vertex, unit */
    uint32_t *base_indices;        /* 3 per base triangle */
    uint32_t *base_source;         /* per base vertex: index of the detailed vertex it is */
    uint16_t *joints;              /* MR_MAX_INFLUENCES per base vertex, or NULL if rigid */
    float *weights;                /* MR_MAX_INFLUENCES per base vertex, or NULL if rigid */
    uint8_t *tri_info;             /* per base triangle: level and decimation, mr_dmm_tri_info */
    float *displacements;          /* micro_vertex_count per base triangle, micromesh.h order;
                                      a triangle uses the vertex count of its own level */
    uint64_t fallback_count;       /* micro-vertices without a facing crossing within
                                      the bound (step 5) */
    uint64_t sample_count;         /* samples of the error report */
    double rms_distance;           /* DMM surface to detailed mesh, model units */
    double max_distance;
    float simplify_error;          /* meshopt's result_error, absolute (model units) */
} mr_dmm_bake;

/* Defaults: target_ratio 0.05, level 3, no error bound, the reach bound
 * alone, all threads. */
mr_dmm_bake_params mr_dmm_bake_params_default(void);

/* Bakes a DMM from a detailed mesh (its positions, indices and skin; normals
 * and uvs are not used). Fails with MR_ERR_INVALID for bad parameters or a
 * mesh without triangles / with non-finite positions or out-of-range indices,
 * MR_ERR_EMBREE when Embree fails, MR_ERR_NOMEM. *out is NULL on failure. */
int mr_dmm_bake_run(const mr_mesh *detail, const mr_dmm_bake_params *params, mr_dmm_bake **out,
                    mr_error *err);

void mr_dmm_bake_free(mr_dmm_bake *bake);

/* Bytes held by the bake's arrays. */
size_t mr_dmm_bake_memory(const mr_dmm_bake *bake);

#endif /* MR_DMM_BAKE_H */
