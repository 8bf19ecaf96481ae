/*
 * dmm_lod.h - how far a dmm object's surface strays from the detailed mesh
 * it was baked from, and each base triangle's coarser levels from its baked
 * one, for "tolerance_px" (issue 16; the kind's levels of detail, one per
 * base triangle, are in dmm_kind.c).
 *
 * The baked surface's error is the two-sided distance between it (its
 * micro-triangles) and the detailed mesh, measured by exact closest-point
 * queries (math/closest_mesh.h) at every distinct vertex position of the
 * detailed mesh (against the level's micro-triangles) and at every
 * micro-vertex a micro-triangle uses and every micro-triangle's centroid
 * (against the detailed mesh); the largest of them all.
 *
 * Why the two-sided largest distance: the frame's error against the ground
 * truth (surface_px, what a tolerance is held to) is the largest screen
 * distance from either surface to the other, so a level must be close to
 * the detail everywhere (one side: no micro-triangle floats off it) and
 * the detail close to the level everywhere (the other side: no detail the
 * level cut off, a spike or a finger the base mesh lost). dmm_bake.h's own
 * report (dmm_bake_max_distance) is the first side alone. Each sample is
 * also given to its owner (mr_dmm_lod_distance's owner), so each base
 * triangle gets its own share.
 *
 * It is a sampled bound, not a proof: between the samples the distance can
 * be larger (a micro-triangle is about as large as a detailed triangle, so
 * its centroid and corners see most of it; a detailed triangle's interior
 * is not sampled against the level). The reference passes (surface_px
 * against "ground_truth") measure what it leaves out.
 */
#ifndef MR_DMM_LOD_H
#define MR_DMM_LOD_H

#include <stdbool.h>
#include <stdint.h>

#include "math/closest_mesh.h"
#include "util/derived.h"
#include "microray.h"

/* The detailed mesh a level is measured against: the caller's positions
 * (kept alive while measured) and triangles, its distinct positions, and
 * its closest-point scene. */
typedef struct mr_dmm_lod_truth {
    const float *pos;
    uint32_t nv;
    uint32_t *distinct;      /* one vertex at each distinct position */
    uint32_t distinct_count;
    mr_closest_mesh closest;
} mr_dmm_lod_truth;

/* The detailed mesh: nv positions pos (3 floats each) and nt triangles idx.
 * who names the caller in errors. *t needs no free on failure. */
int mr_dmm_lod_truth_init(mr_dmm_lod_truth *t, const float *pos, uint32_t nv, const uint32_t *idx,
                          uint32_t nt, const char *who, mr_error *err);
void mr_dmm_lod_truth_free(mr_dmm_lod_truth *t);

/* The two-sided sampled distance (above) between the truth and the nt
 * triangles idx over nv positions pos (a level's micro-triangles, in the
 * same space), on threads threads, from every stride-th sample of each kind
 * (0 or 1: all of them), raising out (not reset). owner NULL: out[0] gets
 * the whole distance. Else owner[k] names triangle k's owner (a base
 * triangle) and out[o] gets owner o's share: of the level's samples, those
 * of its triangles (a vertex counts for every triangle using it); of the
 * truth's points, those nearest one of its triangles. The largest of out is
 * the whole distance either way. */
int mr_dmm_lod_distance(const mr_dmm_lod_truth *t, const float *pos, uint32_t nv,
                        const uint32_t *idx, uint32_t nt, const uint32_t *owner, uint32_t stride,
                        unsigned threads, const char *who, double *out, mr_error *err);

/* ---- the bounds in the derived-data cache ----
 * Measuring a dmm object's bounds takes seconds (the skinned dancer, 5,125
 * base triangles at level 3, rest and 4 poses: about 3 s on 2 cores); they
 * are kept in <cache root>/<key>.mrdle and read by a later job with the
 * same key. The caller's key holds everything the measurement reads
 * (dmm_kind.c: the asset, the object's parameters, each measured pose's
 * node transforms). File (little-endian): a header of 64 bytes, magic
 * "MRDLE\0\r\n", version (2) at 8, header bytes (64) at 12, the base
 * triangle count at 16, MR_DMM_LOD_LEVELS at 20, the key at 24, the
 * payload's CRC-32 at 56, the header's at 60; then per base triangle 13
 * f64: its fine bound, its MR_DMM_LOD_LEVELS error bounds (never growing
 * towards finer levels) and its MR_DMM_LOD_LEVELS bounds without
 * decimation (dmm_kind.c), each finite and >= 0. */
#define MR_DMM_LOD_FILE_VERSION 2u
#define MR_DMM_LOD_LEVELS 6u /* MR_UMESH_MAX_LEVEL + 1 */

/* A dmm object's bounds, per base triangle (the caller's arrays): fine[t]
 * and MR_DMM_LOD_LEVELS entries of error and of whole from t *
 * MR_DMM_LOD_LEVELS. */
typedef struct mr_dmm_lod_table {
    uint32_t triangles;
    double *fine, *error, *whole;
} mr_dmm_lod_table;

/* The table for key: read from cache_dir when a file there holds one for
 * as many triangles, else measure(ctx, err) fills it and it is stored
 * there (cache_dir NULL: measured only). *hit (may be NULL) says which. */
int mr_dmm_lod_table_cached(const char *cache_dir, const uint8_t key[MR_DERIVED_KEY_BYTES],
                            mr_dmm_lod_table *table, int (*measure)(void *ctx, mr_error *err),
                            void *ctx, bool *hit, mr_error *err);

/* ---- per-triangle levels ----
 * With a tolerance every base triangle takes its own level l <= its baked
 * level L (dmm_kind.c): its level-l surface is the one the same encoding
 * holds (dmm_encode.h: the level-l values are a prefix of the level-L
 * ones), so its micro-vertices are micro-vertices of level L, bit for bit
 * (micromesh.h: a vertex's weights are k / n, the same number at every
 * level). How far that surface strays from level L is measured at equal
 * base-domain coordinates, which bounds the distance between the two
 * surfaces both ways.
 *
 * mr_dmm_lod_coarsening computes it exactly (up to double rounding), not by
 * samples: over the intersection of a coarse micro-triangle T with a
 * level-L micro-triangle F both surfaces are affine, so their difference is
 * largest at a corner of that convex polygon (F clipped by T's three
 * half-planes); every such polygon is visited. A decimated edge
 * re-triangulates a strip of T's (micromesh.h), not aligned with the
 * level-L lattice: the same holds for them. */

/* That distance for one base triangle: pos holds its level-fine
 * micro-vertices (3 floats each, micromesh.h order, every lattice vertex,
 * undecimated), tris the count surviving micro-triangles of the coarse
 * surface (mr_umesh_triangles at level <= fine, with its decimation). */
double mr_dmm_lod_coarsening(unsigned fine, const float *pos, unsigned level, const uint32_t *tris,
                             uint32_t count);

#endif
