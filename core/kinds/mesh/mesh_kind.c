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
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/mesh/mesh_kind.h"

struct mr_geom {
    const mr_asset *asset;
    uint32_t vertex_count, triangle_count;
    uint32_t *mesh_first_vertex; /* per asset mesh: offset into the merged arrays */
    float *positions;            /* 3 per vertex + 1 float padding */
    float *normals;              /* 3 per vertex */
    float *tangents;             /* 3 per vertex (0 for meshes without); NULL: no mesh has them */
    uint32_t *indices;           /* 3 per triangle, merged */
    float max_coordinate;        /* largest |coordinate| after the last update */
    RTCGeometry rtc;
};

static void mesh_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    free(g->mesh_first_vertex);
    free(g->positions);
    free(g->normals);
    free(g->tangents);
    free(g->indices);
    free(g);
}

static int mesh_create(const mr_asset *asset, const mr_object_desc *desc, const mr_kind_context *ctx,
                       mr_geom **out, mr_error *err)
{
    (void)desc;
    (void)ctx;
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
    *out = g;
    return MR_OK;
nomem:
    mesh_free(g);
    return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %llu triangles", asset->path,
                        (unsigned long long)nt);
}

static int mesh_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose, const mr_mat4 *transform, unsigned threads,
                       mr_error *err)
{
    (void)frame; /* posed geometry does not depend on the view */
    for (size_t i = 0; i < g->asset->mesh_count; i++) {
        size_t off = (size_t)g->mesh_first_vertex[i] * 3;
        mr_skin_mesh_tangents(g->asset, i, pose, transform, g->positions + off, g->normals + off,
                              g->tangents ? g->tangents + off : NULL, threads);
    }
    /* A transform or pose can scale finite file data past what Embree can
     * build over; refuse the frame rather than hand it inf or 1e30. */
    float biggest = 0;
    for (size_t k = 0; k < (size_t)g->vertex_count * 3; k++) {
        float a = fabsf(g->positions[k]);
        biggest = a > biggest ? a : biggest;
        if (!(a <= MR_MAX_COORDINATE))
            return mr_error_set(err, MR_ERR_INVALID,
                                "%s: posed vertex %zu has a coordinate of %g (limit %g): check the "
                                "object's transform and pose",
                                g->asset->path, k / 3, (double)g->positions[k], MR_MAX_COORDINATE);
    }
    g->max_coordinate = biggest;
    return MR_OK;
}

static int mesh_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                       enum RTCBuildQuality quality, mr_error *err)
{
    return mr_geom_attach_triangles(device, scene, geom_id, quality, g->positions, g->vertex_count,
                                    g->indices, g->triangle_count, &g->rtc, err);
}

static void mesh_commit(mr_geom *g) { mr_geom_commit_vertices(g->rtc); }

static mr_vec3 mesh_normal(const mr_geom *g, unsigned prim, float u, float v)
{
    const uint32_t *tri = g->indices + (size_t)prim * 3;
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
    const uint32_t *tri = g->indices + (size_t)prim * 3;
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
    const uint32_t *tri = g->indices + (size_t)prim * 3;
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
    return mr_trimesh_copy(g->positions, g->vertex_count, g->indices, g->triangle_count, out, err);
}

static size_t mesh_memory(const mr_geom *g)
{
    return ((size_t)g->vertex_count * (g->tangents ? 9 : 6) + 1) * sizeof(float) +
           (size_t)g->triangle_count * 3 * sizeof(uint32_t);
}

static uint64_t mesh_primitives(const mr_geom *g) { return g->triangle_count; }

const mr_kind mr_kind_mesh = {
    .name = "mesh",
    .summary = "triangle meshes, skinned or rigid (the default kind)",
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
    .free = mesh_free,
};
