/*
 * dmm_lod.h - how far a dmm object's subdivision level strays from the
 * detailed mesh it was baked from, for "tolerance_px" (issue 16; the kind's
 * levels of detail are in dmm_kind.c).
 *
 * A level's error is the two-sided distance between its surface (its
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
 * report (dmm_bake_max_distance) is the first side alone.
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
 * same space), on threads threads, into *out; from every stride-th sample
 * of each kind (0 or 1: all of them). */
int mr_dmm_lod_distance(const mr_dmm_lod_truth *t, const float *pos, uint32_t nv,
                        const uint32_t *idx, uint32_t nt, uint32_t stride, unsigned threads,
                        const char *who, double *out, mr_error *err);

/* ---- the errors in the derived-data cache ----
 * Measuring a dmm object's levels takes seconds (1.4 s for the skinned
 * dancer's 4 levels, rest and 4 poses); the errors are kept in
 * <cache root>/dmm/<key>.mrdle and read by a later job with the same key.
 * The caller's key holds everything the measurement reads (dmm_kind.c:
 * the asset, the object's parameters, each measured pose's node
 * transforms). File (little-endian), a header of 104 bytes and nothing
 * else: magic "MRDLE\0\r\n", version (1) at 8, header bytes (104) at 12,
 * the level count (1..MR_DMM_LOD_FILE_LEVELS) at 16, the key at 20, the
 * errors (f64, finest first, finite, >= 0 and never shrinking) at 52, zeros
 * after the last, the header CRC-32 at 100. */
#define MR_DMM_LOD_FILE_VERSION 1u
#define MR_DMM_LOD_FILE_LEVELS 6u

/* count errors for key: read from cache_dir when a file there has them,
 * else measure(ctx, errors, err) and store them there (cache_dir NULL:
 * measured only). *hit (may be NULL) says which; errors are measure's. */
int mr_dmm_lod_errors_cached(const char *cache_dir, const uint8_t key[MR_DERIVED_KEY_BYTES], uint32_t count,
                             double *errors, int (*measure)(void *ctx, double *errors, mr_error *err),
                             void *ctx, bool *hit, mr_error *err);

#endif
