/*
 * svo_fixture.h - shared harness of the SVO ray-casting tests
 * (tests/unit/test_svo_trace.c, tests/hard/test_svo_hard.c): random and
 * hand-classified octrees built directly in the svo.h layout, a brute-force
 * oracle over every leaf box in double, and ray checks against it.
 * Everything is static: each test program includes it once.
 */
#ifndef MR_TEST_SVO_FIXTURE_H
#define MR_TEST_SVO_FIXTURE_H

#include <float.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <cmocka.h>

#include "util/morton.h"
#include "kinds/svo/svo.h"
#include "kinds/svo/svo_build.h"
#include "kinds/svo/svo_trace.h"

/* ---- fixture: random numbers */

typedef struct fx_rng {
    uint64_t s;
} fx_rng;

static uint64_t fx_next(fx_rng *r)
{
    /* splitmix64 */
    uint64_t z = (r->s += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

static double fx_unit(fx_rng *r) /* [0, 1) */
{
    return (double)(fx_next(r) >> 11) * 0x1.0p-53;
}

static double fx_range(fx_rng *r, double lo, double hi)
{
    return lo + (hi - lo) * fx_unit(r);
}

static uint32_t fx_below(fx_rng *r, uint32_t n)
{
    return (uint32_t)(fx_next(r) % n);
}

static uint64_t fx_hash(uint64_t seed, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    fx_rng r = {seed ^ ((uint64_t)level << 58) ^ ((uint64_t)x << 38) ^ ((uint64_t)y << 19) ^ z};
    (void)fx_next(&r);
    r.s ^= ((uint64_t)x * 0x2545f4914f6cdd1dull) ^ ((uint64_t)y * 0x9e3779b97f4a7c15ull) ^ ((uint64_t)z << 7);
    return fx_next(&r);
}

/* ---- fixture: octree built from a classification of cells */

enum { FX_EMPTY = 0, FX_LEAF = 1, FX_SPLIT = 2 };
/* What the cell (level, x, y, z) is: empty, a leaf, or to be subdivided
 * (taken as a leaf at the octree's depth). */
typedef int (*fx_classify)(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z);

typedef struct fx_box {
    unsigned level;
    uint32_t xyz[3];
} fx_box;

typedef struct svo_fx {
    mr_svo svo;
    fx_box *boxes; /* per leaf */
    uint32_t node_cap, leaf_cap;
} svo_fx;

static void fx_free(svo_fx *fx)
{
    free(fx->svo.first_node);
    free(fx->svo.first_leaf);
    free(fx->svo.child_mask);
    free(fx->svo.leaf_mask);
    free(fx->svo.leaves);
    free(fx->boxes);
    memset(fx, 0, sizeof *fx);
}

static void fx_reserve(svo_fx *fx, uint32_t nodes, uint32_t leaves)
{
    if (nodes > fx->node_cap) {
        uint32_t cap = fx->node_cap ? fx->node_cap : 64;
        while (cap < nodes)
            cap *= 2;
        fx->svo.first_node = realloc(fx->svo.first_node, cap * sizeof(uint32_t));
        fx->svo.first_leaf = realloc(fx->svo.first_leaf, cap * sizeof(uint32_t));
        fx->svo.child_mask = realloc(fx->svo.child_mask, cap);
        fx->svo.leaf_mask = realloc(fx->svo.leaf_mask, cap);
        assert_non_null(fx->svo.first_node);
        assert_non_null(fx->svo.first_leaf);
        assert_non_null(fx->svo.child_mask);
        assert_non_null(fx->svo.leaf_mask);
        fx->node_cap = cap;
    }
    if (leaves > fx->leaf_cap) {
        uint32_t cap = fx->leaf_cap ? fx->leaf_cap : 64;
        while (cap < leaves)
            cap *= 2;
        fx->svo.leaves = realloc(fx->svo.leaves, cap * sizeof(mr_svo_leaf));
        fx->boxes = realloc(fx->boxes, cap * sizeof(fx_box));
        assert_non_null(fx->svo.leaves);
        assert_non_null(fx->boxes);
        fx->leaf_cap = cap;
    }
}

/* Fills interior node n (already reserved): all of its children are
 * allocated together, as svo.h requires, then the interior ones filled. */
static void fx_node(svo_fx *fx, uint32_t n, unsigned level, const uint32_t xyz[3], fx_classify cls, void *ctx)
{
    int kind[8];
    unsigned cm = 0, lm = 0, nint = 0, nleaf = 0;
    for (unsigned c = 0; c < 8; c++) {
        const uint32_t x = xyz[0] * 2 + (c & 1), y = xyz[1] * 2 + ((c >> 1) & 1), z = xyz[2] * 2 + (c >> 2);
        int k = cls(ctx, level + 1, x, y, z);
        if (k == FX_SPLIT && level + 1 >= fx->svo.depth)
            k = FX_LEAF;
        kind[c] = k;
        if (k == FX_LEAF) {
            cm |= 1u << c;
            lm |= 1u << c;
            nleaf++;
        } else if (k == FX_SPLIT) {
            cm |= 1u << c;
            nint++;
        }
    }
    const uint32_t fn = fx->svo.node_count, fl = fx->svo.leaf_count;
    fx_reserve(fx, fn + nint, fl + nleaf);
    fx->svo.child_mask[n] = (uint8_t)cm;
    fx->svo.leaf_mask[n] = (uint8_t)lm;
    fx->svo.first_node[n] = fn;
    fx->svo.first_leaf[n] = fl;
    fx->svo.node_count += nint;
    fx->svo.leaf_count += nleaf;
    uint32_t li = fl, ni = fn;
    for (unsigned c = 0; c < 8; c++) {
        const uint32_t cxyz[3] = {xyz[0] * 2 + (c & 1), xyz[1] * 2 + ((c >> 1) & 1), xyz[2] * 2 + (c >> 2)};
        if (kind[c] == FX_LEAF) {
            fx->svo.leaves[li].normal[0] = fx->svo.leaves[li].normal[1] = 0;
            fx->svo.leaves[li].attr = 0;
            fx->boxes[li] = (fx_box){level + 1, {cxyz[0], cxyz[1], cxyz[2]}};
            li++;
        }
    }
    for (unsigned c = 0; c < 8; c++) {
        const uint32_t cxyz[3] = {xyz[0] * 2 + (c & 1), xyz[1] * 2 + ((c >> 1) & 1), xyz[2] * 2 + (c >> 2)};
        if (kind[c] == FX_SPLIT)
            fx_node(fx, ni++, level + 1, cxyz, cls, ctx);
    }
}

static void fx_build(svo_fx *fx, unsigned depth, mr_vec3 origin, float size, fx_classify cls, void *ctx)
{
    memset(fx, 0, sizeof *fx);
    fx->svo.depth = depth;
    fx->svo.origin = origin;
    fx->svo.size = size;
    const int root = cls(ctx, 0, 0, 0, 0);
    if (root == FX_EMPTY)
        return;
    if (root == FX_LEAF) {
        fx_reserve(fx, 0, 1);
        fx->svo.leaf_count = 1;
        fx->svo.leaves[0] = (mr_svo_leaf){{0, 0}, 0};
        fx->boxes[0] = (fx_box){0, {0, 0, 0}};
        return;
    }
    fx_reserve(fx, 1, 0);
    fx->svo.node_count = 1;
    const uint32_t zero[3] = {0, 0, 0};
    fx_node(fx, 0, 0, zero, cls, ctx);
}

/* Random sparse octree: each cell below the root is a leaf with p_leaf, is
 * split with p_split (always above level `dense`), else empty. */
typedef struct fx_random {
    uint64_t seed;
    double p_leaf, p_split;
    unsigned dense;
} fx_random;

static int fx_random_cls(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const fx_random *p = ctx;
    if (level == 0 || level < p->dense)
        return FX_SPLIT;
    const double u = (double)(fx_hash(p->seed, level, x, y, z) >> 11) * 0x1.0p-53;
    if (u < p->p_leaf)
        return FX_LEAF;
    if (u < p->p_leaf + p->p_split)
        return FX_SPLIT;
    return FX_EMPTY;
}

/* ---- fixture: brute force */

/* The planes of a box on one axis, in double. */
static void fx_box_planes(const mr_svo *svo, const fx_box *b, int a, double *lo, double *hi)
{
    const double o[3] = {svo->origin.x, svo->origin.y, svo->origin.z};
    const double cell = (double)svo->size * (1.0 / (double)(1u << MR_SVO_MAX_DEPTH)); /* exact */
    const uint32_t span = (1u << MR_SVO_MAX_DEPTH) >> b->level;
    *lo = o[a] + (double)(b->xyz[a] * span) * cell;
    *hi = o[a] + (double)((b->xyz[a] + 1) * span) * cell;
}

/* A box of cells of one level, [lo, hi) (a level of detail's clip,
 * mr_svo_lod). */
typedef struct fx_clip {
    unsigned level;
    uint32_t lo[3], hi[3];
} fx_clip;

/* Closed slab test of box b, or of its part within clip when clip is not
 * NULL; interval clipped to [tmin, min(tmax, FLT_MAX)]. */
static bool fx_slab_within(const mr_svo *svo, const fx_box *b, const fx_clip *clip, const double org[3],
                           const double dir[3], double tmin, double tmax, double *t0, double *t1)
{
    double e = tmin, x = tmax < FLT_MAX ? tmax : FLT_MAX;
    for (int a = 0; a < 3; a++) {
        double lo, hi;
        fx_box_planes(svo, b, a, &lo, &hi);
        if (clip) {
            const double o[3] = {svo->origin.x, svo->origin.y, svo->origin.z};
            const double cell = ldexp((double)svo->size, -(int)clip->level);
            lo = fmax(lo, o[a] + clip->lo[a] * cell);
            hi = fmin(hi, o[a] + clip->hi[a] * cell);
            if (!(lo < hi))
                return false;
        }
        if (dir[a] == 0.0) {
            if (org[a] < lo || org[a] > hi)
                return false;
            continue;
        }
        double ta = (lo - org[a]) / dir[a], tb = (hi - org[a]) / dir[a];
        if (ta > tb) {
            double s = ta;
            ta = tb;
            tb = s;
        }
        e = ta > e ? ta : e;
        x = tb < x ? tb : x;
    }
    *t0 = e;
    *t1 = x;
    return e <= x;
}

static bool fx_slab(const mr_svo *svo, const fx_box *b, const double org[3], const double dir[3], double tmin,
                    double tmax, double *t0, double *t1)
{
    return fx_slab_within(svo, b, NULL, org, dir, tmin, tmax, t0, t1);
}

typedef struct fx_stats {
    long rays, hits, ties, grazes;
    long exact;      /* rays checked by check_ray_exact */
    long mismatches; /* rays a check failed on (it stops at the first) */
    long nonfinite;  /* hits with a non-finite t or normal */
    double worst_t;  /* largest |t - its leaf's entry| / fx_tol (check_ray: <= 1) */
} fx_stats;

/* Sums b's counts into a, keeps the worst t error (NaN included). */
static inline void fx_stats_add(fx_stats *a, const fx_stats *b)
{
    a->rays += b->rays;
    a->hits += b->hits;
    a->ties += b->ties;
    a->grazes += b->grazes;
    a->exact += b->exact;
    a->mismatches += b->mismatches;
    a->nonfinite += b->nonfinite;
    if (!isnan(a->worst_t) && !(b->worst_t <= a->worst_t))
        a->worst_t = b->worst_t;
}

static bool fx_hit_finite(const mr_svo_hit *h)
{
    return isfinite(h->t) && isfinite(h->ng.x) && isfinite(h->ng.y) && isfinite(h->ng.z);
}

static double fx_tol(const mr_svo *svo, const double dir[3], double t)
{
    const double len = sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
    return 4.0 * FLT_EPSILON * (fabs(t) + (double)svo->size / len);
}

/* Checks the hit's own fields against its leaf: level, coordinates, t at
 * the leaf's entry, the face normal. */
static void fx_check_hit_fields(const svo_fx *fx, const mr_svo_hit *h, const double org[3], const double dir[3],
                                float tmin, double tol)
{
    const mr_svo *svo = &fx->svo;
    assert_true(h->leaf < svo->leaf_count);
    const fx_box *b = &fx->boxes[h->leaf];
    assert_int_equal(h->level, b->level);
    assert_int_equal(h->x, b->xyz[0]);
    assert_int_equal(h->y, b->xyz[1]);
    assert_int_equal(h->z, b->xyz[2]);
    assert_true(isfinite(h->t));
    assert_true(h->t >= tmin);
    if (h->axis < 0) {
        assert_true(h->t == tmin);
        assert_true(h->ng.x == 0.0f && h->ng.y == 0.0f && h->ng.z == 0.0f);
        return;
    }
    const int a = h->axis;
    assert_true(a < 3);
    assert_true(dir[a] != 0.0);
    const float n[3] = {h->ng.x, h->ng.y, h->ng.z};
    for (int k = 0; k < 3; k++)
        assert_true(n[k] == (k == a ? (dir[a] < 0.0 ? 1.0f : -1.0f) : 0.0f));
    double lo, hi;
    fx_box_planes(svo, b, a, &lo, &hi);
    const double tf = ((dir[a] > 0.0 ? lo : hi) - org[a]) / dir[a];
    assert_true(fabs(tf - (double)h->t) <= tol);
}

/* One ray, traversal vs brute force (tolerances: see the top comment). */
static void check_ray(const svo_fx *fx, mr_vec3 o, mr_vec3 d, float tmin, float tmax, fx_stats *st)
{
    const mr_svo *svo = &fx->svo;
    const double org[3] = {o.x, o.y, o.z}, dir[3] = {d.x, d.y, d.z};
    double best = INFINITY, best_proper = INFINITY;
    bool any = false;
    for (uint32_t i = 0; i < svo->leaf_count; i++) {
        double t0, t1;
        if (!fx_slab(svo, &fx->boxes[i], org, dir, tmin, tmax, &t0, &t1))
            continue;
        any = true;
        best = t0 < best ? t0 : best;
        if (t1 - t0 > fx_tol(svo, dir, t0))
            best_proper = t0 < best_proper ? t0 : best_proper;
    }
    mr_svo_hit h;
    memset(&h, 0xab, sizeof h);
    const bool hit = mr_svo_intersect(svo, o, d, tmin, tmax, &h);
    const bool occ = mr_svo_occluded(svo, o, d, tmin, tmax);
    st->rays++;
    st->mismatches += hit != occ;
    assert_int_equal(hit, occ);
    if (!hit) {
        if (best_proper < INFINITY) {
            st->mismatches++;
            fail_msg("miss, brute force enters a leaf properly at t=%.17g (org %.9g %.9g %.9g dir %.9g %.9g "
                     "%.9g, [%.9g, %.9g])",
                     best_proper, o.x, o.y, o.z, d.x, d.y, d.z, tmin, tmax);
        }
        if (any)
            st->grazes++;
        return;
    }
    st->hits++;
    const double tol = fx_tol(svo, dir, best);
    st->nonfinite += !fx_hit_finite(&h);
    fx_check_hit_fields(fx, &h, org, dir, tmin, tol);
    /* The traversal's leaf must be touched (within tol) and entered at the
     * reported t, and nothing entered properly before it. */
    double l0 = 0.0, l1 = 0.0;
    const bool lhit = fx_slab(svo, &fx->boxes[h.leaf], org, dir, tmin, tmax, &l0, &l1);
    if (!lhit) {
        /* a graze lost by rounding on the brute force's side */
        const fx_box *b = &fx->boxes[h.leaf];
        double e = tmin, x = tmax;
        for (int a = 0; a < 3; a++) {
            double lo, hi, ta, tb;
            fx_box_planes(svo, b, a, &lo, &hi);
            if (dir[a] == 0.0)
                continue;
            ta = (lo - org[a]) / dir[a];
            tb = (hi - org[a]) / dir[a];
            e = fmax(e, fmin(ta, tb));
            x = fmin(x, fmax(ta, tb));
        }
        assert_true(e <= x + tol);
        l0 = e;
        st->grazes++;
    }
    const double t_err = fabs((double)h.t - l0) / tol;
    if (!isnan(st->worst_t) && !(t_err <= st->worst_t))
        st->worst_t = t_err; /* a NaN stays */
    if (!(fabs((double)h.t - l0) <= tol)) {
        st->mismatches++;
        fail_msg("t %.9g vs its leaf's entry %.17g (tol %.3g)", (double)h.t, l0, tol);
    }
    if (!((double)h.t <= best_proper + tol)) {
        st->mismatches++;
        fail_msg("t %.9g beyond a proper entry at %.17g", (double)h.t, best_proper);
    }
    if (any && l0 != best)
        st->ties++;
}

/* Exact variant: the caller guarantees every plane's t is exact in both
 * computations, so hit/miss and t must agree exactly, grazes included.
 * Counted into st, if given. */
static void check_ray_exact(const svo_fx *fx, mr_vec3 o, mr_vec3 d, float tmin, float tmax, fx_stats *st)
{
    const mr_svo *svo = &fx->svo;
    const double org[3] = {o.x, o.y, o.z}, dir[3] = {d.x, d.y, d.z};
    double best = INFINITY;
    for (uint32_t i = 0; i < svo->leaf_count; i++) {
        double t0, t1;
        if (fx_slab(svo, &fx->boxes[i], org, dir, tmin, tmax, &t0, &t1))
            best = t0 < best ? t0 : best;
    }
    mr_svo_hit h;
    const bool hit = mr_svo_intersect(svo, o, d, tmin, tmax, &h);
    const bool occ = mr_svo_occluded(svo, o, d, tmin, tmax);
    fx_stats none = {0};
    if (!st)
        st = &none;
    st->rays++;
    st->exact++;
    st->hits += hit;
    st->mismatches += hit != occ || hit != (best < INFINITY) || (hit && !((double)h.t == best));
    st->nonfinite += hit && !fx_hit_finite(&h);
    assert_int_equal(hit, occ);
    if (hit != (best < INFINITY))
        fail_msg("exact ray: traversal %s, brute force %s (t %.17g; org %.9g %.9g %.9g dir %.9g %.9g %.9g)",
                 hit ? "hits" : "misses", best < INFINITY ? "hits" : "misses", best, o.x, o.y, o.z, d.x, d.y,
                 d.z);
    if (!hit)
        return;
    if (!((double)h.t == best))
        fail_msg("exact ray: t %.17g, brute force %.17g (leaf %u level %u %u %u %u; org %.9g %.9g %.9g dir %.9g %.9g "
                 "%.9g, [%.9g, %.9g])",
                 (double)h.t, best, h.leaf, h.level, h.x, h.y, h.z, o.x, o.y, o.z, d.x, d.y, d.z, tmin, tmax);
    fx_check_hit_fields(fx, &h, org, dir, tmin, 0.0);
    double l0, l1;
    assert_true(fx_slab(svo, &fx->boxes[h.leaf], org, dir, tmin, tmax, &l0, &l1));
    assert_true(l0 == best);
}

/* ---- fixture: rays */

/* Rounds three doubles to a float vector. Through volatile stores because
 * GCC 12.2's SLP vectoriser at -O2 drops the double -> float rounding when
 * a rounded value is used again in double (d = c - (float)(c + e) comes out
 * as -e): test rays would then miss their targets. */
static mr_vec3 fx_v3d(double x, double y, double z)
{
    volatile float v[3];
    v[0] = (float)x;
    v[1] = (float)y;
    v[2] = (float)z;
    return mr_v3(v[0], v[1], v[2]);
}

static mr_vec3 fx_cube_point(const mr_svo *svo, double u, double v, double w)
{
    const double s = svo->size;
    return fx_v3d(svo->origin.x + u * s, svo->origin.y + v * s, svo->origin.z + w * s);
}

static mr_vec3 fx_random_dir(fx_rng *r)
{
    for (;;) {
        const double x = fx_range(r, -1, 1), y = fx_range(r, -1, 1), z = fx_range(r, -1, 1);
        const double l2 = x * x + y * y + z * z;
        if (l2 > 1e-4 && l2 <= 1.0) {
            /* random overall scale: dir need not be normalised */
            const double s = pow(10.0, fx_range(r, -2, 2));
            return mr_v3((float)(x * s), (float)(y * s), (float)(z * s));
        }
    }
}

/* A point on a random leaf's box: its centre, a corner, an edge's midpoint
 * or a face's centre (k = 0, 1, 2 in each axis, in half-voxel units). */
static mr_vec3 fx_leaf_point(const svo_fx *fx, fx_rng *r)
{
    const fx_box *b = &fx->boxes[fx_below(r, fx->svo.leaf_count)];
    double p[3];
    for (int a = 0; a < 3; a++) {
        double lo, hi;
        fx_box_planes(&fx->svo, b, a, &lo, &hi);
        const uint32_t k = fx_below(r, 3);
        p[a] = k == 0 ? lo : k == 1 ? 0.5 * (lo + hi) : hi;
    }
    return fx_v3d(p[0], p[1], p[2]);
}

static mr_vec3 fx_sub(mr_vec3 a, mr_vec3 b)
{
    return fx_v3d((double)a.x - b.x, (double)a.y - b.y, (double)a.z - b.z);
}

/* A mix of rays over the octree; ray kinds cycle with i. */
static void fx_random_ray(const svo_fx *fx, fx_rng *r, int i, mr_vec3 *o, mr_vec3 *d, float *tmin, float *tmax)
{
    const mr_svo *svo = &fx->svo;
    *tmin = 0.0f;
    *tmax = INFINITY;
    switch (i % 6) {
    case 0: /* from outside, towards a random point of the cube */
        *o = fx_cube_point(svo, fx_range(r, -1.5, 2.5), fx_range(r, -1.5, 2.5), fx_range(r, -1.5, 2.5));
        *d = fx_sub(fx_cube_point(svo, fx_unit(r), fx_unit(r), fx_unit(r)), *o);
        break;
    case 1: /* from inside, any direction */
        *o = fx_cube_point(svo, fx_unit(r), fx_unit(r), fx_unit(r));
        *d = fx_random_dir(r);
        break;
    case 2: { /* axis-parallel; origin often exactly on a cell plane */
        *o = fx_cube_point(svo, fx_range(r, -0.2, 1.2), fx_range(r, -0.2, 1.2), fx_range(r, -0.2, 1.2));
        if (svo->leaf_count > 0 && fx_below(r, 2)) {
            const mr_vec3 p = fx_leaf_point(fx, r);
            *o = p;
        }
        const int a = (int)fx_below(r, 3);
        float dv[3] = {0.0f, fx_below(r, 2) ? -0.0f : 0.0f, 0.0f};
        dv[a] = (fx_below(r, 2) ? 1.0f : -1.0f) * (float)pow(10.0, fx_range(r, -3, 3));
        float ov[3] = {o->x, o->y, o->z};
        ov[a] = (float)(ov[a] - (double)dv[a] * fx_range(r, 0.0, 2.0) * svo->size / fabs(dv[a]));
        *o = mr_v3(ov[0], ov[1], ov[2]);
        *d = mr_v3(dv[0], dv[1], dv[2]);
        break;
    }
    case 3: /* aimed at a leaf's corner, edge, face or centre from outside */
    case 4:
        if (svo->leaf_count == 0) {
            *o = fx_cube_point(svo, 2, 2, 2);
            *d = mr_v3(-1, -1, -1);
            break;
        }
        *o = fx_cube_point(svo, fx_range(r, -1, 2), fx_range(r, -1, 2), fx_range(r, -1, 2));
        *d = fx_sub(fx_leaf_point(fx, r), *o);
        if (i % 6 == 4) {
            /* and clipped: a segment that may end before the target */
            *tmin = (float)fx_range(r, 0.0, 0.5);
            *tmax = (float)fx_range(r, *tmin, 1.5);
        }
        break;
    default: /* inside, with a window */
        *o = fx_cube_point(svo, fx_unit(r), fx_unit(r), fx_unit(r));
        *d = fx_random_dir(r);
        *tmin = (float)(fx_unit(r) * svo->size / mr_v3_len(*d));
        *tmax = *tmin + (float)(fx_unit(r) * svo->size / mr_v3_len(*d));
        break;
    }
}

#endif /* MR_TEST_SVO_FIXTURE_H */
