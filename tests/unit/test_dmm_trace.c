/*
 * test_dmm_trace.c - tessellation-free traversal of displaced micro-mesh
 * patches (core/geom/dmm_trace.h; paper 000, Algorithms 1-4, eq. 5-13).
 *
 * The oracle is the tessellation itself: every micro-triangle of the patch
 * (mr_umesh_triangles order, vertices from mr_dmm_vertex) tested with the
 * same watertight test (mr_wt_intersect), keeping the closest t. The
 * traversal claims to evaluate the very same micro-vertices with the very
 * same test, so hit/miss must agree exactly and t must agree bit for bit: no
 * tolerance there. Rays are random (fixed seeds, so failures reproduce) and
 * aimed both at random points of the patch's bounds and at random points of
 * its micro-triangles, so most of them hit; every ray is traced for the
 * closest hit and for any hit.
 *
 * Bit-for-bit t also needs each micro-triangle's vertices in the
 * tessellation's order (same first vertex, not only the same winding): the
 * watertight test sums det and the scaled t in vertex order, so a rotated
 * triangle's t differs in the last bits. STRICT_T (default 1) demands that;
 * building with -DSTRICT_T=0 accepts a t that is the same micro-triangle's
 * t with rotated vertices (within 64 ulps, counted and printed), to see
 * past that to other failures. The check_ray flags used by the hard cases
 * (tests/hard/test_dmm_hard.c, which shares this harness) are documented
 * at check_ray.
 *
 * Tolerances where the result is a float computation of its own:
 *  - reported (u, v): lattice coordinates u*n, v*n must lie in the closed
 *    micro-triangle hit (at an edge or a vertex: one of those hit there)
 *    within 1e-3 lattice units (a thousandth of a micro-triangle): the
 *    watertight barycentrics carry a few ulps of relative error divided by
 *    the projected area, which for the random, non-grazing geometry here is
 *    far below that (measured: 0); the exact lattice corners add nothing.
 *    mr_dmm_locate(u, v) must name that micro-triangle, or a neighbour when
 *    (u, v) is within 1e-3 of its boundary.
 *  - ng: parallel to that micro-triangle's normal (cross product of its
 *    float vertices), |ng x n| <= 1e-3 |ng| |n| and ng . n > 0; identical
 *    when the traversal takes the vertices in the tessellation's order, a
 *    rotated start changes only roundings (measured sine <= 5e-7).
 *  - zero displacement, base mode: hit points lie on the base plane within
 *    8 FLT_EPSILON * (|org| + |t dir| + max|v_i|) (max norms): the float
 *    point org + t*dir carries a rounding of each term, t a few ulps from the
 *    watertight division, the micro-vertices one rounding each (micromesh.h);
 *    8 covers the sum of these with a margin. Their base barycentrics match
 *    (u, v) within 1e-4 (the same position error divided by the triangle's
 *    heights, which are >= 0.5 here).
 *  - zero displacement, interpolated mode: mr_dmm_vertex is the quadratic
 *    Bezier patch of eq. 9-11 evaluated in double and rounded once, so it
 *    must match the double evaluation of the control points within one ulp
 *    of the result (half an ulp of rounding; the two double evaluations sum
 *    differently and can straddle a rounding midpoint) plus 2^-40 of the
 *    magnitude of the summed terms (the double error itself, ~2^-50).
 *  - three equal matrices: interpolated vertex vs the matrix applied (in
 *    double) to the base-mode vertex: the base vertex is rounded to float
 *    once (2^-24 |x|), the matrix row spreads that by the row's absolute sum,
 *    and each result is rounded once more (2^-24 |r| twice): 1-2 ulps for the
 *    well-conditioned matrices used.
 *
 * Pyramid buffers are allocated with exactly mr_dmm_trace_pyramid_size
 * entries, so under AddressSanitizer a read past the traversal's prefix
 * fails loudly.
 */
#include <float.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "geom/dmm_encode.h"
#include "geom/dmm_trace.h"
#include "geom/micromesh.h"
#include "math/watertight.h"

#define MAX_VERTS 561u  /* mr_umesh_vertex_count(5) */
#define MAX_TRIS 1024u  /* mr_umesh_triangle_count(5) */
#ifndef STRICT_T
#define STRICT_T 1
#endif

/* ---- deterministic random numbers (xorshift64) */

static uint32_t rnd(uint64_t *s)
{
    *s ^= *s << 13;
    *s ^= *s >> 7;
    *s ^= *s << 17;
    return (uint32_t)(*s >> 11);
}

static double rnd01(uint64_t *s) { return (double)(rnd(s) & 0xFFFFFFu) / 16777216.0; }

static float rndf(uint64_t *s, float lo, float hi) { return lo + (hi - lo) * (float)rnd01(s); }

static mr_vec3 rnd_vec(uint64_t *s, float lo, float hi)
{
    float x = rndf(s, lo, hi), y = rndf(s, lo, hi);
    return mr_v3(x, y, rndf(s, lo, hi));
}

static mr_vec3 rnd_unit(uint64_t *s)
{
    for (;;) {
        mr_vec3 v = rnd_vec(s, -1, 1);
        float l = mr_v3_len(v);
        if (l > 0.1f && l <= 1.0f)
            return mr_v3_scale(v, 1.0f / l);
    }
}

static uint32_t fbits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

static bool v3_finite(mr_vec3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

static float comp(mr_vec3 v, int k) { return k == 0 ? v.x : k == 1 ? v.y : v.z; }

static float vmaxabs(mr_vec3 v) { return fmaxf(fabsf(v.x), fmaxf(fabsf(v.y), fabsf(v.z))); }

/* ---- affine matrices (row-major 3x4, mr_math.h) */

static mr_affine affine_of(const mr_mat4 *m)
{
    mr_affine a;
    memcpy(a.m, m->m, sizeof a.m);
    return a;
}

/* Translation * rotation * (non-uniform) scale. */
static mr_affine affine_trs(mr_vec3 t, mr_vec3 axis, float angle, mr_vec3 s)
{
    mr_quat q = mr_quat_from_axis_angle(mr_v3_normalize_or(axis, mr_v3(0, 0, 1)), angle);
    mr_mat4 m = mr_mat4_from_trs(t, q, s);
    return affine_of(&m);
}

static mr_affine rnd_affine(uint64_t *s, float max_angle)
{
    mr_vec3 t = rnd_vec(s, -2, 2), sc = rnd_vec(s, 0.5f, 2.0f);
    return affine_trs(t, rnd_unit(s), rndf(s, -max_angle, max_angle), sc);
}

/* ---- patch sets: encoded displacements, decoded values and pyramids */

typedef struct patch_set {
    unsigned level;
    uint32_t count;
    mr_dmm_encoded *enc;
    uint16_t *values;          /* count * vertex count */
    uint16_t **minv, **maxv;   /* per patch, exactly the traversal's prefix */
} patch_set;

/* disp: count * mr_umesh_vertex_count(level) floats, micromesh.h order. */
static void set_build(patch_set *s, unsigned level, uint32_t count, const float *disp)
{
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    mr_error err = {0};
    memset(s, 0, sizeof *s);
    s->level = level;
    s->count = count;
    int rc = mr_dmm_encode(level, bits, count, disp, &s->enc, NULL, &err);
    if (rc != MR_OK)
        print_error("encode: %s\n", err.msg);
    assert_int_equal(rc, MR_OK);
    uint32_t vc = mr_umesh_vertex_count(level), full = mr_dmm_pyramid_size(level);
    uint32_t pre = mr_dmm_trace_pyramid_size(level);
    assert_true(pre >= 1 && pre <= full);
    s->values = malloc(sizeof(uint16_t) * vc * count);
    s->minv = calloc(count, sizeof *s->minv);
    s->maxv = calloc(count, sizeof *s->maxv);
    uint16_t *lo = malloc(sizeof(uint16_t) * full), *hi = malloc(sizeof(uint16_t) * full);
    assert_true(s->values && s->minv && s->maxv && lo && hi);
    for (uint32_t t = 0; t < count; t++) {
        uint16_t *v = s->values + (size_t)t * vc;
        assert_int_equal(mr_dmm_decode_values(s->enc, t, v, &err), MR_OK);
        assert_int_equal(mr_dmm_pyramid_build(level, v, lo, hi, &err), MR_OK);
        s->minv[t] = malloc(sizeof(uint16_t) * pre);
        s->maxv[t] = malloc(sizeof(uint16_t) * pre);
        assert_true(s->minv[t] && s->maxv[t]);
        memcpy(s->minv[t], lo, sizeof(uint16_t) * pre);
        memcpy(s->maxv[t], hi, sizeof(uint16_t) * pre);
    }
    free(lo);
    free(hi);
}

static void set_free(patch_set *s)
{
    for (uint32_t t = 0; s->minv && t < s->count; t++) {
        free(s->minv[t]);
        free(s->maxv[t]);
    }
    free(s->minv);
    free(s->maxv);
    free(s->values);
    mr_dmm_encoded_free(s->enc);
    memset(s, 0, sizeof *s);
}

/* mats: three matrices (interpolated mode) or NULL (base mode). */
static mr_dmm_patch set_patch(const patch_set *s, uint32_t t, const mr_umesh_tri *tri,
                              const mr_affine *mats)
{
    mr_dmm_patch p = {.level = s->level,
                      .tri = *tri,
                      .enc = s->enc,
                      .values = s->values + (size_t)t * mr_umesh_vertex_count(s->level),
                      .minv = s->minv[t],
                      .maxv = s->maxv[t]};
    for (int k = 0; k < 3; k++)
        p.mats[k] = mats ? &mats[k] : NULL;
    return p;
}

/* ---- brute force over the tessellation */

typedef struct brute {
    uint32_t ntri, nvert, n;
    uint32_t idx[3 * MAX_TRIS];
    uint32_t a[MAX_VERTS], b[MAX_VERTS];
    mr_vec3 v[MAX_VERTS];
    /* the last brute_hit's ray: which micro-triangles it hits and at what t */
    bool hits[MAX_TRIS];
    float t[MAX_TRIS];
} brute;

static void brute_init(brute *bf, const mr_dmm_patch *p)
{
    bf->n = mr_umesh_segments(p->level);
    bf->nvert = mr_umesh_vertex_count(p->level);
    bf->ntri = mr_umesh_triangles(p->level, 0, bf->idx);
    assert_int_equal(bf->ntri, mr_umesh_triangle_count(p->level));
    for (uint32_t i = 0; i < bf->nvert; i++) {
        assert_true(mr_umesh_vertex_coords(p->level, i, &bf->a[i], &bf->b[i]));
        bf->v[i] = mr_dmm_vertex(p, bf->a[i], bf->b[i]);
    }
}

static bool brute_tri(const brute *bf, const mr_wt_ray *r, uint32_t k, float tmin, float tmax,
                      mr_wt_hit *h)
{
    const uint32_t *i = bf->idx + 3 * k;
    return mr_wt_intersect(r, bf->v[i[0]], bf->v[i[1]], bf->v[i[2]], tmin, tmax, h);
}

/* Closest hit over every micro-triangle; *tri gets the first one at that t.
 * Every micro-triangle's verdict is kept in bf->hits, bf->t. */
static bool brute_hit(brute *bf, const mr_wt_ray *r, float tmin, float tmax, float *t,
                      uint32_t *tri)
{
    bool found = false;
    for (uint32_t k = 0; k < bf->ntri; k++) {
        mr_wt_hit h;
        bf->hits[k] = brute_tri(bf, r, k, tmin, tmax, &h);
        bf->t[k] = bf->hits[k] ? h.t : 0;
        if (bf->hits[k] && (!found || h.t < *t)) {
            found = true;
            *t = h.t;
            *tri = k;
        }
    }
    return found;
}

/* Lattice barycentrics of point (x, y) in micro-triangle k. */
static void lattice_bary(const brute *bf, uint32_t k, double x, double y, double w[3])
{
    const uint32_t *i = bf->idx + 3 * k;
    double ax = bf->a[i[0]], ay = bf->b[i[0]], bx = bf->a[i[1]], by = bf->b[i[1]];
    double cx = bf->a[i[2]], cy = bf->b[i[2]];
    double det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
    w[1] = ((x - ax) * (cy - ay) - (cx - ax) * (y - ay)) / det;
    w[2] = ((bx - ax) * (y - ay) - (x - ax) * (by - ay)) / det;
    w[0] = 1.0 - w[1] - w[2];
}

static mr_vec3 tri_normal(const brute *bf, uint32_t k)
{
    const uint32_t *i = bf->idx + 3 * k;
    return mr_v3_cross(mr_v3_sub(bf->v[i[1]], bf->v[i[0]]), mr_v3_sub(bf->v[i[2]], bf->v[i[0]]));
}

/* Whether micro-triangle k has watertight t = t exactly: with its vertices
 * in the tessellation's order, or (rotated) started at another corner of
 * the same winding. Rotation keeps the edge functions (the same floats, so
 * the same hit/miss) but sums det and the scaled t in another order. */
static bool tri_has_t(const brute *bf, const mr_wt_ray *r, uint32_t k, float tmin, float tmax,
                      float t, bool rotated)
{
    const uint32_t *i = bf->idx + 3 * k;
    for (int s = rotated ? 1 : 0; s < (rotated ? 3 : 1); s++) {
        mr_wt_hit h;
        if (mr_wt_intersect(r, bf->v[i[s]], bf->v[i[(s + 1) % 3]], bf->v[i[(s + 2) % 3]], tmin,
                            tmax, &h) &&
            fbits(h.t) == fbits(t))
            return true;
    }
    return false;
}

/* Some micro-triangle's t, in tessellation order (0), only rotated (1), or
 * no micro-triangle's (-1); r is the ray of the last brute_hit. */
static int source_of(const brute *bf, const mr_wt_ray *r, float tmin, float tmax, float t)
{
    for (uint32_t k = 0; k < bf->ntri; k++)
        if (bf->hits[k] && fbits(bf->t[k]) == fbits(t))
            return 0;
    for (uint32_t k = 0; k < bf->ntri; k++)
        if (tri_has_t(bf, r, k, tmin, tmax, t, true))
            return 1;
    return -1;
}

typedef struct check_stats {
    uint64_t rays, hits;
    uint64_t rotated;  /* t only some micro-triangle's t with rotated vertices */
    uint64_t tied;     /* t a few ulps above the closest: a tie at an edge or vertex */
    double worst_uv;   /* lattice units outside the hit micro-triangle */
    double worst_ng;   /* sine of the angle between ng and the oracle's normal */
} check_stats;

/* check_ray flags */
enum {
    CHECK_FINE = 1, /* (u, v) in the micro-triangle hit, ng parallel to its normal */
    CHECK_TIES = 2, /* accept t a few ulps above the closest (see check_ray) */
    CHECK_LOOSE = 4, /* zero-area micro-triangles: no brute-force agreement (see check_ray) */
    CHECK_AIMED = CHECK_TIES | CHECK_FINE, /* rays aimed exactly at vertices and edges */
};

static void print_ray(mr_vec3 org, mr_vec3 dir, float tmin, float tmax)
{
    print_error("ray org (%a, %a, %a) dir (%a, %a, %a) tmin %a tmax %a\n", (double)org.x,
                (double)org.y, (double)org.z, (double)dir.x, (double)dir.y, (double)dir.z,
                (double)tmin, (double)tmax);
}

static float ulps_up(float t, int n)
{
    for (int i = 0; i < n; i++)
        t = nextafterf(t, INFINITY);
    return t;
}

static void fail_ray(const char *what, const mr_dmm_patch *p, mr_vec3 org, mr_vec3 dir,
                     float tmin, float tmax)
{
    print_error("level %u %s: %s\n", p->level, p->mats[0] ? "interpolated" : "base", what);
    print_ray(org, dir, tmin, tmax);
    fail();
}

static bool hit_finite(const mr_dmm_hit *h)
{
    return isfinite(h->t) && isfinite(h->u) && isfinite(h->v) && v3_finite(h->ng);
}

/* (u, v) in some micro-triangle hit at (practically) t, ng parallel to its
 * normal; mr_dmm_locate names that micro-triangle or, on its boundary, a
 * neighbour. Several candidates at an edge or a vertex. */
static void check_fine(const brute *bf, const mr_dmm_patch *p, const mr_dmm_ray *r,
                       const mr_dmm_hit *h, float tmin, float tmax, check_stats *cs)
{
    double x = (double)h->u * bf->n, y = (double)h->v * bf->n;
    double best_uv = INFINITY, best_ng = INFINITY;
    uint32_t best = 0;
    float ttop = ulps_up(h->t, STRICT_T ? 4 : 64); /* see check_ray */
    for (uint32_t k = 0; k < bf->ntri; k++) {
        if (!bf->hits[k] || bf->t[k] > ttop)
            continue;
        double w[3];
        lattice_bary(bf, k, x, y, w);
        double out_by = fmax(0.0, -fmin(w[0], fmin(w[1], w[2])));
        mr_vec3 n = tri_normal(bf, k);
        double dot = (double)h->ng.x * n.x + (double)h->ng.y * n.y + (double)h->ng.z * n.z;
        double cx = (double)h->ng.y * n.z - (double)h->ng.z * n.y;
        double cy = (double)h->ng.z * n.x - (double)h->ng.x * n.z;
        double cz = (double)h->ng.x * n.y - (double)h->ng.y * n.x;
        double ln = (double)mr_v3_len(h->ng) * (double)mr_v3_len(n);
        double sine = ln > 0 && dot > 0 ? sqrt(cx * cx + cy * cy + cz * cz) / ln : 1.0;
        if (fmax(out_by, sine) < fmax(best_uv, best_ng))
            best_uv = out_by, best_ng = sine, best = k;
    }
    if (cs) {
        cs->worst_uv = fmax(cs->worst_uv, best_uv);
        cs->worst_ng = fmax(cs->worst_ng, best_ng);
    }
    if (!(best_uv <= 1e-3 && best_ng <= 1e-3)) {
        print_error("(u, v) = (%g, %g), ng = (%g, %g, %g): best micro-triangle %u is %g "
                    "lattice units away, ng off by sine %g\n",
                    (double)h->u, (double)h->v, (double)h->ng.x, (double)h->ng.y,
                    (double)h->ng.z, best, best_uv, best_ng);
        fail_ray("(u, v) or ng do not match the micro-triangle hit", p, r->org, r->dir, tmin,
                 tmax);
    }
    uint32_t la[3], lb[3];
    mr_dmm_locate(p->level, h->u, h->v, la, lb);
    const uint32_t *ti = bf->idx + 3 * best;
    int same = 0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            same += la[i] == bf->a[ti[j]] && lb[i] == bf->b[ti[j]];
    double w[3];
    lattice_bary(bf, best, x, y, w);
    if (!(same == 3 || fmin(w[0], fmin(w[1], w[2])) < 1e-3))
        fail_ray("mr_dmm_locate names another micro-triangle", p, r->org, r->dir, tmin, tmax);
}

/* Traces one ray through the traversal (closest and any hit) and the brute
 * force and asserts they agree; returns whether it hit, the hit in *out.
 *
 * t must be the closest micro-triangle's t bit for bit. With CHECK_TIES
 * (rays aimed exactly at vertices and edges, where several micro-triangles
 * are hit at the same point) it may instead be another hit micro-triangle's
 * t, bit for bit, up to 4 ulps above the closest: the watertight test
 * compares a candidate against the shrinking tmax in scaled form
 * (t_scaled <= tmax * det), which can reject a t that rounds 1-3 ulps below
 * tmax, so the traversal, which tests in another order than the brute force,
 * may keep the first of two practically equal hits.
 *
 * CHECK_LOOSE is for patches whose micro-triangles have zero area (collinear
 * or coincident corners): the watertight test's edge functions are then
 * rounding noise and can all share a sign, so it reports phantom hits at a
 * meaningless t, possibly far from the (correctly culled) geometry. The
 * brute force is no oracle there; what must still hold is that nothing
 * crashes, a hit is finite, inside [tmin, tmax] and some micro-triangle's
 * watertight t. */
static bool check_ray(brute *bf, const mr_dmm_patch *p, mr_vec3 org, mr_vec3 dir,
                      float tmin, float tmax, mr_dmm_hit *out, mr_dmm_trace_stats *st,
                      check_stats *cs, int flags)
{
    mr_dmm_ray r = mr_dmm_ray_setup(org, dir);
    float bt = 0;
    uint32_t btri = 0;
    bool bhit = brute_hit(bf, &r.wt, tmin, tmax, &bt, &btri);
    float tm = tmax;
    mr_dmm_hit h;
    memset(&h, 0, sizeof h);
    bool hit = mr_dmm_intersect(p, &r, tmin, &tm, false, &h, st);
    bool loose = (flags & CHECK_LOOSE) != 0;
    char msg[200];
    if (cs) {
        cs->rays++;
        cs->hits += hit;
    }
    if (hit != bhit && !loose) {
        snprintf(msg, sizeof msg, "traversal %s t=%a, brute force %s t=%a (micro-triangle %u)",
                 hit ? "hit" : "miss", (double)h.t, bhit ? "hit" : "miss", (double)bt, btri);
        fail_ray(msg, p, org, dir, tmin, tmax);
    }
    if (!hit) {
        assert_true(fbits(tm) == fbits(tmax)); /* untouched on a miss */
    } else {
        if (!hit_finite(&h)) {
            snprintf(msg, sizeof msg, "non-finite hit t=%g u=%g v=%g ng=(%g, %g, %g)",
                     (double)h.t, (double)h.u, (double)h.v, (double)h.ng.x, (double)h.ng.y,
                     (double)h.ng.z);
            fail_ray(msg, p, org, dir, tmin, tmax);
        }
        if (!(h.t >= tmin && h.t <= tmax)) {
            snprintf(msg, sizeof msg, "hit t=%a outside [tmin, tmax]", (double)h.t);
            fail_ray(msg, p, org, dir, tmin, tmax);
        }
        assert_true(fbits(tm) == fbits(h.t));
        /* base-domain barycentrics, whatever the geometry */
        assert_true(h.u >= -1e-4f && h.v >= -1e-4f && h.u + h.v <= 1 + 1e-4f);
        int src = fbits(h.t) == fbits(bt) ? 0 : source_of(bf, &r.wt, tmin, tmax, h.t);
        float top = (flags & CHECK_TIES) ? ulps_up(bt, 4) : bt, bottom = bt;
        if (src == 1) /* only without STRICT_T: the rotated sums round either way,
                       * by many ulps when t is small against the vertices */
            top = ulps_up(bt, 64), bottom = -ulps_up(-bt, 64);
        if (cs && src == 1)
            cs->rotated++;
        if (cs && src == 0 && fbits(h.t) != fbits(bt))
            cs->tied++;
        if (src < 0 || (src == 1 && STRICT_T) ||
            (!loose && !(h.t >= bottom && h.t <= top))) {
            snprintf(msg, sizeof msg, "traversal t=%a, brute force t=%a (micro-triangle %u)%s",
                     (double)h.t, (double)bt, btri,
                     src == 1 ? ": the traversal's t is a micro-triangle's t with its vertices "
                                "rotated (winding started at another corner)"
                     : src < 0 ? ": no micro-triangle has that t"
                               : "");
            fail_ray(msg, p, org, dir, tmin, tmax);
        }
        if ((flags & CHECK_FINE) && !loose)
            check_fine(bf, p, &r, &h, tmin, tmax, cs);
        if (out)
            *out = h;
    }
    /* any hit: same verdict, a t some micro-triangle really has */
    float ta = tmax;
    mr_dmm_hit ah;
    memset(&ah, 0, sizeof ah);
    bool any = mr_dmm_intersect(p, &r, tmin, &ta, true, &ah, NULL);
    if (any != bhit && !loose) {
        snprintf(msg, sizeof msg, "any-hit %s, brute force %s", any ? "hit" : "miss",
                 bhit ? "hit" : "miss");
        fail_ray(msg, p, org, dir, tmin, tmax);
    }
    if (any) {
        if (!(hit_finite(&ah) && fbits(ta) == fbits(ah.t) && ta >= tmin && ta <= tmax)) {
            snprintf(msg, sizeof msg, "any-hit t=%a u=%g v=%g: not finite or outside the "
                     "interval", (double)ah.t, (double)ah.u, (double)ah.v);
            fail_ray(msg, p, org, dir, tmin, tmax);
        }
        int src = source_of(bf, &r.wt, tmin, tmax, ta);
        if (src < 0 || (src == 1 && STRICT_T)) {
            snprintf(msg, sizeof msg, "any-hit t=%a is %s", (double)ta,
                     src < 0 ? "no micro-triangle's t"
                             : "a micro-triangle's t only with its vertices rotated");
            fail_ray(msg, p, org, dir, tmin, tmax);
        }
    }
    return hit;
}

/* Point at barycentrics (w1, w2) of a random micro-triangle of the
 * tessellation. */
static mr_vec3 rnd_surface_point(const brute *bf, uint64_t *s)
{
    const uint32_t *i = bf->idx + 3 * (rnd(s) % bf->ntri);
    float w1 = (float)rnd01(s), w2 = (float)rnd01(s);
    if (w1 + w2 > 1)
        w1 = 1 - w1, w2 = 1 - w2;
    mr_vec3 p = mr_v3_scale(bf->v[i[0]], 1 - w1 - w2);
    return mr_v3_add(p, mr_v3_add(mr_v3_scale(bf->v[i[1]], w1), mr_v3_scale(bf->v[i[2]], w2)));
}

/* Random ray: aimed at a surface point (even calls) or a point of the
 * bounds (odd), from a sphere around the bounds or from inside them. */
static void rnd_ray(const brute *bf, mr_vec3 lo, mr_vec3 hi, uint64_t *s, uint32_t i,
                    mr_vec3 *org, mr_vec3 *dir, float *tmin, float *tmax)
{
    mr_vec3 c = mr_v3_scale(mr_v3_add(lo, hi), 0.5f), ext = mr_v3_sub(hi, lo);
    float radius = 1.5f * mr_v3_len(ext) + 1e-3f;
    mr_vec3 target;
    if (i % 2 == 0)
        target = rnd_surface_point(bf, s);
    else
        target = mr_v3_add(lo, mr_v3_mul(ext, rnd_vec(s, 0, 1)));
    if (i % 7 == 3)
        *org = mr_v3_add(lo, mr_v3_mul(ext, rnd_vec(s, 0, 1))); /* inside the bounds */
    else
        *org = mr_v3_add(c, mr_v3_scale(rnd_unit(s), radius));
    *dir = mr_v3_scale(mr_v3_sub(target, *org), rndf(s, 0.25f, 4.0f));
    if (!(mr_v3_len(*dir) > 0))
        *dir = rnd_unit(s);
    *tmin = 0;
    *tmax = INFINITY;
    if (i % 5 == 4) { /* a finite segment */
        *tmin = rndf(s, 0.0f, 0.2f);
        *tmax = rndf(s, 0.2f, 0.6f);
    }
}

static void random_disp(uint64_t *s, float *d, uint32_t n, float lo, float hi)
{
    for (uint32_t i = 0; i < n; i++)
        d[i] = rndf(s, lo, hi);
}

static mr_umesh_tri rnd_tri(uint64_t *s)
{
    mr_umesh_tri t;
    for (int k = 0; k < 3; k++) {
        t.pos[k] = rnd_vec(s, -2, 2);
        t.dir[k] = mr_v3_scale(rnd_unit(s), rndf(s, 0.3f, 1.5f));
    }
    return t;
}

static bool inside(mr_vec3 v, mr_vec3 lo, mr_vec3 hi)
{
    return v.x >= lo.x && v.y >= lo.y && v.z >= lo.z && v.x <= hi.x && v.y <= hi.y &&
           v.z <= hi.z;
}

/* ---- 1. traversal == brute force */

static void traversal_vs_brute(bool interpolated, uint64_t seed)
{
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    uint64_t s = seed;
    enum { PATCHES = 4, RAYS = 250 };
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * PATCHES);
        assert_non_null(disp);
        random_disp(&s, disp, vc * PATCHES, -0.3f, 0.5f);
        patch_set set;
        set_build(&set, level, PATCHES, disp);
        check_stats cs = {0};
        for (uint32_t t = 0; t < PATCHES; t++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++)
                mats[k] = rnd_affine(&s, 1.6f);
            mr_dmm_patch p = set_patch(&set, t, &tri, interpolated ? mats : NULL);
            if (t % 2) /* half the patches with the caller-cached pad */
                mr_dmm_patch_pad(&p, p.pad);
            brute_init(bf, &p);
            mr_vec3 lo, hi;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            for (uint32_t i = 0; i < RAYS; i++) {
                mr_vec3 org, dir;
                float tmin, tmax;
                rnd_ray(bf, lo, hi, &s, i, &org, &dir, &tmin, &tmax);
                check_ray(bf, &p, org, dir, tmin, tmax, NULL, NULL, &cs, CHECK_FINE);
            }
        }
        /* most rays are aimed at the surface: a suite that only misses
         * would prove nothing */
        assert_true(cs.hits * 4 > cs.rays);
        printf("  level %u %s: %llu/%llu rays hit (%llu t off by winding only), worst (u,v) "
               "%.2g lattice, ng %.2g\n",
               level, interpolated ? "interpolated" : "base", (unsigned long long)cs.hits,
               (unsigned long long)cs.rays, (unsigned long long)cs.rotated, cs.worst_uv,
               cs.worst_ng);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

static void test_brute_base(void **state)
{
    (void)state;
    traversal_vs_brute(false, 0x9e3779b97f4a7c15ull);
}

static void test_brute_interpolated(void **state)
{
    (void)state;
    traversal_vs_brute(true, 0xd1b54a32d192ed03ull);
}

/* ---- 2. bounds contain every micro-vertex */

static void bounds_case(const mr_dmm_patch *p)
{
    mr_vec3 lo, hi;
    assert_true(mr_dmm_patch_bounds(p, &lo, &hi));
    uint32_t n = mr_umesh_segments(p->level);
    for (uint32_t b = 0; b <= n; b++)
        for (uint32_t a = 0; a + b <= n; a++) {
            mr_vec3 v = mr_dmm_vertex(p, a, b);
            if (!inside(v, lo, hi)) {
                print_error("level %u vertex (%u, %u) = (%a, %a, %a) outside (%a %a %a)-(%a %a "
                            "%a)\n",
                            p->level, a, b, (double)v.x, (double)v.y, (double)v.z,
                            (double)lo.x, (double)lo.y, (double)lo.z, (double)hi.x,
                            (double)hi.y, (double)hi.z);
                fail();
            }
        }
}

static void test_bounds(void **state)
{
    (void)state;
    uint64_t s = 0x1234567887654321ull;
    enum { PATCHES = 12 };
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * PATCHES);
        assert_non_null(disp);
        random_disp(&s, disp, vc * PATCHES, -1.0f, 2.0f);
        patch_set set;
        set_build(&set, level, PATCHES, disp);
        for (uint32_t t = 0; t < PATCHES; t++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++) {
                if (t % 3 == 0) {
                    mats[k] = rnd_affine(&s, 3.1f);
                } else {
                    /* strongly non-rigid: arbitrary linear part (shear,
                     * non-uniform scale, near-singular, reflections) */
                    for (int e = 0; e < 12; e++)
                        mats[k].m[e] = rndf(&s, -3.0f, 3.0f);
                    if (t % 3 == 2) /* collapse a column: singular */
                        mats[k].m[0] = mats[k].m[4] = mats[k].m[8] = 0;
                }
            }
            mr_dmm_patch p = set_patch(&set, t, &tri, NULL);
            if (t % 2)
                mr_dmm_patch_pad(&p, p.pad);
            bounds_case(&p);
            p = set_patch(&set, t, &tri, mats);
            if (t % 2)
                mr_dmm_patch_pad(&p, p.pad);
            bounds_case(&p);
        }
        set_free(&set);
        free(disp);
    }
}

/* ---- 3. zero displacement */

static void test_zero_base(void **state)
{
    (void)state;
    uint64_t s = 0x51ed270b27d4a1f9ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = calloc(vc, sizeof(float));
        assert_non_null(disp);
        patch_set set;
        set_build(&set, level, 1, disp);
        for (int rep = 0; rep < 4; rep++) {
            /* well-shaped: heights >= 0.5 for the (u, v) tolerance */
            mr_umesh_tri tri;
            tri.pos[0] = rnd_vec(&s, -0.2f, 0.2f);
            tri.pos[1] = mr_v3_add(tri.pos[0], mr_v3(rndf(&s, 1.5f, 2.5f), rndf(&s, -.2f, .2f),
                                                     rndf(&s, -.3f, .3f)));
            tri.pos[2] = mr_v3_add(tri.pos[0], mr_v3(rndf(&s, -.2f, .2f), rndf(&s, 1.5f, 2.5f),
                                                     rndf(&s, -.3f, .3f)));
            for (int k = 0; k < 3; k++)
                tri.dir[k] = rnd_unit(&s);
            mr_dmm_patch p = set_patch(&set, 0, &tri, NULL);
            brute_init(bf, &p);
            double e1[3] = {tri.pos[1].x - tri.pos[0].x, tri.pos[1].y - tri.pos[0].y,
                            tri.pos[1].z - tri.pos[0].z};
            double e2[3] = {tri.pos[2].x - tri.pos[0].x, tri.pos[2].y - tri.pos[0].y,
                            tri.pos[2].z - tri.pos[0].z};
            double nrm[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};
            double nl = sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]);
            float vmax =
                fmaxf(vmaxabs(tri.pos[0]), fmaxf(vmaxabs(tri.pos[1]), vmaxabs(tri.pos[2])));
            mr_vec3 lo, hi;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            int hits = 0;
            for (uint32_t i = 0; i < 200; i++) {
                /* a base point at known barycentrics, from either side */
                float w1 = (float)rnd01(&s), w2 = (float)rnd01(&s);
                if (w1 + w2 > 1)
                    w1 = 1 - w1, w2 = 1 - w2;
                mr_vec3 target = mr_v3_add(
                    tri.pos[0], mr_v3_add(mr_v3_scale(mr_v3_sub(tri.pos[1], tri.pos[0]), w1),
                                          mr_v3_scale(mr_v3_sub(tri.pos[2], tri.pos[0]), w2)));
                mr_vec3 org = mr_v3_add(target, mr_v3_scale(rnd_unit(&s), rndf(&s, 0.5f, 4.0f)));
                mr_vec3 dir = mr_v3_sub(target, org);
                mr_dmm_hit h;
                if (!check_ray(bf, &p, org, dir, 0, INFINITY, &h, NULL, NULL, CHECK_FINE))
                    continue;
                hits++;
                double x[3] = {(double)org.x + (double)h.t * dir.x,
                               (double)org.y + (double)h.t * dir.y,
                               (double)org.z + (double)h.t * dir.z};
                double rel[3] = {x[0] - tri.pos[0].x, x[1] - tri.pos[0].y, x[2] - tri.pos[0].z};
                double dist = (rel[0] * nrm[0] + rel[1] * nrm[1] + rel[2] * nrm[2]) / nl;
                double tol = 8.0 * FLT_EPSILON *
                             (vmaxabs(org) + fabs(h.t) * vmaxabs(dir) + vmaxabs(tri.pos[0]) + vmax);
                if (fabs(dist) > tol) {
                    print_error("hit %g off the base plane (tolerance %g)\n", dist, tol);
                    fail();
                }
                /* base barycentrics of the hit point (least squares in the plane) */
                double g11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2];
                double g22 = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2];
                double g12 = e1[0] * e2[0] + e1[1] * e2[1] + e1[2] * e2[2];
                double r1 = rel[0] * e1[0] + rel[1] * e1[1] + rel[2] * e1[2];
                double r2 = rel[0] * e2[0] + rel[1] * e2[1] + rel[2] * e2[2];
                double det = g11 * g22 - g12 * g12;
                double bu = (r1 * g22 - r2 * g12) / det, bv = (r2 * g11 - r1 * g12) / det;
                assert_true(fabs(bu - h.u) < 1e-4 && fabs(bv - h.v) < 1e-4);
            }
            /* rays at interior base points from outside the plane hit, bar
             * the few aimed within rounding of the boundary */
            assert_true(hits >= 190);
        }
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* Quadratic Bezier patch of eq. 9-11 at the micro-vertex (a, b), in double;
 * *mag gets the magnitude of the terms summed (for the tolerance). */
static void bezier_point(const mr_umesh_tri *rest, const mr_affine *mats, double u, double v,
                         double out[3], double *mag)
{
    /* alpha weighs v0 (x200), beta v1 (x020), gamma v2 (x002) */
    double w[3] = {1.0 - u - v, u, v};
    double cp[3][3][3]; /* cp[i][j] = M_i v_j */
    *mag = 0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            const float *m = mats[i].m;
            const mr_vec3 x = rest->pos[j];
            for (int r = 0; r < 3; r++) {
                cp[i][j][r] = (double)m[4 * r] * x.x + (double)m[4 * r + 1] * x.y +
                              (double)m[4 * r + 2] * x.z + (double)m[4 * r + 3];
                double terms = fabs((double)m[4 * r] * x.x) + fabs((double)m[4 * r + 1] * x.y) +
                               fabs((double)m[4 * r + 2] * x.z) + fabs((double)m[4 * r + 3]);
                *mag = fmax(*mag, terms);
            }
        }
    for (int r = 0; r < 3; r++) {
        double x200 = cp[0][0][r], x020 = cp[1][1][r], x002 = cp[2][2][r];
        double x110 = 0.5 * (cp[0][1][r] + cp[1][0][r]);
        double x011 = 0.5 * (cp[1][2][r] + cp[2][1][r]);
        double x101 = 0.5 * (cp[0][2][r] + cp[2][0][r]);
        out[r] = w[0] * w[0] * x200 + w[1] * w[1] * x020 + w[2] * w[2] * x002 +
                 2 * w[0] * w[1] * x110 + 2 * w[1] * w[2] * x011 + 2 * w[0] * w[2] * x101;
    }
}

static void test_zero_interpolated_bezier(void **state)
{
    (void)state;
    uint64_t s = 0xabcdef0123456789ull;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
        float *disp = calloc(vc, sizeof(float));
        assert_non_null(disp);
        patch_set set;
        set_build(&set, level, 1, disp);
        double worst = 0;
        for (int rep = 0; rep < 8; rep++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++)
                mats[k] = rnd_affine(&s, 2.5f); /* bends up to ~140 degrees apart */
            mr_dmm_patch p = set_patch(&set, 0, &tri, mats);
            for (uint32_t b = 0; b <= n; b++)
                for (uint32_t a = 0; a + b <= n; a++) {
                    double ref[3], mag;
                    bezier_point(&tri, mats, (double)a / n, (double)b / n, ref, &mag);
                    mr_vec3 v = mr_dmm_vertex(&p, a, b);
                    for (int k = 0; k < 3; k++) {
                        double d = fabs((double)comp(v, k) - ref[k]);
                        double tol = 0x1p-23 * fabs(ref[k]) + 0x1p-40 * mag;
                        worst = fmax(worst, d / tol);
                        if (d > tol) {
                            print_error("level %u (%u, %u) axis %d: %a vs Bezier %a\n", level,
                                        a, b, k, (double)comp(v, k), ref[k]);
                            fail();
                        }
                    }
                }
        }
        printf("  level %u: worst |vertex - Bezier| %.2f of tolerance\n", level, worst);
        set_free(&set);
        free(disp);
    }
}

static void test_equal_matrices(void **state)
{
    (void)state;
    uint64_t s = 0x0badc0ffee0ddf00ull;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
        enum { PATCHES = 4 };
        float *disp = malloc(sizeof(float) * vc * PATCHES);
        assert_non_null(disp);
        random_disp(&s, disp, vc * PATCHES, -0.5f, 0.5f);
        patch_set set;
        set_build(&set, level, PATCHES, disp);
        for (uint32_t t = 0; t < PATCHES; t++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine m = rnd_affine(&s, 3.1f), mats[3] = {m, m, m};
            mr_dmm_patch pi = set_patch(&set, t, &tri, mats), pb = set_patch(&set, t, &tri, NULL);
            for (uint32_t b = 0; b <= n; b++)
                for (uint32_t a = 0; a + b <= n; a++) {
                    mr_vec3 x = mr_dmm_vertex(&pb, a, b), v = mr_dmm_vertex(&pi, a, b);
                    for (int r = 0; r < 3; r++) {
                        const float *row = m.m + 4 * r;
                        double ref = (double)row[0] * x.x + (double)row[1] * x.y +
                                     (double)row[2] * x.z + (double)row[3];
                        float rf = (float)ref;
                        double spread = fabs((double)row[0]) + fabs((double)row[1]) +
                                        fabs((double)row[2]);
                        double tol = 0x1p-24 * (2.0 * fabs(ref) + spread * vmaxabs(x));
                        if (fabs((double)comp(v, r) - (double)rf) > tol) {
                            print_error("level %u (%u, %u): %a vs M x %a\n", level, a, b,
                                        (double)comp(v, r), (double)rf);
                            fail();
                        }
                    }
                }
        }
        set_free(&set);
        free(disp);
    }
}

/* ---- 4. culling works: few micro-triangles per ray */

static void test_counters(void **state)
{
    (void)state;
    uint64_t s = 0x7777777712345678ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const unsigned level = 5;
    enum { PATCHES = 4, RAYS = 300 };
    uint32_t vc = mr_umesh_vertex_count(level);
    float *disp = malloc(sizeof(float) * vc * PATCHES);
    assert_non_null(disp);
    random_disp(&s, disp, vc * PATCHES, -0.1f, 0.2f);
    patch_set set;
    set_build(&set, level, PATCHES, disp);
    for (int mode = 0; mode < 2; mode++) {
        mr_dmm_trace_stats st = {0};
        uint64_t rays = 0, hits = 0;
        for (uint32_t t = 0; t < PATCHES; t++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++)
                mats[k] = rnd_affine(&s, 1.0f);
            mr_dmm_patch p = set_patch(&set, t, &tri, mode ? mats : NULL);
            brute_init(bf, &p);
            mr_vec3 lo, hi;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            for (uint32_t i = 0; i < RAYS; i++) {
                mr_vec3 org, dir;
                float tmin, tmax;
                rnd_ray(bf, lo, hi, &s, i, &org, &dir, &tmin, &tmax);
                mr_dmm_trace_stats one = {0};
                hits += check_ray(bf, &p, org, dir, tmin, tmax, NULL, &one, NULL, CHECK_FINE);
                rays++;
                st.boxes += one.boxes;
                st.triangles += one.triangles;
                assert_true(one.triangles <= mr_umesh_triangle_count(level));
            }
        }
        double mean_tris = (double)st.triangles / (double)rays;
        double mean_boxes = (double)st.boxes / (double)rays;
        printf("  level 5 %s: %.1f micro-triangles and %.1f boxes per ray (%llu/%llu hit)\n",
               mode ? "interpolated" : "base", mean_tris, mean_boxes, (unsigned long long)hits,
               (unsigned long long)rays);
        assert_true(hits > 0);
        assert_true(mean_tris < 0.1 * mr_umesh_triangle_count(level));
        assert_true(st.boxes > 0);
    }
    set_free(&set);
    free(disp);
    free(bf);
}

/* A pad cached by the caller (mr_dmm_patch_pad) gives exactly the results of
 * the pad computed per call: same bounds, same hits bit for bit. */
static void test_cached_pad(void **state)
{
    (void)state;
    uint64_t s = 0x6a09e667f3bcc908ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc);
        assert_non_null(disp);
        random_disp(&s, disp, vc, -0.3f, 0.3f);
        patch_set set;
        set_build(&set, level, 1, disp);
        for (int mode = 0; mode < 2; mode++) {
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++)
                mats[k] = rnd_affine(&s, 1.5f);
            mr_dmm_patch p = set_patch(&set, 0, &tri, mode ? mats : NULL), q = p;
            mr_dmm_patch_pad(&q, q.pad);
            for (int k = 0; k < 3; k++)
                assert_true(q.pad[k] > 0 && isfinite(q.pad[k]));
            mr_vec3 lo, hi, lo2, hi2;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            assert_true(mr_dmm_patch_bounds(&q, &lo2, &hi2));
            assert_memory_equal(&lo, &lo2, sizeof lo);
            assert_memory_equal(&hi, &hi2, sizeof hi);
            brute_init(bf, &p);
            for (uint32_t i = 0; i < 100; i++) {
                mr_vec3 org, dir;
                float tmin, tmax;
                rnd_ray(bf, lo, hi, &s, i, &org, &dir, &tmin, &tmax);
                mr_dmm_ray r = mr_dmm_ray_setup(org, dir);
                mr_dmm_hit h1, h2;
                memset(&h1, 0, sizeof h1);
                memset(&h2, 0, sizeof h2);
                float t1 = tmax, t2 = tmax;
                bool a = mr_dmm_intersect(&p, &r, tmin, &t1, false, &h1, NULL);
                bool b = mr_dmm_intersect(&q, &r, tmin, &t2, false, &h2, NULL);
                assert_true(a == b && fbits(t1) == fbits(t2));
                assert_memory_equal(&h1, &h2, sizeof h1);
            }
        }
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* Bad or trivial arguments: empty interval, a level out of range. */
static void test_arguments(void **state)
{
    (void)state;
    float disp[15] = {0};
    patch_set set;
    set_build(&set, 2, 1, disp);
    mr_umesh_tri tri = {{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}}, {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}}};
    mr_dmm_patch p = set_patch(&set, 0, &tri, NULL);
    mr_dmm_ray r = mr_dmm_ray_setup(mr_v3(0.25f, 0.25f, 1), mr_v3(0, 0, -1));
    mr_dmm_hit h;
    float tmax = 5;
    assert_true(mr_dmm_intersect(&p, &r, 0, &tmax, false, &h, NULL));
    assert_true(h.t == 1.0f && tmax == 1.0f);
    assert_true(fabsf(h.u - 0.25f) < 1e-6f && fabsf(h.v - 0.25f) < 1e-6f);
    tmax = 0.5f; /* hit beyond tmax */
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, false, &h, NULL));
    assert_true(tmax == 0.5f);
    tmax = 0.5f; /* empty interval */
    assert_false(mr_dmm_intersect(&p, &r, 2.0f, &tmax, false, &h, NULL));
    tmax = NAN;
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, false, &h, NULL));
    tmax = 5;
    assert_false(mr_dmm_intersect(&p, &r, 1.5f, &tmax, false, &h, NULL)); /* behind tmin */
    assert_int_equal(mr_dmm_trace_leaf_sublevel(0), 0);
    assert_int_equal(mr_dmm_trace_leaf_sublevel(5), 4);
    assert_int_equal(mr_dmm_trace_pyramid_size(5), mr_dmm_pyramid_size(4));
    assert_int_equal(mr_dmm_trace_pyramid_size(0), 1);
    p.level = MR_UMESH_MAX_LEVEL + 1;
    tmax = 5;
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, false, &h, NULL));
    set_free(&set);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_arguments),
        cmocka_unit_test(test_brute_base),
        cmocka_unit_test(test_brute_interpolated),
        cmocka_unit_test(test_bounds),
        cmocka_unit_test(test_zero_base),
        cmocka_unit_test(test_zero_interpolated_bezier),
        cmocka_unit_test(test_equal_matrices),
        cmocka_unit_test(test_counters),
        cmocka_unit_test(test_cached_pad),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
