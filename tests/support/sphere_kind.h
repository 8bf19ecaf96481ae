/*
 * sphere_kind.h - a geometry kind that lives entirely under tests/: proof
 * that a new kind is its own code plus one registration line.
 *
 * "kind": "test_sphere", "test_sphere": {"radius": R}: an icosphere of
 * radius R (ignores the asset's meshes). It exercises every part of the
 * descriptor:
 *   - a parameter table (one NUMBER field) the server reads generically and
 *     the schema generator turns into a block;
 *   - derived data through the one derived-data cache (util/derived.h) in
 *     the folder the renderer hands it (<cache root>/test_sphere/): the
 *     tessellated unit sphere, stored as a file keyed by its subdivision and
 *     read back by the next create;
 *   - its own per-frame stats fields (scale, steps, cache hit);
 *   - the SEQUENTIAL frame order: a one-line "simulation" whose scale after
 *     frame n depends on every frame before it, so a frame rendered out of
 *     order is right only if the renderer replays frames 0..n-1.
 * Include it in one test file and register with
 *   mr_kind_register(&test_sphere_kind, &err);
 */
#ifndef TEST_SPHERE_KIND_H
#define TEST_SPHERE_KIND_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/kind.h"
#include "util/crc32.h"
#include "util/derived.h"
#include "util/le.h"

#define TEST_SPHERE_SUBDIV 3u

typedef struct test_sphere_params {
    float radius;
} test_sphere_params;

struct mr_geom {
    float radius;
    uint32_t vertex_count, triangle_count;
    float *unit;       /* 3 per vertex: the unit sphere (derived data) */
    float *positions;  /* 3 per vertex + 1 padding */
    uint32_t *indices;
    double scale;      /* the simulated state */
    unsigned steps;    /* updates since create or rewind */
    bool cache_hit;    /* create read the unit sphere from the cache */
    RTCGeometry rtc;
};

/* Icosahedron split `subdiv` times, vertices pushed onto the unit sphere;
 * shared midpoints are not merged (a soup is enough for a test). */
static int test_sphere_build(uint32_t subdiv, float **unit, uint32_t **indices, uint32_t *nv,
                             uint32_t *nt)
{
    const float t = 1.6180339887f;
    const float base_v[12][3] = {{-1, t, 0}, {1, t, 0},  {-1, -t, 0}, {1, -t, 0},
                                 {0, -1, t}, {0, 1, t},  {0, -1, -t}, {0, 1, -t},
                                 {t, 0, -1}, {t, 0, 1},  {-t, 0, -1}, {-t, 0, 1}};
    const uint32_t base_t[20][3] = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                                    {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                                    {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                                    {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
    uint32_t tris = 20u << (2 * subdiv);
    float *v = malloc((size_t)tris * 9 * sizeof(float));
    uint32_t *ix = malloc((size_t)tris * 3 * sizeof(uint32_t));
    if (!v || !ix) {
        free(v);
        free(ix);
        return MR_ERR_NOMEM;
    }
    /* each face split into 4^subdiv triangles on a barycentric lattice */
    uint32_t n = 1u << subdiv, out = 0;
    for (int f = 0; f < 20; f++) {
        const float *a = base_v[base_t[f][0]], *b = base_v[base_t[f][1]], *c = base_v[base_t[f][2]];
        for (uint32_t i = 0; i < n; i++)
            for (uint32_t j = 0; j < n - i; j++)
                for (int up = 0; up < (j + i + 1 < n ? 2 : 1); up++) {
                    uint32_t l[3][2] = {{i, j}, {i + 1, j}, {i, j + 1}};
                    if (up) {
                        l[0][0] = i + 1; l[0][1] = j + 1;
                        l[1][0] = i;     l[1][1] = j + 1;
                        l[2][0] = i + 1; l[2][1] = j;
                    }
                    for (int k = 0; k < 3; k++) {
                        float u = (float)l[k][0] / (float)n, w = (float)l[k][1] / (float)n;
                        float p[3];
                        for (int d = 0; d < 3; d++)
                            p[d] = a[d] + u * (b[d] - a[d]) + w * (c[d] - a[d]);
                        float len = sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
                        for (int d = 0; d < 3; d++)
                            v[(size_t)out * 9 + (size_t)k * 3 + (size_t)d] = p[d] / len;
                        ix[(size_t)out * 3 + (size_t)k] = out * 3 + (uint32_t)k;
                    }
                    out++;
                }
    }
    *unit = v;
    *indices = ix;
    *nv = out * 3;
    *nt = out;
    return MR_OK;
}

/* The derived data on disk, through the one derived-data cache
 * (core/util/derived.h): the envelope, the vertex count at 16, the key at
 * 20, then the unit vertices (little-endian floats) and their CRC-32. */
static const mr_derived_format TEST_SPHERE_FORMAT = {
    .name = "sphere file",
    .ext = "sphere",
    .magic = {'M', 'R', 'S', 'P', 'H', 'E', 'R', 'E'},
    .version = 1,
    .header_bytes = 56,
    .key_at = 20,
    .max_bytes = 64u << 20,
};

static int test_sphere_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    mr_geom *g = ctx;
    const size_t head = TEST_SPHERE_FORMAT.header_bytes, bytes = (size_t)g->vertex_count * 12;
    if (mr_le_get_u32(buf + 16) != g->vertex_count || size != head + bytes + 4)
        return mr_derived_bad(&TEST_SPHERE_FORMAT, err, "not the sphere of this subdivision");
    if (mr_crc32(buf + head, bytes) != mr_le_get_u32(buf + head + bytes))
        return mr_derived_bad(&TEST_SPHERE_FORMAT, err, "vertex CRC mismatch");
    for (size_t i = 0; i < (size_t)g->vertex_count * 3; i++)
        g->unit[i] = mr_le_get_f32(buf + head + i * 4);
    return MR_OK;
}

static int test_sphere_serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **out,
                                 size_t *size, mr_error *err)
{
    const mr_geom *g = ctx;
    const size_t head = TEST_SPHERE_FORMAT.header_bytes, bytes = (size_t)g->vertex_count * 12;
    uint8_t *buf = calloc(1, head + bytes + 4);
    if (!buf)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    mr_le_put_u32(buf + 16, g->vertex_count);
    for (size_t i = 0; i < (size_t)g->vertex_count * 3; i++)
        mr_le_put_f32(buf + head + i * 4, g->unit[i]);
    mr_le_put_u32(buf + head + bytes, mr_crc32(buf + head, bytes));
    mr_derived_header_seal(&TEST_SPHERE_FORMAT, key, buf);
    *out = buf;
    *size = head + bytes + 4;
    return MR_OK;
}

static int test_sphere_derive(void *ctx, mr_error *err)
{
    mr_geom *g = ctx;
    uint32_t nv, nt;
    float *unit;
    uint32_t *indices;
    if (test_sphere_build(TEST_SPHERE_SUBDIV, &unit, &indices, &nv, &nt) < 0)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    memcpy(g->unit, unit, (size_t)nv * 12);
    free(unit);
    free(indices);
    return MR_OK;
}

static const mr_derived_ops TEST_SPHERE_CACHE = {test_sphere_parse, test_sphere_serialise,
                                                 test_sphere_derive};

static void test_sphere_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    free(g->unit);
    free(g->positions);
    free(g->indices);
    free(g);
}

static int test_sphere_create(const mr_asset *asset, const mr_object_desc *desc,
                              const mr_kind_context *ctx, mr_geom **out, mr_error *err)
{
    (void)asset;
    *out = NULL;
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "test_sphere: out of memory");
    g->radius = ((const test_sphere_params *)desc->params)->radius;
    g->scale = 1.0;
    if (test_sphere_build(TEST_SPHERE_SUBDIV, &g->unit, &g->indices, &g->vertex_count,
                          &g->triangle_count) < 0 ||
        !(g->positions = calloc((size_t)g->vertex_count * 3 + 1, sizeof(float)))) {
        test_sphere_free(g);
        return mr_error_set(err, MR_ERR_NOMEM, "test_sphere: out of memory");
    }
    /* the unit sphere: read back from the cache, or derived and stored */
    mr_derived_key_builder kb;
    uint8_t key[MR_DERIVED_KEY_BYTES];
    mr_derived_key_begin(&kb, "microray test sphere", TEST_SPHERE_FORMAT.version, 1);
    mr_derived_key_u32(&kb, TEST_SPHERE_SUBDIV);
    mr_derived_key_end(&kb, key);
    int rc = mr_derived_get(ctx ? ctx->cache_dir : NULL, key, &TEST_SPHERE_FORMAT,
                            &TEST_SPHERE_CACHE, g, &g->cache_hit, err);
    if (rc < 0) {
        test_sphere_free(g);
        return rc;
    }
    *out = g;
    return MR_OK;
}

/* One step of the "simulation": the scale relaxes towards a target that
 * swings with the frame time, so it remembers every earlier frame. */
static int test_sphere_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                              const mr_mat4 *transform, unsigned threads, mr_error *err)
{
    double t = frame ? frame->time : 0;
    g->scale = 0.6 * g->scale + 0.4 * (1.0 + 0.5 * sin(3.0 * t));
    g->steps++;
    mr_mat4 id = mr_mat4_identity();
    const mr_mat4 *m = transform ? transform : &id;
    float s = g->radius * (float)g->scale;
    for (uint32_t i = 0; i < g->vertex_count; i++) {
        const float *u = g->unit + (size_t)i * 3;
        mr_vec3 p = mr_mat4_point(m, mr_v3(u[0] * s, u[1] * s, u[2] * s));
        g->positions[(size_t)i * 3] = p.x;
        g->positions[(size_t)i * 3 + 1] = p.y;
        g->positions[(size_t)i * 3 + 2] = p.z;
    }
    return MR_OK;
}

static int test_sphere_rewind(mr_geom *g, mr_error *err)
{
    g->scale = 1.0;
    g->steps = 0;
    return MR_OK;
}

static int test_sphere_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                              enum RTCBuildQuality quality, mr_error *err)
{
    return mr_geom_attach_triangles(device, scene, geom_id, quality, g->positions,
                                    g->vertex_count, g->indices, g->triangle_count, &g->rtc, err);
}

static bool test_sphere_commit(mr_geom *g)
{
    mr_geom_commit_vertices(g->rtc);
    return true;
}

static mr_vec3 test_sphere_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    const float *a = g->unit + (size_t)prim * 9;
    float w = 1.0f - u - v;
    return mr_v3(w * a[0] + u * a[3] + v * a[6], w * a[1] + u * a[4] + v * a[7],
                 w * a[2] + u * a[5] + v * a[8]);
}

static int test_sphere_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return mr_trimesh_copy(g->positions, g->vertex_count, g->indices, g->triangle_count, out, err);
}

static size_t test_sphere_memory(const mr_geom *g)
{
    return ((size_t)g->vertex_count * 6 + 1) * sizeof(float) +
           (size_t)g->triangle_count * 3 * sizeof(uint32_t);
}

static uint64_t test_sphere_primitives(const mr_geom *g) { return g->triangle_count; }

static const mr_kind_stat TEST_SPHERE_STATS[] = {
    {"test_sphere_scale", "1", "the simulated scale after this frame", MR_STAT_MAX},
    {"test_sphere_steps", "count", "updates applied since create or rewind", MR_STAT_SUM},
    {"test_sphere_cache_hit", "count", "1 if create read the sphere from the cache (first frame)",
     MR_STAT_ONCE},
};

static void test_sphere_frame_stats(const mr_geom *g, double *values)
{
    values[0] = g->scale;
    values[1] = g->steps;
    values[2] = g->cache_hit;
}

static const mr_param TEST_SPHERE_PARAMS[] = {
    {.field = "radius", .type = MR_PARAM_NUMBER, .offset = offsetof(test_sphere_params, radius),
     .lo = 0, .hi = 100, .flags = MR_PARAM_LO_OPEN, .def = 1,
     .description = "Radius at frame 0, model units."},
};

static const mr_param_table TEST_SPHERE_TABLE = {
    .params = TEST_SPHERE_PARAMS,
    .count = 1,
    .size = sizeof(test_sphere_params),
    .expect = "an object of test_sphere parameters",
};

static const mr_kind test_sphere_kind = {
    .name = "test_sphere",
    .summary = "A test kind: a simulated sphere (tests/support/sphere_kind.h).",
    .params = &TEST_SPHERE_TABLE,
    .frame_order = MR_FRAMES_SEQUENTIAL,
    .has_derived = true,
    .stats = TEST_SPHERE_STATS,
    .stat_count = 3,
    .create = test_sphere_create,
    .update = test_sphere_update,
    .attach = test_sphere_attach,
    .commit = test_sphere_commit,
    .normal = test_sphere_normal,
    .tessellate = test_sphere_tessellate,
    .memory = test_sphere_memory,
    .primitives = test_sphere_primitives,
    .frame_stats = test_sphere_frame_stats,
    .rewind = test_sphere_rewind,
    .free = test_sphere_free,
};

#endif
