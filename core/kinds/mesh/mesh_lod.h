/*
 * mesh_lod.h - a triangle mesh's levels of detail, for "tolerance_px"
 * (issue 16): a chain of meshoptimizer simplifications of the rest-pose
 * mesh, each with the distance it strays from the full mesh, and the pick
 * of the coarsest level whose distance, projected by this frame's camera,
 * stays below the tolerance.
 *
 * Level 0 is the mesh itself; level k asks meshoptimizer for about
 * 1/2^k of its triangles (each level simplified from the full mesh, so
 * errors do not pile up) and the chain ends when a level is not at least
 * 10 % smaller than the one before. Levels keep the full mesh's vertices
 * (meshoptimizer picks a subset, over the mesh welded by position: see
 * weld in mesh_lod.c): one skinned vertex array serves them all.
 *
 * A level's error is its two-sided distance to the full mesh, measured by
 * exact closest-point queries (math/closest_mesh.h) at every distinct vertex
 * position of the full mesh (against the level) and, on every level
 * triangle, at its centroid and the points of a barycentric grid but its
 * corners (against the full mesh): an m x m grid, m = mr_mesh_lod_grid,
 * about MR_MESH_LOD_SAMPLES points per level (at least the edge midpoints),
 * so a coarse level's few large triangles are looked at inside too. It is
 * the Hausdorff distance at those points: between them it can be exceeded
 * (a sampled bound, not a proof), which the reference passes measure. Rigid transforms scale it by
 * at most the transform's largest stretch (mr_lod_stretch, kinds/lod.h); skinning
 * by bones that do not stretch keeps each bone's part rigid, and where
 * weights blend two bones the level and the full mesh blend alike at
 * shared vertices, so the rest-pose error is the prediction there too (not
 * a bound: the reference passes measure it). The mesh kind also measures
 * its levels in a few poses of the object's clip (mr_mesh_lod_measure).
 */
#ifndef MR_MESH_LOD_H
#define MR_MESH_LOD_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"

#define MR_MESH_LOD_MAX 16
/* Points a level's triangles are sampled at, about (mr_mesh_lod_grid). */
#define MR_MESH_LOD_SAMPLES 8192

typedef struct mr_mesh_lod {
    uint32_t level_count;                 /* 1.. MR_MESH_LOD_MAX */
    uint32_t *indices[MR_MESH_LOD_MAX];   /* [0] is the caller's (not owned) */
    uint32_t triangles[MR_MESH_LOD_MAX];
    double error[MR_MESH_LOD_MAX];        /* distance to level 0 (rest space); error[0] = 0 */
    uint32_t *distinct;                   /* a vertex at each distinct position */
    uint32_t distinct_count;
} mr_mesh_lod;

/* Builds the chain over the rest-pose positions and normals (3 floats per
 * vertex, nv of them) and the nt triangles idx (kept by reference as level
 * 0), on threads threads. who names the asset in errors. */
int mr_mesh_lod_build(mr_mesh_lod *lod, const float *pos, const float *normals, uint32_t nv,
                      const uint32_t *idx, uint32_t nt, unsigned threads, const char *who,
                      mr_error *err);
void mr_mesh_lod_free(mr_mesh_lod *lod);

/* Measures the levels again over the mesh posed otherwise (pos: nv posed
 * vertices, the same triangles) and raises each level's error to what it
 * finds there: the same two-sided distance, from every stride-th distinct
 * position and every stride-th triangle of each level. Linear blend skinning moves a coarse triangle's corners by
 * their own bones while the surface it stands for bends between them, so a
 * level can stray farther in a pose than at rest. */
int mr_mesh_lod_measure(mr_mesh_lod *lod, const float *pos, uint32_t nv, uint32_t stride,
                        unsigned threads, const char *who, mr_error *err);
/* The subdivisions of each edge of a level triangle the error samples at
 * when the level (or the part measured) has `triangles` triangles: about
 * MR_MESH_LOD_SAMPLES points in all, 2 (the edge midpoints) to 32. */
uint32_t mr_mesh_lod_grid(uint32_t triangles);

/* Bytes the levels beyond 0 hold. */
size_t mr_mesh_lod_memory(const mr_mesh_lod *lod);

#endif
