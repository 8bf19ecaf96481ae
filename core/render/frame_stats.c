/* frame_stats.c - the frame-stats field tables (a frame's, an error entry's) and their
 * accessors (frame_stats.h). */
#include "render/frame_stats.h"

#include <limits.h>
#include <string.h>

const char *mr_bvh_update_name(mr_bvh_update u)
{
    switch (u) {
    case MR_BVH_BUILD: return "build";
    case MR_BVH_REFIT: return "refit";
    default: return "none";
    }
}

const mr_stat_group mr_stat_group_seconds = {
    "seconds", "Seconds spent per stage of the frame; the job's totals and medians sum them up.",
    false};
const mr_stat_group mr_stat_group_bytes = {"bytes", "Memory held while the frame was rendered.",
                                           false};
const mr_stat_group mr_stat_group_cache = {
    "cache", "What the scene cache did for the job's assets (only on the frame that asked it: the first).",
    true};
const mr_stat_group mr_stat_group_replay = {
    "replay",
    "Frames of a simulation (a kind whose frame N needs frames 0..N-1) computed again, untraced, "
    "before this frame: only on a frame rendered out of order (a resumed or retried job).",
    true};

#define AT(member) offsetof(mr_frame_stats, member)
/* The per-stage timings (doubles of seconds) and the memory figures
 * (uint64 counts of bytes). */
#define SECONDS(key, member, what) {&mr_stat_group_seconds, key, MR_STAT_F64, AT(member), "s", what, 0}
#define BYTES(key, member, what) {&mr_stat_group_bytes, key, MR_STAT_U64, AT(member), "bytes", what, 0}
/* A field made from others when written (stored nowhere). */
#define DERIVED(group, key, type, what) {group, key, type, 0, "", what, 0}

const mr_stat_field mr_frame_stat_fields[] = {
    {NULL, "frame", MR_STAT_INT, AT(frame), "", "The frame's index in the job.", 0},
    {NULL, "time", MR_STAT_F64, AT(time), "s", "The frame's time on the job's timeline.", 0},
    DERIVED(NULL, "file", MR_STAT_FRAME_FILE, "The frame's EXR file, NNNN.exr."),
    SECONDS("load", load_s, "Asset import (or scene-cache lookup), charged to the first frame."),
    SECONDS("derive", derive_s, "Setting up the job's objects: each kind's derived data (bakes, "
                                "voxelisations) built, or read from the derived-data cache, "
                                "charged to the first frame."),
    SECONDS("pose", pose_s, "Pose evaluation and deformation."),
    SECONDS("bvh", bvh_s, "Embree's build or refit of the tree."),
    SECONDS("trace", trace_s, "Primary and shadow rays with shading."),
    SECONDS("encode", encode_s, "EXR encoding and writing."),
    SECONDS("total", total_s, "Everything for this frame, encode included."),
    {&mr_stat_group_seconds, "reference", MR_STAT_F64, AT(reference_s), "s",
     "The reference passes (the job's \"reference\"): setting up the reference scenes (on the "
     "first frame), rendering the frame through them and comparing; never part of total. Only "
     "on frames that ran them.",
     MR_STAT_OPTIONAL},
    {NULL, "bvh", MR_STAT_BVH, AT(bvh), "",
     "What happened to the tree: build (first frame), refit (later frames of animated scenes) or "
     "none (nothing moved).", 0},
    {NULL, "rays", MR_STAT_U64, AT(rays), "count", "Primary and shadow rays traced.", 0},
    {NULL, "mrays_per_s", MR_STAT_F64, AT(mrays_per_s), "Mrays/s", "Rays / trace seconds / 10^6.", 0},
    {NULL, "triangles", MR_STAT_U64, AT(triangles), "count", "Primitives in the scene.", 0},
    BYTES("geometry", geometry_bytes, "microray's vertex, normal and index arrays."),
    BYTES("bvh", bvh_bytes, "What Embree itself holds (its memory monitor: the acceleration structure)."),
    BYTES("peak_rss", peak_rss_bytes, "The process's peak resident set so far."),
    {NULL, "scene_diagonal", MR_STAT_F32, AT(scene_diagonal), "scene units",
     "Bounding-box diagonal of the frame's scene, the unit of depth errors.", 0},
    {NULL, "speckle_pct", MR_STAT_F64, AT(speckle_pct), "%",
     "Isolated dark pixels (shadow acne, pinholes): pixels darker than 0.6x the median of 8 "
     "neighbours that all hit one object, as % of such interior pixels.", 0},
    DERIVED(&mr_stat_group_cache, "result", MR_STAT_CACHE_RESULT,
            "hit (every asset came from the cache), partial or miss."),
    {&mr_stat_group_cache, "assets_cached", MR_STAT_U32, AT(assets_cached), "count",
     "Assets the scene cache already held.", 0},
    {&mr_stat_group_cache, "assets_loaded", MR_STAT_U32, AT(assets_loaded), "count",
     "Assets imported for this job.", 0},
    {&mr_stat_group_cache, "saved_s", MR_STAT_F64, AT(load_saved_s), "s", "Import seconds the cache saved.", 0},
    {&mr_stat_group_replay, "frames", MR_STAT_U32, AT(replay_frames), "count",
     "Frames simulated again before this one.", 0},
    {&mr_stat_group_replay, "checkpoint", MR_STAT_U32, AT(replay_checkpoint), "count",
     "The frames held by the checkpoint the replay started from (0: from frame 0).", 0},
};
const size_t mr_frame_stat_field_count = sizeof mr_frame_stat_fields / sizeof *mr_frame_stat_fields;

/* The figures of one reference pass (mr_frame_error), as mr_film_compare
 * gives them (microray.h, "compare"). */
#define ERR_AT(member) offsetof(mr_frame_error, member)
const mr_stat_field mr_frame_error_fields[] = {
    {NULL, "reference", MR_STAT_REFERENCE, ERR_AT(reference), "",
     "What the frame was compared with: \"tessellated\" (every object as its exact "
     "tessellation) or \"ground_truth\" (every object as what its kind approximates, where it "
     "has one; its tessellation otherwise).", 0},
    {NULL, "coverage_error_pct", MR_STAT_F64, ERR_AT(coverage_error_pct), "%",
     "Pixels hit in exactly one of the frame and the reference, as % of pixels hit in either.", 0},
    {NULL, "holes", MR_STAT_U64, ERR_AT(holes), "count",
     "Pixels the reference hits together with all 8 neighbours that the frame misses: gaps, not "
     "an outline a little off.", 0},
    {NULL, "depth_rmse", MR_STAT_F64, ERR_AT(depth_rmse), "scene diagonal",
     "RMS of the depth difference over pixels hit in both, relative to the reference's scene "
     "diagonal.", 0},
    {NULL, "depth_max", MR_STAT_F64, ERR_AT(depth_max), "scene diagonal",
     "Largest depth difference over pixels hit in both, relative to the same diagonal.", 0},
    {NULL, "normal_mean_deg", MR_STAT_F64, ERR_AT(normal_mean_deg), "degrees",
     "Mean angle between the shading normals over pixels hit in both.", 0},
    {NULL, "psnr_rgb_db", MR_STAT_F64, ERR_AT(psnr_rgb_db), "dB",
     "PSNR of the colour (RGB clamped to [0, 1]); 999 for identical colour.", MR_STAT_LOWER_WORSE},
    {NULL, "speckle_pct", MR_STAT_F64, ERR_AT(speckle_pct), "%",
     "The reference frame's own isolated dark pixels (the frame's speckle_pct beside it).", 0},
    {NULL, "surface_px", MR_STAT_F64, ERR_AT(surface_px), "px",
     "How far apart the frame's and the reference's surfaces are on screen: for every pixel one "
     "of them hits, the least over the other's hits within 8 pixels of their screen distance "
     "(less half a pixel) plus the depth difference beyond what the two pixels span, in pixels at "
     "its depth; the largest (README, Error metrics; what \"tolerance_px\" is held to).", 0},
};
const size_t mr_frame_error_field_count = sizeof mr_frame_error_fields / sizeof *mr_frame_error_fields;

const char *mr_reference_name(mr_reference_type t)
{
    return t == MR_REFERENCE_GROUND_TRUTH ? "ground_truth" : "tessellated";
}

static double number_at(const void *p, mr_stat_type type)
{
    switch (type) {
    case MR_STAT_INT: return *(const int *)p;
    case MR_STAT_U32: return *(const uint32_t *)p;
    case MR_STAT_U64: return (double)*(const uint64_t *)p;
    case MR_STAT_F32: return *(const float *)p;
    case MR_STAT_F64: return *(const double *)p;
    case MR_STAT_BVH: return (double)*(const mr_bvh_update *)p;
    case MR_STAT_REFERENCE: return (double)*(const mr_reference_type *)p;
    default: return 0;
    }
}

static void set_number_at(void *p, mr_stat_type type, double v)
{
    switch (type) {
    case MR_STAT_INT: *(int *)p = v > INT_MIN && v < INT_MAX ? (int)v : 0; break;
    case MR_STAT_U32: *(uint32_t *)p = v > 0 && v < 4294967296.0 ? (uint32_t)v : 0; break;
    case MR_STAT_U64: *(uint64_t *)p = v > 0 && v < 1.8e19 ? (uint64_t)v : 0; break;
    case MR_STAT_F32: *(float *)p = (float)v; break;
    case MR_STAT_F64: *(double *)p = v; break;
    case MR_STAT_BVH:
        *(mr_bvh_update *)p = v >= MR_BVH_NONE && v <= MR_BVH_REFIT ? (mr_bvh_update)(int)v : MR_BVH_NONE;
        break;
    case MR_STAT_REFERENCE:
        *(mr_reference_type *)p = v == MR_REFERENCE_GROUND_TRUTH ? MR_REFERENCE_GROUND_TRUTH
                                                                 : MR_REFERENCE_TESSELLATED;
        break;
    default: break;
    }
}

double mr_frame_stat_number(const mr_frame_stats *st, const mr_stat_field *f)
{
    return number_at((const char *)st + f->offset, f->type);
}

void mr_frame_stat_set_number(mr_frame_stats *st, const mr_stat_field *f, double v)
{
    set_number_at((char *)st + f->offset, f->type, v);
}

double mr_frame_error_number(const mr_frame_error *e, const mr_stat_field *f)
{
    return number_at((const char *)e + f->offset, f->type);
}

void mr_frame_error_set_number(mr_frame_error *e, const mr_stat_field *f, double v)
{
    set_number_at((char *)e + f->offset, f->type, v);
}

const char *mr_frame_cache_result(const mr_frame_stats *st)
{
    return st->assets_loaded ? (st->assets_cached ? "partial" : "miss") : "hit";
}

/* Whether name is taken by a field or group of the frame object, or by
 * its "error" or "lod" entries. */
static bool table_name(const char *name)
{
    if (!strcmp(name, "error") || !strcmp(name, "lod"))
        return true;
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *f = &mr_frame_stat_fields[i];
        if (!strcmp(f->group ? f->group->name : f->name, name))
            return true;
    }
    return false;
}

int mr_frame_stats_add_extra(mr_frame_stats *st, const char *name, const char *unit, double value,
                             mr_error *err)
{
    if (!st || !name || !name[0] || strspn(name, "abcdefghijklmnopqrstuvwxyz0123456789_") != strlen(name))
        return mr_error_set(err, MR_ERR_INVALID, "frame stats: extra field name '%s' is not [a-z0-9_]+",
                            name ? name : "(null)");
    if (table_name(name))
        return mr_error_set(err, MR_ERR_INVALID, "frame stats: extra field '%s' is a field of every frame",
                            name);
    for (uint32_t i = 0; i < st->extra_count; i++)
        if (!strcmp(st->extras[i].name, name))
            return mr_error_set(err, MR_ERR_INVALID, "frame stats: extra field '%s' added twice", name);
    if (st->extra_count >= MR_FRAME_EXTRAS_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "frame stats: more than %d extra fields (at '%s')",
                            MR_FRAME_EXTRAS_MAX, name);
    st->extras[st->extra_count++] = (mr_frame_extra){name, unit ? unit : "", value};
    return MR_OK;
}
