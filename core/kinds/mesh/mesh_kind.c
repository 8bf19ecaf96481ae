/*
 * mesh_kind.c - the triangle mesh kind: all meshes of an asset, skinned (linear
 * blend skinning, core/anim) or rigid, merged into one Embree TRIANGLE
 * geometry so an object's primitive ids run 0..triangles-1.
 *
 * Vertex and index arrays are ours, handed to Embree as shared buffers: Embree
 * reads them in place, refits over them when they change, and its memory
 * monitor then counts only its acceleration structure. The vertex array has
 * one float of padding because Embree loads vertices with 16-byte reads.
 *
 * Meshes with texture coordinates carry their tangents (asset.h), skinned
 * with the vertices; the tangent at a hit interpolates the three vertices'
 * (the renderer fits it to the shading normal). A mesh without them has
 * none (zero tangents, no tangent at its hits).
 *
 * The exact reference of a triangle mesh is itself.
 *
 * With "tolerance_px" the mesh has levels of detail (mesh_lod.h): each
 * level its own Embree geometry over the one skinned vertex array (so the
 * object takes one geometry id per level), and each frame enables only the
 * coarsest level whose error, projected by the frame's camera at the posed
 * mesh's nearest depth, stays below the tolerance. Primitive ids, normals
 * and the tessellation are the chosen level's; its ground truth is the
 * full mesh (kind.h `reference`). The chain is derived data: kept in the
 * cache (<cache root>/mesh/, mesh_lod_file.h) and read by later jobs.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/mesh/mesh_kind.h"

#include "kinds/lod.h"
#include "kinds/mesh/mesh_lod.h"
#include "kinds/mesh/mesh_lod_file.h"
#include "util/clock.h"

struct mr_geom {
    const mr_asset *asset;
    uint32_t vertex_count, triangle_count;
    uint32_t *mesh_first_vertex; /* per asset mesh: offset into the merged arrays */
    float *positions;            /* 3 per vertex + 1 float padding */
    float *normals;              /* 3 per vertex */
    float *tangents;             /* 3 per vertex (0 for meshes without); NULL: no mesh has them */
    uint32_t *indices;           /* 3 per triangle, merged: level 0 */
    mr_vec3 lo, hi;              /* with levels: the bounds level's posed bounds grown by its
                                    error, after the last update */
    double tolerance_px;         /* 0: no levels of detail */
    mr_mesh_lod lod;             /* level_count 1 without a tolerance */
    double lod_build_s;
    uint32_t level;              /* the level this frame traces */
    double predicted_px;         /* its error projected by this frame's camera */
    const uint32_t *cur_indices; /* lod.indices[level] */
    uint32_t cur_triangles;
    uint32_t bounds_level;       /* the level whose bounds place the mesh each frame
                                    (mr_lod_bounds_level) */
    uint32_t posed;              /* bit k: level k's vertices are posed for the current pose */
    mr_lod_switch sw;            /* the level enabled in Embree; dirty: levels posed since the
                                    last commit */
    /* the vertices level k > 0 uses, as indices into asset mesh i:
     * level_vertices[k][level_first[k][i] .. level_first[k][i + 1]) */
    uint32_t *level_vertices[MR_MESH_LOD_MAX];
    uint32_t *level_first[MR_MESH_LOD_MAX];
    uint32_t *level_merged[MR_MESH_LOD_MAX]; /* the same vertices in the merged arrays */
    RTCGeometry rtc[MR_MESH_LOD_MAX];
};

static void mesh_free(mr_geom *g)
{
    if (!g)
        return;
    for (uint32_t k = 0; k < MR_MESH_LOD_MAX; k++)
        if (g->rtc[k])
            rtcReleaseGeometry(g->rtc[k]);
    for (uint32_t k = 1; k < MR_MESH_LOD_MAX; k++) {
        free(g->level_vertices[k]);
        free(g->level_first[k]);
        free(g->level_merged[k]);
    }
    mr_mesh_lod_free(&g->lod);
    free(g->mesh_first_vertex);
    free(g->positions);
    free(g->normals);
    free(g->tangents);
    free(g->indices);
    free(g);
}

/* The poses the levels are measured in (mesh_lod.h, mr_mesh_lod_measure;
 * mr_lod_pose_times): those of the object's first pose description when it
 * plays a clip or moves joints, as posed positions of every vertex (n
 * arrays into posed[0..n), malloc'ed; none without a pose). */
static int lod_poses(const mr_geom *g, const mr_object_desc *desc, unsigned threads,
                     float *posed[MR_LOD_POSES], uint32_t *n, mr_error *err)
{
    const mr_asset *a = g->asset;
    *n = 0;
    if (!desc || desc->pose_count == 0)
        return MR_OK;
    const mr_pose_desc *d = &desc->poses[0];
    double times[MR_LOD_POSES];
    const uint32_t count = mr_lod_pose_times(a, d, times);
    mr_pose *pose = NULL;
    int rc = mr_pose_new(a, &pose, err);
    for (uint32_t j = 0; j < count && rc == MR_OK; j++) {
        float *p = malloc(((size_t)g->vertex_count * 3 + 1) * sizeof(float));
        if (!p) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory posing levels", a->path);
            break;
        }
        posed[(*n)++] = p;
        if ((rc = mr_pose_eval(pose, a, d, times[j], err)) < 0)
            break;
        for (size_t i = 0; i < a->mesh_count; i++)
            mr_skin_mesh(a, i, pose, NULL, p + (size_t)g->mesh_first_vertex[i] * 3, NULL, threads);
    }
    mr_pose_free(pose);
    return rc;
}

/* Which vertices each level beyond 0 uses (mr_geom level_vertices). */
static bool level_vertex_lists(mr_geom *g)
{
    const mr_asset *a = g->asset;
    uint8_t *used = malloc(g->vertex_count ? g->vertex_count : 1);
    if (!used)
        return false;
    bool ok = true;
    for (uint32_t k = 1; k < g->lod.level_count && ok; k++) {
        memset(used, 0, g->vertex_count);
        uint32_t n = 0;
        for (size_t e = 0; e < (size_t)g->lod.triangles[k] * 3; e++) {
            n += !used[g->lod.indices[k][e]];
            used[g->lod.indices[k][e]] = 1;
        }
        g->level_vertices[k] = malloc((n ? n : 1) * sizeof(uint32_t));
        g->level_merged[k] = malloc((n ? n : 1) * sizeof(uint32_t));
        g->level_first[k] = malloc((a->mesh_count + 1) * sizeof(uint32_t));
        if (!(ok = g->level_vertices[k] && g->level_merged[k] && g->level_first[k]))
            break;
        uint32_t j = 0;
        for (size_t i = 0; i < a->mesh_count; i++) {
            g->level_first[k][i] = j;
            uint32_t first = g->mesh_first_vertex[i];
            for (uint32_t v = 0; v < a->meshes[i].vertex_count; v++)
                if (used[first + v]) {
                    g->level_vertices[k][j] = v;
                    g->level_merged[k][j++] = first + v;
                }
        }
        g->level_first[k][a->mesh_count] = j;
    }
    free(used);
    return ok;
}

static int mesh_create(const mr_asset *asset, const mr_object_desc *desc, const mr_kind_context *ctx,
                       mr_geom **out, mr_error *err)
{
    *out = NULL;
    uint64_t nv = 0, nt = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        nv += asset->meshes[i].vertex_count;
        nt += asset->meshes[i].triangle_count;
    }
    if (nt == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: no triangles to render", asset->path);
    if (nv > MR_MAX_ASSET_VERTICES || nt > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT, "%s: %llu vertices / %llu triangles exceed the caps",
                            asset->path, (unsigned long long)nv, (unsigned long long)nt);
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        goto nomem;
    g->asset = asset;
    g->vertex_count = (uint32_t)nv;
    g->triangle_count = (uint32_t)nt;
    g->mesh_first_vertex = calloc(asset->mesh_count, sizeof *g->mesh_first_vertex);
    g->positions = calloc(nv * 3 + 1, sizeof(float));
    g->normals = calloc(nv * 3, sizeof(float));
    g->indices = malloc(nt * 3 * sizeof(uint32_t));
    if (!g->mesh_first_vertex || !g->positions || !g->normals || !g->indices)
        goto nomem;
    for (size_t i = 0; i < asset->mesh_count && !g->tangents; i++)
        if (asset->meshes[i].tangents && !(g->tangents = calloc(nv * 3, sizeof(float))))
            goto nomem;
    uint32_t v0 = 0, t0 = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        g->mesh_first_vertex[i] = v0;
        for (uint64_t k = 0; k < (uint64_t)m->triangle_count * 3; k++)
            g->indices[(uint64_t)t0 * 3 + k] = m->indices[k] + v0;
        v0 += m->vertex_count;
        t0 += m->triangle_count;
    }
    g->tolerance_px = desc ? desc->tolerance_px : 0;
    g->lod = (mr_mesh_lod){.level_count = 1, .indices = {g->indices}, .triangles = {g->triangle_count}};
    if (g->tolerance_px > 0) {
        /* the rest pose's merged positions and normals (update overwrites them) */
        for (size_t i = 0; i < asset->mesh_count; i++) {
            size_t at = (size_t)g->mesh_first_vertex[i] * 3,
                   bytes = (size_t)asset->meshes[i].vertex_count * 3 * sizeof(float);
            memcpy(g->positions + at, asset->meshes[i].positions, bytes);
            memcpy(g->normals + at, asset->meshes[i].normals, bytes);
        }
        double t = mr_now();
        mr_error e;
        float *posed[MR_LOD_POSES] = {NULL};
        uint32_t poses = 0;
        const unsigned threads = ctx ? ctx->threads : 0;
        int rc = lod_poses(g, desc, threads, posed, &poses, &e);
        if (rc == MR_OK)
            rc = mr_mesh_lod_cached(ctx ? ctx->cache_dir : NULL, &g->lod, g->positions, g->normals,
                                    g->vertex_count, g->indices, g->triangle_count,
                                    (const float *const *)posed, poses, threads, asset->path, NULL, &e);
        for (uint32_t j = 0; j < poses; j++)
            free(posed[j]);
        if (rc < 0) {
            mesh_free(g);
            return mr_error_set(err, rc, "%s", e.msg);
        }
        if (!level_vertex_lists(g))
            goto nomem;
        g->lod_build_s = mr_now() - t;
        g->bounds_level = mr_lod_bounds_level(g->lod.error, g->lod.level_count, asset);
    }
    g->cur_indices = g->indices;
    g->cur_triangles = g->triangle_count;
    g->sw.enabled = UINT32_MAX;
    *out = g;
    return MR_OK;
nomem:
    mesh_free(g);
    return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %llu triangles", asset->path,
                        (unsigned long long)nt);
}

/* Poses level k's vertices (level 0: all of them) and checks them: a
 * transform or pose can scale finite file data past what Embree can build
 * over; the frame is refused rather than hand it inf or 1e30. */
static int pose_level(mr_geom *g, uint32_t k, const mr_pose *pose, const mr_mat4 *transform,
                      unsigned threads, mr_error *err)
{
    const mr_asset *a = g->asset;
    for (size_t i = 0; i < a->mesh_count; i++) {
        size_t off = (size_t)g->mesh_first_vertex[i] * 3;
        float *tangents = g->tangents ? g->tangents + off : NULL;
        if (k == 0)
            mr_skin_mesh_tangents(a, i, pose, transform, g->positions + off, g->normals + off,
                                  tangents, threads);
        else
            mr_skin_mesh_vertices(a, i, pose, transform, g->level_vertices[k] + g->level_first[k][i],
                                  g->level_first[k][i + 1] - g->level_first[k][i],
                                  g->positions + off, g->normals + off, tangents, threads);
    }
    size_t count = k == 0 ? g->vertex_count : g->level_first[k][a->mesh_count];
    for (size_t j = 0; j < count; j++) {
        size_t v = k == 0 ? j : g->level_merged[k][j];
        for (int c = 0; c < 3; c++)
            if (!(fabsf(g->positions[3 * v + c]) <= MR_MAX_COORDINATE))
                return mr_error_set(err, MR_ERR_INVALID,
                                    "%s: posed vertex %zu has a coordinate of %g (limit %g): check "
                                    "the object's transform and pose",
                                    a->path, v, (double)g->positions[3 * v + c], MR_MAX_COORDINATE);
    }
    g->posed |= 1u << k;
    g->sw.dirty |= 1u << k;
    return MR_OK;
}

/* The bounds of level k's posed vertices grown by pad. */
static void level_bounds(mr_geom *g, uint32_t k, float pad)
{
    mr_vec3 lo = mr_v3(INFINITY, INFINITY, INFINITY), hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    size_t count = k == 0 ? g->vertex_count : g->level_first[k][g->asset->mesh_count];
    for (size_t j = 0; j < count; j++) {
        size_t v = k == 0 ? j : g->level_merged[k][j];
        mr_vec3 p = mr_v3(g->positions[3 * v], g->positions[3 * v + 1], g->positions[3 * v + 2]);
        lo = mr_v3_min(lo, p);
        hi = mr_v3_max(hi, p);
    }
    g->lo = mr_v3_sub(lo, mr_v3(pad, pad, pad));
    g->hi = mr_v3_add(hi, mr_v3(pad, pad, pad));
}

/* Without levels: the whole mesh posed. With levels: the bounds level
 * posed first; its bounds grown by its error (the full mesh lies within
 * that distance of it) say how near the mesh comes to the camera, which
 * picks the coarsest level whose error projected there stays below the
 * tolerance; then that level's vertices are posed, unless they already are
 * for this pose (a frame where only the camera moved). */
static int mesh_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose, const mr_mat4 *transform, unsigned threads,
                       mr_error *err)
{
    int rc;
    if (!(frame && frame->view_only))
        g->posed = 0;
    bool levels = g->lod.level_count > 1;
    double stretch = levels && transform ? mr_lod_stretch(transform) : 1.0;
    uint32_t b = g->bounds_level;
    if (!(g->posed & 1u << b)) {
        if ((rc = pose_level(g, b, pose, transform, threads, err)) < 0)
            return rc;
        if (levels) /* only a level's pick reads the bounds */
            level_bounds(g, b, (float)(g->lod.error[b] * stretch));
    }
    g->level = 0;
    g->predicted_px = 0;
    if (levels && frame) {
        double px = mr_camera_px_per_unit(&frame->camera, frame->width, frame->height, g->lo, g->hi);
        g->level = mr_lod_pick(g->lod.error, g->lod.level_count, px * stretch, g->tolerance_px,
                               &g->predicted_px);
    }
    if (!(g->posed & 1u << g->level) &&
        (rc = pose_level(g, g->level, pose, transform, threads, err)) < 0)
        return rc;
    g->cur_indices = g->lod.indices[g->level];
    g->cur_triangles = g->lod.triangles[g->level];
    return MR_OK;
}

/* One geometry per level, all over the one vertex array; only the frame's
 * level is enabled (commit), built as mr_lod_build_quality says. */
static int mesh_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                       enum RTCBuildQuality quality, mr_error *err)
{
    quality = mr_lod_build_quality(g->lod.level_count, quality);
    for (uint32_t k = 0; k < g->lod.level_count; k++) {
        int rc = mr_geom_attach_triangles(device, scene, geom_id + k, quality, g->positions,
                                          g->vertex_count, g->lod.indices[k], g->lod.triangles[k],
                                          &g->rtc[k], err);
        if (rc < 0)
            return rc;
        if (g->lod.level_count > 1)
            rtcDisableGeometry(g->rtc[k]);
    }
    g->sw.enabled = g->lod.level_count > 1 ? UINT32_MAX : 0;
    return MR_OK;
}

static RTCGeometry level_geometry(void *g, uint32_t k) { return ((mr_geom *)g)->rtc[k]; }

static void level_commit(void *g, uint32_t k) { mr_geom_commit_vertices(((mr_geom *)g)->rtc[k]); }

static bool mesh_commit(mr_geom *g)
{
    return mr_lod_commit(&g->sw, g->level, g->lod.level_count, g, level_geometry, level_commit);
}

static uint32_t mesh_geometry_ids(const mr_geom *g) { return g->lod.level_count; }

static mr_vec3 mesh_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    const uint32_t *tri = g->cur_indices + (size_t)prim * 3;
    const float *n0 = g->normals + (size_t)tri[0] * 3;
    const float *n1 = g->normals + (size_t)tri[1] * 3;
    const float *n2 = g->normals + (size_t)tri[2] * 3;
    float w = 1.0f - u - v;
    return mr_v3(w * n0[0] + u * n1[0] + v * n2[0], w * n0[1] + u * n1[1] + v * n2[1],
                 w * n0[2] + u * n1[2] + v * n2[2]);
}

static bool mesh_tangent(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 *out)
{
    if (!g->tangents)
        return false;
    const uint32_t *tri = g->cur_indices + (size_t)prim * 3;
    const float *t0 = g->tangents + (size_t)tri[0] * 3;
    const float *t1 = g->tangents + (size_t)tri[1] * 3;
    const float *t2 = g->tangents + (size_t)tri[2] * 3;
    float w = 1.0f - u - v;
    *out = mr_v3(w * t0[0] + u * t1[0] + v * t2[0], w * t0[1] + u * t1[1] + v * t2[1],
                 w * t0[2] + u * t1[2] + v * t2[2]);
    return out->x != 0.0f || out->y != 0.0f || out->z != 0.0f; /* 0: a mesh without */
}

/* The hit lifted onto the surface the vertex normals describe (Hanika,
 * "Hacking the shadow terminator", Ray Tracing Gems II, 2021): for each
 * corner k whose tangent plane (position v_k, normal n_k) p lies below,
 * p moves up along n_k by its depth below that plane, weighted by the
 * corner's barycentric weight. Where the surface is convex the point rises
 * off the flat triangle towards the curved surface the normals interpolate,
 * about as far as that surface stands off it (quadratic in the distance to
 * the corners, zero at them); where it is concave or flat the point stays.
 * Shadow rays from there clear the neighbouring triangles a ray from the
 * flat triangle would graze. */
static bool mesh_shading_point(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 p,
                               mr_vec3 *lifted)
{
    const uint32_t *tri = g->cur_indices + (size_t)prim * 3;
    const float w[3] = {1.0f - u - v, u, v};
    mr_vec3 out = p;
    for (int k = 0; k < 3; k++) {
        const float *x = g->positions + (size_t)tri[k] * 3, *nn = g->normals + (size_t)tri[k] * 3;
        mr_vec3 n = mr_v3_normalize_or(mr_v3(nn[0], nn[1], nn[2]), mr_v3(0, 0, 0));
        float depth = mr_v3_dot(mr_v3_sub(p, mr_v3(x[0], x[1], x[2])), n);
        if (depth < 0)
            out = mr_v3_add(out, mr_v3_scale(n, -depth * w[k]));
    }
    *lifted = out;
    return true;
}

static int mesh_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return mr_trimesh_copy(g->positions, g->vertex_count, g->cur_indices, g->cur_triangles, out, err);
}

/* The levels beyond 0: their triangles and the lists of their vertices. */
static size_t lod_bytes(const mr_geom *g)
{
    size_t b = mr_mesh_lod_memory(&g->lod);
    for (uint32_t k = 1; k < g->lod.level_count; k++)
        b += (size_t)g->level_first[k][g->asset->mesh_count] * 2 * sizeof(uint32_t) +
             (g->asset->mesh_count + 1) * sizeof(uint32_t);
    return b;
}

static size_t mesh_memory(const mr_geom *g)
{
    return ((size_t)g->vertex_count * (g->tangents ? 9 : 6) + 1) * sizeof(float) +
           (size_t)g->triangle_count * 3 * sizeof(uint32_t) + lod_bytes(g);
}

static uint64_t mesh_primitives(const mr_geom *g) { return g->cur_triangles; }

/* Ground truth: with levels of detail, the full mesh (the reference pass
 * draws its objects without a tolerance); without, none. */
static int mesh_reference(const mr_object_desc *obj, mr_reference_type type,
                          mr_reference_objects *out, mr_error *err)
{
    if (type == MR_REFERENCE_GROUND_TRUTH && !(obj->tolerance_px > 0))
        return MR_OK;
    return mr_reference_objects_add(out, obj, err);
}

enum { S_LEVEL, S_ERROR_PX, S_TRIANGLES, S_LOD_BYTES, S_LOD_BUILD_S, S_COUNT };

static const mr_kind_stat MESH_STATS[S_COUNT] = {
    {"mesh_lod_level", "level",
     "the level of detail traced (\"tolerance_px\"; 0: the full mesh, as without one)",
     MR_STAT_MAX},
    {"mesh_lod_error_px", "px",
     "the level's predicted error: its measured distance to the full mesh, projected at the posed "
     "mesh's nearest depth by this frame's camera", MR_STAT_MAX},
    {"mesh_triangles", "count", "triangles traced (the chosen levels')", MR_STAT_SUM},
    {"mesh_lod_bytes", "bytes", "what the levels beyond the full mesh hold (triangles, vertex lists)",
     MR_STAT_SUM},
    {"mesh_lod_build_s", "s",
     "simplifying the levels and measuring their error (at rest and in poses) at creation",
     MR_STAT_ONCE},
};

static bool mesh_lod(const mr_geom *g, uint32_t *level, double *error_px)
{
    *level = g->level;
    *error_px = g->predicted_px;
    return g->tolerance_px > 0;
}

static void mesh_frame_stats(const mr_geom *g, double *values)
{
    values[S_LEVEL] = g->level;
    values[S_ERROR_PX] = g->predicted_px;
    values[S_TRIANGLES] = g->cur_triangles;
    values[S_LOD_BYTES] = (double)lod_bytes(g);
    values[S_LOD_BUILD_S] = g->lod_build_s;
}

static bool mesh_derives(const mr_object_desc *desc) { return desc->tolerance_px > 0; }

const mr_kind mr_kind_mesh = {
    .name = "mesh",
    .summary = "triangle meshes, skinned or rigid (the default kind)",
    .has_lod = true,
    .has_derived = true, /* the levels of detail of an object with "tolerance_px" */
    .derives = mesh_derives,
    .lod = mesh_lod,
    .stats = MESH_STATS,
    .stat_count = S_COUNT,
    .frame_stats = mesh_frame_stats,
    .create = mesh_create,
    .update = mesh_update,
    .attach = mesh_attach,
    .commit = mesh_commit,
    .normal = mesh_normal,
    .tangent = mesh_tangent,
    .shading_point = mesh_shading_point,
    .tessellate = mesh_tessellate,
    .memory = mesh_memory,
    .primitives = mesh_primitives,
    .geometry_ids = mesh_geometry_ids,
    .reference = mesh_reference,
    .free = mesh_free,
};
