/*
 * lod.c - the level pick and transform stretch shared by kinds with levels
 * of detail (lod.h).
 */
#include <math.h>

#include "kinds/lod.h"

uint32_t mr_lod_pick(const double *error, uint32_t count, double px_per_unit, double tolerance_px,
                     double *predicted_px)
{
    uint32_t pick = 0;
    if (isfinite(px_per_unit))
        for (uint32_t k = 1; k < count; k++)
            if (error[k] * px_per_unit <= tolerance_px)
                pick = k;
    if (!isfinite(px_per_unit))
        *predicted_px = error[0] > 0 ? MR_LOD_UNBOUNDED_PX : 0;
    else
        *predicted_px = error[pick] * px_per_unit;
    return pick;
}

double mr_lod_stretch(const mr_mat4 *t)
{
    const float *m = t->m; /* row-major: row r is m[4r .. 4r + 2] */
    double ata[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double s = 0;
            for (int r = 0; r < 3; r++)
                s += (double)m[4 * r + i] * m[4 * r + j];
            ata[i][j] = s;
        }
    double worst = 0;
    for (int i = 0; i < 3; i++)
        worst = fmax(worst, fabs(ata[i][0]) + fabs(ata[i][1]) + fabs(ata[i][2]));
    return sqrt(worst);
}

enum RTCBuildQuality mr_lod_build_quality(uint32_t levels, enum RTCBuildQuality quality)
{
    return levels > 1 && quality == RTC_BUILD_QUALITY_REFIT ? RTC_BUILD_QUALITY_LOW : quality;
}

uint32_t mr_lod_bounds_level(const double *error, uint32_t count, const mr_asset *asset)
{
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t i = 0; i < asset->mesh_count; i++)
        for (size_t v = 0; v < (size_t)asset->meshes[i].vertex_count * 3; v++) {
            double x = asset->meshes[i].positions[v];
            lo[v % 3] = fmin(lo[v % 3], x);
            hi[v % 3] = fmax(hi[v % 3], x);
        }
    double d2 = 0;
    for (int c = 0; c < 3; c++)
        d2 += hi[c] > lo[c] ? (hi[c] - lo[c]) * (hi[c] - lo[c]) : 0;
    uint32_t level = 0;
    for (uint32_t k = 1; k < count; k++)
        if (error[k] <= MR_LOD_BOUNDS_ERROR * sqrt(d2))
            level = k;
    return level;
}

uint32_t mr_lod_pose_times(const mr_asset *a, const mr_pose_desc *d, double *times)
{
    if (!d)
        return 0;
    double duration = 0;
    if (d->has_clip && !d->has_time) {
        int ci = d->clip_name ? mr_asset_find_clip(a, d->clip_name) : d->clip_index;
        if (ci >= 0 && (size_t)ci < a->clip_count && d->speed != 0)
            duration = a->clips[ci].duration / fabs(d->speed);
    }
    if (!(duration > 0)) {
        times[0] = 0;
        return 1;
    }
    for (uint32_t j = 0; j < MR_LOD_POSES; j++)
        times[j] = duration * (j + 0.5) / MR_LOD_POSES;
    return MR_LOD_POSES;
}

bool mr_lod_commit(mr_lod_switch *s, uint32_t cur, uint32_t count, void *ctx,
                   RTCGeometry (*geometry)(void *ctx, uint32_t level),
                   void (*commit)(void *ctx, uint32_t level))
{
    bool changed = s->dirty != 0;
    if (s->enabled != cur) {
        if (s->enabled != UINT32_MAX)
            rtcDisableGeometry(geometry(ctx, s->enabled));
        rtcEnableGeometry(geometry(ctx, cur));
        s->enabled = cur;
        changed = true;
    }
    for (uint32_t k = 0; k < count; k++)
        if (s->dirty & 1u << k)
            commit(ctx, k);
    s->dirty = 0;
    return changed;
}
