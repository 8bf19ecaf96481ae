/*
 * renderer.h - renders the frames of one job.
 *
 * A renderer owns the job's objects (one geometry kind instance each) and one
 * Embree scene. Per frame it evaluates the camera path and each object's pose,
 * deforms what moved, refits (animated scenes) or builds (first frame, static
 * scenes, or force_rebuild) the BVH, and traces the frame into a film.
 *
 * Animated scenes use the refit recipe of REFERENCE.md (scene DYNAMIC + LOW,
 * geometry REFIT): the first frame builds, later frames refit the same tree.
 * Static scenes build once with MEDIUM quality and never touch Embree again.
 */
#ifndef MR_RENDERER_H
#define MR_RENDERER_H

#include <stdatomic.h>

#include "asset/asset.h"
#include "job.h"
#include "render/device.h"
#include "render/film.h"

typedef struct mr_renderer mr_renderer;

typedef struct mr_renderer_options {
    /* Rebuild the BVH every frame (same fast LOW-quality builder) instead of
     * refitting it: the baseline refit is measured against in benchmarks. */
    bool force_rebuild;
    /* When set to true (from any thread) a render in progress stops within
     * one tile and mr_renderer_render fails with MR_ERR_CANCELLED. May be NULL. */
    const atomic_bool *cancel;
} mr_renderer_options;

typedef enum mr_bvh_update {
    MR_BVH_NONE = 0, /* nothing moved: the previous frame's tree was reused */
    MR_BVH_BUILD,    /* built from scratch */
    MR_BVH_REFIT     /* same tree, bounds refitted to the moved vertices */
} mr_bvh_update;

/* "none", "build" or "refit" (stats.json's "bvh"). */
const char *mr_bvh_update_name(mr_bvh_update u);

/* Per-frame statistics (stats.json documents the same fields). */
typedef struct mr_frame_stats {
    int frame;
    double time;              /* frame time on the job's timeline, s */
    double load_s;            /* asset import charged to this frame (the first) */
    uint32_t assets_cached;   /* first frame: assets a scene cache already held */
    uint32_t assets_loaded;   /* first frame: assets imported for this job */
    double load_saved_s;      /* first frame: import seconds the cache saved */
    double pose_s;            /* pose evaluation and skinning */
    double bvh_s;             /* Embree build or refit */
    mr_bvh_update bvh;        /* what happened to the BVH this frame */
    double trace_s;           /* primary + shadow rays and shading */
    double encode_s;          /* EXR encoding and writing (filled by the caller) */
    double total_s;           /* everything for this frame, encode included */
    uint64_t rays;            /* primary + shadow rays traced */
    double mrays_per_s;       /* rays / trace_s / 1e6 */
    uint64_t triangles;       /* primitives in the scene */
    uint64_t geometry_bytes;  /* microray's vertex/index/normal arrays */
    uint64_t bvh_bytes;       /* Embree's own allocations (memory monitor) */
    uint64_t peak_rss_bytes;  /* process peak resident set so far */
    float scene_diagonal;     /* bounding-box diagonal of the frame's scene */
} mr_frame_stats;

/* assets[i] is the import of job->assets[i]; the renderer borrows them (they
 * must outlive it). Fails naming the object for unknown clips/cameras. */
int mr_renderer_new(mr_device *dev, const mr_job *job, mr_asset *const *assets,
                    const mr_renderer_options *opt, mr_renderer **out, mr_error *err);
void mr_renderer_free(mr_renderer *r);

/* Renders frame `index` (0 <= index < job->frame_count) into film, which must
 * be job->output.width x height. */
int mr_renderer_render(mr_renderer *r, size_t index, mr_film *film, mr_frame_stats *stats,
                       mr_error *err);

/* Peak resident set size of the process, bytes. */
uint64_t mr_peak_rss_bytes(void);

#endif
