/* tiling.c - tiling and blending heights and their bounds (tiling.h). */
#include "kinds/displaced/tiling.h"

#include "util/parallel.h"
#include "util/thread_block.h"

#include <math.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>

#define SQRT3 1.7320508075688772
#define WIDEN 1e-12

static inline double dmin(double a, double b) { return a < b ? a : b; }
static inline double dmax(double a, double b) { return a > b ? a : b; }

/* erf^-1 by Newton's method on erf from Winitzki's approximation. */
static double erfinv(double y)
{
    if (y <= -1)
        return -6;
    if (y >= 1)
        return 6;
    double a = 0.147, l = log(1 - y * y), t = 2 / (M_PI * a) + l / 2;
    double x = copysign(sqrt(sqrt(t * t - l / a) - t), y);
    for (int k = 0; k < 4; k++)
        x -= (erf(x) - y) / (2 / sqrt(M_PI) * exp(-x * x));
    return x;
}

typedef struct ranked {
    double v;
    uint32_t i;
} ranked;

static int by_value(const void *a, const void *b)
{
    double x = ((const ranked *)a)->v, y = ((const ranked *)b)->v;
    return x < y ? -1 : x > y ? 1 : 0;
}

size_t mr_dproc_memory(const mr_dproc *p)
{
    return sizeof *p + mr_image_bytes(p->gauss) + mr_dgrid_memory(&p->gex);
}

double mr_dproc_height_of_blend(const mr_dproc *p, double b)
{
    double pos = (b - p->lut_lo) * p->lut_per_blend;
    pos = pos < 0 ? 0 : pos > MR_TILING_LUT - 1 ? MR_TILING_LUT - 1 : pos;
    int k = (int)pos;
    if (k > MR_TILING_LUT - 2)
        k = MR_TILING_LUT - 2;
    double f = pos - k, v = p->lut[k] + f * ((double)p->lut[k + 1] - p->lut[k]);
    return p->offset + p->scale * v;
}

int mr_dproc_init(mr_dproc *p, const mr_image *ex, double uv_off_u, double uv_off_v,
                  double uv_scale, double triangle_size, uint32_t seed, uint32_t range,
                  double scale, double offset, unsigned threads, mr_error *err)
{
    memset(p, 0, sizeof *p);
    if (range == 0 || (range & (range - 1)))
        return mr_error_set(err, MR_ERR_INVALID, "a procedural range must be a power of two, got %u",
                            range);
    /* a process-unique id keys the caches (never 0, never reused) */
    static _Atomic uint64_t next_id = 1;
    p->id = atomic_fetch_add(&next_id, 1);
    size_t n = (size_t)ex->width * ex->height;
    ranked *r = malloc(n * sizeof *r);
    int rc = mr_image_new(ex->width, ex->height, MR_SAMPLE_F32, &p->gauss, err);
    if (rc < 0 || !r) {
        free(r);
        mr_dproc_free(p);
        return rc < 0 ? rc : mr_error_set(err, MR_ERR_NOMEM, "out of memory for a procedural texture");
    }
    double unit = mr_image_unit(ex);
    for (uint32_t y = 0; y < ex->height; y++)
        for (uint32_t x = 0; x < ex->width; x++) {
            size_t i = (size_t)y * ex->width + x;
            r[i] = (ranked){mr_image_sample(ex, x, y) / unit, (uint32_t)i};
        }
    qsort(r, n, sizeof *r, by_value);
    /* T (eq. 4.3): rank -> uniform -> Gaussian; equal values share a rank */
    float *g = p->gauss->samples;
    for (size_t a = 0; a < n;) {
        size_t b = a;
        while (b < n && r[b].v == r[a].v)
            b++;
        double u = ((double)(a + b - 1) / 2 + 0.5) / (double)n;
        double t = 0.5 + MR_TILING_SIGMA * sqrt(2.0) * erfinv(2 * u - 1);
        for (size_t k = a; k < b; k++)
            g[r[k].i] = (float)t;
        a = b;
    }
    p->range = range;
    p->inv_range = 1.0 / range;
    while ((1u << p->top) < range)
        p->top++;
    p->uv_off[0] = uv_off_u;
    p->uv_off[1] = uv_off_v;
    p->uv_scale = uv_scale;
    p->tri = triangle_size;
    p->seed = seed;
    p->scale = scale;
    p->offset = offset;
    if ((rc = mr_dgrid_init(&p->gex, p->gauss, 0, 1.0, 0.0, threads, err)) < 0) {
        free(r);
        mr_dproc_free(p);
        return rc;
    }
    /* the global blend bound (tiling.h) */
    double nlo = p->gex.gmin - 0.5, nhi = p->gex.gmax - 0.5, dlo = 1 / SQRT3, dhi = 1;
    p->blend_lo = dmin(nlo / dlo, nlo / dhi) + 0.5 - WIDEN;
    p->blend_hi = dmax(nhi / dlo, nhi / dhi) + 0.5 + WIDEN;
    /* T^-1 (eq. 4.4) on the blend's whole range */
    p->lut_lo = p->blend_lo;
    p->lut_hi = p->blend_hi > p->blend_lo ? p->blend_hi : p->blend_lo + 1e-9;
    p->lut_per_blend = (MR_TILING_LUT - 1) / (p->lut_hi - p->lut_lo);
    for (int k = 0; k < MR_TILING_LUT; k++) {
        double y = p->lut_lo + (p->lut_hi - p->lut_lo) * k / (MR_TILING_LUT - 1);
        double u = 0.5 * (1 + erf((y - 0.5) / (MR_TILING_SIGMA * sqrt(2.0))));
        size_t idx = (size_t)(u * (double)n);
        p->lut[k] = (float)r[idx < n ? idx : n - 1].v;
    }
    for (int k = 1; k < MR_TILING_LUT; k++) /* monotone whatever float does */
        p->lut[k] = p->lut[k] < p->lut[k - 1] ? p->lut[k - 1] : p->lut[k];
    free(r);
    return MR_OK;
}

/* ---- spaces ------------------------------------------------------------------------ */

void mr_dproc_grid_of(const mr_dproc *p, float u, float v, double g[2])
{
    double x = p->uv_off[0] + ((double)u - 0.5) * p->uv_scale;
    double y = p->uv_off[1] + ((double)v - 0.5) * p->uv_scale;
    /* uv' = lx e1 + ly e2: ly = y / (s sqrt3/2), lx = (x - ly s/2) / s */
    double ly = y / (p->tri * SQRT3 / 2), lx = (x - ly * p->tri / 2) / p->tri;
    g[0] = lx * p->range;
    g[1] = ly * p->range;
}

/* Texture-space point of lattice point (lx, ly). */
static inline void uv_of(const mr_dproc *p, double lx, double ly, double *x, double *y)
{
    *x = p->tri * lx + p->tri * 0.5 * ly;
    *y = p->tri * SQRT3 * 0.5 * ly;
}

/* The random offset of lattice vertex (a, b): two numbers in [0, 1). */
static inline void vertex_offset(const mr_dproc *p, int64_t a, int64_t b, double o[2])
{
    const uint64_t z = mr_mix64((uint64_t)a * 0x9e3779b97f4a7c15ull ^ (uint64_t)b * 0xc2b2ae3d27d4eb4full ^
                                ((uint64_t)p->seed << 17 | 0x5bd1e995ull));
    o[0] = (double)(z >> 40) / 16777216.0;
    o[1] = (double)((z >> 16) & 0xffffff) / 16777216.0;
}

/* The Gaussianised example (float samples), bilinear and repeating, at
 * texture point (x, y). (mr_floor_small and one wrap per axis: 47 -> 35 ns
 * a height, the same bits.) */
static inline double gauss_at(const mr_dproc *p, double x, double y)
{
    const mr_dgrid *g = &p->gex;
    double fx = x * g->w, fy = y * g->h, x0 = mr_floor_small(fx), y0 = mr_floor_small(fy);
    double tx = fx - x0, ty = fy - y0;
    uint32_t i0 = (uint32_t)mr_dgrid_wrap((int64_t)x0, g->w), i1 = i0 + 1 == g->w ? 0 : i0 + 1;
    uint32_t j0 = (uint32_t)mr_dgrid_wrap((int64_t)y0, g->h), j1 = j0 + 1 == g->h ? 0 : j0 + 1;
    const float *r0 = (const float *)g->samples + (size_t)(g->h - 1 - j0) * g->w;
    const float *r1 = (const float *)g->samples + (size_t)(g->h - 1 - j1) * g->w;
    double a = r0[i0], b = r0[i1], c = r1[i0], d = r1[i1];
    return (a + tx * (b - a)) + ty * ((c + tx * (d - c)) - (a + tx * (b - a)));
}

/* The lattice triangle of lattice point (lx, ly): its vertices and weights. */
static inline void lattice_tri(double lx, double ly, int64_t v[3][2], double w[3])
{
    double ax = mr_floor_small(lx), ay = mr_floor_small(ly), fx = lx - ax, fy = ly - ay;
    int64_t a = (int64_t)ax, b = (int64_t)ay;
    if (fx + fy <= 1) {
        v[0][0] = a, v[0][1] = b, v[1][0] = a + 1, v[1][1] = b, v[2][0] = a, v[2][1] = b + 1;
        w[0] = 1 - fx - fy, w[1] = fx, w[2] = fy;
    } else {
        v[0][0] = a + 1, v[0][1] = b + 1, v[1][0] = a, v[1][1] = b + 1, v[2][0] = a + 1, v[2][1] = b;
        w[0] = fx + fy - 1, w[1] = 1 - fx, w[2] = 1 - fy;
    }
}

/* The offsets of the last lattice triangle a thread blended in: the
 * heights asked for one after the other (a node's grid points, a cell's)
 * mostly share it, and hashing its three vertices was a quarter of a
 * height (35 -> 25 ns). */
typedef struct offsets {
    uint64_t id; /* the texture's (0: none yet) */
    int64_t v0[2];
    bool upper;
    double o[3][2];
} offsets;

static _Thread_local offsets last_offsets;

static inline const offsets *offsets_of(const mr_dproc *p, const int64_t v[3][2])
{
    offsets *m = &last_offsets;
    bool upper = v[1][0] != v[0][0] + 1;
    if (m->id != p->id || m->v0[0] != v[0][0] || m->v0[1] != v[0][1] || m->upper != upper) {
        for (int k = 0; k < 3; k++)
            vertex_offset(p, v[k][0], v[k][1], m->o[k]);
        m->id = p->id, m->v0[0] = v[0][0], m->v0[1] = v[0][1], m->upper = upper;
    }
    return m;
}

double mr_dproc_blend(const mr_dproc *p, int64_t i, int64_t j)
{
    double lx = (double)i * p->inv_range, ly = (double)j * p->inv_range;
    int64_t v[3][2];
    double w[3], x, y, num = -0.5, den = 0;
    lattice_tri(lx, ly, v, w);
    uv_of(p, lx, ly, &x, &y);
    const offsets *m = offsets_of(p, v);
    for (int k = 0; k < 3; k++) {
        num += w[k] * gauss_at(p, x + m->o[k][0], y + m->o[k][1]);
        den += w[k] * w[k];
    }
    return num / sqrt(den) + 0.5;
}

/* Per-thread direct-mapped caches of grid heights and square bounds: rays
 * near each other ask for the same ones, and each height costs three
 * bilinear look-ups of the example (a blend bound: three pyramid searches
 * a half). Heights are kept in tiles: tile (X, Y) holds the (TILE + 1)^2
 * grid points of square (X, Y) of side TILE (its last row and column are
 * also the next tiles'), so the exact bound of a square of side up to
 * TILE is a few comparisons within one tile, and a cell's corners come
 * from one look-up, where a cache of single heights was looked up 6.0 M
 * times a frame for the plane at range 128 (bounds of squares of sides 1,
 * 2 and 4 asked for 6, 12 and 30 heights, a cell for 4) and missed a
 * sixth of them. The blend bounds of larger squares are kept one a
 * square. An entry holds exactly what the computation returns, so results
 * do not depend on it (or on which thread filled it). */
#define TILE_LOG 2
#define TILE (1 << TILE_LOG)
_Static_assert(TILE == MR_DPROC_EXACT_LEG, "a tile is a square of the exact bound's largest side");
#define TCACHE 4096
#define BCACHE 4096

typedef struct htile {
    uint64_t id;
    int64_t x, y;
    double h[TILE + 1][TILE + 1]; /* [j][i]: grid point (x TILE + i, y TILE + j) */
} htile;

typedef struct bentry {
    uint64_t id;
    int64_t x, y;
    int level;
    double lo, hi;
} bentry;

/* A thread's caches, 1.1 MB: on the heap (thread_block.h; a tile cache
 * of 1,024 in thread-local storage: the plane at range 128 in 1.08-1.20
 * of the time). */
typedef struct caches {
    htile tiles[TCACHE];
    bentry bounds[BCACHE];
} caches;

static mr_thread_block caches_block = MR_THREAD_BLOCK_INIT;
static _Thread_local void *my;

/* This thread's caches (zeroed: id 0 is no entry), or NULL: then nothing
 * is kept. */
static caches *my_caches(void) { return mr_thread_block_get(&caches_block, &my, sizeof(caches)); }

static inline size_t slot_of(int64_t a, int64_t b, int64_t c, size_t n)
{
    uint64_t z = (uint64_t)a * 0x9e3779b97f4a7c15ull ^ (uint64_t)b * 0xc2b2ae3d27d4eb4full ^
                 (uint64_t)c * 0x165667b19e3779f9ull;
    z ^= z >> 29;
    return (size_t)(z * 0xbf58476d1ce4e5b9ull >> 40) & (n - 1);
}

/* Tile (x, y) when this thread has it, else NULL. */
static inline const htile *tile_kept(const mr_dproc *p, int64_t x, int64_t y)
{
    const caches *c = my_caches();
    const htile *e = c ? &c->tiles[slot_of(x, y, 0, TCACHE)] : NULL;
    return e && e->id == p->id && e->x == x && e->y == y ? e : NULL;
}

/* Makes tile (x, y) into *e: the grid points on its edges that a kept
 * neighbour holds are copied from it (the same bits), the rest blended
 * (into h first: a neighbour may sit in e's own slot). */
static void tile_make(const mr_dproc *p, int64_t x, int64_t y, htile *e)
{
    double h[TILE + 1][TILE + 1];
    bool known[TILE + 1][TILE + 1] = {{false}};
    const htile *l = tile_kept(p, x - 1, y), *r = tile_kept(p, x + 1, y);
    const htile *d = tile_kept(p, x, y - 1), *u = tile_kept(p, x, y + 1);
    for (int k = 0; k <= TILE; k++) {
        if (l)
            h[k][0] = l->h[k][TILE], known[k][0] = true;
        if (r)
            h[k][TILE] = r->h[k][0], known[k][TILE] = true;
        if (d)
            h[0][k] = d->h[TILE][k], known[0][k] = true;
        if (u)
            h[TILE][k] = u->h[0][k], known[TILE][k] = true;
    }
    for (int j = 0; j <= TILE; j++)
        for (int i = 0; i <= TILE; i++)
            if (!known[j][i])
                h[j][i] = mr_dproc_height_of_blend(p, mr_dproc_blend(p, x * TILE + i, y * TILE + j));
    memcpy(e->h, h, sizeof h);
    e->id = p->id, e->x = x, e->y = y;
}

/* Tile (x, y): kept, or made (into *spare when there is no cache). */
static const htile *tile_of(const mr_dproc *p, int64_t x, int64_t y, htile *spare)
{
    const htile *t = tile_kept(p, x, y);
    if (t)
        return t;
    caches *c = my_caches();
    htile *e = c ? &c->tiles[slot_of(x, y, 0, TCACHE)] : spare;
    tile_make(p, x, y, e);
    return e;
}

double mr_dproc_height(const mr_dproc *p, int64_t i, int64_t j)
{
    htile spare;
    return tile_of(p, i >> TILE_LOG, j >> TILE_LOG, &spare)->h[j & (TILE - 1)][i & (TILE - 1)];
}

/* The least and largest height of square (x, y) of side 2^level <= TILE,
 * from the tile holding it. */
static void tile_bound(const htile *t, int level, int64_t x, int64_t y, double *lo, double *hi)
{
    const int sh = TILE_LOG - level, n = 1 << level;
    const int i0 = (int)(x & ((1 << sh) - 1)) << level, j0 = (int)(y & ((1 << sh) - 1)) << level;
    double l = INFINITY, h = -INFINITY;
    for (int j = j0; j <= j0 + n; j++)
        for (int i = i0; i <= i0 + n; i++)
            l = dmin(l, t->h[j][i]), h = dmax(h, t->h[j][i]);
    *lo = l, *hi = h;
}

void mr_dproc_child_heights(const mr_dproc *p, int level, int64_t x, int64_t y, double lo[4],
                            double hi[4])
{
    htile spare;
    const htile *t = tile_of(p, x >> (TILE_LOG - level), y >> (TILE_LOG - level), &spare);
    for (int k = 0; k < 4; k++)
        tile_bound(t, level - 1, 2 * x + (k & 1), 2 * y + (k >> 1), &lo[k], &hi[k]);
}

static double height_at(const void *p, int64_t i, int64_t j) { return mr_dproc_height(p, i, j); }

mr_dheights mr_dproc_heights(const mr_dproc *p) { return (mr_dheights){height_at, p}; }

/* ---- bounds ------------------------------------------------------------------------- */

static void heights_of(const mr_dproc *p, double blo, double bhi, double *lo, double *hi)
{
    double a = mr_dproc_height_of_blend(p, blo - WIDEN), b = mr_dproc_height_of_blend(p, bhi + WIDEN);
    *lo = dmin(a, b);
    *hi = dmax(a, b);
}

void mr_dproc_global_heights(const mr_dproc *p, double *lo, double *hi)
{
    heights_of(p, p->blend_lo, p->blend_hi, lo, hi);
}

bool mr_dproc_square_heights_kept(const mr_dproc *p, int level, int64_t x, int64_t y, double *lo,
                                  double *hi)
{
    if (level <= TILE_LOG) {
        const htile *t = tile_kept(p, x >> (TILE_LOG - level), y >> (TILE_LOG - level));
        if (t)
            tile_bound(t, level, x, y, lo, hi);
        return t != NULL;
    }
    const caches *c = my_caches();
    const bentry *e = c ? &c->bounds[slot_of(x, y, level, BCACHE)] : NULL;
    if (e && e->id == p->id && e->x == x && e->y == y && e->level == level) {
        *lo = e->lo, *hi = e->hi;
        return true;
    }
    return false;
}

void mr_dproc_square_heights(const mr_dproc *p, int level, int64_t x, int64_t y, double *lo,
                             double *hi)
{
    if (level > p->top) {
        mr_dproc_global_heights(p, lo, hi);
        return;
    }
    if (level <= TILE_LOG) { /* exact: the tile's points (its halves' bounds, tiling.h) */
        htile spare;
        tile_bound(tile_of(p, x >> (TILE_LOG - level), y >> (TILE_LOG - level), &spare), level, x,
                   y, lo, hi);
        return;
    }
    if (mr_dproc_square_heights_kept(p, level, x, y, lo, hi))
        return;
    const int64_t n = (int64_t)1 << level;
    double l2, h2;
    mr_dproc_tri_heights(p, x * n, y * n, n, lo, hi);
    mr_dproc_tri_heights(p, (x + 1) * n, (y + 1) * n, -n, &l2, &h2);
    *lo = dmin(*lo, l2), *hi = dmax(*hi, h2);
    caches *c = my_caches();
    if (c)
        c->bounds[slot_of(x, y, level, BCACHE)] = (bentry){p->id, x, y, level, *lo, *hi};
}

void mr_dproc_tri_heights(const mr_dproc *p, int64_t bx, int64_t by, int64_t s, double *lo,
                          double *hi)
{
    if (s >= -MR_DPROC_EXACT_LEG && s <= MR_DPROC_EXACT_LEG) {
        /* a few cell halves: the surface over each is linear between its
         * three grid points (every micro-vertex in it interpolates their
         * heights), so the node's grid points bound it exactly, where the
         * bound below is as wide as the three tiles' samples around it */
        int64_t n = s < 0 ? -s : s, sg = s < 0 ? -1 : 1;
        double l = INFINITY, h = -INFINITY;
        for (int64_t j = 0; j <= n; j++)
            for (int64_t i = 0; i + j <= n; i++) {
                double v = mr_dproc_height(p, bx + sg * i, by + sg * j);
                l = dmin(l, v), h = dmax(h, v);
            }
        *lo = l, *hi = h;
        return;
    }
    double q[3][2] = {{(double)bx, (double)by}, {(double)(bx + s), (double)by},
                      {(double)bx, (double)(by + s)}};
    /* the lattice triangle: the one holding the node's centroid */
    double cx = (q[0][0] + q[1][0] + q[2][0]) / 3 * p->inv_range;
    double cy = (q[0][1] + q[1][1] + q[2][1]) / 3 * p->inv_range;
    int64_t v[3][2];
    double wc[3];
    lattice_tri(cx, cy, v, wc);
    double wlo[3] = {INFINITY, INFINITY, INFINITY}, whi[3] = {-INFINITY, -INFINITY, -INFINITY};
    double ulo = INFINITY, uhi = -INFINITY, vlo = INFINITY, vhi = -INFINITY;
    for (int m = 0; m < 3; m++) {
        double lx = q[m][0] * p->inv_range, ly = q[m][1] * p->inv_range, x, y;
        /* weights of the lattice triangle's vertices at this node vertex:
         * from its right-angle vertex v0, legs +x +y (lower) or -x -y */
        double sgn = v[1][0] == v[0][0] + 1 ? 1 : -1;
        double dx = sgn * (lx - (double)v[0][0]), dy = sgn * (ly - (double)v[0][1]);
        double w[3] = {1 - dx - dy, dx, dy};
        for (int k = 0; k < 3; k++) {
            double c = w[k] < 0 ? 0 : w[k] > 1 ? 1 : w[k];
            wlo[k] = dmin(wlo[k], c), whi[k] = dmax(whi[k], c);
        }
        uv_of(p, lx, ly, &x, &y);
        ulo = dmin(ulo, x), uhi = dmax(uhi, x), vlo = dmin(vlo, y), vhi = dmax(vhi, y);
    }
    double nlo = -0.5, nhi = -0.5, d2lo = 0, d2hi = 0;
    const mr_dgrid *g = &p->gex;
    for (int k = 0; k < 3; k++) {
        double o[2], glo, ghi;
        vertex_offset(p, v[k][0], v[k][1], o);
        /* the footprint's cells in the example (bilinear reads a cell's corners) */
        int64_t i0 = (int64_t)floor((ulo + o[0]) * g->w), i1 = (int64_t)floor((uhi + o[0]) * g->w);
        int64_t j0 = (int64_t)floor((vlo + o[1]) * g->h), j1 = (int64_t)floor((vhi + o[1]) * g->h);
        mr_dgrid_range_samples(g, i0, i1, j0, j1, &glo, &ghi);
        double a = wlo[k] * glo, b = wlo[k] * ghi, c = whi[k] * glo, d = whi[k] * ghi;
        nlo += dmin(dmin(a, b), dmin(c, d));
        nhi += dmax(dmax(a, b), dmax(c, d));
        d2lo += wlo[k] * wlo[k];
        d2hi += whi[k] * whi[k];
    }
    double dlo = sqrt(dmax(d2lo, 1.0 / 3)), dhi = sqrt(dmin(dmax(d2hi, 1.0 / 3), 1.0));
    if (dlo > dhi)
        dlo = dhi;
    double b0 = nlo / dlo, b1 = nlo / dhi, b2 = nhi / dlo, b3 = nhi / dhi;
    double blo = dmin(dmin(b0, b1), dmin(b2, b3)) + 0.5, bhi = dmax(dmax(b0, b1), dmax(b2, b3)) + 0.5;
    heights_of(p, blo, bhi, lo, hi);
}

void mr_dproc_free(mr_dproc *p)
{
    if (!p)
        return;

    mr_dgrid_free(&p->gex);
    mr_image_free(p->gauss);
    memset(p, 0, sizeof *p);
}


/* ---- levels of detail ----------------------------------------------------------- */

typedef struct distance_ctx {
    const mr_dproc *fine, *coarse;
    const double *tri;
    int64_t step; /* fine grid units per coarse one */
    double worst[MR_MAX_THREADS];
} distance_ctx;

static void distance_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    distance_ctx *c = vctx;
    const int64_t s = c->step;
    double worst = c->worst[worker];
    for (size_t t = begin; t < end; t++) {
        const double *q = c->tri + 6 * t;
        double lo[2] = {q[0], q[1]}, hi[2] = {q[0], q[1]};
        for (int k = 1; k < 3; k++)
            for (int a = 0; a < 2; a++)
                lo[a] = dmin(lo[a], q[2 * k + a]), hi[a] = dmax(hi[a], q[2 * k + a]);
        for (int64_t j = (int64_t)floor(lo[1]); j <= (int64_t)ceil(hi[1]); j++)
            for (int64_t i = (int64_t)floor(lo[0]); i <= (int64_t)ceil(hi[0]); i++) {
                int64_t ci = mr_floor_div(i, s), cj = mr_floor_div(j, s);
                double fx = (double)(i - ci * s) / (double)s, fy = (double)(j - cj * s) / (double)s;
                double h10 = mr_dproc_height(c->coarse, ci + 1, cj);
                double h01 = mr_dproc_height(c->coarse, ci, cj + 1), h;
                if (fx + fy <= 1) {
                    double h00 = mr_dproc_height(c->coarse, ci, cj);
                    h = h00 + fx * (h10 - h00) + fy * (h01 - h00);
                } else {
                    double h11 = mr_dproc_height(c->coarse, ci + 1, cj + 1);
                    h = h11 + (1 - fx) * (h01 - h11) + (1 - fy) * (h10 - h11);
                }
                worst = dmax(worst, fabs(mr_dproc_height(c->fine, i, j) - h));
            }
    }
    c->worst[worker] = worst;
}

double mr_dproc_distance(const mr_dproc *fine, const mr_dproc *coarse, const double *tri, size_t n,
                         unsigned threads)
{
    distance_ctx *c = calloc(1, sizeof *c);
    if (!c)
        return INFINITY; /* no bound: the coarse level is never picked */
    c->fine = fine, c->coarse = coarse, c->tri = tri;
    c->step = (int64_t)llround(fine->range / coarse->range);
    mr_parallel_for(threads, n, 1, distance_range, c);
    double worst = 0;
    for (unsigned w = 0; w < MR_MAX_THREADS; w++)
        worst = dmax(worst, c->worst[w]);
    free(c);
    return worst;
}
