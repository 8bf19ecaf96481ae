/*
 * lod.h - what every kind with levels of detail shares ("tolerance_px",
 * issue 16; kind.h has_lod): the pick of a level from the errors its levels
 * stray by, and the stretch of an object's transform that scales them.
 *
 * A kind measures, once, how far (in its rest space) each of its levels
 * strays from its ground truth; per frame it projects those distances by
 * mr_camera_px_per_unit (render/camera.h) at the object's nearest depth and
 * traces the coarsest level that stays below the tolerance.
 */
#ifndef MR_LOD_H
#define MR_LOD_H

#include <stdbool.h>
#include <stdint.h>

#include <embree3/rtcore.h>

#include "anim/pose.h"
#include "asset/asset.h"
#include "microray.h"

#define MR_LOD_UNBOUNDED_PX 1e9

/* Levels are ordered finest first: error[k] (world or rest-space units, >= 0)
 * is how far level k strays. Returns the largest k < count whose
 * error[k] * px_per_unit is at most tolerance_px, or 0 (the finest) when
 * none is or px_per_unit is not finite (the object reaches the camera's
 * plane). *predicted_px gets the picked level's projected error: when
 * px_per_unit is not finite and the level strays at all, unbounded, given
 * as MR_LOD_UNBOUNDED_PX (stats are JSON numbers). */
uint32_t mr_lod_pick(const double *error, uint32_t count, double px_per_unit, double tolerance_px,
                     double *predicted_px);

/* An upper bound of the largest factor by which the transform's linear part
 * stretches a length: sqrt of the largest absolute row sum of A^T A (which
 * bounds its largest eigenvalue); exact for rotations times a uniform or an
 * axis-aligned scale. */
double mr_lod_stretch(const mr_mat4 *transform);

/* The build quality of a kind's level geometries (one Embree geometry per
 * level, one enabled per frame) when the renderer asks for `quality`:
 * with several levels, LOW instead of REFIT. A refitted tree keeps the
 * topology of the pose it was built in, which would be the pose of the
 * frame that first enabled the level, and a resumed job must trace the
 * uninterrupted run's trees. */
enum RTCBuildQuality mr_lod_build_quality(uint32_t levels, enum RTCBuildQuality quality);

/* A kind's levels in Embree: one geometry per level, only the frame's
 * enabled. */
typedef struct mr_lod_switch {
    uint32_t enabled; /* the level enabled, UINT32_MAX: none yet */
    uint32_t dirty;   /* bit k: level k was set up since the last commit */
} mr_lod_switch;

/* A kind's commit (kind.h) of its levels: enables level cur (disabling the
 * one enabled before) and commits the dirty levels, geometry(ctx, k) giving
 * level k's Embree geometry and commit(ctx, k) committing it (a disabled
 * level is built when it is enabled; one set up for an older pose is set up
 * again first). Returns whether anything changed: a camera that moved
 * without changing the level leaves Embree's scene as it was. */
bool mr_lod_commit(mr_lod_switch *s, uint32_t cur, uint32_t count, void *ctx,
                   RTCGeometry (*geometry)(void *ctx, uint32_t level),
                   void (*commit)(void *ctx, uint32_t level));

/* The level whose posed bounds, grown by its error, place an object for
 * the pick each frame: the coarsest (of count, finest first) whose error
 * is within MR_LOD_BOUNDS_ERROR of asset's rest-pose bounding-box
 * diagonal, so the growth moves the nearest depth by little while the
 * bounds cost a coarse level's vertices; 0 when none is. */
#define MR_LOD_BOUNDS_ERROR 0.02
uint32_t mr_lod_bounds_level(const double *error, uint32_t count, const mr_asset *asset);

/* Poses of an object's clip its levels are measured in besides the rest
 * pose (skinning bends coarse geometry otherwise than the detail), and
 * the share of the samples taken in each (every MR_LOD_POSE_STRIDE-th: the
 * coarse levels' misfits in a pose span limbs, not single points). */
#define MR_LOD_POSES 4
#define MR_LOD_POSE_STRIDE 4

/* The times of those poses in pose description d of asset a (the object's
 * first): MR_LOD_POSES evenly over one run of its clip ((j + 0.5) / n of
 * its duration); one (time 0) when d is fixed in time or plays no clip; none
 * when d is NULL. Returns how many, into times[MR_LOD_POSES]. */
uint32_t mr_lod_pose_times(const mr_asset *a, const mr_pose_desc *d, double *times);

#endif
