/*
 * frame_stats.h - what a frame's statistics are: the struct the renderer,
 * the worker and the encoding caller fill (mr_frame_stats), and the one
 * table of its fields (mr_frame_stat_fields) that everything else is driven
 * by: the stats writer (stats.json, the stored per-frame object, the HTTP
 * frame and job stats and the "frame" event: server/stats_json.c), its
 * reader (the HTTP job stats rebuild totals from stored frames) and the
 * API's schema of a frame's stats (schemas/openapi.yaml, generated from the
 * table by `make openapi`). A new field is a struct member plus a table row.
 *
 * A geometry kind's own per-frame fields (an extra "simulate" phase, its
 * counters) are not table rows: the renderer appends them to the frame as
 * extras (mr_frame_stats_add_extra), and the writer emits them after the
 * table's fields as "name": value, in the order they were added.
 *
 * No JSON here (core/ has none): the table says names, types, units and
 * where each value lives; the writer decides how a type is spelled.
 */
#ifndef MR_FRAME_STATS_H
#define MR_FRAME_STATS_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "microray.h"

typedef enum mr_bvh_update {
    MR_BVH_NONE = 0, /* nothing moved: the previous frame's tree was reused */
    MR_BVH_BUILD,    /* built from scratch */
    MR_BVH_REFIT     /* same tree, bounds refitted to the moved vertices */
} mr_bvh_update;

/* "none", "build" or "refit" (stats.json's "bvh"). */
const char *mr_bvh_update_name(mr_bvh_update u);

/* Most extras one frame carries: a few per kind, for a few kinds. */
#define MR_FRAME_EXTRAS_MAX 8

/* One per-frame field beyond the table's, e.g. {"simulate_s", "s", 0.02}. */
typedef struct mr_frame_extra {
    const char *name;  /* stats.json key; borrowed: a kind's static table */
    const char *unit;  /* "s", "count", "bytes", ...; borrowed */
    double value;
} mr_frame_extra;

/* Per-frame statistics. Every member but the extras has a row in
 * mr_frame_stat_fields (test_stats_json checks they agree). */
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
    uint32_t extra_count;     /* extras[0, extra_count) are set */
    mr_frame_extra extras[MR_FRAME_EXTRAS_MAX];
} mr_frame_stats;

/* Appends an extra field to the frame. name must be a non-empty run of
 * [a-z0-9_], and neither a field or group name of the table nor an extra
 * already added (MR_ERR_INVALID); at most MR_FRAME_EXTRAS_MAX extras
 * (MR_ERR_LIMIT). name and unit are borrowed: they must outlive st. */
int mr_frame_stats_add_extra(mr_frame_stats *st, const char *name, const char *unit, double value,
                             mr_error *err);

/* ---- the field table ---------------------------------------------------- */

/* How a field's value is stored in mr_frame_stats (and so how it is read
 * and written). The last two are derived, not stored (offset 0): the
 * writer makes them from other fields and readers skip them. */
typedef enum mr_stat_type {
    MR_STAT_INT,          /* int */
    MR_STAT_U32,          /* uint32_t */
    MR_STAT_U64,          /* uint64_t */
    MR_STAT_F32,          /* float */
    MR_STAT_F64,          /* double */
    MR_STAT_BVH,          /* mr_bvh_update, written as mr_bvh_update_name() */
    MR_STAT_FRAME_FILE,   /* the frame's EXR file name, from the frame index */
    MR_STAT_CACHE_RESULT  /* "hit", "partial" or "miss", from assets_cached/assets_loaded */
} mr_stat_type;

/* A JSON object some fields are nested in ("seconds": {...}). */
typedef struct mr_stat_group {
    const char *name;
    const char *description;
    /* Written only for frames where one of the group's integer fields is
     * non-zero (the scene cache reports only on the frame that asked it). */
    bool optional;
} mr_stat_group;

typedef struct mr_stat_field {
    const mr_stat_group *group; /* NULL: a member of the frame object itself */
    const char *name;           /* JSON key within its group */
    mr_stat_type type;
    size_t offset;              /* offsetof(mr_frame_stats, ...) of the value */
    const char *unit;           /* "s", "bytes", "count", ... or "" */
    const char *description;    /* one sentence, for the API schema */
} mr_stat_field;

/* The fields in the order they are written; a group's fields are
 * consecutive. */
extern const mr_stat_field mr_frame_stat_fields[];
extern const size_t mr_frame_stat_field_count;

/* The groups "seconds" (the per-stage timings that job totals and medians
 * sum up), "bytes" and "cache". */
extern const mr_stat_group mr_stat_group_seconds, mr_stat_group_bytes, mr_stat_group_cache;

/* The value of a stored numeric field (INT, U32, U64, F32, F64, BVH) as a
 * double; 0 for derived types. */
double mr_frame_stat_number(const mr_frame_stats *st, const mr_stat_field *f);
/* Sets a stored numeric field from a double, converted as the type needs
 * (integers truncate; negative, NaN and out-of-range counts become 0);
 * derived types are left alone. */
void mr_frame_stat_set_number(mr_frame_stats *st, const mr_stat_field *f, double v);

/* "hit" (every asset came from the cache), "partial" or "miss" for the
 * frame's cache counters. */
const char *mr_frame_cache_result(const mr_frame_stats *st);

#endif
