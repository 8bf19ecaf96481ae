/*
 * dmm.c - the displaced micro-mesh (DMM) kind (paper 000, issue 4), mode
 * `tessellated`: the exact reference and the pre-tessellation baseline.
 *
 * create   bakes every mesh of the asset (dmm_bake.h: meshoptimizer base mesh
 *          whose vertices keep their bone weights, Embree-measured
 *          displacements), then encodes and decodes the displacements
 *          (dmm_encode.h), so what is rendered is exactly what a DMM file
 *          would store, not the unquantised bake;
 * update   skins the BASE vertices and their directions with the pose (linear
 *          blend skinning, mr_skin_mesh on a mesh made of the base arrays;
 *          static meshes are placed by their node), then evaluates every
 *          micro-vertex P = sum w_i v_i + d sum w_i n_i (eq. 5, the paper's
 *          `base` deformation: displacement along the interpolated skinned
 *          normals, not renormalised) with micromesh.h, in parallel over base
 *          triangles. Each base triangle is evaluated from its own data in a
 *          fixed order, so positions are bit-identical for any thread count;
 *          micromesh.h's edge rule makes micro-vertices on shared base edges
 *          bit-identical on both sides, so the micro-triangle mesh is
 *          watertight although every base triangle owns its micro-vertices;
 * attach   one Embree TRIANGLE geometry over the micro-triangles, with shared
 *          buffers (see mesh.c), primitive id = base triangle * 4^level +
 *          micro-triangle (micromesh.h row order);
 * normal   the micro-triangle's geometric normal.
 *
 * Micro-vertices are duplicated per base triangle (not shared across edges):
 * it keeps evaluation embarrassingly parallel and costs about 3x the vertex
 * memory of a shared layout, which only matters for this baseline mode.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "geom/dmm_bake.h"
#include "geom/dmm_encode.h"
#include "geom/geom.h"
#include "geom/micromesh.h"
#include "util/parallel.h"

#define EVAL_GRAIN 64

struct mr_geom {
    const mr_asset *asset;
    unsigned level;
    uint32_t micro_vertices;      /* per base triangle */
    uint32_t micro_triangles;     /* per base triangle */
    mr_dmm_bake **bakes;          /* per asset mesh; NULL for a mesh without triangles */
    uint32_t *mesh_first_base;    /* per asset mesh: first base vertex in the merged arrays */
    uint32_t base_vertex_count, base_triangle_count;
    uint32_t *base_indices;       /* 3 per base triangle, merged vertex numbering */
    float *disp;                  /* decoded displacements, micro_vertices per base triangle */
    float *base_pos, *base_dir;   /* posed base vertices (world), 3 each per base vertex */
    float *last_pos, *last_dir;   /* what the micro-vertices were last evaluated from */
    bool evaluated;
    uint32_t vertex_count, triangle_count;
    float *positions;             /* 3 per micro-vertex + 1 float padding (Embree 16-byte loads) */
    uint32_t *indices;            /* 3 per micro-triangle */
    size_t encoded_bytes;         /* bytes of the encoded records (what a file stores) */
    float max_coordinate;
    RTCGeometry rtc;
};

static void dmm_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    if (g->bakes)
        for (size_t i = 0; i < g->asset->mesh_count; i++)
            mr_dmm_bake_free(g->bakes[i]);
    free(g->bakes);
    free(g->mesh_first_base);
    free(g->base_indices);
    free(g->disp);
    free(g->base_pos);
    free(g->base_dir);
    free(g->last_pos);
    free(g->last_dir);
    free(g->positions);
    free(g->indices);
    free(g);
}

/* Encodes the bake's displacements and decodes them into out, so the
 * rendered surface carries exactly the quantisation a stored DMM has. */
static int quantise(const mr_dmm_bake *b, float *out, size_t *bytes, mr_error *err)
{
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    mr_dmm_encoded *enc = NULL;
    int rc = mr_dmm_encode(b->level, bits, b->base_triangle_count, b->displacements, &enc, NULL,
                           err);
    if (rc < 0)
        return rc;
    for (uint32_t t = 0; t < b->base_triangle_count && rc >= 0; t++)
        rc = mr_dmm_decode_floats(enc, t, out + (size_t)t * b->micro_vertex_count, err);
    *bytes += (size_t)enc->triangle_count * enc->record_bytes;
    mr_dmm_encoded_free(enc);
    return rc;
}

static int dmm_create(const mr_asset *asset, const mr_object_desc *desc, mr_geom **out,
                      mr_error *err)
{
    *out = NULL;
    const mr_dmm_desc *d = &desc->dmm;
    if (d->mode != MR_DMM_TESSELLATED)
        return mr_error_set(err, MR_ERR_INVALID,
                            "dmm mode %d is not implemented yet (only \"tessellated\")",
                            (int)d->mode);
    if (d->level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "dmm level %u is outside 0..%u", d->level,
                            MR_UMESH_MAX_LEVEL);
    if (d->base_triangles == 0 && !(d->base_ratio > 0 && d->base_ratio <= 1))
        return mr_error_set(err, MR_ERR_INVALID, "dmm base_ratio %g is outside (0, 1]",
                            (double)d->base_ratio);
    int rc = MR_OK;
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating a dmm object");
    g->asset = asset;
    g->level = d->level;
    g->micro_vertices = mr_umesh_vertex_count(d->level);
    g->micro_triangles = mr_umesh_triangle_count(d->level);
    g->bakes = calloc(asset->mesh_count ? asset->mesh_count : 1, sizeof *g->bakes);
    g->mesh_first_base = calloc(asset->mesh_count ? asset->mesh_count : 1, sizeof(uint32_t));
    if (!g->bakes || !g->mesh_first_base)
        goto nomem;

    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = d->level;
    bp.target_triangles = d->base_triangles;
    bp.target_ratio = d->base_ratio;
    bp.threads = 0; /* the bake does not depend on it */
    uint64_t nv = 0, nt = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        if (asset->meshes[i].triangle_count == 0)
            continue;
        if ((rc = mr_dmm_bake_run(&asset->meshes[i], &bp, &g->bakes[i], err)) < 0) {
            mr_error_prefix(err, "%s: mesh %zu: ", asset->path, i);
            goto fail;
        }
        g->mesh_first_base[i] = (uint32_t)nv;
        nv += g->bakes[i]->base_vertex_count;
        nt += g->bakes[i]->base_triangle_count;
        if (nv > MR_MAX_ASSET_VERTICES || nt * g->micro_triangles > MR_MAX_ASSET_TRIANGLES ||
            nt * g->micro_vertices > MR_MAX_ASSET_VERTICES) {
            rc = mr_error_set(err, MR_ERR_LIMIT,
                              "%s: %llu base triangles at level %u exceed the caps (%u "
                              "micro-triangles / vertices)",
                              asset->path, (unsigned long long)nt, g->level,
                              MR_MAX_ASSET_TRIANGLES);
            goto fail;
        }
    }
    if (nt == 0) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: no triangles to render", asset->path);
        goto fail;
    }
    g->base_vertex_count = (uint32_t)nv;
    g->base_triangle_count = (uint32_t)nt;
    g->vertex_count = (uint32_t)(nt * g->micro_vertices);
    g->triangle_count = (uint32_t)(nt * g->micro_triangles);
    g->base_indices = malloc(nt * 3 * sizeof(uint32_t));
    g->disp = malloc((size_t)g->vertex_count * sizeof(float));
    g->base_pos = calloc(nv * 3, sizeof(float));
    g->base_dir = calloc(nv * 3, sizeof(float));
    g->last_pos = calloc(nv * 3, sizeof(float));
    g->last_dir = calloc(nv * 3, sizeof(float));
    g->positions = calloc((size_t)g->vertex_count * 3 + 1, sizeof(float));
    g->indices = malloc((size_t)g->triangle_count * 3 * sizeof(uint32_t));
    if (!g->base_indices || !g->disp || !g->base_pos || !g->base_dir || !g->last_pos ||
        !g->last_dir || !g->positions || !g->indices)
        goto nomem;

    /* Micro-triangle indices of one base triangle, reused with an offset. */
    uint32_t *local = malloc((size_t)g->micro_triangles * 3 * sizeof(uint32_t));
    if (!local)
        goto nomem;
    uint32_t local_count = mr_umesh_triangles(g->level, 0, local);
    uint32_t t0 = 0;
    for (size_t i = 0; i < asset->mesh_count && rc >= 0; i++) {
        const mr_dmm_bake *b = g->bakes[i];
        if (!b)
            continue;
        for (uint64_t k = 0; k < (uint64_t)b->base_triangle_count * 3; k++)
            g->base_indices[(uint64_t)t0 * 3 + k] = b->base_indices[k] + g->mesh_first_base[i];
        rc = quantise(b, g->disp + (size_t)t0 * g->micro_vertices, &g->encoded_bytes, err);
        t0 += b->base_triangle_count;
    }
    for (uint32_t t = 0; t < g->base_triangle_count && local_count == g->micro_triangles; t++) {
        uint32_t *dst = g->indices + (size_t)t * g->micro_triangles * 3;
        for (uint32_t k = 0; k < g->micro_triangles * 3; k++)
            dst[k] = local[k] + t * g->micro_vertices;
    }
    free(local);
    if (rc < 0)
        goto fail;
    if (local_count != g->micro_triangles) {
        rc = mr_error_set(err, MR_ERR_INVALID, "micro-mesh topology of level %u is inconsistent",
                          g->level);
        goto fail;
    }
    *out = g;
    return MR_OK;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a dmm object", asset->path);
fail:
    dmm_free(g);
    return rc;
}

typedef struct eval_ctx {
    mr_geom *g;
    uint32_t bad[MR_MAX_THREADS]; /* per worker: first failing base triangle + 1, or 0 */
} eval_ctx;

static void eval_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    eval_ctx *c = ctx;
    mr_geom *g = c->g;
    mr_vec3 pts[561]; /* mr_umesh_vertex_count(MR_UMESH_MAX_LEVEL) */
    for (size_t t = begin; t < end; t++) {
        mr_umesh_tri tri;
        for (int k = 0; k < 3; k++) {
            const float *p = g->base_pos + (size_t)g->base_indices[t * 3 + k] * 3;
            const float *n = g->base_dir + (size_t)g->base_indices[t * 3 + k] * 3;
            tri.pos[k] = mr_v3(p[0], p[1], p[2]);
            tri.dir[k] = mr_v3(n[0], n[1], n[2]);
        }
        mr_error e = {0};
        if (mr_umesh_eval_all(&tri, g->level, 0, g->disp + t * g->micro_vertices, pts, &e) < 0) {
            if (c->bad[worker] == 0)
                c->bad[worker] = (uint32_t)t + 1;
            continue;
        }
        float *dst = g->positions + t * g->micro_vertices * 3;
        for (uint32_t v = 0; v < g->micro_vertices; v++) {
            dst[v * 3] = pts[v].x;
            dst[v * 3 + 1] = pts[v].y;
            dst[v * 3 + 2] = pts[v].z;
        }
    }
}

static int dmm_update(mr_geom *g, const mr_pose *pose, const mr_mat4 *transform, unsigned threads,
                      mr_error *err)
{
    /* Pose the base mesh: a one-mesh view of the asset whose vertices are the
     * base vertices with their own weights (the bake kept them). */
    for (size_t i = 0; i < g->asset->mesh_count; i++) {
        const mr_dmm_bake *b = g->bakes[i];
        if (!b)
            continue;
        mr_mesh m = g->asset->meshes[i];
        m.vertex_count = b->base_vertex_count;
        m.triangle_count = b->base_triangle_count;
        m.positions = b->base_positions;
        m.normals = b->base_directions;
        m.uvs = NULL;
        m.indices = b->base_indices;
        m.joints = b->joints;
        m.weights = b->weights;
        if (!b->joints || !b->weights) {
            m.joint_count = 0;
            m.joint_nodes = NULL;
            m.inverse_bind = NULL;
            m.joints = NULL;
            m.weights = NULL;
        }
        mr_asset view = *g->asset;
        view.mesh_count = 1;
        view.meshes = &m;
        size_t off = (size_t)g->mesh_first_base[i] * 3;
        mr_skin_mesh(&view, 0, pose, transform, g->base_pos + off, g->base_dir + off, threads);
    }
    size_t nb = (size_t)g->base_vertex_count * 3 * sizeof(float);
    /* Static objects (and frames where nothing moved) keep their micro-vertices. */
    if (g->evaluated && memcmp(g->base_pos, g->last_pos, nb) == 0 &&
        memcmp(g->base_dir, g->last_dir, nb) == 0)
        return MR_OK;
    eval_ctx *c = calloc(1, sizeof *c);
    if (!c)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory updating a dmm object");
    c->g = g;
    mr_parallel_for(threads, g->base_triangle_count, EVAL_GRAIN, eval_range, c);
    uint32_t bad = 0;
    for (unsigned w = 0; w < MR_MAX_THREADS; w++)
        if (c->bad[w] && (bad == 0 || c->bad[w] < bad))
            bad = c->bad[w];
    free(c);
    g->evaluated = false;
    if (bad)
        return mr_error_set(err, MR_ERR_INVALID,
                            "%s: base triangle %u is not finite after posing: check the object's "
                            "transform and pose",
                            g->asset->path, bad - 1);
    float biggest = 0;
    for (size_t k = 0; k < (size_t)g->vertex_count * 3; k++) {
        float a = fabsf(g->positions[k]);
        biggest = a > biggest ? a : biggest;
        if (!(a <= MR_MAX_COORDINATE))
            return mr_error_set(err, MR_ERR_INVALID,
                                "%s: posed micro-vertex %zu has a coordinate of %g (limit %g): "
                                "check the object's transform and pose",
                                g->asset->path, k / 3, (double)g->positions[k],
                                MR_MAX_COORDINATE);
    }
    g->max_coordinate = biggest;
    memcpy(g->last_pos, g->base_pos, nb);
    memcpy(g->last_dir, g->base_dir, nb);
    g->evaluated = true;
    return MR_OK;
}

static int dmm_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                      enum RTCBuildQuality quality, mr_error *err)
{
    return mr_geom_attach_triangles(device, scene, geom_id, quality, g->positions, g->vertex_count,
                                    g->indices, g->triangle_count, &g->rtc, err);
}

static void dmm_commit(mr_geom *g) { mr_geom_commit_vertices(g->rtc); }

static mr_vec3 vertex(const mr_geom *g, uint32_t i)
{
    const float *p = g->positions + (size_t)i * 3;
    return mr_v3(p[0], p[1], p[2]);
}

static mr_vec3 dmm_normal(const mr_geom *g, unsigned prim, float u, float v)
{
    (void)u;
    (void)v;
    if (prim >= g->triangle_count)
        return mr_v3(0, 0, 1);
    const uint32_t *tri = g->indices + (size_t)prim * 3;
    mr_vec3 p0 = vertex(g, tri[0]), p1 = vertex(g, tri[1]), p2 = vertex(g, tri[2]);
    return mr_v3_cross(mr_v3_sub(p1, p0), mr_v3_sub(p2, p0));
}

static int dmm_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return mr_trimesh_copy(g->positions, g->vertex_count, g->indices, g->triangle_count, out, err);
}

static size_t dmm_memory(const mr_geom *g)
{
    size_t bytes = sizeof *g + g->asset->mesh_count * (sizeof(void *) + sizeof(uint32_t));
    for (size_t i = 0; i < g->asset->mesh_count; i++)
        if (g->bakes[i])
            bytes += mr_dmm_bake_memory(g->bakes[i]);
    bytes += (size_t)g->base_triangle_count * 3 * sizeof(uint32_t);
    bytes += (size_t)g->base_vertex_count * 12 * sizeof(float);
    bytes += (size_t)g->vertex_count * sizeof(float);
    bytes += ((size_t)g->vertex_count * 3 + 1) * sizeof(float);
    bytes += (size_t)g->triangle_count * 3 * sizeof(uint32_t);
    return bytes;
}

static uint64_t dmm_primitives(const mr_geom *g) { return g->triangle_count; }

const mr_geom_ops mr_geom_dmm_ops = {
    .name = "dmm",
    .create = dmm_create,
    .update = dmm_update,
    .attach = dmm_attach,
    .commit = dmm_commit,
    .normal = dmm_normal,
    .tessellate = dmm_tessellate,
    .memory = dmm_memory,
    .primitives = dmm_primitives,
    .free = dmm_free,
};
