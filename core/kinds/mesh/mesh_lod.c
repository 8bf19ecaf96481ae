/*
 * mesh_lod.c - a triangle mesh's levels of detail (mesh_lod.h).
 */
#include "kinds/mesh/mesh_lod.h"

#include <math.h>
#include <meshoptimizer.h>
#include <stdlib.h>
#include <string.h>

#include "math/closest_mesh.h"

/* Fewer triangles than this are not worth a level. */
#define LOD_MIN_TRIANGLES 8

typedef struct error_ctx {
    const mr_closest_mesh *full, *level;
    const float *pos;                  /* the mesh's vertices, as measured */
    const uint32_t *samples;           /* vertices at distinct positions (sample_count) */
    const uint32_t *level_idx;
    uint32_t sample_count;
    uint32_t stride;                   /* every stride-th level triangle */
    uint32_t grid;                     /* mr_mesh_lod_grid of the level */
    double worst[MR_MAX_THREADS];
} error_ctx;

static void vertex_point(const float *pos, uint32_t v, double p[3])
{
    p[0] = pos[3 * (size_t)v], p[1] = pos[3 * (size_t)v + 1], p[2] = pos[3 * (size_t)v + 2];
}

uint32_t mr_mesh_lod_grid(uint32_t triangles)
{
    double m = ceil(sqrt(2.0 * MR_MESH_LOD_SAMPLES / (triangles ? triangles : 1)));
    return m < 2 ? 2 : m > 32 ? 32 : (uint32_t)m;
}

/* Items [0, sample_count): the full mesh's sampled positions against the
 * level; then one per stride-th level triangle: its centroid and the
 * points of its barycentric grid (mr_mesh_lod_grid) but its corners,
 * against the full mesh. */
static void error_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    error_ctx *c = vctx;
    double worst = c->worst[worker];
    for (size_t i = begin; i < end; i++) {
        double p[3];
        if (i < c->sample_count) {
            vertex_point(c->pos, c->samples[i], p);
            worst = fmax(worst, mr_closest_mesh_distance(c->level, p, NULL));
            continue;
        }
        const uint32_t *t = c->level_idx + 3 * (i - c->sample_count) * c->stride;
        double v[3][3];
        for (int k = 0; k < 3; k++)
            vertex_point(c->pos, t[k], v[k]);
        for (int k = 0; k < 3; k++)
            p[k] = (v[0][k] + v[1][k] + v[2][k]) / 3.0;
        worst = fmax(worst, mr_closest_mesh_distance(c->full, p, NULL));
        uint32_t m = c->grid;
        for (uint32_t a = 0; a <= m; a++)
            for (uint32_t b = 0; a + b <= m; b++) {
                if ((a == m) + (b == m) + (a + b == 0) > 0)
                    continue; /* a corner: a vertex of the full mesh */
                double wa = (double)a / m, wb = (double)b / m, wc = 1.0 - wa - wb;
                for (int k = 0; k < 3; k++)
                    p[k] = wc * v[0][k] + wa * v[1][k] + wb * v[2][k];
                worst = fmax(worst, mr_closest_mesh_distance(c->full, p, NULL));
            }
    }
    c->worst[worker] = worst;
}

int mr_mesh_lod_measure(mr_mesh_lod *lod, const float *pos, uint32_t nv, uint32_t stride,
                        unsigned threads, const char *who, mr_error *err)
{
    if (lod->level_count < 2)
        return MR_OK;
    stride = stride ? stride : 1;
    uint32_t n = (lod->distinct_count + stride - 1) / stride;
    uint32_t *samples = malloc((n ? n : 1) * sizeof *samples);
    if (!samples)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
    for (uint32_t i = 0; i < n; i++)
        samples[i] = lod->distinct[(size_t)i * stride];
    mr_closest_mesh full;
    int rc = mr_closest_mesh_init(&full, NULL, pos, nv, lod->indices[0], lod->triangles[0], who, err);
    for (uint32_t k = 1; k < lod->level_count && rc == MR_OK; k++) {
        mr_closest_mesh lm;
        if ((rc = mr_closest_mesh_init(&lm, full.device, pos, nv, lod->indices[k], lod->triangles[k],
                                       who, err)) < 0)
            break;
        size_t tris = (lod->triangles[k] + (size_t)stride - 1) / stride;
        error_ctx c = {.full = &full, .level = &lm, .pos = pos, .samples = samples,
                       .level_idx = lod->indices[k], .sample_count = n, .stride = stride,
                       .grid = mr_mesh_lod_grid((uint32_t)tris)};
        mr_parallel_for(threads, (size_t)n + tris, 256, error_range, &c);
        mr_closest_mesh_free(&lm);
        for (unsigned t = 0; t < MR_MAX_THREADS; t++)
            lod->error[k] = fmax(lod->error[k], c.worst[t]);
        lod->error[k] = fmax(lod->error[k], lod->error[k - 1]); /* coarser never promises better */
    }
    mr_closest_mesh_free(&full);
    free(samples);
    return rc;
}

/* Vertices welded by position: meshoptimizer treats a vertex split for its
 * normals (a faceted mesh stores one per corner) as a border it must keep,
 * so it simplifies the welded mesh; each corner of a level's triangle then
 * goes back to the split vertex at its position whose normal is nearest the
 * triangle's own (ties: the lowest index), so faceted parts stay faceted and
 * smooth ones smooth. */
typedef struct weld {
    uint32_t count;     /* distinct positions */
    uint32_t *remap;    /* vertex -> position */
    float *pos;         /* 3 per position */
    uint32_t *idx;      /* the triangles over positions */
    uint32_t *first;    /* position p's vertices: members[first[p] .. first[p + 1]) */
    uint32_t *members;
} weld;

static void weld_free(weld *w)
{
    free(w->remap);
    free(w->pos);
    free(w->idx);
    free(w->first);
    free(w->members);
}

static bool weld_build(weld *w, const float *pos, uint32_t nv, const uint32_t *idx, uint32_t nt)
{
    memset(w, 0, sizeof *w);
    w->remap = malloc((size_t)nv * sizeof *w->remap);
    w->idx = malloc((size_t)nt * 3 * sizeof *w->idx);
    w->first = calloc((size_t)nv + 1, sizeof *w->first);
    w->members = malloc((size_t)nv * sizeof *w->members);
    if (!w->remap || !w->idx || !w->first || !w->members)
        return false;
    w->count = (uint32_t)meshopt_generateVertexRemap(w->remap, NULL, nv, pos, nv, 3 * sizeof(float));
    if (!(w->pos = malloc((size_t)(w->count ? w->count : 1) * 3 * sizeof(float))))
        return false;
    meshopt_remapVertexBuffer(w->pos, pos, nv, 3 * sizeof(float), w->remap);
    meshopt_remapIndexBuffer(w->idx, idx, (size_t)nt * 3, w->remap);
    for (uint32_t v = 0; v < nv; v++)
        w->first[w->remap[v] + 1]++;
    for (uint32_t p = 0; p < w->count; p++)
        w->first[p + 1] += w->first[p];
    uint32_t *next = malloc(((size_t)w->count + 1) * sizeof *next);
    if (!next)
        return false;
    memcpy(next, w->first, ((size_t)w->count + 1) * sizeof *next);
    for (uint32_t v = 0; v < nv; v++) /* ascending: each list sorted */
        w->members[next[w->remap[v]]++] = v;
    free(next);
    return true;
}

/* The vertex at welded position p whose normal is nearest n. */
static uint32_t pick_vertex(const weld *w, const float *normals, uint32_t p, const double n[3])
{
    uint32_t best = w->members[w->first[p]];
    double best_dot = -INFINITY;
    for (uint32_t k = w->first[p]; k < w->first[p + 1]; k++) {
        const float *m = normals + 3 * (size_t)w->members[k];
        double d = n[0] * m[0] + n[1] * m[1] + n[2] * m[2];
        if (d > best_dot) {
            best_dot = d;
            best = w->members[k];
        }
    }
    return best;
}

/* A level over welded positions back to the mesh's vertices. */
static void unweld(const weld *w, const float *normals, const uint32_t *in, uint32_t tris,
                   uint32_t *out)
{
    for (uint32_t t = 0; t < tris; t++) {
        const float *a = w->pos + 3 * (size_t)in[3 * t], *b = w->pos + 3 * (size_t)in[3 * t + 1],
                    *c = w->pos + 3 * (size_t)in[3 * t + 2];
        double e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
        double e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                       e1[0] * e2[1] - e1[1] * e2[0]};
        for (int k = 0; k < 3; k++)
            out[3 * t + k] = pick_vertex(w, normals, in[3 * t + k], n);
    }
}

int mr_mesh_lod_build(mr_mesh_lod *lod, const float *pos, const float *normals, uint32_t nv,
                      const uint32_t *idx, uint32_t nt, unsigned threads, const char *who,
                      mr_error *err)
{
    memset(lod, 0, sizeof *lod);
    lod->level_count = 1;
    lod->indices[0] = (uint32_t *)idx;
    lod->triangles[0] = nt;
    if (nt < 2 * LOD_MIN_TRIANGLES)
        return MR_OK;
    int rc = MR_OK;
    uint32_t *scratch = malloc((size_t)nt * 3 * sizeof *scratch);
    weld w;
    if (!scratch || !weld_build(&w, pos, nv, idx, nt) ||
        !(lod->distinct = malloc((w.count ? w.count : 1) * sizeof *lod->distinct))) {
        free(scratch);
        weld_free(&w);
        mr_mesh_lod_free(lod);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for levels of detail", who);
    }
    lod->distinct_count = w.count;
    for (uint32_t p = 0; p < w.count; p++)
        lod->distinct[p] = w.members[w.first[p]];
    for (uint32_t k = 1; k < MR_MESH_LOD_MAX; k++) {
        uint32_t before = lod->triangles[k - 1];
        size_t target = (size_t)(nt >> k) * 3;
        if (target < 3 * LOD_MIN_TRIANGLES)
            break;
        /* each level from the full mesh; no error limit: the count decides
         * and the measured error says what it cost */
        size_t n = meshopt_simplify(scratch, w.idx, (size_t)nt * 3, w.pos, w.count,
                                    3 * sizeof(float), target, 1.0f, 0, NULL);
        uint32_t tris = (uint32_t)(n / 3);
        if (tris < LOD_MIN_TRIANGLES || (double)tris > 0.9 * before)
            break;
        uint32_t *level = malloc(n * sizeof *level);
        if (!level) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for levels of detail", who);
            break;
        }
        unweld(&w, normals, scratch, tris, level);
        lod->indices[k] = level;
        lod->triangles[k] = tris;
        lod->level_count = k + 1;
    }
    free(scratch);
    weld_free(&w);
    if (rc == MR_OK)
        rc = mr_mesh_lod_measure(lod, pos, nv, 1, threads, who, err);
    if (rc < 0)
        mr_mesh_lod_free(lod);
    return rc;
}

void mr_mesh_lod_free(mr_mesh_lod *lod)
{
    for (uint32_t k = 1; k < lod->level_count; k++)
        free(lod->indices[k]);
    free(lod->distinct);
    memset(lod, 0, sizeof *lod);
}

size_t mr_mesh_lod_memory(const mr_mesh_lod *lod)
{
    size_t b = (size_t)lod->distinct_count * sizeof(uint32_t);
    for (uint32_t k = 1; k < lod->level_count; k++)
        b += (size_t)lod->triangles[k] * 3 * sizeof(uint32_t);
    return b;
}
