/*
 * skeleton.c - contraction skeletonisation of an octree's voxel graph, its
 * segmentation into bones and the posable rig (see skeleton.h for the
 * method and the choices made where the thesis is silent).
 *
 * Everything numeric runs in double on positions normalised to the unit
 * cube. Parallel loops only write per-item outputs; every sum that crosses
 * items is taken serially in a fixed order, so results are the same for any
 * thread count.
 */
#include "kinds/svo/skeleton.h"

#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim/pose.h"
#include "util/dup.h"
#include "util/morton.h"
#include "kinds/svo/voxelize.h"
#include "util/parallel.h"

#define SK_GRAIN 256u
/* Bones a graph vertex keeps while its weights are smoothed. */
#define SK_KEEP 8u
/* Neighbours of a cell in a 3x3x3 block. */
#define SK_NBR 26u
/* Weight steps tried when the palette overflows (divisors of 255). */
static const unsigned sk_steps[] = {1, 3, 5, 15, 17, 51, 85, 255};

typedef struct sk_params {
    double omega, delta;
    unsigned max_iterations, rounds, threads;
} sk_params;

static int sk_resolve(const mr_svo_skeleton_params *p, unsigned depth, sk_params *r, mr_error *err)
{
    mr_svo_skeleton_params d = {0};
    if (p)
        d = *p;
    if (d.omega != 0.0f) {
        if (!isfinite(d.omega) || d.omega < MR_SVO_SKELETON_MIN_OMEGA || d.omega > 1.0f)
            return mr_error_set(err, MR_ERR_INVALID, "skeleton: omega %g is not in [2^-20, 1] (unit cube units)",
                                (double)d.omega);
        r->omega = d.omega;
    } else {
        r->omega = ldexp(1.0, -(int)(depth < 5 ? depth : 5));
    }
    if (d.delta != 0.0f) {
        if (!isfinite(d.delta) || d.delta < 0.0f)
            return mr_error_set(err, MR_ERR_INVALID, "skeleton: delta %g must be finite and > 0", (double)d.delta);
        r->delta = d.delta;
    } else {
        r->delta = 0.05;
    }
    if (d.max_iterations > MR_SVO_SKELETON_MAX_ITERATIONS)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: max_iterations %u above %u", d.max_iterations,
                            MR_SVO_SKELETON_MAX_ITERATIONS);
    r->max_iterations = d.max_iterations ? d.max_iterations : 1000u;
    if (d.smooth_rounds > MR_SVO_SKELETON_MAX_SMOOTH_ROUNDS)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: smooth_rounds %u above %u", d.smooth_rounds,
                            MR_SVO_SKELETON_MAX_SMOOTH_ROUNDS);
    r->rounds = d.smooth_rounds ? d.smooth_rounds : 2u;
    r->threads = d.threads;
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* the level-L cells and their 26-neighbour graph                           */

/* The octree's leaves in Morton order (keys) and where each sits in
 * svo->leaves. */
typedef struct sk_leaves {
    uint32_t n;
    unsigned depth;
    mr_svo_key *keys;
    uint32_t *index;
} sk_leaves;

static void sk_leaves_free(sk_leaves *l)
{
    free(l->keys);
    free(l->index);
    memset(l, 0, sizeof *l);
}

static int sk_leaves_collect(const mr_svo *svo, sk_leaves *l, mr_error *err)
{
    memset(l, 0, sizeof *l);
    if (svo->leaf_count == 0)
        return MR_OK;
    if (svo->depth < 1 || svo->depth > MR_SVO_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_FORMAT, "skeleton: octree depth %u not in 1..%u", svo->depth,
                            MR_SVO_MAX_DEPTH);
    if (!(svo->size > 0.0f) || !isfinite(svo->size) || !isfinite(svo->origin.x) || !isfinite(svo->origin.y) ||
        !isfinite(svo->origin.z))
        return mr_error_set(err, MR_ERR_FORMAT, "skeleton: octree cube (origin, size %g) is not finite and positive",
                            (double)svo->size);
    if (svo->node_count > 0 && (!svo->first_node || !svo->first_leaf || !svo->child_mask || !svo->leaf_mask))
        return mr_error_set(err, MR_ERR_FORMAT, "skeleton: octree with %u nodes lacks its node arrays",
                            svo->node_count);
    l->depth = svo->depth;
    l->keys = malloc((size_t)svo->leaf_count * sizeof *l->keys);
    l->index = malloc((size_t)svo->leaf_count * sizeof *l->index);
    if (!l->keys || !l->index) {
        sk_leaves_free(l);
        return mr_error_set(err, MR_ERR_NOMEM, "skeleton: out of memory for %u leaf keys", svo->leaf_count);
    }
    int rc = mr_svo_collect_keys(svo, l->keys, l->index, err);
    if (rc < 0) {
        sk_leaves_free(l);
        return rc;
    }
    l->n = svo->leaf_count;
    return MR_OK;
}

/* Occupied cells at level L (saturating just above cap). */
static uint64_t sk_count_cells(const sk_leaves *l, unsigned L, uint64_t cap)
{
    uint64_t cnt = 0, last = UINT64_MAX;
    const unsigned D = l->depth;
    for (uint32_t i = 0; i < l->n && cnt <= cap; i++) {
        const mr_svo_key k = l->keys[i];
        const uint64_t c = k.code >> (3u * (D - L));
        if (k.level >= L) {
            if (c != last) {
                cnt++;
                last = c;
            }
        } else {
            const unsigned e = 3u * (L - k.level);
            if (e >= 63u)
                return cap + 1;
            cnt += 1ull << e;
            last = c + (1ull << e) - 1u;
        }
    }
    return cnt;
}

static void sk_fill_cells(const sk_leaves *l, unsigned L, uint64_t *codes)
{
    uint64_t last = UINT64_MAX;
    uint32_t n = 0;
    const unsigned D = l->depth;
    for (uint32_t i = 0; i < l->n; i++) {
        const mr_svo_key k = l->keys[i];
        const uint64_t c = k.code >> (3u * (D - L));
        if (k.level >= L) {
            if (c != last)
                codes[n++] = last = c;
        } else {
            const uint64_t span = 1ull << (3u * (L - k.level));
            for (uint64_t j = 0; j < span; j++)
                codes[n++] = c + j;
            last = c + span - 1u;
        }
    }
}

/* Index of code in the increasing codes[0, n), or -1. */
static int64_t sk_find(const uint64_t *codes, uint32_t n, uint64_t code)
{
    uint32_t lo = 0, hi = n;
    while (lo < hi) {
        const uint32_t mid = lo + (hi - lo) / 2u;
        if (codes[mid] < code)
            lo = mid + 1u;
        else
            hi = mid;
    }
    return lo < n && codes[lo] == code ? (int64_t)lo : -1;
}

typedef struct sk_graph {
    uint32_t n;
    unsigned level;
    uint64_t *code;   /* n, increasing */
    uint32_t *nbr;    /* SK_NBR per vertex, the first nbr_n[i] used, in offset order */
    uint8_t *nbr_slot; /* offset slot (0..25) of each entry of nbr */
    uint8_t *nbr_n;
    /* Pairs of offset slots that are 26-neighbours of each other: with the
     * centre they make the triangles of a vertex's one-ring. */
    unsigned npair;
    uint8_t pair[2][SK_NBR * SK_NBR / 2];
    /* Per vertex, the pairs whose two slots are both occupied: tri[tri_off[i]
     * .. tri_off[i + 1] - 1] (NULL when not wanted). */
    uint32_t *tri_off;
    uint8_t *tri;
} sk_graph;

static void sk_graph_free(sk_graph *g)
{
    free(g->code);
    free(g->nbr);
    free(g->nbr_slot);
    free(g->nbr_n);
    free(g->tri_off);
    free(g->tri);
    memset(g, 0, sizeof *g);
}

static void sk_adjacency_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_graph *g = ctx;
    const uint32_t res = 1u << g->level;
    for (size_t i = begin; i < end; i++) {
        uint32_t x, y, z, k = 0, slot = 0;
        mr_morton_decode(g->code[i], &x, &y, &z);
        for (int dz = -1; dz <= 1; dz++)
            for (int dy = -1; dy <= 1; dy++)
                for (int dx = -1; dx <= 1; dx++) {
                    if (!dx && !dy && !dz)
                        continue;
                    const uint8_t this_slot = (uint8_t)slot++;
                    const int64_t nx = (int64_t)x + dx, ny = (int64_t)y + dy, nz = (int64_t)z + dz;
                    if (nx < 0 || ny < 0 || nz < 0 || nx >= res || ny >= res || nz >= res)
                        continue;
                    const int64_t j = sk_find(g->code, g->n, mr_morton_encode((uint32_t)nx, (uint32_t)ny, (uint32_t)nz));
                    if (j >= 0) {
                        g->nbr_slot[i * SK_NBR + k] = this_slot;
                        g->nbr[i * SK_NBR + k++] = (uint32_t)j;
                    }
                }
        g->nbr_n[i] = (uint8_t)k;
    }
}

/* The graph of the occupied cells at level L (codes taken over when given). */
/* Bit mask of the occupied offset slots of vertex i. */
static uint32_t sk_slot_mask(const sk_graph *g, size_t i)
{
    uint32_t m = 0;
    for (unsigned t = 0; t < g->nbr_n[i]; t++)
        m |= 1u << g->nbr_slot[i * SK_NBR + t];
    return m;
}

static void sk_tri_count_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_graph *g = ctx;
    for (size_t i = begin; i < end; i++) {
        const uint32_t m = sk_slot_mask(g, i);
        uint32_t k = 0;
        for (unsigned t = 0; t < g->npair; t++)
            k += (m >> g->pair[0][t]) & (m >> g->pair[1][t]) & 1u;
        g->tri_off[i + 1u] = k;
    }
}

static void sk_tri_fill_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_graph *g = ctx;
    for (size_t i = begin; i < end; i++) {
        const uint32_t m = sk_slot_mask(g, i);
        uint32_t k = g->tri_off[i];
        for (unsigned t = 0; t < g->npair; t++)
            if ((m >> g->pair[0][t]) & (m >> g->pair[1][t]) & 1u)
                g->tri[k++] = (uint8_t)t;
    }
}

static int sk_graph_build(const sk_leaves *l, unsigned L, uint32_t n, uint64_t *codes, bool tris, unsigned threads,
                          sk_graph *g, mr_error *err)
{
    memset(g, 0, sizeof *g);
    g->n = n;
    g->level = L;
    g->code = codes ? codes : malloc((size_t)n * sizeof *g->code);
    g->nbr = malloc((size_t)n * SK_NBR * sizeof *g->nbr);
    g->nbr_slot = malloc((size_t)n * SK_NBR + 1u);
    g->nbr_n = malloc(n ? n : 1u);
    if (!g->code || !g->nbr || !g->nbr_slot || !g->nbr_n) {
        sk_graph_free(g);
        return mr_error_set(err, MR_ERR_NOMEM, "skeleton: out of memory for a graph of %u vertices", n);
    }
    if (!codes)
        sk_fill_cells(l, L, g->code);
    int off[SK_NBR][3], t = 0;
    for (int dz = -1; dz <= 1; dz++)
        for (int dy = -1; dy <= 1; dy++)
            for (int dx = -1; dx <= 1; dx++)
                if (dx || dy || dz) {
                    off[t][0] = dx;
                    off[t][1] = dy;
                    off[t++][2] = dz;
                }
    for (unsigned a = 0; a < SK_NBR; a++)
        for (unsigned b = a + 1u; b < SK_NBR; b++)
            if (abs(off[a][0] - off[b][0]) <= 1 && abs(off[a][1] - off[b][1]) <= 1 && abs(off[a][2] - off[b][2]) <= 1) {
                g->pair[0][g->npair] = (uint8_t)a;
                g->pair[1][g->npair++] = (uint8_t)b;
            }
    mr_parallel_for(threads, n, SK_GRAIN, sk_adjacency_range, g);
    if (!tris)
        return MR_OK;
    if (!(g->tri_off = calloc((size_t)n + 1u, sizeof *g->tri_off)))
        goto nomem;
    mr_parallel_for(threads, n, SK_GRAIN, sk_tri_count_range, g);
    for (uint32_t i = 0; i < n; i++)
        g->tri_off[i + 1u] += g->tri_off[i];
    if (!(g->tri = malloc((size_t)g->tri_off[n] + 1u)))
        goto nomem;
    mr_parallel_for(threads, n, SK_GRAIN, sk_tri_fill_range, g);
    return MR_OK;
nomem:
    sk_graph_free(g);
    return mr_error_set(err, MR_ERR_NOMEM, "skeleton: out of memory for the one-rings of %u vertices", n);
}

/* ------------------------------------------------------------------------ */
/* one-ring area                                                             */

/* Total area of the one-ring triangles (v, n_a, n_b), n_a and n_b
 * 26-neighbours of v and of each other. */
static double sk_area(const sk_graph *g, const double *pos, uint32_t i)
{
    const unsigned k = g->nbr_n[i];
    if (k < 2)
        return 0.0;
    uint32_t at[SK_NBR]; /* only the occupied slots are read */
    for (unsigned t = 0; t < k; t++)
        at[g->nbr_slot[(size_t)i * SK_NBR + t]] = g->nbr[(size_t)i * SK_NBR + t];
    const double *v = pos + 3u * i;
    double sum = 0.0;
    for (uint32_t e = g->tri_off[i]; e < g->tri_off[i + 1u]; e++) {
        const unsigned t = g->tri[e];
        const double *p = pos + 3u * at[g->pair[0][t]], *q = pos + 3u * at[g->pair[1][t]];
        const double ax = p[0] - v[0], ay = p[1] - v[1], az = p[2] - v[2];
        const double bx = q[0] - v[0], by = q[1] - v[1], bz = q[2] - v[2];
        const double cx = ay * bz - az * by, cy = az * bx - ax * bz, cz = ax * by - ay * bx;
        sum += sqrt(cx * cx + cy * cy + cz * cz);
    }
    return 0.5 * sum;
}


/* ------------------------------------------------------------------------ */
/* fixed-radius neighbours: uniform grid of cell omega over distinct points  */

/* Dense grid: cells of edge max(omega, 1 / SK_GRID_MAX) over the unit cube,
 * so points within omega of each other are in the same or adjacent cells. */
#define SK_GRID_MAX 64u /* res^3 <= 2^18, see sk_mgrid_build */

typedef struct sk_mgrid {
    double omega;
    uint32_t res;     /* cells per axis */
    double cell;      /* cell edge */
    uint32_t nd;      /* distinct points */
    uint32_t nocc;    /* occupied cells */
    double *dp;       /* 3 per distinct point */
    uint32_t *dn;     /* vertices at each distinct point */
    uint32_t *dcell;  /* grid cell of each distinct point */
    uint32_t *first;  /* res^3: distinct points of cell c are first[c] .. end[c] - 1 (0, 0 when empty) */
    uint32_t *end;
    uint32_t *occ;    /* occupied cells, to clear first/end on the next build */
    uint32_t *vcell;  /* grid cell of each vertex */
    uint32_t *order;  /* vertices sorted by cell, then position */
    uint32_t *tmp;
    uint32_t *vd;     /* distinct point of each vertex */
} sk_mgrid;

static void sk_mgrid_free(sk_mgrid *m)
{
    free(m->dp);
    free(m->dn);
    free(m->dcell);
    free(m->first);
    free(m->end);
    free(m->occ);
    free(m->vcell);
    free(m->order);
    free(m->tmp);
    free(m->vd);
    memset(m, 0, sizeof *m);
}

static int sk_mgrid_alloc(sk_mgrid *m, uint32_t n, double omega)
{
    memset(m, 0, sizeof *m);
    m->omega = omega;
    m->cell = omega > 1.0 / SK_GRID_MAX ? omega : 1.0 / SK_GRID_MAX;
    const double r = ceil(1.0 / m->cell);
    m->res = r < 1.0 ? 1u : r > SK_GRID_MAX ? SK_GRID_MAX : (uint32_t)r;
    const size_t c = n ? n : 1u, cells = (size_t)m->res * m->res * m->res;
    m->dp = malloc(c * 3u * sizeof *m->dp);
    m->dn = malloc(c * sizeof *m->dn);
    m->dcell = malloc(c * sizeof *m->dcell);
    m->first = calloc(cells, sizeof *m->first);
    m->end = calloc(cells, sizeof *m->end);
    m->occ = malloc(c * sizeof *m->occ);
    m->vcell = malloc(c * sizeof *m->vcell);
    m->order = malloc(c * sizeof *m->order);
    m->tmp = malloc(c * sizeof *m->tmp);
    m->vd = malloc(c * sizeof *m->vd);
    if (!m->dp || !m->dn || !m->dcell || !m->first || !m->end || !m->occ || !m->vcell || !m->order || !m->tmp ||
        !m->vd) {
        sk_mgrid_free(m);
        return MR_ERR_NOMEM;
    }
    return MR_OK;
}

static uint32_t sk_grid_coord(const sk_mgrid *m, double x)
{
    const double g = floor(x / m->cell);
    return g <= 0.0 ? 0u : g >= (double)(m->res - 1u) ? m->res - 1u : (uint32_t)g;
}

/* Position order of two vertices (then index), for finding coincident ones. */
static bool sk_pos_less(const double *pos, uint32_t a, uint32_t b)
{
    for (unsigned k = 0; k < 3; k++)
        if (pos[3u * a + k] != pos[3u * b + k])
            return pos[3u * a + k] < pos[3u * b + k];
    return a < b;
}

/* Rebuilds the grid for the positions pos[0, n). */
static void sk_mgrid_build(sk_mgrid *m, const double *pos, uint32_t n)
{
    const uint32_t R = m->res;
    for (uint32_t k = 0; k < m->nocc; k++)
        m->first[m->occ[k]] = m->end[m->occ[k]] = 0;
    for (uint32_t i = 0; i < n; i++) {
        m->vcell[i] = sk_grid_coord(m, pos[3u * i]) +
                      R * (sk_grid_coord(m, pos[3u * i + 1u]) + R * sk_grid_coord(m, pos[3u * i + 2u]));
        m->order[i] = i;
    }
    /* Stable LSD radix sort of the vertices by cell (res^3 <= 2^18: two
     * 9-bit digits), so coincident vertices stay in index order. */
    for (unsigned shift = 0; shift < 18u; shift += 9u) {
        uint32_t count[513];
        memset(count, 0, sizeof count);
        for (uint32_t i = 0; i < n; i++)
            count[((m->vcell[m->order[i]] >> shift) & 511u) + 1u]++;
        for (unsigned d = 0; d < 512u; d++)
            count[d + 1u] += count[d];
        for (uint32_t i = 0; i < n; i++)
            m->tmp[count[(m->vcell[m->order[i]] >> shift) & 511u]++] = m->order[i];
        uint32_t *t = m->order;
        m->order = m->tmp;
        m->tmp = t;
    }
    m->nd = m->nocc = 0;
    for (uint32_t b = 0; b < n;) {
        const uint32_t c = m->vcell[m->order[b]];
        uint32_t e = b + 1u;
        while (e < n && m->vcell[m->order[e]] == c)
            e++;
        /* insertion sort by position: cells hold few distinct positions */
        for (uint32_t t = b + 1u; t < e; t++) {
            const uint32_t v = m->order[t];
            uint32_t u = t;
            while (u > b && sk_pos_less(pos, v, m->order[u - 1u])) {
                m->order[u] = m->order[u - 1u];
                u--;
            }
            m->order[u] = v;
        }
        m->occ[m->nocc++] = c;
        m->first[c] = m->nd;
        for (uint32_t t = b; t < e; t++) {
            const uint32_t v = m->order[t];
            if (t == b || memcmp(pos + 3u * v, pos + 3u * m->order[t - 1u], 3u * sizeof *pos) != 0) {
                memcpy(m->dp + 3u * m->nd, pos + 3u * v, 3u * sizeof *pos);
                m->dn[m->nd] = 0;
                m->dcell[m->nd++] = c;
            }
            m->dn[m->nd - 1u]++;
            m->vd[v] = m->nd - 1u;
        }
        m->end[c] = m->nd;
        b = e;
    }
}

/* Calls fn(ctx, d) for every distinct point d within omega (inclusive) of
 * distinct point q, in a fixed order (cells by offset, points by position),
 * so sums over them do not depend on the thread count. */
typedef void (*sk_visit)(void *ctx, uint32_t d);

static void sk_for_near(const sk_mgrid *m, uint32_t q, sk_visit fn, void *ctx)
{
    const uint32_t R = m->res, c = m->dcell[q];
    const int64_t gx = c % R, gy = (c / R) % R, gz = c / R / R;
    const double *qp = m->dp + 3u * q;
    const double r2 = m->omega * m->omega;
    for (int64_t z = gz - 1; z <= gz + 1; z++)
        for (int64_t y = gy - 1; y <= gy + 1; y++)
            for (int64_t x = gx - 1; x <= gx + 1; x++) {
                if (x < 0 || y < 0 || z < 0 || x >= R || y >= R || z >= R)
                    continue;
                const size_t cc = (size_t)x + R * ((size_t)y + R * (size_t)z);
                for (uint32_t d = m->first[cc]; d < m->end[cc]; d++) {
                    const double *p = m->dp + 3u * d;
                    const double ex = p[0] - qp[0], ey = p[1] - qp[1], ez = p[2] - qp[2];
                    if (ex * ex + ey * ey + ez * ez <= r2)
                        fn(ctx, d);
                }
            }
}

/* ------------------------------------------------------------------------ */
/* contraction                                                               */

typedef struct sk_contract {
    const sk_graph *g;
    sk_mgrid *m;
    const double *cur;
    double *next;
    const double *rho;
    double *area;
    double *mpos; /* merged position per distinct point */
    double *move;
} sk_contract;

typedef struct sk_mean {
    const sk_mgrid *m;
    double s[3], n;
} sk_mean;

static void sk_mean_add(void *ctx, uint32_t d)
{
    sk_mean *a = ctx;
    const double w = a->m->dn[d];
    for (int k = 0; k < 3; k++)
        a->s[k] += w * a->m->dp[3u * d + (unsigned)k];
    a->n += w;
}

static void sk_merge_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_contract *c = ctx;
    for (size_t q = begin; q < end; q++) {
        sk_mean a = {c->m, {0, 0, 0}, 0};
        sk_for_near(c->m, (uint32_t)q, sk_mean_add, &a);
        /* a.n >= 1: q is within omega of itself */
        for (int k = 0; k < 3; k++)
            c->mpos[3u * q + (unsigned)k] = a.s[k] / a.n;
    }
}

static void sk_update_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_contract *c = ctx;
    const sk_graph *g = c->g;
    for (size_t i = begin; i < end; i++) {
        const double *v = c->cur + 3u * i;
        double s[3] = {v[0], v[1], v[2]};
        const unsigned k = g->nbr_n[i];
        if (k > 0) {
            s[0] = s[1] = s[2] = 0.0;
            for (unsigned t = 0; t < k; t++) {
                const double *n = c->cur + 3u * g->nbr[i * SK_NBR + t];
                s[0] += n[0];
                s[1] += n[1];
                s[2] += n[2];
            }
            for (int a = 0; a < 3; a++)
                s[a] /= (double)k;
        }
        const double a = sk_area(g, c->cur, (uint32_t)i);
        c->area[i] = a;
        double beta = c->rho[i] > 0.0 ? a / c->rho[i] : 0.0;
        beta = beta > 1.0 ? 1.0 : beta;
        const double *m = c->mpos + 3u * c->m->vd[i];
        double *o = c->next + 3u * i;
        double d2 = 0.0;
        for (int t = 0; t < 3; t++) {
            o[t] = m[t] + beta * (s[t] - m[t]);
            d2 += (o[t] - v[t]) * (o[t] - v[t]);
        }
        c->move[i] = sqrt(d2);
    }
}

static void sk_area_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_contract *c = ctx;
    for (size_t i = begin; i < end; i++)
        c->area[i] = sk_area(c->g, c->cur, (uint32_t)i);
}

/* ------------------------------------------------------------------------ */
/* weld and forest                                                           */

static uint32_t sk_uf_find(uint32_t *p, uint32_t x)
{
    while (p[x] != x) {
        p[x] = p[p[x]];
        x = p[x];
    }
    return x;
}

/* BFS over the group graph (CSR off/adj) from start; visited nodes are
 * appended to queue (returns how many), dist/par filled for them. */
static uint32_t sk_bfs(const uint32_t *off, const uint32_t *adj, uint32_t start, uint32_t *queue, int32_t *dist,
                       int32_t *par)
{
    uint32_t head = 0, tail = 0;
    queue[tail++] = start;
    dist[start] = 0;
    par[start] = -1;
    while (head < tail) {
        const uint32_t u = queue[head++];
        for (uint32_t e = off[u]; e < off[u + 1u]; e++) {
            const uint32_t w = adj[e];
            if (dist[w] >= 0)
                continue;
            dist[w] = dist[u] + 1;
            par[w] = (int32_t)u;
            queue[tail++] = w;
        }
    }
    return tail;
}

static uint32_t sk_farthest(const uint32_t *queue, uint32_t count, const int32_t *dist)
{
    uint32_t best = queue[0];
    for (uint32_t i = 1; i < count; i++) {
        const uint32_t u = queue[i];
        if (dist[u] > dist[best] || (dist[u] == dist[best] && u < best))
            best = u;
    }
    return best;
}

typedef struct sk_union {
    uint32_t *uf;
    uint32_t q;
} sk_union;

static void sk_union_add(void *ctx, uint32_t d)
{
    sk_union *u = ctx;
    if (d <= u->q)
        return;
    const uint32_t a = sk_uf_find(u->uf, u->q), b = sk_uf_find(u->uf, d);
    if (a < b)
        u->uf[b] = a;
    else if (b < a)
        u->uf[a] = b;
}

static int sk_pair_cmp(const void *pa, const void *pb)
{
    const uint64_t a = *(const uint64_t *)pa, b = *(const uint64_t *)pb;
    return (a > b) - (a < b);
}

/* Welds the contracted positions into groups and builds the forest. */
static int sk_weld(const sk_graph *g, const double *pos, double omega, const mr_svo *svo, mr_svo_skeleton *out,
                   mr_error *err)
{
    int rc = MR_OK;
    const uint32_t n = g->n;
    sk_mgrid m = {0};
    uint32_t *uf = NULL, *group = NULL, *gid = NULL, *off = NULL, *adj = NULL, *queue = NULL, *bone_of = NULL;
    int32_t *dist = NULL, *par = NULL;
    uint64_t *pairs = NULL;
    double *sum = NULL;
    uint32_t *cnt = NULL;
    if (sk_mgrid_alloc(&m, n, omega) < 0)
        goto nomem;
    sk_mgrid_build(&m, pos, n);
    uf = malloc((size_t)m.nd * sizeof *uf);
    group = malloc((size_t)n * sizeof *group);
    gid = malloc((size_t)m.nd * sizeof *gid);
    if (!uf || !group || !gid)
        goto nomem;
    for (uint32_t d = 0; d < m.nd; d++)
        uf[d] = d;
    for (uint32_t q = 0; q < m.nd; q++) {
        sk_union u = {uf, q};
        sk_for_near(&m, q, sk_union_add, &u);
    }
    /* Groups numbered by their first vertex (Morton order). */
    uint32_t ng = 0;
    for (uint32_t d = 0; d < m.nd; d++)
        gid[d] = UINT32_MAX;
    for (uint32_t i = 0; i < n; i++) {
        const uint32_t r = sk_uf_find(uf, m.vd[i]);
        if (gid[r] == UINT32_MAX)
            gid[r] = ng++;
        group[i] = gid[r];
    }
    /* Group graph: graph edges between different groups. */
    size_t np = 0, cap = 0;
    for (uint32_t i = 0; i < n; i++)
        for (unsigned t = 0; t < g->nbr_n[i]; t++) {
            const uint32_t j = g->nbr[(size_t)i * SK_NBR + t];
            if (j > i && group[i] != group[j])
                cap++;
        }
    pairs = malloc((cap ? cap : 1u) * sizeof *pairs);
    off = calloc((size_t)ng + 1u, sizeof *off);
    if (!pairs || !off)
        goto nomem;
    for (uint32_t i = 0; i < n; i++)
        for (unsigned t = 0; t < g->nbr_n[i]; t++) {
            const uint32_t j = g->nbr[(size_t)i * SK_NBR + t];
            if (j > i && group[i] != group[j]) {
                const uint32_t a = group[i] < group[j] ? group[i] : group[j];
                const uint32_t b = group[i] ^ group[j] ^ a;
                pairs[np++] = ((uint64_t)a << 32) | b;
            }
        }
    qsort(pairs, np, sizeof *pairs, sk_pair_cmp);
    size_t nu = 0;
    for (size_t e = 0; e < np; e++)
        if (nu == 0 || pairs[e] != pairs[nu - 1u])
            pairs[nu++] = pairs[e];
    for (size_t e = 0; e < nu; e++) {
        off[(pairs[e] >> 32) + 1u]++;
        off[(pairs[e] & 0xffffffffu) + 1u]++;
    }
    for (uint32_t u = 0; u < ng; u++)
        off[u + 1u] += off[u];
    adj = malloc((nu ? 2u * nu : 1u) * sizeof *adj);
    queue = malloc((size_t)ng * sizeof *queue);
    bone_of = malloc((size_t)ng * sizeof *bone_of);
    dist = malloc((size_t)ng * sizeof *dist);
    par = malloc((size_t)ng * sizeof *par);
    if (!adj || !queue || !bone_of || !dist || !par)
        goto nomem;
    {
        /* Neighbour lists sorted by group, so the BFS numbering of the
         * bones is fixed. */
        uint32_t *fill = malloc(((size_t)ng + 1u) * sizeof *fill);
        if (!fill)
            goto nomem;
        memcpy(fill, off, ((size_t)ng + 1u) * sizeof *fill);
        for (size_t e = 0; e < nu; e++) {
            const uint32_t a = (uint32_t)(pairs[e] >> 32), b = (uint32_t)(pairs[e] & 0xffffffffu);
            adj[fill[a]++] = b;
            adj[fill[b]++] = a;
        }
        free(fill);
        for (uint32_t u = 0; u < ng; u++) {
            /* insertion sort: lists are short */
            for (uint32_t e = off[u] + 1u; e < off[u + 1u]; e++) {
                const uint32_t x = adj[e];
                uint32_t f = e;
                while (f > off[u] && adj[f - 1u] > x) {
                    adj[f] = adj[f - 1u];
                    f--;
                }
                adj[f] = x;
            }
        }
    }
    for (uint32_t u = 0; u < ng; u++) {
        dist[u] = -1;
        bone_of[u] = UINT32_MAX;
    }
    out->position = malloc((ng ? ng : 1u) * sizeof *out->position);
    out->parent = malloc((ng ? ng : 1u) * sizeof *out->parent);
    sum = calloc((size_t)ng * 3u + 1u, sizeof *sum);
    cnt = calloc((size_t)ng + 1u, sizeof *cnt);
    if (!out->position || !out->parent || !sum || !cnt)
        goto nomem;
    uint32_t nb = 0;
    for (uint32_t g0 = 0; g0 < ng; g0++) {
        if (bone_of[g0] != UINT32_MAX)
            continue;
        /* Two sweeps: the midpoint of a longest BFS path is the centre of a
         * tree (and near it for graphs with cycles). */
        uint32_t k = sk_bfs(off, adj, g0, queue, dist, par);
        const uint32_t a = sk_farthest(queue, k, dist);
        for (uint32_t t = 0; t < k; t++)
            dist[queue[t]] = -1;
        k = sk_bfs(off, adj, a, queue, dist, par);
        const uint32_t b = sk_farthest(queue, k, dist);
        uint32_t centre = b;
        for (int32_t steps = dist[b] / 2; steps > 0; steps--)
            centre = (uint32_t)par[centre];
        for (uint32_t t = 0; t < k; t++)
            dist[queue[t]] = -1;
        k = sk_bfs(off, adj, centre, queue, dist, par);
        for (uint32_t t = 0; t < k; t++) {
            const uint32_t u = queue[t];
            bone_of[u] = nb;
            out->parent[nb] = par[u] < 0 ? -1 : (int32_t)bone_of[par[u]];
            nb++;
        }
        for (uint32_t t = 0; t < k; t++)
            dist[queue[t]] = -1;
    }
    /* Bone positions: mean contracted position of the group, in bind space. */
    for (uint32_t i = 0; i < n; i++) {
        const uint32_t u = group[i];
        for (int a = 0; a < 3; a++)
            sum[3u * u + (unsigned)a] += pos[3u * i + (unsigned)a];
        cnt[u]++;
    }
    for (uint32_t u = 0; u < ng; u++) {
        const double s = svo->size;
        const uint32_t k = bone_of[u];
        out->position[k] = mr_v3((float)(svo->origin.x + s * (sum[3u * u] / cnt[u])),
                                 (float)(svo->origin.y + s * (sum[3u * u + 1u] / cnt[u])),
                                 (float)(svo->origin.z + s * (sum[3u * u + 2u] / cnt[u])));
    }
    out->bone_count = nb;
    for (uint32_t i = 0; i < n; i++)
        out->cell_bone[i] = bone_of[group[i]];
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "skeleton: out of memory welding %u vertices", n);
cleanup:
    sk_mgrid_free(&m);
    free(uf);
    free(group);
    free(gid);
    free(off);
    free(adj);
    free(queue);
    free(bone_of);
    free(dist);
    free(par);
    free(pairs);
    free(sum);
    free(cnt);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* skeletonize                                                               */

void mr_svo_skeleton_free(mr_svo_skeleton *s)
{
    if (!s)
        return;
    free(s->position);
    free(s->parent);
    free(s->cell_code);
    free(s->cell_bone);
    memset(s, 0, sizeof *s);
}

int mr_svo_skeletonize(const mr_svo *svo, const mr_svo_skeleton_params *p, mr_svo_skeleton *out, mr_error *err)
{
    int rc = MR_OK;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: out is NULL");
    memset(out, 0, sizeof *out);
    if (!svo)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: svo is NULL");
    sk_params prm;
    if ((rc = sk_resolve(p, svo->depth <= MR_SVO_MAX_DEPTH ? svo->depth : MR_SVO_MAX_DEPTH, &prm, err)) < 0)
        return rc;
    out->omega = (float)prm.omega;
    sk_leaves lv = {0};
    sk_graph g = {0};
    sk_mgrid m = {0};
    double *cur = NULL, *next = NULL, *rho = NULL, *area = NULL, *mpos = NULL, *move = NULL;
    if ((rc = sk_leaves_collect(svo, &lv, err)) < 0)
        goto cleanup;
    if (lv.n == 0)
        goto cleanup; /* empty octree: empty skeleton */
    /* Working level: nearest to omega in log scale, coarser while too big. */
    const unsigned D = lv.depth;
    long lw = lround(-log2(prm.omega));
    unsigned L0 = lw < 0 ? 0u : lw > (long)D ? D : (unsigned)lw, L = L0;
    uint64_t nv = sk_count_cells(&lv, L, MR_SVO_SKELETON_MAX_VERTICES);
    while (nv > MR_SVO_SKELETON_MAX_VERTICES && L > 0) {
        L--;
        nv = sk_count_cells(&lv, L, MR_SVO_SKELETON_MAX_VERTICES);
    }
    if (L < L0)
        prm.omega = ldexp(1.0, -(int)L);
    out->omega = (float)prm.omega;
    out->level = L;
    const uint32_t n = (uint32_t)nv;
    if ((rc = sk_graph_build(&lv, L, n, NULL, true, prm.threads, &g, err)) < 0)
        goto cleanup;
    out->graph_vertices = n;
    cur = malloc((size_t)n * 3u * sizeof *cur);
    next = malloc((size_t)n * 3u * sizeof *next);
    rho = malloc((size_t)n * sizeof *rho);
    area = malloc((size_t)n * sizeof *area);
    mpos = malloc((size_t)n * 3u * sizeof *mpos);
    move = malloc((size_t)n * sizeof *move);
    out->cell_code = malloc((size_t)n * sizeof *out->cell_code);
    out->cell_bone = malloc((size_t)n * sizeof *out->cell_bone);
    if (!cur || !next || !rho || !area || !mpos || !move || !out->cell_code || !out->cell_bone ||
        sk_mgrid_alloc(&m, n, prm.omega) < 0) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "skeleton: out of memory for %u graph vertices", n);
        goto cleanup;
    }
    memcpy(out->cell_code, g.code, (size_t)n * sizeof *g.code);
    const double cell = ldexp(1.0, -(int)L);
    for (uint32_t i = 0; i < n; i++) {
        uint32_t x, y, z;
        mr_morton_decode(g.code[i], &x, &y, &z);
        cur[3u * i] = ((double)x + 0.5) * cell;
        cur[3u * i + 1u] = ((double)y + 0.5) * cell;
        cur[3u * i + 2u] = ((double)z + 0.5) * cell;
    }
    sk_contract c = {&g, &m, cur, next, rho, area, mpos, move};
    mr_parallel_for(prm.threads, n, SK_GRAIN, sk_area_range, &c);
    memcpy(rho, area, (size_t)n * sizeof *rho);
    double moved = 0.0;
    unsigned it = 0;
    while (it < prm.max_iterations) {
        sk_mgrid_build(&m, c.cur, n);
        mr_parallel_for(prm.threads, m.nd, SK_GRAIN, sk_merge_range, &c);
        mr_parallel_for(prm.threads, n, SK_GRAIN, sk_update_range, &c);
        moved = 0.0;
        for (uint32_t i = 0; i < n; i++)
            moved += move[i];
        double *t = (double *)c.cur;
        c.cur = c.next;
        c.next = t;
        it++;
        if (moved < prm.delta)
            break;
    }
    out->iterations = it;
    out->final_movement = moved;
    /* Thinness (eq. 5.7.1) on the final positions. */
    mr_parallel_for(prm.threads, n, SK_GRAIN, sk_area_range, &c);
    double sa = 0.0, sr = 0.0;
    for (uint32_t i = 0; i < n; i++) {
        sa += area[i];
        sr += rho[i];
    }
    out->thinness_error_percent = sr > 0.0 ? 100.0 * sa / sr : 0.0;
    rc = sk_weld(&g, c.cur, prm.omega, svo, out, err);
cleanup:
    if (rc < 0) {
        const float om = out->omega;
        mr_svo_skeleton_free(out);
        out->omega = om;
    }
    sk_leaves_free(&lv);
    sk_graph_free(&g);
    sk_mgrid_free(&m);
    free(cur);
    free(next);
    free(rho);
    free(area);
    free(mpos);
    free(move);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* segmentation and soft weights                                             */

/* Checks s against svo and collects the leaves. */
static int sk_check_pair(const mr_svo *svo, const mr_svo_skeleton *s, sk_leaves *lv, mr_error *err)
{
    if (!svo || !s)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: NULL svo or skeleton");
    if (svo->leaf_count > 0 && (s->graph_vertices == 0 || !s->cell_code || !s->cell_bone || s->bone_count == 0))
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: the skeleton is empty but the octree has %u leaves",
                            svo->leaf_count);
    int rc = sk_leaves_collect(svo, lv, err);
    if (rc < 0)
        return rc;
    if (lv->n > 0 && s->level > lv->depth) {
        sk_leaves_free(lv);
        return mr_error_set(err, MR_ERR_INVALID, "skeleton: working level %u below the octree's depth %u", s->level,
                            svo->depth);
    }
    for (uint32_t i = 0; i < s->graph_vertices; i++)
        if (s->cell_bone[i] >= s->bone_count || (i > 0 && s->cell_code[i] <= s->cell_code[i - 1u])) {
            sk_leaves_free(lv);
            return mr_error_set(err, MR_ERR_INVALID, "skeleton: mapping entry %u is inconsistent", i);
        }
    return MR_OK;
}

/* Leaf centre in level-L cell units. */
static void sk_leaf_centre(const mr_svo_key *k, unsigned D, unsigned L, double u[3])
{
    uint32_t x, y, z;
    mr_morton_decode(k->code, &x, &y, &z);
    const double half = ldexp(0.5, (int)(D - k->level)), scale = ldexp(1.0, -(int)(D - L));
    u[0] = ((double)x + half) * scale;
    u[1] = ((double)y + half) * scale;
    u[2] = ((double)z + half) * scale;
}

/* The graph vertex holding leaf k (its ancestor at L, or the cell holding
 * its centre), or -1. */
static int64_t sk_leaf_cell(const mr_svo_skeleton *s, const mr_svo_key *k, unsigned D)
{
    const unsigned L = s->level;
    uint64_t code;
    if (k->level >= L) {
        code = k->code >> (3u * (D - L));
    } else {
        double u[3];
        sk_leaf_centre(k, D, L, u);
        code = mr_morton_encode((uint32_t)u[0], (uint32_t)u[1], (uint32_t)u[2]);
    }
    return sk_find(s->cell_code, s->graph_vertices, code);
}

int mr_svo_skeleton_segment(const mr_svo *svo, const mr_svo_skeleton *s, uint32_t *leaf_bone, mr_error *err)
{
    sk_leaves lv;
    if (!leaf_bone && svo && svo->leaf_count > 0)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton segment: leaf_bone is NULL");
    int rc = sk_check_pair(svo, s, &lv, err);
    if (rc < 0)
        return rc;
    for (uint32_t t = 0; t < lv.n; t++) {
        const int64_t c = sk_leaf_cell(s, &lv.keys[t], lv.depth);
        if (c < 0) {
            rc = mr_error_set(err, MR_ERR_INVALID,
                              "skeleton segment: leaf %u lies in no cell of the skeleton (another octree?)",
                              lv.index[t]);
            break;
        }
        leaf_bone[lv.index[t]] = s->cell_bone[c];
    }
    sk_leaves_free(&lv);
    return rc;
}

/* Sparse bone weights of up to cap entries. */
typedef struct sk_wlist {
    unsigned n;
    uint32_t bone[27u * SK_KEEP];
    double w[27u * SK_KEEP];
} sk_wlist;

static void sk_wlist_add(sk_wlist *l, uint32_t bone, double w)
{
    for (unsigned i = 0; i < l->n; i++)
        if (l->bone[i] == bone) {
            l->w[i] += w;
            return;
        }
    l->bone[l->n] = bone;
    l->w[l->n++] = w;
}

/* Sorts by decreasing weight (ties: lower bone) and keeps the first keep. */
static void sk_wlist_top(sk_wlist *l, unsigned keep)
{
    for (unsigned i = 1; i < l->n; i++) {
        const uint32_t b = l->bone[i];
        const double w = l->w[i];
        unsigned j = i;
        while (j > 0 && (l->w[j - 1u] < w || (l->w[j - 1u] == w && l->bone[j - 1u] > b))) {
            l->bone[j] = l->bone[j - 1u];
            l->w[j] = l->w[j - 1u];
            j--;
        }
        l->bone[j] = b;
        l->w[j] = w;
    }
    if (l->n > keep)
        l->n = keep;
}

typedef struct sk_soft {
    const sk_graph *g;
    const mr_svo_skeleton *s;
    const sk_leaves *lv;
    const uint32_t *wn_in; /* bones per vertex */
    const uint32_t *wb_in; /* SK_KEEP per vertex */
    const double *ww_in;
    uint32_t *wn_out;
    uint32_t *wb_out;
    double *ww_out;
    /* per leaf, Morton order: MR_SVO_INFLUENCES bones and float weights */
    uint16_t *leaf_joint;
    float *leaf_w; /* all 0 for a leaf outside the mapping */
} sk_soft;

static void sk_soft_add_vertex(const sk_soft *c, sk_wlist *l, uint32_t v, double scale)
{
    for (uint32_t k = 0; k < c->wn_in[v]; k++)
        sk_wlist_add(l, c->wb_in[(size_t)v * SK_KEEP + k], scale * c->ww_in[(size_t)v * SK_KEEP + k]);
}

static void sk_smooth_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_soft *c = ctx;
    sk_wlist l;
    for (size_t i = begin; i < end; i++) {
        l.n = 0;
        const unsigned k = c->g->nbr_n[i];
        sk_soft_add_vertex(c, &l, (uint32_t)i, 1.0);
        for (unsigned t = 0; t < k; t++)
            sk_soft_add_vertex(c, &l, c->g->nbr[i * SK_NBR + t], 1.0);
        sk_wlist_top(&l, SK_KEEP);
        double tot = 0.0;
        for (unsigned t = 0; t < l.n; t++)
            tot += l.w[t];
        c->wn_out[i] = l.n;
        for (unsigned t = 0; t < l.n; t++) {
            c->wb_out[i * SK_KEEP + t] = l.bone[t];
            c->ww_out[i * SK_KEEP + t] = l.w[t] / tot;
        }
    }
}

static void sk_leaf_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_soft *c = ctx;
    const unsigned D = c->lv->depth, L = c->s->level;
    const int64_t res = (int64_t)1 << L;
    sk_wlist l;
    for (size_t t = begin; t < end; t++) {
        l.n = 0;
        double u[3];
        sk_leaf_centre(&c->lv->keys[t], D, L, u);
        int64_t b[3];
        double f[3];
        for (int a = 0; a < 3; a++) {
            const double h = u[a] - 0.5;
            b[a] = (int64_t)floor(h);
            f[a] = h - (double)b[a];
        }
        double tot = 0.0;
        for (unsigned corner = 0; corner < 8u; corner++) {
            int64_t q[3];
            double w = 1.0;
            bool ok = true;
            for (int a = 0; a < 3; a++) {
                const unsigned bit = (corner >> a) & 1u;
                q[a] = b[a] + bit;
                w *= bit ? f[a] : 1.0 - f[a];
                ok = ok && q[a] >= 0 && q[a] < res;
            }
            if (!ok || !(w > 0.0))
                continue;
            const int64_t v = sk_find(c->s->cell_code, c->s->graph_vertices,
                                      mr_morton_encode((uint32_t)q[0], (uint32_t)q[1], (uint32_t)q[2]));
            if (v < 0)
                continue;
            sk_soft_add_vertex(c, &l, (uint32_t)v, w);
            tot += w;
        }
        if (sk_leaf_cell(c->s, &c->lv->keys[t], D) < 0)
            l.n = 0;
        sk_wlist_top(&l, MR_SVO_INFLUENCES);
        for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
            c->leaf_joint[t * MR_SVO_INFLUENCES + k] = k < l.n ? (uint16_t)l.bone[k] : 0u;
            c->leaf_w[t * MR_SVO_INFLUENCES + k] = k < l.n ? (float)(l.w[k] / tot) : 0.0f;
        }
    }
}

/* Float top-4 weights of every leaf in Morton order (lv filled). */
static int sk_soft_weights(const mr_svo *svo, const mr_svo_skeleton *s, unsigned rounds, unsigned threads,
                           sk_leaves *lv, uint16_t **leaf_joint, float **leaf_w, mr_error *err)
{
    int rc = MR_OK;
    sk_graph g = {0};
    uint64_t *codes = NULL;
    uint32_t *wn[2] = {NULL, NULL}, *wb[2] = {NULL, NULL};
    double *ww[2] = {NULL, NULL};
    *leaf_joint = NULL;
    *leaf_w = NULL;
    if ((rc = sk_check_pair(svo, s, lv, err)) < 0)
        return rc;
    if (lv->n == 0)
        return MR_OK;
    if (s->bone_count > MR_MAX_ASSET_JOINTS) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "skeleton: %u bones do not fit 16-bit joint indices", s->bone_count);
        goto cleanup;
    }
    const uint32_t n = s->graph_vertices;
    codes = malloc((size_t)n * sizeof *codes);
    if (!codes)
        goto nomem;
    memcpy(codes, s->cell_code, (size_t)n * sizeof *codes);
    rc = sk_graph_build(lv, s->level, n, codes, false, threads, &g, err);
    codes = NULL; /* owned by g now */
    if (rc < 0)
        goto cleanup;
    for (int k = 0; k < 2; k++) {
        wn[k] = malloc((size_t)n * sizeof *wn[k]);
        wb[k] = malloc((size_t)n * SK_KEEP * sizeof *wb[k]);
        ww[k] = malloc((size_t)n * SK_KEEP * sizeof *ww[k]);
        if (!wn[k] || !wb[k] || !ww[k])
            goto nomem;
    }
    for (uint32_t i = 0; i < n; i++) {
        wn[0][i] = 1;
        wb[0][(size_t)i * SK_KEEP] = s->cell_bone[i];
        ww[0][(size_t)i * SK_KEEP] = 1.0;
    }
    sk_soft c = {&g, s, lv, NULL, NULL, NULL, NULL, NULL, NULL, NULL, NULL};
    int cur = 0;
    for (unsigned r = 0; r < rounds; r++) {
        c.wn_in = wn[cur];
        c.wb_in = wb[cur];
        c.ww_in = ww[cur];
        c.wn_out = wn[cur ^ 1];
        c.wb_out = wb[cur ^ 1];
        c.ww_out = ww[cur ^ 1];
        mr_parallel_for(threads, n, SK_GRAIN, sk_smooth_range, &c);
        cur ^= 1;
    }
    c.wn_in = wn[cur];
    c.wb_in = wb[cur];
    c.ww_in = ww[cur];
    *leaf_joint = malloc((size_t)lv->n * MR_SVO_INFLUENCES * sizeof **leaf_joint);
    *leaf_w = malloc((size_t)lv->n * MR_SVO_INFLUENCES * sizeof **leaf_w);
    if (!*leaf_joint || !*leaf_w)
        goto nomem;
    c.leaf_joint = *leaf_joint;
    c.leaf_w = *leaf_w;
    mr_parallel_for(threads, lv->n, SK_GRAIN, sk_leaf_range, &c);
    uint32_t bad = 0;
    while (bad < lv->n && (*leaf_w)[(size_t)bad * MR_SVO_INFLUENCES] > 0.0f)
        bad++;
    if (bad < lv->n)
        rc = mr_error_set(err, MR_ERR_INVALID,
                          "skeleton weights: a leaf lies in no cell of the skeleton (another octree?)");
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "skeleton weights: out of memory");
cleanup:
    if (rc < 0) {
        free(*leaf_joint);
        free(*leaf_w);
        *leaf_joint = NULL;
        *leaf_w = NULL;
        sk_leaves_free(lv);
    }
    sk_graph_free(&g);
    free(codes);
    for (int k = 0; k < 2; k++) {
        free(wn[k]);
        free(wb[k]);
        free(ww[k]);
    }
    return rc;
}

/* Quantised influences of one leaf: multiples of step summing to 255,
 * sorted by decreasing weight (ties: lower bone), zero slots bone 0. */
static void sk_quantize(const uint16_t *j, const float *w, unsigned step, uint16_t *oj, uint8_t *ow)
{
    uint8_t q[MR_SVO_INFLUENCES];
    mr_svo_quantize_weights(w, MR_SVO_INFLUENCES, step, q);
    unsigned idx[MR_SVO_INFLUENCES];
    for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++)
        idx[k] = k;
    for (unsigned a = 1; a < MR_SVO_INFLUENCES; a++) {
        const unsigned x = idx[a];
        unsigned b = a;
        while (b > 0 && (q[idx[b - 1u]] < q[x] || (q[idx[b - 1u]] == q[x] && j[idx[b - 1u]] > j[x]))) {
            idx[b] = idx[b - 1u];
            b--;
        }
        idx[b] = x;
    }
    for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
        ow[k] = q[idx[k]];
        oj[k] = ow[k] ? j[idx[k]] : 0u;
    }
}

int mr_svo_skeleton_weights(const mr_svo *svo, const mr_svo_skeleton *s, const mr_svo_skeleton_params *p,
                            uint16_t *joints, uint8_t *weights, mr_error *err)
{
    if (!svo || !s)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton weights: NULL svo or skeleton");
    if ((!joints || !weights) && svo->leaf_count > 0)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton weights: NULL output arrays");
    sk_params prm;
    int rc = sk_resolve(p, svo->depth <= MR_SVO_MAX_DEPTH ? svo->depth : MR_SVO_MAX_DEPTH, &prm, err);
    if (rc < 0)
        return rc;
    sk_leaves lv;
    uint16_t *lj = NULL;
    float *lw = NULL;
    if ((rc = sk_soft_weights(svo, s, prm.rounds, prm.threads, &lv, &lj, &lw, err)) < 0)
        return rc;
    for (uint32_t t = 0; t < lv.n; t++) {
        const size_t o = (size_t)lv.index[t] * MR_SVO_INFLUENCES;
        sk_quantize(lj + (size_t)t * MR_SVO_INFLUENCES, lw + (size_t)t * MR_SVO_INFLUENCES, 1u, joints + o,
                    weights + o);
    }
    free(lj);
    free(lw);
    sk_leaves_free(&lv);
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* rig                                                                       */

/* Does name spell "bone<k>" for some k < count (canonical decimal)? */
static bool sk_is_bone_name(const char *name, uint32_t count)
{
    if (strncmp(name, "bone", 4) != 0 || name[4] < '0' || name[4] > '9')
        return false;
    const char *d = name + 4;
    if (d[0] == '0' && d[1] != '\0')
        return false;
    uint64_t v = 0;
    for (; *d; d++) {
        if (*d < '0' || *d > '9' || v > UINT32_MAX)
            return false;
        v = v * 10u + (uint64_t)(*d - '0');
    }
    return v < count;
}


/* Leaf containing finest-level cell (x, y, z), or -1. */
static int64_t sk_find_leaf(const mr_svo *svo, uint32_t x, uint32_t y, uint32_t z)
{
    if (svo->node_count == 0)
        return svo->leaf_count == 1 ? 0 : -1;
    const unsigned D = svo->depth;
    uint32_t node = 0;
    for (unsigned l = 0; l < D; l++) {
        const unsigned sh = D - l - 1u;
        const unsigned ch = ((x >> sh) & 1u) | (((y >> sh) & 1u) << 1) | (((z >> sh) & 1u) << 2);
        const unsigned cm = svo->child_mask[node], lm = svo->leaf_mask[node], below = (1u << ch) - 1u;
        if (!(cm & (1u << ch)))
            return -1;
        if (lm & (1u << ch)) {
            const uint64_t li = (uint64_t)svo->first_leaf[node] + mr_svo_popcount8(lm & below);
            return li < svo->leaf_count ? (int64_t)li : -1;
        }
        const uint64_t ni = (uint64_t)svo->first_node[node] + mr_svo_popcount8(cm & ~lm & below);
        if (ni >= svo->node_count)
            return -1;
        node = (uint32_t)ni;
    }
    return -1;
}

typedef struct sk_bind {
    const mr_svo *svo;
    const mr_svo_skeleton *s;
    const float *pos;     /* bind-space vertex positions */
    const uint16_t *lj;   /* per leaf (svo->leaves order) */
    const uint8_t *lw;
    uint16_t *joints;     /* MR_MAX_INFLUENCES per vertex */
    float *weights;
} sk_bind;

static void sk_bind_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sk_bind *c = ctx;
    const mr_svo *svo = c->svo;
    const double res = ldexp(1.0, (int)svo->depth);
    for (size_t v = begin; v < end; v++) {
        const float *p = c->pos + 3u * v;
        uint16_t *oj = c->joints + v * MR_MAX_INFLUENCES;
        float *ow = c->weights + v * MR_MAX_INFLUENCES;
        for (unsigned k = 0; k < MR_MAX_INFLUENCES; k++) {
            oj[k] = 0;
            ow[k] = 0.0f;
        }
        const double f[3] = {((double)p[0] - svo->origin.x) / svo->size * res,
                             ((double)p[1] - svo->origin.y) / svo->size * res,
                             ((double)p[2] - svo->origin.z) / svo->size * res};
        int64_t leaf = -1;
        if (f[0] >= 0.0 && f[1] >= 0.0 && f[2] >= 0.0 && f[0] < res && f[1] < res && f[2] < res)
            leaf = sk_find_leaf(svo, (uint32_t)f[0], (uint32_t)f[1], (uint32_t)f[2]);
        if (leaf >= 0) {
            for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
                oj[k] = c->lj[(size_t)leaf * MR_SVO_INFLUENCES + k];
                ow[k] = (float)c->lw[(size_t)leaf * MR_SVO_INFLUENCES + k] / 255.0f;
            }
            continue;
        }
        /* Outside every voxel: the nearest bone, wholly. */
        uint32_t best = 0;
        double bd = INFINITY;
        for (uint32_t b = 0; b < c->s->bone_count; b++) {
            const mr_vec3 q = c->s->position[b];
            const double dx = (double)q.x - p[0], dy = (double)q.y - p[1], dz = (double)q.z - p[2];
            const double d = dx * dx + dy * dy + dz * dz;
            if (d < bd) {
                bd = d;
                best = b;
            }
        }
        oj[0] = (uint16_t)best;
        ow[0] = 1.0f;
    }
}

/* The palette of the rigged octree at weight step `step`; MR_ERR_LIMIT when
 * it does not fit. */
static int sk_build_palette(const mr_svo *svo, const sk_leaves *lv, const uint16_t *fj, const float *fw,
                            unsigned step, mr_svo *o, uint16_t *lj, uint8_t *lw, uint32_t *table, size_t tsize)
{
    const size_t mask = tsize - 1u;
    for (size_t i = 0; i < tsize; i++)
        table[i] = UINT32_MAX;
    uint32_t count = 0;
    for (uint32_t t = 0; t < lv->n; t++) {
        const uint32_t li = lv->index[t];
        const mr_svo_attr *src = &svo->palette[svo->leaves[li].attr];
        mr_svo_attr a;
        memset(&a, 0, sizeof a);
        memcpy(a.albedo, src->albedo, sizeof a.albedo);
        a.mesh = src->mesh;
        sk_quantize(fj + (size_t)t * MR_SVO_INFLUENCES, fw + (size_t)t * MR_SVO_INFLUENCES, step, a.joints,
                    a.weights);
        memcpy(lj + (size_t)li * MR_SVO_INFLUENCES, a.joints, sizeof a.joints);
        memcpy(lw + (size_t)li * MR_SVO_INFLUENCES, a.weights, sizeof a.weights);
        uint64_t h = 1469598103934665603ull;
        const uint8_t bytes[16] = {a.albedo[0], a.albedo[1], a.albedo[2], a.mesh,
                                   (uint8_t)a.joints[0], (uint8_t)(a.joints[0] >> 8), (uint8_t)a.joints[1],
                                   (uint8_t)(a.joints[1] >> 8), (uint8_t)a.joints[2], (uint8_t)(a.joints[2] >> 8),
                                   (uint8_t)a.joints[3], (uint8_t)(a.joints[3] >> 8), a.weights[0], a.weights[1],
                                   a.weights[2], a.weights[3]};
        for (int k = 0; k < 16; k++)
            h = (h ^ bytes[k]) * 1099511628211ull;
        size_t slot = (size_t)(h ^ (h >> 29)) & mask;
        for (;;) {
            const uint32_t e = table[slot];
            if (e == UINT32_MAX) {
                if (count == MR_SVO_MAX_PALETTE)
                    return MR_ERR_LIMIT;
                table[slot] = count;
                o->palette[count] = a;
                o->leaves[li].attr = (uint16_t)count;
                count++;
                break;
            }
            const mr_svo_attr *b = &o->palette[e];
            if (memcmp(b->albedo, a.albedo, 3) == 0 && b->mesh == a.mesh &&
                memcmp(b->joints, a.joints, sizeof a.joints) == 0 &&
                memcmp(b->weights, a.weights, sizeof a.weights) == 0) {
                o->leaves[li].attr = (uint16_t)e;
                break;
            }
            slot = (slot + 1u) & mask;
        }
    }
    o->palette_count = count;
    return MR_OK;
}

int mr_svo_skeleton_rig(const mr_asset *asset, const mr_svo *svo, const mr_svo_skeleton *s,
                        const mr_svo_skeleton_params *p, mr_asset **out_asset, mr_svo **out_svo, mr_error *err)
{
    int rc = MR_OK;
    if (!out_asset || !out_svo)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: NULL output pointer");
    *out_asset = NULL;
    *out_svo = NULL;
    if (!asset || !svo || !s)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: NULL asset, svo or skeleton");
    if (s->bone_count == 0 || !s->position || !s->parent)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: the skeleton has no bones");
    if (s->bone_count > MR_MAX_ASSET_JOINTS)
        return mr_error_set(err, MR_ERR_LIMIT, "skeleton rig: %u bones above the %u joints a mesh can name",
                            s->bone_count, MR_MAX_ASSET_JOINTS);
    if (asset->node_count == 0 || asset->nodes[0].parent != -1)
        return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: the asset has no root node");
    if (asset->node_count + s->bone_count > MR_MAX_ASSET_NODES)
        return mr_error_set(err, MR_ERR_LIMIT, "skeleton rig: %zu nodes and %u bones above the node cap %u",
                            asset->node_count, s->bone_count, MR_MAX_ASSET_NODES);
    for (uint32_t b = 0; b < s->bone_count; b++)
        if (s->parent[b] >= (int32_t)b || s->parent[b] < -1)
            return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: bone %u has parent %d (must be -1 or lower)", b,
                                (int)s->parent[b]);
    for (size_t i = 0; i < asset->node_count; i++)
        if (asset->nodes[i].name && sk_is_bone_name(asset->nodes[i].name, s->bone_count))
            return mr_error_set(err, MR_ERR_CONFLICT, "skeleton rig: the asset already has a node named '%s'",
                                asset->nodes[i].name);
    for (uint32_t i = 0; i < svo->palette_count && svo->palette; i++)
        if (svo->palette[i].mesh >= asset->mesh_count)
            return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: palette entry %u names mesh %u of %zu", i,
                                svo->palette[i].mesh, asset->mesh_count);
    for (uint32_t i = 0; i < svo->leaf_count; i++)
        if (!svo->leaves || svo->leaves[i].attr >= svo->palette_count)
            return mr_error_set(err, MR_ERR_INVALID, "skeleton rig: leaf %u names palette entry out of range", i);
    sk_params prm;
    if ((rc = sk_resolve(p, svo->depth <= MR_SVO_MAX_DEPTH ? svo->depth : MR_SVO_MAX_DEPTH, &prm, err)) < 0)
        return rc;

    sk_leaves lv = {0};
    uint16_t *fj = NULL, *lj = NULL;
    float *fw = NULL;
    uint8_t *lw = NULL;
    uint32_t *table = NULL;
    mr_svo *o = NULL;
    mr_asset *a = NULL;
    mr_pose *rest = NULL, *rest2 = NULL;
    if ((rc = sk_soft_weights(svo, s, prm.rounds, prm.threads, &lv, &fj, &fw, err)) < 0)
        goto cleanup;

    /* The octree copy. */
    const uint32_t nl = svo->leaf_count, nn = svo->node_count;
    if (!(o = calloc(1, sizeof *o)))
        goto nomem;
    *o = *svo;
    o->first_node = o->first_leaf = NULL;
    o->child_mask = o->leaf_mask = NULL;
    o->leaves = NULL;
    o->leaf_keys = NULL;
    o->palette = NULL;
    o->palette_count = 0;
    o->first_node = mr_memdup(svo->first_node, (size_t)nn * sizeof *svo->first_node);
    o->first_leaf = mr_memdup(svo->first_leaf, (size_t)nn * sizeof *svo->first_leaf);
    o->child_mask = mr_memdup(svo->child_mask, nn);
    o->leaf_mask = mr_memdup(svo->leaf_mask, nn);
    o->leaves = mr_memdup(svo->leaves, (size_t)nl * sizeof *svo->leaves);
    o->leaf_keys = mr_memdup(svo->leaf_keys, (size_t)nl * sizeof *svo->leaf_keys);
    o->palette = malloc(MR_SVO_MAX_PALETTE * sizeof *o->palette);
    lj = malloc(((size_t)nl + 1u) * MR_SVO_INFLUENCES * sizeof *lj);
    lw = malloc(((size_t)nl + 1u) * MR_SVO_INFLUENCES * sizeof *lw);
    const size_t tsize = 4u * MR_SVO_MAX_PALETTE;
    table = malloc(tsize * sizeof *table);
    if ((nn && (!o->first_node || !o->first_leaf || !o->child_mask || !o->leaf_mask)) || (nl && !o->leaves) ||
        (nl && svo->leaf_keys && !o->leaf_keys) || !o->palette || !lj || !lw || !table)
        goto nomem;
    rc = MR_ERR_LIMIT;
    for (size_t k = 0; k < sizeof sk_steps / sizeof sk_steps[0] && rc == MR_ERR_LIMIT; k++)
        rc = sk_build_palette(svo, &lv, fj, fw, sk_steps[k], o, lj, lw, table, tsize);
    if (rc < 0) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "skeleton rig: more than %u palette entries even with hard weights",
                          MR_SVO_MAX_PALETTE);
        goto cleanup;
    }
    {
        mr_svo_attr *shrunk = realloc(o->palette, (o->palette_count ? o->palette_count : 1u) * sizeof *shrunk);
        if (shrunk)
            o->palette = shrunk;
    }

    /* The asset copy with bone nodes. */
    if ((rc = mr_pose_new(asset, &rest, err)) < 0)
        goto cleanup;
    const size_t n0 = asset->node_count;
    if ((rc = mr_asset_copy_shell(asset, s->bone_count, &a)) < 0)
        goto nomem;
    mr_mat4 root_inv;
    if (!mr_mat4_inverse(&rest->global[0], &root_inv)) {
        rc = mr_error_set(err, MR_ERR_INVALID, "skeleton rig: the root node's transform is singular");
        goto cleanup;
    }
    for (uint32_t b = 0; b < s->bone_count; b++) {
        char name[32];
        snprintf(name, sizeof name, "bone%u", b);
        mr_node *nd = &a->nodes[n0 + b];
        if (!(nd->name = mr_strdup(name)))
            goto nomem;
        a->node_count = n0 + b + 1u;
        const mr_vec3 q = s->position[b];
        if (s->parent[b] < 0) {
            mr_mat4 t = mr_mat4_from_trs(q, mr_quat_identity(), mr_v3(1, 1, 1));
            nd->parent = 0;
            nd->local = mr_mat4_mul(&root_inv, &t);
        } else {
            const mr_vec3 pq = s->position[s->parent[b]];
            nd->parent = (int)(n0 + (size_t)s->parent[b]);
            nd->local = mr_mat4_from_trs(mr_v3_sub(q, pq), mr_quat_identity(), mr_v3(1, 1, 1));
        }
    }
    if ((rc = mr_pose_new(a, &rest2, err)) < 0)
        goto cleanup;
    for (size_t mi = 0; mi < asset->mesh_count; mi++) {
        const mr_mesh *src = &asset->meshes[mi];
        mr_mesh *dst = &a->meshes[mi];
        const uint32_t nv = src->vertex_count;
        dst->node = src->node;
        if (src->name && !(dst->name = mr_strdup(src->name)))
            goto nomem;
        dst->vertex_count = nv;
        dst->triangle_count = src->triangle_count;
        dst->positions = malloc(((size_t)nv + 1u) * 3u * sizeof *dst->positions);
        dst->normals = malloc(((size_t)nv + 1u) * 3u * sizeof *dst->normals);
        dst->indices = mr_memdup(src->indices, (size_t)src->triangle_count * 3u * sizeof *src->indices);
        dst->uvs = mr_memdup(src->uvs, (size_t)nv * 2u * sizeof *src->uvs);
        dst->joint_nodes = malloc((size_t)s->bone_count * sizeof *dst->joint_nodes);
        dst->inverse_bind = malloc((size_t)s->bone_count * sizeof *dst->inverse_bind);
        dst->joints = malloc(((size_t)nv + 1u) * MR_MAX_INFLUENCES * sizeof *dst->joints);
        dst->weights = malloc(((size_t)nv + 1u) * MR_MAX_INFLUENCES * sizeof *dst->weights);
        if (!dst->positions || !dst->normals || (src->triangle_count && !dst->indices) || (src->uvs && nv && !dst->uvs) ||
            !dst->joint_nodes || !dst->inverse_bind || !dst->joints || !dst->weights)
            goto nomem;
        dst->joint_count = s->bone_count;
        const bool rigid = src->joint_count == 0;
        const mr_mat4 g = rigid && src->node >= 0 && (size_t)src->node < n0 ? rest->global[src->node]
                                                                             : mr_mat4_identity();
        const mr_mat4 nm = mr_mat4_normal_matrix(&g);
        for (uint32_t v = 0; v < nv; v++) {
            mr_vec3 x = mr_v3(src->positions[3u * v], src->positions[3u * v + 1u], src->positions[3u * v + 2u]);
            mr_vec3 n = src->normals ? mr_v3(src->normals[3u * v], src->normals[3u * v + 1u],
                                             src->normals[3u * v + 2u])
                                     : mr_v3(0, 0, 1);
            if (rigid) {
                x = mr_mat4_point(&g, x);
                n = mr_v3_normalize_or(mr_mat4_dir(&nm, n), n);
            }
            dst->positions[3u * v] = x.x;
            dst->positions[3u * v + 1u] = x.y;
            dst->positions[3u * v + 2u] = x.z;
            dst->normals[3u * v] = n.x;
            dst->normals[3u * v + 1u] = n.y;
            dst->normals[3u * v + 2u] = n.z;
        }
        if (mr_mesh_tangents(dst) < 0)
            goto nomem;
        for (uint32_t b = 0; b < s->bone_count; b++) {
            dst->joint_nodes[b] = (int)(n0 + b);
            if (!mr_mat4_inverse(&rest2->global[n0 + b], &dst->inverse_bind[b])) {
                rc = mr_error_set(err, MR_ERR_INVALID, "skeleton rig: bone %u's rest transform is singular", b);
                goto cleanup;
            }
        }
        sk_bind bc = {svo, s, dst->positions, lj, lw, dst->joints, dst->weights};
        mr_parallel_for(prm.threads, nv, SK_GRAIN, sk_bind_range, &bc);
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "skeleton rig: out of memory");
cleanup:
    if (rc < 0) {
        mr_asset_free(a);
        mr_svo_voxelize_free(o);
        a = NULL;
        o = NULL;
    }
    *out_asset = a;
    *out_svo = o;
    mr_pose_free(rest);
    mr_pose_free(rest2);
    sk_leaves_free(&lv);
    free(fj);
    free(fw);
    free(lj);
    free(lw);
    free(table);
    return rc;
}
