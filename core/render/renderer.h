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
#include "render/frame_stats.h"

typedef struct mr_renderer mr_renderer;

typedef struct mr_renderer_options {
    /* Rebuild the BVH every frame (same fast LOW-quality builder) instead of
     * refitting it: the baseline refit is measured against in benchmarks. */
    bool force_rebuild;
    /* When set to true (from any thread) a render in progress stops within
     * one tile and mr_renderer_render fails with MR_ERR_CANCELLED. May be NULL. */
    const atomic_bool *cancel;
    /* Root of the derived-data cache (bakes, voxelisations, ...): each kind
     * that keeps derived data reads and writes <cache_dir>/<kind name>/
     * (kind.h). NULL: nothing is kept on disk. Borrowed. */
    const char *cache_dir;
} mr_renderer_options;

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
