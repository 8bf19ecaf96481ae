/*
 * displaced_kind.c - the displacement-mapped kind (paper 003, issue 14).
 *
 * create   merges the asset's meshes (every one needs texture coordinates)
 *          into one base mesh, maps every corner to grid space (dgrid.h:
 *          u W, v H of the texture's mip level) and sets up one mr_dbase per
 *          base triangle (dsurf.h); the height texture's min/max pyramid is
 *          built here (about 1 ms per million texels on two threads,
 *          cheaper than reading it back from a disk cache, so the kind
 *          keeps no derived data); mode tessellated also lays out the
 *          micro-triangles (their count and order depend only on the
 *          texture coordinates);
 * update   poses the base mesh like the mesh kind (linear blend skinning,
 *          the object transform), then per base triangle: the gradients of
 *          P and N over grid space and the Embree box (three parallelograms,
 *          dtrace.h), or, tessellated, every micro-vertex again;
 * attach   tessellation_free and raymarch: one Embree USER geometry, one
 *          primitive per base triangle, refit every frame for animated
 *          objects (the renderer asks for REFIT); tessellated: TRIANGLE;
 * normal   the geometric normal of the micro-triangle hit.
 *
 * Heights are in world units: the displacement does not scale with the
 * object's transform or its bones (the normal is a unit vector, eq. 2.1).
 */
#include <limits.h>
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "asset/image.h"
#include "kinds/displaced/dgrid.h"
#include "kinds/displaced/displaced_kind.h"
#include "kinds/displaced/dsurf.h"
#include "kinds/displaced/dtrace.h"
#include "kinds/displaced/tiling.h"
#include "kinds/lod.h"
#include "kinds/user_rays.h"
#include "util/clock.h"
#include "util/parallel.h"

#define UPDATE_GRAIN 32

/* The traversal's work counters, added to by every Embree callback: one
 * stripe per thread, each 128 bytes apart so no two stripes' counters
 * share a cache line. On one shared line the two cores passed it back and
 * forth on every call (add_stats was 4.7 % of displaced-sphere's profile;
 * its trace, medians of 5 interleaved runs: 113 ms shared, 106 striped,
 * 108 counting nothing). A thread owns its stripe while it lives
 * (my_stripe), so it adds without a locked instruction, which cost 3.5 %
 * of the sphere's process at 400 texels per unit; threads beyond the
 * first COUNT_STRIPES - 1 alive at once share the last stripe and lock. */
#define COUNT_STRIPES 16
typedef struct count_stripe {
    _Atomic uint64_t calls, nodes, cells, tests;
    char apart[96];
} count_stripe;

struct mr_geom {
    const mr_asset *asset;
    mr_displaced_params par;
    const char *texture_name;      /* for messages */
    uint32_t vertex_count, triangle_count;
    uint32_t *mesh_first_vertex;
    double *grid_uv;               /* per vertex: grid coordinates (2) */
    float *positions, *normals;    /* posed base vertices (3 each, + 1 float padding) */
    uint32_t *indices;             /* 3 per base triangle */
    mr_dgrid grid;                 /* texture source */
    mr_dproc proc;                 /* procedural source */
    bool procedural;
    mr_dbase *bases;
    mr_dgrad *grads;
    mr_droots *roots;              /* texture source: each triangle's roots (fixed by its UVs) */
    mr_dproots *proots;            /* procedural source: the same */
    float *boxes;                  /* 6 per base triangle */
    mr_dscene scene;
    /* tessellated */
    uint32_t *tess_vfirst, *tess_tfirst; /* per base triangle + 1 */
    uint32_t tess_vertices, tess_triangles;
    float *tess_pos;               /* 3 per micro-vertex + 1 padding */
    uint32_t *tess_idx;
    double bounds_s;               /* last update's seconds */
    count_stripe counts[COUNT_STRIPES];
    RTCGeometry rtc;
    /* Levels of detail ("tolerance_px"; kinds/lod.h): this object is the
     * finest (its "level" or "range"), coarser[k - 1] the same surface at
     * mip level level + k (procedural: range / 2^k) over this object's
     * posed base mesh (shares_base: its positions and normals are this
     * object's). */
    bool shares_base;
    double tolerance_px;           /* 0: no levels */
    uint32_t lod_count, lod_cur;   /* levels (1: none); the frame's */
    uint32_t lod_posed;            /* levels set up for this pose */
    mr_lod_switch lod_sw;          /* the level enabled in Embree; dirty: levels set up since
                                      the last commit */
    mr_geom *coarser[MR_DISPLACED_LOD_MAX - 1];
    double lod_error[MR_DISPLACED_LOD_MAX]; /* finest first: distance to the ground truth */
    double height_reach;           /* the largest |height|: the surface lies within it of the
                                      base mesh */
    double predicted_px, lod_build_s;
};

/* The level traced this frame. */
static mr_geom *traced(const mr_geom *g)
{
    return g->lod_cur == 0 ? (mr_geom *)g : g->coarser[g->lod_cur - 1];
}

static bool tessellated(const mr_geom *g) { return g->par.method == MR_DISPLACED_TESSELLATED; }

static void displaced_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    for (uint32_t k = 1; k < g->lod_count; k++)
        displaced_free(g->coarser[k - 1]);
    free(g->mesh_first_vertex);
    free(g->grid_uv);
    if (!g->shares_base) {
        free(g->positions);
        free(g->normals);
    }
    free(g->indices);
    mr_dgrid_free(&g->grid);
    mr_dproc_free(&g->proc);
    free(g->bases);
    free(g->grads);
    free(g->roots);
    free(g->proots);
    free(g->boxes);
    free(g->tess_vfirst);
    free(g->tess_tfirst);
    free(g->tess_pos);
    free(g->tess_idx);
    free(g);
}

/* ---- tessellation ------------------------------------------------------------------ */

/* Deduplication of one base triangle's micro-vertices by their records. */
typedef struct vkey {
    uint64_t k1, k2;
} vkey;

typedef struct vtable {
    vkey *keys;
    uint32_t *vals;
    size_t cap;   /* power of two; unused slots have vals == UINT32_MAX */
    size_t count; /* slots used */
} vtable;

static vkey key_of(const mr_dvert *v)
{
    vkey k = {(uint64_t)v->kind << 56 | (uint64_t)v->idx << 48 | (uint64_t)v->fam << 40, 0};
    if (v->kind == MR_DV_GRID)
        k.k2 = (uint64_t)(uint32_t)v->a | (uint64_t)(uint32_t)v->b << 32, k.k1 |= (uint64_t)((v->a >> 32) & 0xffff) << 16 | (uint64_t)((v->b >> 32) & 0xffff);
    else if (v->kind == MR_DV_EDGE)
        k.k2 = (uint64_t)v->a;
    return k;
}

/* Empties t, with room for about `want` vertices (at most 2^16 at first:
 * a base triangle's box can hold far more cells than the triangle, and
 * vtable_get grows the table as vertices come). */
static bool vtable_reset(vtable *t, size_t want)
{
    size_t cap = 64;
    while (cap < want * 2 && cap < (size_t)1 << 17)
        cap *= 2;
    t->count = 0;
    if (cap > t->cap) {
        vkey *k = realloc(t->keys, cap * sizeof *k);
        uint32_t *v = k ? realloc(t->vals, cap * sizeof *v) : NULL;
        if (k)
            t->keys = k;
        if (!k || !v)
            return false;
        t->vals = v;
        t->cap = cap;
    }
    memset(t->vals, 0xff, t->cap * sizeof *t->vals);
    return true;
}

static size_t vtable_slot(const vtable *t, vkey k)
{
    uint64_t h = (k.k1 * 0x9e3779b97f4a7c15ull) ^ (k.k2 * 0xc2b2ae3d27d4eb4full);
    h ^= h >> 29;
    const size_t mask = t->cap - 1;
    size_t s = (size_t)h & mask;
    while (t->vals[s] != UINT32_MAX && (t->keys[s].k1 != k.k1 || t->keys[s].k2 != k.k2))
        s = (s + 1) & mask;
    return s;
}

/* Twice the slots, every entry moved; false when out of memory (t as it was). */
static bool vtable_grow(vtable *t)
{
    vtable n = {.cap = t->cap * 2, .count = t->count};
    n.keys = malloc(n.cap * sizeof *n.keys);
    n.vals = malloc(n.cap * sizeof *n.vals);
    if (!n.keys || !n.vals) {
        free(n.keys), free(n.vals);
        return false;
    }
    memset(n.vals, 0xff, n.cap * sizeof *n.vals);
    for (size_t i = 0; i < t->cap; i++)
        if (t->vals[i] != UINT32_MAX) {
            const size_t s = vtable_slot(&n, t->keys[i]);
            n.keys[s] = t->keys[i];
            n.vals[s] = t->vals[i];
        }
    free(t->keys), free(t->vals);
    *t = n;
    return true;
}

/* Index of k, or a new slot (*fresh) given index `next`; UINT32_MAX when
 * out of memory. */
static uint32_t vtable_get(vtable *t, vkey k, uint32_t next, bool *fresh)
{
    if (2 * (t->count + 1) > t->cap && !vtable_grow(t))
        return UINT32_MAX;
    const size_t s = vtable_slot(t, k);
    if (t->vals[s] == UINT32_MAX) {
        t->keys[s] = k;
        t->vals[s] = next;
        t->count++;
        *fresh = true;
        return next;
    }
    *fresh = false;
    return t->vals[s];
}

/* The micro-triangles of base triangle t in the tessellation's order:
 * calls emit_v for each new micro-vertex (in order) and emit_t per
 * micro-triangle with local vertex indices, while `full` (NULL: never)
 * says there is room. Returns MR_OK, MR_ERR_LIMIT when full stopped it
 * or MR_ERR_NOMEM. */
typedef struct tess_sink {
    void (*vertex)(void *user, const mr_dvert *v);
    void (*triangle)(void *user, uint32_t a, uint32_t b, uint32_t c);
    bool (*full)(void *user);
    void *user;
} tess_sink;

static int tessellate_base(const mr_dbase *b, vtable *vt, const tess_sink *sink)
{
    uint32_t nv = 0;
    if (b->flat) {
        static _Thread_local mr_dvert pts[1024];
        int n = mr_dsurf_flat_boundary(b, pts, 1024);
        for (int k = 0; k < n; k++)
            sink->vertex(sink->user, &pts[k]);
        for (int k = 1; k + 1 < n; k++)
            sink->triangle(sink->user, 0, (uint32_t)k, (uint32_t)k + 1);
        return MR_OK;
    }
    int64_t i0, i1, j0, j1;
    mr_dbase_cells(b, &i0, &i1, &j0, &j1);
    size_t cells = i1 >= i0 && j1 >= j0 ? (size_t)(i1 - i0 + 1) * (size_t)(j1 - j0 + 1) : 0;
    if (!vtable_reset(vt, cells + 16))
        return MR_ERR_NOMEM;
    for (int64_t j = j0; j <= j1; j++) {
        if (sink->full && sink->full(sink->user))
            return MR_ERR_LIMIT;
        for (int64_t i = i0; i <= i1; i++) {
            mr_dcell c;
            mr_dsurf_cell(b, i, j, 2, &c);
            uint32_t local[2 * MR_DSURF_MAX_POLY];
            for (int k = 0; k < c.nv; k++) {
                bool fresh;
                local[k] = vtable_get(vt, key_of(&c.v[k]), nv, &fresh);
                if (local[k] == UINT32_MAX)
                    return MR_ERR_NOMEM;
                if (fresh) {
                    sink->vertex(sink->user, &c.v[k]);
                    nv++;
                }
            }
            for (int k = 0; k < c.nt; k++)
                sink->triangle(sink->user, local[c.tri[k][0]], local[c.tri[k][1]], local[c.tri[k][2]]);
        }
    }
    return MR_OK;
}

/* Counting pass: the tessellation's micro-vertices and micro-triangles so
 * far (v, t), full past the caps. */
typedef struct count_sink {
    uint64_t v, t;
} count_sink;
static void count_v(void *u, const mr_dvert *v) { (void)v, ((count_sink *)u)->v++; }
static void count_t(void *u, uint32_t a, uint32_t b, uint32_t c)
{
    (void)a, (void)b, (void)c;
    ((count_sink *)u)->t++;
}
static bool count_full(void *u)
{
    const count_sink *c = u;
    return c->v > MR_MAX_ASSET_VERTICES || c->t > MR_MAX_ASSET_TRIANGLES;
}

/* Filling pass: positions from the current pose, indices offset. */
typedef struct fill_sink {
    const mr_geom *g;
    const mr_dbase *b;
    float *pos;
    uint32_t *idx;
    uint32_t v0, nv, nt;
    bool indices;
} fill_sink;

static void fill_v(void *u, const mr_dvert *v)
{
    fill_sink *f = u;
    mr_vec3 p = mr_dsurf_vertex(f->b, &f->g->scene.heights, v);
    float *o = f->pos + (size_t)f->nv++ * 3;
    o[0] = p.x, o[1] = p.y, o[2] = p.z;
}

static void fill_t(void *u, uint32_t a, uint32_t b, uint32_t c)
{
    fill_sink *f = u;
    if (f->indices) {
        uint32_t *o = f->idx + (size_t)f->nt * 3;
        o[0] = f->v0 + a, o[1] = f->v0 + b, o[2] = f->v0 + c;
    }
    f->nt++;
}

static int tess_layout(mr_geom *g, const char *what, mr_error *err)
{
    size_t nt = g->triangle_count;
    g->tess_vfirst = malloc((nt + 1) * sizeof(uint32_t));
    g->tess_tfirst = malloc((nt + 1) * sizeof(uint32_t));
    vtable vt = {0};
    if (!g->tess_vfirst || !g->tess_tfirst)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory tessellating", what);
    /* two micro-triangles a whole cell: the base triangles' area in cells
     * says at once when the caps cannot hold them (counting them first
     * would make every cell of a tessellation of billions) */
    double cells = 0;
    for (size_t k = 0; k < nt; k++) {
        const double(*gk)[2] = g->bases[k].g;
        cells += 0.5 * fabs((gk[1][0] - gk[0][0]) * (gk[2][1] - gk[0][1]) -
                            (gk[2][0] - gk[0][0]) * (gk[1][1] - gk[0][1]));
    }
    count_sink c = {0};
    int rc = cells > (double)MR_MAX_ASSET_TRIANGLES ? MR_ERR_LIMIT : MR_OK;
    size_t k = 0;
    for (; k < nt && rc == MR_OK; k++) {
        g->tess_vfirst[k] = (uint32_t)c.v;
        g->tess_tfirst[k] = (uint32_t)c.t;
        tess_sink s = {count_v, count_t, count_full, &c};
        if ((rc = tessellate_base(&g->bases[k], &vt, &s)) == MR_OK && count_full(&c))
            rc = MR_ERR_LIMIT;
    }
    free(vt.keys);
    free(vt.vals);
    if (rc == MR_ERR_NOMEM)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory tessellating", what);
    if (rc == MR_ERR_LIMIT) {
        char why[96];
        if (k)
            snprintf(why, sizeof why, "base triangle %zu reached %llu", k - 1, (unsigned long long)c.t);
        else
            snprintf(why, sizeof why, "the base mesh covers %.3g cells, two each", cells);
        return mr_error_set(err, MR_ERR_LIMIT,
                            "%s: the tessellation would have more than %u micro-triangles (%s): use a "
                            "coarser \"level\" or \"range\", or method \"tessellation_free\"",
                            what, MR_MAX_ASSET_TRIANGLES, why);
    }
    const uint64_t v = c.v, t = c.t;
    g->tess_vfirst[nt] = (uint32_t)v;
    g->tess_tfirst[nt] = (uint32_t)t;
    g->tess_vertices = (uint32_t)v;
    g->tess_triangles = (uint32_t)t;
    g->tess_pos = calloc((size_t)v * 3 + 1, sizeof(float));
    g->tess_idx = malloc(((size_t)t * 3 + 1) * sizeof(uint32_t));
    if (!g->tess_pos || !g->tess_idx)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %llu micro-triangles", what,
                            (unsigned long long)t);
    return MR_OK;
}

typedef struct tess_ctx {
    mr_geom *g;
    float *pos;
    uint32_t *idx;
    bool indices;
    _Atomic bool failed;
} tess_ctx;

static void tess_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    tess_ctx *c = ctx;
    vtable vt = {0};
    for (size_t k = begin; k < end; k++) {
        fill_sink f = {.g = c->g, .b = &c->g->bases[k],
                       .pos = c->pos + (size_t)c->g->tess_vfirst[k] * 3,
                       .idx = c->idx + (size_t)c->g->tess_tfirst[k] * 3,
                       .v0 = c->g->tess_vfirst[k], .indices = c->indices};
        tess_sink s = {fill_v, fill_t, NULL, &f};
        if (tessellate_base(f.b, &vt, &s) != MR_OK)
            atomic_store(&c->failed, true);
    }
    free(vt.keys);
    free(vt.vals);
}

/* Micro-vertices (and indices) of the current pose into pos / idx. */
static int tess_fill(mr_geom *g, float *pos, uint32_t *idx, bool indices, unsigned threads,
                     mr_error *err)
{
    tess_ctx c = {.g = g, .pos = pos, .idx = idx, .indices = indices};
    atomic_init(&c.failed, false);
    mr_parallel_for(threads, g->triangle_count, 1, tess_range, &c);
    if (atomic_load(&c.failed))
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory tessellating", g->asset->path);
    return MR_OK;
}

/* ---- create ------------------------------------------------------------------------ */

static const mr_asset *param_asset(const mr_kind_context *ctx, uint32_t ref)
{
    return ref && ctx && ctx->assets && ref - 1 < ctx->asset_count ? ctx->assets[ref - 1] : NULL;
}

/* The surface of par over the asset's nv vertices and nt triangles; with
 * share, over share's posed base mesh (a coarser level of detail). */
static int create_surface(const mr_asset *asset, const mr_displaced_params *par,
                          const mr_asset *tex, uint32_t nv, uint32_t nt, unsigned threads,
                          const mr_geom *share, mr_geom **out, mr_error *err)
{
    *out = NULL;
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating a displaced object");
    int rc = MR_OK;
    g->asset = asset;
    g->par = *par;
    g->texture_name = tex->path;
    g->vertex_count = nv;
    g->triangle_count = nt;
    g->mesh_first_vertex = calloc(asset->mesh_count ? asset->mesh_count : 1, sizeof(uint32_t));
    g->grid_uv = malloc((size_t)nv * 2 * sizeof(double));
    g->shares_base = share != NULL;
    g->positions = share ? share->positions : calloc((size_t)nv * 3 + 1, sizeof(float));
    g->normals = share ? share->normals : calloc((size_t)nv * 3 + 1, sizeof(float));
    g->indices = malloc(nt * 3 * sizeof(uint32_t));
    g->bases = calloc(nt, sizeof *g->bases);
    g->grads = calloc(nt, sizeof *g->grads);
    g->roots = par->procedural ? NULL : calloc(nt, sizeof *g->roots);
    g->proots = par->procedural ? calloc(nt, sizeof *g->proots) : NULL;
    g->boxes = calloc(nt * 6, sizeof(float));
    if (!g->mesh_first_vertex || !g->grid_uv || !g->positions || !g->normals || !g->indices ||
        !g->bases || !g->grads || !g->boxes || (par->procedural ? !g->proots : !g->roots))
        goto nomem;
    g->procedural = par->procedural;
    if (g->procedural) {
        if ((rc = mr_dproc_init(&g->proc, tex->image, par->uv_offset[0], par->uv_offset[1],
                                par->uv_scale, par->triangle_size, par->seed, par->range,
                                par->scale, par->offset, threads, err)) < 0)
            goto fail;
        g->scene = (mr_dscene){.bases = g->bases, .grads = g->grads, .proc = &g->proc,
                               .proots = g->proots, .heights = mr_dproc_heights(&g->proc),
                               .local = (mr_dlocal)par->local, .march_steps = par->steps};
    } else {
        if ((rc = mr_dgrid_init(&g->grid, tex->image, par->level, par->scale, par->offset,
                                threads, err)) < 0)
            goto fail;
        g->scene = (mr_dscene){.bases = g->bases, .grads = g->grads, .grid = &g->grid,
                               .roots = g->roots,
                               .heights = mr_dgrid_heights(&g->grid),
                               .local = (mr_dlocal)par->local, .march_steps = par->steps};
    }
    uint32_t v0 = 0, t0 = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        g->mesh_first_vertex[i] = v0;
        for (uint32_t k = 0; k < m->vertex_count; k++) {
            double *gv = g->grid_uv + (size_t)(v0 + k) * 2;
            if (g->procedural) {
                mr_dproc_grid_of(&g->proc, m->uvs[k * 2], m->uvs[k * 2 + 1], gv);
            } else {
                gv[0] = (double)m->uvs[k * 2] * g->grid.w;
                gv[1] = (double)m->uvs[k * 2 + 1] * g->grid.h;
            }
            if (!share) {
                memcpy(g->positions + (size_t)(v0 + k) * 3, m->positions + (size_t)k * 3,
                       3 * sizeof(float));
                memcpy(g->normals + (size_t)(v0 + k) * 3, m->normals + (size_t)k * 3,
                       3 * sizeof(float));
            }
        }
        for (uint64_t k = 0; k < (uint64_t)m->triangle_count * 3; k++)
            g->indices[(uint64_t)t0 * 3 + k] = m->indices[k] + v0;
        v0 += m->vertex_count;
        t0 += m->triangle_count;
    }
    for (size_t t = 0; t < nt; t++) {
        const uint32_t *tri = g->indices + t * 3;
        double gg[3][2];
        const float *p[3], *n[3];
        for (int k = 0; k < 3; k++) {
            gg[k][0] = g->grid_uv[(size_t)tri[k] * 2];
            gg[k][1] = g->grid_uv[(size_t)tri[k] * 2 + 1];
            p[k] = g->positions + (size_t)tri[k] * 3;
            n[k] = g->normals + (size_t)tri[k] * 3;
        }
        mr_dbase_init(&g->bases[t], gg, p, n, &g->scene.heights);
        double hlo, hhi;
        if (g->procedural) {
            mr_dtrace_proc_roots(&g->proc, &g->bases[t], &g->proots[t], &hlo, &hhi);
        } else {
            mr_dtrace_roots(&g->grid, &g->bases[t], &g->roots[t]);
            mr_dtrace_root_heights(&g->grid, &g->bases[t], &hlo, &hhi);
        }
        g->grads[t].hlo = hlo;
        g->grads[t].hhi = hhi;
        if (g->par.method == MR_DISPLACED_TESSELLATION_FREE) {
            /* cells that floats can place (MR_DTRACE_MAX_PAD_CELLS), in the
             * rest pose: a pose that shrinks a triangle pads its boxes by
             * more cells, but it has no more cells to visit than before */
            mr_dgrad rest;
            mr_dgrad_init(&rest, &g->bases[t], hlo, hhi);
            if (rest.local && !(fmax(rest.lpad[0], rest.lpad[1]) <= MR_DTRACE_MAX_PAD_CELLS)) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "%s: base triangle %zu spans so many height cells that float "
                                  "coordinates cannot place its micro-vertices within %g cells: "
                                  "lower displaced.range or the heights (displaced.scale, "
                                  "displaced.offset), raise displaced.level or procedural.triangle_size, "
                                  "or shrink the texture coordinates' span",
                                  asset->path, t, MR_DTRACE_MAX_PAD_CELLS);
                goto fail;
            }
        }
    }
    if (tessellated(g)) {
        if ((rc = tess_layout(g, asset->path, err)) < 0 ||
            (rc = tess_fill(g, g->tess_pos, g->tess_idx, true, threads, err)) < 0)
            goto fail;
    }
    *out = g;
    return MR_OK;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a displaced object", asset->path);
fail:
    displaced_free(g);
    return rc;
}

/* ---- levels of detail ---------------------------------------------------------------- */

/* How far the surface at mip level lv strays from the surface at mip level
 * 0 (truth), the ground truth: the distance of their height fields
 * (mr_dgrid_distance). At equal texture coordinates the two surfaces differ
 * by their height difference along the unit normal (their base points are
 * the same affine map of the texture coordinates), so it bounds how far
 * apart they are, but for one second-order term: the interpolated normal
 * turns across a coarse cell, which moves a height h by about h times the
 * square of the angle it turns. The reference passes measure the whole
 * (tests/unit/test_displaced_lod.c). */
static double level_error(const mr_dgrid *truth, const mr_dgrid *lv, unsigned threads)
{
    return mr_dgrid_distance(truth, lv, threads);
}

/* Levels of detail: the texture's mip levels from the object's own up to
 * the first of one sample (at most MR_DISPLACED_LOD_MAX), each with its
 * distance to mip level 0, the ground truth (level_error). */
static int create_levels(mr_geom *g, const mr_asset *tex, unsigned threads, mr_error *err)
{
    double t0 = mr_now();
    mr_dgrid finest = {0};
    const mr_dgrid *truth = &g->grid;
    int rc = MR_OK;
    if (g->par.level > 0) {
        if ((rc = mr_dgrid_init(&finest, tex->image, 0, g->par.scale, g->par.offset, threads,
                                err)) < 0)
            return rc;
        truth = &finest;
        g->lod_error[0] = level_error(truth, &g->grid, threads);
    }
    const mr_dgrid *last = &g->grid;
    while (g->lod_count < MR_DISPLACED_LOD_MAX && (last->w > 1 || last->h > 1) &&
           g->par.level + g->lod_count <= MR_DISPLACED_MAX_LEVEL) {
        mr_displaced_params p = g->par;
        p.level += g->lod_count;
        /* A mip level with no more cells than the mesh has base triangles is
         * a few micro-triangles per base triangle: traced as its
         * tessellation, which holds less than the tessellation-free set-up
         * of its triangles (their gradients, boxes and roots) and which
         * Embree's own triangles intersect faster than a traversal per
         * base triangle. */
        uint32_t s = 1u << p.level;
        uint64_t cells = (uint64_t)((tex->image->width + s - 1) / s) *
                         ((tex->image->height + s - 1) / s);
        if (p.method == MR_DISPLACED_TESSELLATION_FREE && cells <= g->triangle_count)
            p.method = MR_DISPLACED_TESSELLATED;
        mr_geom *c;
        if ((rc = create_surface(g->asset, &p, tex, g->vertex_count, g->triangle_count, threads,
                                 g, &c, err)) < 0)
            break;
        g->coarser[g->lod_count - 1] = c;
        g->lod_error[g->lod_count] = level_error(truth, &c->grid, threads);
        g->lod_count++;
        last = &c->grid;
    }
    mr_dgrid_free(&finest);
    g->height_reach = fmax(fabs(mr_dgrid_height_of(&g->grid, g->grid.gmin)),
                           fabs(mr_dgrid_height_of(&g->grid, g->grid.gmax)));
    g->lod_build_s = mr_now() - t0;
    return rc;
}

/* Levels of detail, procedural source: the same tiling and blending at
 * half the range, a quarter, ... down to 1 (at most MR_DISPLACED_LOD_MAX
 * levels), each with its distance (mr_dproc_distance) to the ground truth
 * its reference pass draws: the same texture at twice the object's range
 * (at the largest range, the object's own). Heights are world units along
 * the unit normal, as for a height texture (level_error). */
static int create_proc_levels(mr_geom *g, const mr_asset *tex, unsigned threads, mr_error *err)
{
    double t0 = mr_now();
    const mr_displaced_params *par = &g->par;
    const size_t nt = g->triangle_count;
    const uint32_t up = par->range < MR_DISPLACED_MAX_RANGE ? 2 : 1;
    double *tri = malloc(nt * 6 * sizeof(double) + 1); /* in the truth's grid coordinates */
    if (!tri)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for levels of detail",
                            g->asset->path);
    for (size_t t = 0; t < nt; t++)
        for (int k = 0; k < 3; k++)
            for (int a = 0; a < 2; a++)
                tri[6 * t + 2 * k + a] = g->grid_uv[(size_t)g->indices[3 * t + k] * 2 + a] * up;
    mr_dproc finer = {0};
    const mr_dproc *truth = &g->proc;
    int rc = MR_OK;
    if (up > 1) {
        if ((rc = mr_dproc_init(&finer, tex->image, par->uv_offset[0], par->uv_offset[1],
                                par->uv_scale, par->triangle_size, par->seed, par->range * up,
                                par->scale, par->offset, threads, err)) < 0) {
            free(tri);
            return rc;
        }
        truth = &finer;
        g->lod_error[0] = mr_dproc_distance(truth, &g->proc, tri, nt, threads);
    }
    for (uint32_t r = par->range / 2; r >= 1 && g->lod_count < MR_DISPLACED_LOD_MAX; r /= 2) {
        mr_displaced_params p = *par;
        p.range = r;
        mr_geom *c;
        if ((rc = create_surface(g->asset, &p, tex, g->vertex_count, g->triangle_count, threads, g,
                                 &c, err)) < 0)
            break;
        g->coarser[g->lod_count - 1] = c;
        g->lod_error[g->lod_count] = mr_dproc_distance(truth, &c->proc, tri, nt, threads);
        g->lod_count++;
    }
    if (truth == &finer)
        mr_dproc_free(&finer);
    free(tri);
    double lo, hi;
    mr_dproc_global_heights(&g->proc, &lo, &hi);
    g->height_reach = fmax(fabs(lo), fabs(hi));
    g->lod_build_s = mr_now() - t0;
    return rc;
}

static int displaced_create(const mr_asset *asset, const mr_object_desc *desc,
                            const mr_kind_context *ctx, mr_geom **out, mr_error *err)
{
    *out = NULL;
    if (!desc->params)
        return mr_error_set(err, MR_ERR_INVALID, "a displaced object needs its parameters");
    const mr_displaced_params *par = desc->params;
    const mr_asset *tex = param_asset(ctx, par->procedural ? par->example : par->texture);
    if (!tex)
        return mr_error_set(err, MR_ERR_INVALID, "a displaced object needs its height %s",
                            par->procedural ? "example" : "texture");
    if (!tex->image)
        return mr_error_set(err, MR_ERR_INVALID,
                            "displaced %s %s is a model, not an image (PNG, JPEG or EXR)",
                            par->procedural ? "example" : "texture", tex->path);
    uint64_t nv = 0, nt = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        if (!m->uvs && m->triangle_count)
            return mr_error_set(err, MR_ERR_FORMAT,
                                "%s: mesh %zu (\"%s\") has no texture coordinates, which a "
                                "displaced object needs",
                                asset->path, i, m->name ? m->name : "");
        nv += m->vertex_count;
        nt += m->triangle_count;
    }
    if (nt == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: no triangles to render", asset->path);
    if (nv > MR_MAX_ASSET_VERTICES || nt > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT, "%s: %llu vertices / %llu triangles exceed the caps",
                            asset->path, (unsigned long long)nv, (unsigned long long)nt);
    unsigned threads = ctx ? ctx->threads : 0;
    mr_geom *g;
    int rc = create_surface(asset, par, tex, (uint32_t)nv, (uint32_t)nt, threads, NULL, &g, err);
    if (rc < 0)
        return rc;
    g->lod_count = 1;
    g->lod_sw.enabled = UINT32_MAX;
    g->tolerance_px = desc->tolerance_px > 0 ? desc->tolerance_px : 0;
    if (g->tolerance_px > 0 &&
        (rc = (par->procedural ? create_proc_levels : create_levels)(g, tex, threads, err)) < 0) {
        displaced_free(g);
        return rc;
    }
    *out = g;
    return MR_OK;
}

/* ---- update ------------------------------------------------------------------------ */

typedef struct update_ctx {
    mr_geom *g;
    uint32_t bad[MR_MAX_THREADS];
} update_ctx;

static bool finite_bounded(const float v[3])
{
    return fabsf(v[0]) <= MR_MAX_COORDINATE && fabsf(v[1]) <= MR_MAX_COORDINATE &&
           fabsf(v[2]) <= MR_MAX_COORDINATE;
}

static void update_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    update_ctx *c = ctx;
    mr_geom *g = c->g;
    for (size_t t = begin; t < end; t++) {
        const uint32_t *tri = g->indices + t * 3;
        const float *p[3], *n[3];
        for (int k = 0; k < 3; k++) {
            p[k] = g->positions + (size_t)tri[k] * 3;
            n[k] = g->normals + (size_t)tri[k] * 3;
        }
        mr_dbase *b = &g->bases[t];
        mr_dbase_pose(b, p, n);
        mr_dgrad_init(&g->grads[t], b, g->grads[t].hlo, g->grads[t].hhi);
        float *box = g->boxes + t * 6;
        mr_dtrace_tri_box(b, &g->scene.heights, &g->grads[t], box, box + 3);
        if (!finite_bounded(box) || !finite_bounded(box + 3))
            if (!c->bad[worker])
                c->bad[worker] = (uint32_t)t + 1;
    }
}

/* The surface of level g (its bases, gradients and boxes, or its
 * micro-vertices) over its posed base mesh. */
static int update_surface(mr_geom *g, unsigned threads, mr_error *err)
{
    update_ctx *c = calloc(1, sizeof *c);
    if (!c)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory updating a displaced object");
    c->g = g;
    mr_parallel_for(threads, g->triangle_count, UPDATE_GRAIN, update_range, c);
    uint32_t bad = 0;
    for (unsigned w = 0; w < MR_MAX_THREADS; w++)
        if (c->bad[w] && (!bad || c->bad[w] < bad))
            bad = c->bad[w];
    free(c);
    g->scene.pose = mr_dscene_new_pose(); /* the bases moved: cells made before are stale */
    if (bad)
        return mr_error_set(err, MR_ERR_INVALID,
                            "%s: the displaced surface of base triangle %u is not finite or "
                            "beyond %g: check the heights' scale and the object's transform",
                            g->asset->path, bad - 1, MR_MAX_COORDINATE);
    int rc = MR_OK;
    if (tessellated(g) && (rc = tess_fill(g, g->tess_pos, g->tess_idx, false, threads, err)) == MR_OK)
        for (size_t k = 0; k < (size_t)g->tess_vertices * 3; k++)
            if (!(fabsf(g->tess_pos[k]) <= MR_MAX_COORDINATE)) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "%s: micro-vertex %zu is not finite or beyond %g: check the "
                                  "heights' scale and the object's transform",
                                  g->asset->path, k / 3, MR_MAX_COORDINATE);
                break;
            }
    return rc;
}

/* The level whose distance to the ground truth, projected at the posed base
 * mesh's nearest depth (its bounds grown by the largest height: the surface
 * lies within them), stays below the tolerance. Heights are world units
 * whatever the transform (the normal is a unit vector), so the distances
 * need no stretch. */
static void pick_level(mr_geom *g, const mr_geom_frame *frame)
{
    mr_vec3 lo = mr_v3(INFINITY, INFINITY, INFINITY), hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    for (size_t v = 0; v < g->vertex_count; v++) {
        mr_vec3 p = mr_v3(g->positions[3 * v], g->positions[3 * v + 1], g->positions[3 * v + 2]);
        lo = mr_v3_min(lo, p);
        hi = mr_v3_max(hi, p);
    }
    float pad = (float)g->height_reach;
    lo = mr_v3_sub(lo, mr_v3(pad, pad, pad));
    hi = mr_v3_add(hi, mr_v3(pad, pad, pad));
    double px = mr_camera_px_per_unit(&frame->camera, frame->width, frame->height, lo, hi);
    g->lod_cur = mr_lod_pick(g->lod_error, g->lod_count, px, g->tolerance_px, &g->predicted_px);
}

/* Poses the base mesh (unless only the camera moved), picks the level
 * (with a tolerance) and sets up its surface, unless it already is for
 * this pose. */
static int displaced_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                            const mr_mat4 *transform, unsigned threads, mr_error *err)
{
    double t0 = mr_now();
    if (!(frame && frame->view_only)) {
        for (size_t i = 0; i < g->asset->mesh_count; i++) {
            size_t off = (size_t)g->mesh_first_vertex[i] * 3;
            mr_skin_mesh(g->asset, i, pose, transform, g->positions + off, g->normals + off,
                         threads);
        }
        for (size_t k = 0; k < (size_t)g->vertex_count * 3; k++)
            if (!(fabsf(g->positions[k]) <= MR_MAX_COORDINATE))
                return mr_error_set(err, MR_ERR_INVALID,
                                    "%s: posed vertex %zu has a coordinate of %g (limit %g): "
                                    "check the object's transform and pose",
                                    g->asset->path, k / 3, (double)g->positions[k],
                                    MR_MAX_COORDINATE);
        g->lod_posed = 0;
    }
    if (g->lod_count > 1 && frame)
        pick_level(g, frame);
    int rc = MR_OK;
    if (!(g->lod_posed & 1u << g->lod_cur)) {
        if ((rc = update_surface(traced(g), threads, err)) < 0)
            return rc;
        g->lod_posed |= 1u << g->lod_cur;
        g->lod_sw.dirty |= 1u << g->lod_cur;
    }
    g->bounds_s = mr_now() - t0;
    return rc;
}

/* ---- Embree ------------------------------------------------------------------------ */

static void bounds_cb(const struct RTCBoundsFunctionArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const float *b = g->boxes + (size_t)args->primID * 6;
    struct RTCBounds *o = args->bounds_o;
    o->lower_x = b[0], o->lower_y = b[1], o->lower_z = b[2];
    o->upper_x = b[3], o->upper_y = b[4], o->upper_z = b[5];
}

/* Ray i of an N-packet set up for the traversal, the thread's kept copy
 * (user_rays.h). */
MR_RAY_SETUP_CACHE_REF(ray_setup, mr_dray, mr_dray_setup)

static bool trace_one(mr_geom *g, unsigned prim, void *ray, unsigned N, unsigned i, bool any,
                      mr_dhit *h, mr_dstats *st)
{
    const mr_dray *r = ray_setup(ray, N, i);
    if (!r)
        return false;
    float *tfar = mr_ray_f(ray, N, MR_RAY_TFAR, i), tnear = *mr_ray_f(ray, N, MR_RAY_TNEAR, i);
    st->calls++;
    if (g->par.method == MR_DISPLACED_RAYMARCH)
        return mr_dtrace_march(&g->scene, prim, r, tnear, tfar, h, st);
    return mr_dtrace_intersect(&g->scene, prim, r, tnear, tfar, any, h, st);
}

/* The stripes owned by live threads (bit s: stripe s), given back by the
 * key's destructor when a thread exits. */
#define SHARED_STRIPE (COUNT_STRIPES - 1)
static _Atomic uint32_t stripes_owned;
static pthread_key_t stripe_key;
static pthread_once_t stripe_once = PTHREAD_ONCE_INIT;

static void stripe_give_back(void *owned)
{
    const unsigned s = (unsigned)(uintptr_t)owned - 1;
    /* (release: the next owner, which acquires, sees this thread's counts) */
    atomic_fetch_and_explicit(&stripes_owned, ~(1u << s), memory_order_release);
}

static void stripe_key_make(void)
{
    if (pthread_key_create(&stripe_key, stripe_give_back) != 0)
        atomic_store(&stripes_owned, (1u << SHARED_STRIPE) - 1); /* none to own: all share */
}

/* This thread's stripe of the counters: its own (taken on its first
 * count, while one is free) or SHARED_STRIPE. */
static unsigned my_stripe(void)
{
    static _Thread_local unsigned mine = UINT_MAX;
    if (mine != UINT_MAX)
        return mine;
    pthread_once(&stripe_once, stripe_key_make);
    uint32_t owned = atomic_load_explicit(&stripes_owned, memory_order_relaxed);
    for (;;) {
        const uint32_t free = ~owned & ((1u << SHARED_STRIPE) - 1);
        if (!free)
            return mine = SHARED_STRIPE;
        const unsigned s = (unsigned)__builtin_ctz(free);
        if (atomic_compare_exchange_weak_explicit(&stripes_owned, &owned, owned | 1u << s,
                                                  memory_order_acquire, memory_order_relaxed)) {
            if (pthread_setspecific(stripe_key, (void *)(uintptr_t)(s + 1)) == 0)
                return mine = s;
            /* no way to give it back at exit: share instead */
            stripe_give_back((void *)(uintptr_t)(s + 1));
            return mine = SHARED_STRIPE;
        }
    }
}

/* Adds n to counter x of this thread's stripe: a plain read and write
 * where the thread owns it (no other thread writes it, and the frame's
 * reader reads when every callback has returned), else a locked add. */
static inline void count_add(_Atomic uint64_t *x, uint64_t n, bool own)
{
    if (!n) /* (most calls make no cell and, at coarse levels, visit no node) */
        return;
    if (own)
        atomic_store_explicit(x, atomic_load_explicit(x, memory_order_relaxed) + n,
                              memory_order_relaxed);
    else
        atomic_fetch_add_explicit(x, n, memory_order_relaxed);
}

static void add_stats(mr_geom *g, const mr_dstats *st)
{
    const unsigned s = my_stripe();
    const bool own = s != SHARED_STRIPE;
    count_stripe *c = &g->counts[s];
    count_add(&c->nodes, st->nodes, own);
    count_add(&c->cells, st->cells, own);
    count_add(&c->tests, st->triangles, own);
    count_add(&c->calls, st->calls, own);
}

/* Writes hit h of lane i, whose tfar was `before` when the callback
 * began. A hit at the distance of the ray's hit so far on another of this
 * object's base triangles (a ray through a micro-vertex or edge on a
 * shared base edge) goes to the lower triangle id, so the winner does not
 * depend on the order Embree enters the triangles in (a packet enters
 * them in another order than a single ray). */
static void write_hit(const struct RTCIntersectFunctionNArguments *args, unsigned i,
                      const mr_dhit *h, float before)
{
    unsigned N = args->N;
    void *hit = (float *)args->rayhit + MR_RAY_FIELDS * N;
    if (h->t == before && *mr_ray_u(hit, N, MR_HIT_GEOM, i) == args->geomID &&
        *mr_ray_u(hit, N, MR_HIT_PRIM, i) < args->primID)
        return;
    mr_ray_write_hit(args, i, h->ng, h->b1, h->b2);
}

/* An N-packet's rays as mr_dtrace_intersect_packet takes them, set up on
 * demand by ray_setup. */
static mr_drays packet_rays(void *ray, unsigned N)
{
    return (mr_drays){.n = (int)N,
                      .o = {mr_ray_f(ray, N, MR_RAY_ORG, 0), mr_ray_f(ray, N, MR_RAY_ORG + 1, 0),
                            mr_ray_f(ray, N, MR_RAY_ORG + 2, 0)},
                      .d = {mr_ray_f(ray, N, MR_RAY_DIR, 0), mr_ray_f(ray, N, MR_RAY_DIR + 1, 0),
                            mr_ray_f(ray, N, MR_RAY_DIR + 2, 0)},
                      .tmin = mr_ray_f(ray, N, MR_RAY_TNEAR, 0),
                      .tmax = mr_ray_f(ray, N, MR_RAY_TFAR, 0),
                      .setup = ray_setup,
                      .ctx = ray};
}

/* The lanes of an N-packet a callback for base triangle t traces: a
 * packet's valid lanes (mr_dtrace_intersect_packet tests them against T's
 * box in T's own frame, tighter than its Embree box: testing that too
 * first cost more than it saved, texture plane at 100 texels per unit:
 * trace 0.96 without it), a single valid ray if it can meet t's Embree
 * box (mr_rays_in_box; the box holds the displaced surface,
 * mr_dtrace_tri_box), or every valid one for ray marching, the
 * comparator, left as it was. */
static uint32_t lanes_to_trace(const mr_geom *g, void *ray, unsigned N, const int *valid,
                               uint32_t t)
{
    if (g->par.method == MR_DISPLACED_RAYMARCH || (N > 1 && N <= MR_DPACKET_MAX))
        return mr_valid_lanes(N, valid);
    const float *box = g->boxes + (size_t)t * 6;
    return mr_rays_in_box(ray, N, valid, box, box + 3);
}

/* Ray marching and packets wider than the tracer's go ray by ray; the
 * others together (mr_dtrace_intersect_packet). */
static bool by_lane(const mr_geom *g, unsigned N)
{
    return g->par.method == MR_DISPLACED_RAYMARCH || N > MR_DPACKET_MAX;
}

static void intersect_cb(const struct RTCIntersectFunctionNArguments *args)
{
    mr_geom *g = args->geometryUserPtr;
    unsigned N = args->N;
    const uint32_t lanes = lanes_to_trace(g, args->rayhit, N, args->valid, args->primID);
    if (!lanes)
        return;
    mr_dstats st = {0};
    if (by_lane(g, N)) {
        for (uint32_t m = lanes; m; m &= m - 1) {
            const unsigned i = (unsigned)__builtin_ctz(m);
            const float before = *mr_ray_f(args->rayhit, N, MR_RAY_TFAR, i);
            mr_dhit h;
            if (trace_one(g, args->primID, args->rayhit, N, i, false, &h, &st))
                write_hit(args, i, &h, before);
        }
    } else {
        float before[MR_DPACKET_MAX];
        for (uint32_t m = lanes; m; m &= m - 1) {
            const unsigned i = (unsigned)__builtin_ctz(m);
            before[i] = *mr_ray_f(args->rayhit, N, MR_RAY_TFAR, i);
        }
        const mr_drays rays = packet_rays(args->rayhit, N);
        mr_dhit hits[MR_DPACKET_MAX];
        st.calls += (uint64_t)mr_popcount32(lanes);
        const uint32_t hm = mr_dtrace_intersect_packet(&g->scene, args->primID, &rays, lanes,
                                                       hits, &st);
        for (uint32_t m = hm; m; m &= m - 1) {
            const unsigned i = (unsigned)__builtin_ctz(m);
            write_hit(args, i, &hits[i], before[i]);
        }
    }
    add_stats(g, &st);
}

static void occluded_cb(const struct RTCOccludedFunctionNArguments *args)
{
    mr_geom *g = args->geometryUserPtr;
    unsigned N = args->N;
    const uint32_t lanes = lanes_to_trace(g, args->ray, N, args->valid, args->primID);
    if (!lanes)
        return;
    mr_dstats st = {0};
    if (by_lane(g, N) || N == 1) {
        for (uint32_t m = lanes; m; m &= m - 1) {
            const unsigned i = (unsigned)__builtin_ctz(m);
            if (trace_one(g, args->primID, args->ray, N, i, true, NULL, &st))
                *mr_ray_f(args->ray, N, MR_RAY_TFAR, i) = -INFINITY;
        }
    } else {
        /* a packet of shadow rays: traversed together like primary rays
         * (their closest hits found, which costs a little more than any
         * hit but shares the nodes) */
        const mr_drays rays = packet_rays(args->ray, N);
        mr_dhit hits[MR_DPACKET_MAX];
        st.calls += (uint64_t)mr_popcount32(lanes);
        uint32_t hm = mr_dtrace_intersect_packet(&g->scene, args->primID, &rays, lanes, hits, &st);
        for (uint32_t m = hm; m; m &= m - 1)
            *mr_ray_f(args->ray, N, MR_RAY_TFAR, (unsigned)__builtin_ctz(m)) = -INFINITY;
    }
    add_stats(g, &st);
}

static int attach_level(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                        enum RTCBuildQuality quality, mr_error *err)
{
    if (tessellated(g))
        return mr_geom_attach_triangles(device, scene, geom_id, quality, g->tess_pos,
                                        g->tess_vertices, g->tess_idx, g->tess_triangles, &g->rtc,
                                        err);
    return mr_geom_attach_user(device, scene, geom_id, quality, g->triangle_count, g, bounds_cb, intersect_cb,
                               occluded_cb, "displaced", &g->rtc, err);
}

/* One geometry per level, consecutive ids; only the frame's level is
 * enabled (commit), built as mr_lod_build_quality says. */
static int displaced_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                            enum RTCBuildQuality quality, mr_error *err)
{
    quality = mr_lod_build_quality(g->lod_count, quality);
    for (uint32_t k = 0; k < g->lod_count; k++) {
        mr_geom *l = k == 0 ? g : g->coarser[k - 1];
        int rc = attach_level(l, device, scene, geom_id + k, quality, err);
        if (rc < 0)
            return rc;
        if (g->lod_count > 1)
            rtcDisableGeometry(l->rtc);
    }
    g->lod_sw.enabled = g->lod_count > 1 ? UINT32_MAX : 0;
    return MR_OK;
}

static mr_geom *level_of(mr_geom *g, uint32_t k) { return k == 0 ? g : g->coarser[k - 1]; }

static RTCGeometry level_geometry(void *g, uint32_t k) { return level_of(g, k)->rtc; }

static void commit_level(void *g, uint32_t k)
{
    mr_geom *l = level_of(g, k);
    if (tessellated(l))
        mr_geom_commit_vertices(l->rtc);
    else
        rtcCommitGeometry(l->rtc);
}

static bool displaced_commit(mr_geom *g)
{
    return mr_lod_commit(&g->lod_sw, g->lod_cur, g->lod_count, g, level_geometry, commit_level);
}

static uint32_t displaced_geometry_ids(const mr_geom *g) { return g->lod_count; }

static mr_vec3 displaced_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    g = traced(g);
    if (tessellated(g)) {
        if (prim >= g->tess_triangles)
            return mr_v3(0, 0, 1);
        const uint32_t *t = g->tess_idx + (size_t)prim * 3;
        mr_vec3 p[3];
        for (int k = 0; k < 3; k++)
            p[k] = mr_v3(g->tess_pos[(size_t)t[k] * 3], g->tess_pos[(size_t)t[k] * 3 + 1],
                         g->tess_pos[(size_t)t[k] * 3 + 2]);
        return mr_v3_cross(mr_v3_sub(p[1], p[0]), mr_v3_sub(p[2], p[0]));
    }
    /* the micro-triangle the ray hit (tessellation-free) or the one under
     * the marched hit point (raymarch, mr_dtrace_march): the normal the
     * traversal handed Embree */
    return ng;
}

static int displaced_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    g = traced(g);
    if (tessellated(g))
        return mr_trimesh_copy(g->tess_pos, g->tess_vertices, g->tess_idx, g->tess_triangles, out,
                               err);
    /* the exact reference of the traced surface: the same micro-triangles */
    mr_geom tmp = *g;
    tmp.tess_vfirst = tmp.tess_tfirst = NULL;
    int rc = tess_layout(&tmp, g->asset->path, err);
    if (rc == MR_OK)
        rc = tess_fill(&tmp, tmp.tess_pos, tmp.tess_idx, true, 0, err);
    if (rc == MR_OK) {
        *out = (mr_trimesh){.vertex_count = tmp.tess_vertices, .triangle_count = tmp.tess_triangles,
                            .positions = tmp.tess_pos, .indices = tmp.tess_idx};
        tmp.tess_pos = NULL;
        tmp.tess_idx = NULL;
    }
    free(tmp.tess_vfirst);
    free(tmp.tess_tfirst);
    free(tmp.tess_pos);
    free(tmp.tess_idx);
    return rc;
}

static size_t base_bytes(const mr_geom *g)
{
    size_t nv = g->vertex_count, nt = g->triangle_count;
    size_t floats = g->shares_base ? 0 : 6; /* posed positions and normals */
    return sizeof *g + nv * (2 * sizeof(double) + floats * sizeof(float)) +
           nt * 3 * sizeof(uint32_t) +
           nt * (sizeof(mr_dbase) + sizeof(mr_dgrad) + 6 * sizeof(float)) +
           (g->roots ? nt * sizeof *g->roots : 0) + (g->proots ? nt * sizeof *g->proots : 0) +
           g->asset->mesh_count * sizeof(uint32_t);
}

static size_t tess_bytes(const mr_geom *g)
{
    if (!g->tess_pos)
        return 0;
    return ((size_t)g->tess_vertices * 3 + 1) * sizeof(float) +
           ((size_t)g->tess_triangles * 3 + 1) * sizeof(uint32_t) +
           ((size_t)g->triangle_count + 1) * 2 * sizeof(uint32_t);
}

static size_t source_bytes(const mr_geom *g)
{
    return g->procedural ? mr_dproc_memory(&g->proc) : mr_dgrid_memory(&g->grid);
}

/* Every level's. */
static size_t displaced_memory(const mr_geom *g)
{
    size_t b = base_bytes(g) + source_bytes(g) + tess_bytes(g);
    for (uint32_t k = 1; k < g->lod_count; k++)
        b += displaced_memory(g->coarser[k - 1]);
    return b;
}

static uint64_t displaced_primitives(const mr_geom *g)
{
    g = traced(g);
    return tessellated(g) ? g->tess_triangles : g->triangle_count;
}

/* Steps per ray: displaced_nodes / rays. Embree's share of the memory is
 * the frame's bvh bytes; the tessellation's is in its geometry bytes. */
enum { S_BOUNDS_S, S_CALLS, S_NODES, S_CELLS, S_TESTS, S_BASE_BYTES, S_MIPMAP_BYTES, S_LEVEL,
       S_ERROR_PX, S_LOD_BYTES, S_LOD_BUILD_S, S_COUNT };

static const mr_kind_stat STATS[S_COUNT] = {
    {"displaced_bounds_s", "s", "Seconds the displaced objects spent on this frame's bounds "
                                "(per-triangle gradients and Embree boxes) or tessellation",
     MR_STAT_SUM},
    {"displaced_calls", "count", "Base triangles entered (rays whose path met a triangle's "
                                 "Embree box); divided by rays: triangles entered per ray",
     MR_STAT_SUM},
    {"displaced_nodes", "count", "Pyramid nodes bounded and tested (ray marching: samples); a "
                                 "packet of rays through one triangle shares each node's box, "
                                 "so divided by rays: traversal steps per ray of the packets",
     MR_STAT_SUM},
    {"displaced_cells", "count", "Texels (grid cells) the traversal cut into micro-triangles; a "
                                 "thread keeps the cells it made for the pose, so a cell met "
                                 "again is counted once per thread",
     MR_STAT_SUM},
    {"displaced_tests", "count", "Micro-triangles (or bilinear patches) intersected", MR_STAT_SUM},
    {"displaced_base_bytes", "bytes", "Base mesh, per-triangle set-up and boxes", MR_STAT_SUM},
    {"displaced_mipmap_bytes", "bytes", "Height texture pyramid and mip level held (procedural: "
                                        "the Gaussianised example and its pyramid)", MR_STAT_SUM},
    {"displaced_lod_level", "level",
     "the height texture's mip level traced, or how many times a procedural source's \"range\" "
     "was halved (\"tolerance_px\" picks it; without, \"level\" or 0)",
     MR_STAT_MAX},
    {"displaced_lod_error_px", "px",
     "the level's predicted error: its height difference to the ground truth (mip level 0; "
     "procedural: twice the range), projected at the posed surface's nearest depth by this "
     "frame's camera (0 without \"tolerance_px\")", MR_STAT_MAX},
    {"displaced_lod_bytes", "bytes",
     "what the levels coarser than the object's own hold (their mip levels or procedural "
     "textures, pyramids and per-triangle set-up)", MR_STAT_SUM},
    {"displaced_lod_build_s", "s",
     "making the coarser levels and measuring their error at creation", MR_STAT_ONCE},
};

/* The level traced: the height texture's mip level, or how many times a
 * procedural source's range was halved. */
static unsigned lod_level(const mr_geom *g)
{
    return g->procedural ? g->lod_cur : traced(g)->par.level;
}

static bool displaced_lod(const mr_geom *g, uint32_t *level, double *error_px)
{
    *level = lod_level(g);
    *error_px = g->predicted_px;
    return g->tolerance_px > 0;
}

static void displaced_frame_stats(const mr_geom *cg, double *v)
{
    /* the counters are this frame's: read and cleared (only this object's
     * callbacks update them, and they have all returned) */
    mr_geom *g = (mr_geom *)cg;
    v[S_BOUNDS_S] = g->bounds_s;
    v[S_CALLS] = v[S_NODES] = v[S_CELLS] = v[S_TESTS] = 0;
    for (uint32_t k = 0; k < g->lod_count; k++) {
        mr_geom *l = k == 0 ? g : g->coarser[k - 1];
        for (int c = 0; c < COUNT_STRIPES; c++) {
            count_stripe *cs = &l->counts[c];
            v[S_NODES] += (double)atomic_exchange(&cs->nodes, 0);
            v[S_TESTS] += (double)atomic_exchange(&cs->tests, 0);
            v[S_CALLS] += (double)atomic_exchange(&cs->calls, 0);
            v[S_CELLS] += (double)atomic_exchange(&cs->cells, 0);
        }
    }
    v[S_BASE_BYTES] = (double)base_bytes(g);
    v[S_MIPMAP_BYTES] = (double)source_bytes(g);
    v[S_LEVEL] = lod_level(g);
    v[S_ERROR_PX] = g->predicted_px;
    v[S_LOD_BYTES] = (double)(displaced_memory(g) - base_bytes(g) - source_bytes(g) - tess_bytes(g));
    v[S_LOD_BUILD_S] = g->lod_build_s;
    g->bounds_s = 0;
}

/* ---- the "displaced" block ------------------------------------------------------------ */

static const char *const METHODS[] = {"tessellation_free", "tessellated", "raymarch"};
static const char *const LOCALS[] = {"triangles", "bilinear"};

enum { P_TEXTURE, P_PROCEDURAL, P_SCALE, P_OFFSET, P_LEVEL, P_RANGE, P_METHOD, P_STEPS, P_LOCAL };
enum { Q_EXAMPLE, Q_OFFSET, Q_SCALE, Q_TRIANGLE, Q_SEED };

static int after_procedural(void *values, const bool *given, mr_param_error *err)
{
    const mr_displaced_params *d = values;
    if (!given[P_TEXTURE] && !given[P_PROCEDURAL])
        return mr_param_fail(err, MR_ERR_INVALID, "",
                             "a displaced object needs a height source: \"texture\" (an image "
                             "asset) or \"procedural\" (tiling and blending of an example)");
    if (given[P_PROCEDURAL] && (!d->procedural || !d->example))
        return mr_param_fail(err, MR_ERR_INVALID, "procedural",
                             "expected an object with an \"example\" (the name of an image asset)");
    return MR_OK;
}

static int after_level(void *values, const bool *given, mr_param_error *err)
{
    (void)values;
    if (given[P_LEVEL] && given[P_PROCEDURAL])
        return mr_param_fail(err, MR_ERR_INVALID, "level",
                             "\"level\" picks the height texture's mip level; a procedural "
                             "source is sampled at \"range\"");
    return MR_OK;
}

static int after_range(void *values, const bool *given, mr_param_error *err)
{
    const mr_displaced_params *d = values;
    if (given[P_RANGE] && given[P_TEXTURE])
        return mr_param_fail(err, MR_ERR_INVALID, "range",
                             "\"range\" subdivides a procedural source's lattice; a texture is "
                             "sampled at its texels (\"level\" picks a mip level)");
    if (d->range & (d->range - 1))
        return mr_param_fail(err, MR_ERR_INVALID, "range", "expected a power of two, got %u",
                             d->range);
    return MR_OK;
}

static int after_steps(void *values, const bool *given, mr_param_error *err)
{
    const mr_displaced_params *d = values;
    if (given[P_STEPS] && d->method != MR_DISPLACED_RAYMARCH)
        return mr_param_fail(err, MR_ERR_INVALID, "steps",
                             "\"steps\" is for method \"raymarch\" only");
    return MR_OK;
}

static int after_example(void *values, const bool *given, mr_param_error *err)
{
    (void)values;
    if (!given[Q_EXAMPLE])
        return mr_param_fail(err, MR_ERR_INVALID, "example",
                             "expected \"example\": the name of an image asset to tile");
    return MR_OK;
}

static const mr_param PROC_PARAMS[] = {
    [Q_EXAMPLE] = {.field = "example", .type = MR_PARAM_ASSET,
                   .offset = offsetof(mr_displaced_params, example), .after = after_example,
                   .description = "The example image (an asset of the job's \"assets\") whose "
                                  "tiles are blended (thesis 4.1, Heitz and Neyret 2018)."},
    [Q_OFFSET] = {.field = "offset", .type = MR_PARAM_NUMBERS,
                  .offset = offsetof(mr_displaced_params, uv_offset), .max_items = 2, .lo = -1e6,
                  .hi = 1e6, .def = 0,
                  .description = "Texture-space offset of the procedural texture (eq. 4.5)."},
    [Q_SCALE] = {.field = "scale", .type = MR_PARAM_NUMBER,
                 .offset = offsetof(mr_displaced_params, uv_scale), .lo = 0, .hi = 1e6,
                 .flags = MR_PARAM_LO_OPEN, .def = 1,
                 .description = "Texture-space scale of the procedural texture (eq. 4.5): uv' = "
                                "offset + (uv - 0.5) scale."},
    [Q_TRIANGLE] = {.field = "triangle_size", .type = MR_PARAM_NUMBER,
                    .offset = offsetof(mr_displaced_params, triangle_size), .lo = 0, .hi = 16,
                    .flags = MR_PARAM_LO_OPEN, .def = 0.25,
                    .description = "Edge of a lattice triangle in the example's texture space "
                                   "(eq. 4.6; 1/4 works well, HN19)."},
    [Q_SEED] = {.field = "seed", .type = MR_PARAM_INT,
                .offset = offsetof(mr_displaced_params, seed), .lo = 0, .hi = 4294967295.0,
                .def = 0, .description = "Picks the lattice vertices' random example positions."},
};

static const mr_param_table PROC_TABLE = {
    .params = PROC_PARAMS,
    .count = sizeof PROC_PARAMS / sizeof PROC_PARAMS[0],
    .size = sizeof(mr_displaced_params),
    .expect = "an object of procedural texture parameters",
    .schema_rules = "{\"required\": [\"example\"]}",
};

static const mr_param DISPLACED_PARAMS[] = {
    [P_TEXTURE] = {.field = "texture", .type = MR_PARAM_ASSET,
                   .offset = offsetof(mr_displaced_params, texture), .conflicts = "procedural",
                   .description = "The height texture: an image asset of the job's \"assets\" "
                                  "(PNG 8/16 bit, JPEG, or EXR with Y, R G B or one channel; "
                                  "colour becomes luminance), repeating; sample (i, j) sits at "
                                  "texture coordinates (i / width, j / height), the picture's "
                                  "bottom row at v = 0."},
    [P_PROCEDURAL] = {.field = "procedural", .type = MR_PARAM_FLAG_OBJECT,
                      .offset = offsetof(mr_displaced_params, procedural), .sub = &PROC_TABLE,
                      .after = after_procedural,
                      .description = "An infinite by-example texture instead of a height "
                                     "texture: tiling and blending of an example image "
                                     "(thesis chapter 5)."},
    [P_SCALE] = {.field = "scale", .type = MR_PARAM_NUMBER,
                 .offset = offsetof(mr_displaced_params, scale), .lo = -1e6, .hi = 1e6, .def = 0.1,
                 .description = "Height of a texture value of 1 (8 and 16 bit images read 0..1), "
                                "in world units along the unit interpolated normal."},
    [P_OFFSET] = {.field = "offset", .type = MR_PARAM_NUMBER,
                  .offset = offsetof(mr_displaced_params, offset), .lo = -1e6, .hi = 1e6, .def = 0,
                  .description = "Height of a texture value of 0: height = offset + scale * value."},
    [P_LEVEL] = {.field = "level", .type = MR_PARAM_INT,
                 .offset = offsetof(mr_displaced_params, level), .lo = 0,
                 .hi = MR_DISPLACED_MAX_LEVEL, .def = 0, .after = after_level,
                 .description = "Mip level of the height texture the surface samples (0: every "
                                "texel; k: 2^k x 2^k texels averaged): the level of detail."},
    [P_RANGE] = {.field = "range", .type = MR_PARAM_INT,
                 .offset = offsetof(mr_displaced_params, range), .lo = 1,
                 .hi = MR_DISPLACED_MAX_RANGE, .def = MR_DISPLACED_DEFAULT_RANGE,
                 .after = after_range,
                 .description = "Procedural source: subdivisions of a lattice square per side, a "
                                "power of two (the thesis' range, its level of detail)."},
    [P_METHOD] = {.field = "method", .type = MR_PARAM_ENUM,
                  .offset = offsetof(mr_displaced_params, method), MR_PARAM_CHOICES(METHODS),
                  .def = MR_DISPLACED_TESSELLATION_FREE,
                  .description = "\"tessellation_free\": D-BVH traversal of the height pyramid in an "
                                 "Embree user geometry (no micro-triangles stored). "
                                 "\"tessellated\": the same micro-triangles as Embree triangles "
                                 "(the exact reference and memory baseline). \"raymarch\": fixed-step "
                                 "ray marching (the thesis' comparator; approximate)."},
    [P_STEPS] = {.field = "steps", .type = MR_PARAM_INT,
                 .offset = offsetof(mr_displaced_params, steps), .lo = 1,
                 .hi = MR_DISPLACED_MAX_STEPS, .def = MR_DISPLACED_DEFAULT_STEPS,
                 .after = after_steps,
                 .description = "Ray marching: equal steps per ray over a base triangle's box."},
    [P_LOCAL] = {.field = "local", .type = MR_PARAM_ENUM,
                 .offset = offsetof(mr_displaced_params, local), MR_PARAM_CHOICES(LOCALS),
                 .def = MR_DLOCAL_TRIANGLES,
                 .description = "Leaf intersection of tessellation_free: \"triangles\" (two per "
                                "texel, the tessellation's) or \"bilinear\" (cells wholly inside "
                                "a base triangle as bilinear patches of their four corners)."},
};

static const mr_param_table DISPLACED_TABLE = {
    .params = DISPLACED_PARAMS,
    .count = sizeof DISPLACED_PARAMS / sizeof DISPLACED_PARAMS[0],
    .size = sizeof(mr_displaced_params),
    .expect = "an object of displacement parameters",
    .schema_rules =
        "{\"anyOf\": [{\"required\": [\"texture\"]}, {\"required\": [\"procedural\"]}],"
        " \"allOf\": ["
        "{\"if\": {\"required\": [\"procedural\"]}, \"then\": {\"not\": {\"required\": [\"level\"]}}},"
        "{\"if\": {\"required\": [\"texture\"]}, \"then\": {\"not\": {\"required\": [\"range\"]}}},"
        "{\"if\": {\"required\": [\"steps\"]}, \"then\": {\"required\": [\"method\"], "
        "\"properties\": {\"method\": {\"const\": \"raymarch\"}}}},"
        "{\"properties\": {\"range\": {\"enum\": [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, "
        "2048, 4096]}}}]}",
};

/* References (kind.h): "tessellated" is the same micro-triangles as Embree
 * triangles (method "tessellated": exact, so tessellation_free must match
 * it and ray marching shows its own error); "ground_truth" is a dense
 * pre-tessellation: a height texture's every texel (mip level 0)
 * tessellated, or, since a procedural source has no finest level, the next
 * finer one (twice the range: four times the micro-triangles), which shows
 * the detail the object's level leaves out. An object at level 0 has none
 * beyond its tessellation (nor one at the largest range), unless it has a
 * tolerance: it may then trace coarser levels. The ground truth pass draws
 * its objects without a tolerance; the tessellated pass keeps it, and so
 * tessellates the level the object picks by the same rule. */
static int displaced_reference(const mr_object_desc *obj, mr_reference_type type,
                               mr_reference_objects *out, mr_error *err)
{
    const mr_displaced_params *src = obj->params;
    if (type == MR_REFERENCE_GROUND_TRUTH &&
        (src->procedural ? src->range >= MR_DISPLACED_MAX_RANGE
                         : src->level == 0 && !(obj->tolerance_px > 0)))
        return MR_OK;
    mr_displaced_params *p = mr_reference_alloc(out, sizeof *p, err);
    if (!p)
        return MR_ERR_NOMEM;
    *p = *src;
    p->method = MR_DISPLACED_TESSELLATED;
    if (type == MR_REFERENCE_GROUND_TRUTH) {
        if (src->procedural)
            p->range = 2 * src->range;
        else
            p->level = 0;
    }
    mr_object_desc d = *obj;
    d.params = p;
    return mr_reference_objects_add(out, &d, err);
}

const mr_kind mr_kind_displaced = {
    .name = "displaced",
    .summary = "Parameters of a displacement-mapped object (kind \"displaced\", paper 003): the "
               "asset's meshes, which need texture coordinates, displaced along their unit "
               "interpolated normals by a height texture or a procedural tiling-and-blending "
               "texture, two triangles per texel, posed (skinned) like any mesh, and traced "
               "without tessellation.",
    .params = &DISPLACED_TABLE,
    .stats = STATS,
    .stat_count = sizeof STATS / sizeof STATS[0],
    .has_lod = true,
    .lod = displaced_lod,
    .frame_stats = displaced_frame_stats,
    .create = displaced_create,
    .update = displaced_update,
    .attach = displaced_attach,
    .commit = displaced_commit,
    .geometry_ids = displaced_geometry_ids,
    .normal = displaced_normal,
    .tessellate = displaced_tessellate,
    .memory = displaced_memory,
    .primitives = displaced_primitives,
    .reference = displaced_reference,
    .free = displaced_free,
};
