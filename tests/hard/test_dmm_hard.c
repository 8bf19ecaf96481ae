/*
 * test_dmm_hard.c - hard cases for the tessellation-free DMM traversal
 * (core/geom/dmm_trace.h): extreme deformations, degenerate base triangles,
 * displacements at the quantisation limits, grazing rays, rays starting
 * inside a patch, rays at a shared edge between two patches, rays at every
 * micro-vertex, axis-parallel rays and rays from far away.
 *
 * In every case: nothing crashes, no hit carries a NaN, every micro-vertex
 * lies in mr_dmm_patch_bounds, and the traversal agrees with the brute force
 * over the tessellation (every micro-triangle from mr_dmm_vertex, tested
 * with the same watertight test): hit/miss exactly, t bit for bit (STRICT_T,
 * see below). Where a hit is guaranteed by construction (a ray through an
 * interior point of a watertight surface that does not fold under it) the
 * test also demands the hit.
 *
 * STRICT_T 1 (default) demands the traversal's t equal the brute force's
 * bit for bit. With -DSTRICT_T=0, a t that is the same micro-triangle's
 * watertight t with its vertices started at another corner (same vertices,
 * same winding, so the same edge functions and the same hit/miss; only the
 * sums of det and of the scaled t round differently) is accepted and
 * counted. Rays aimed exactly at vertices and edges use CHECK_TIES (a t up
 * to 4 ulps above the closest, see check_ray); patches with zero-area
 * micro-triangles use CHECK_LOOSE (no oracle, robustness only).
 *
 * The harness (random numbers, patch sets, brute force, check_ray) is the
 * one of tests/unit/test_dmm_trace.c, repeated so each test builds alone.
 *
 * Tolerances:
 *  - (u, v): always inside the base domain within 1e-4 (the barycentrics of
 *    the watertight test are non-negative ratios summing to 1 up to a
 *    rounding); on well-shaped geometry with non-grazing rays also inside
 *    the micro-triangle hit within 1e-3 lattice units, ng within a
 *    milliradian of its normal (as in tests/unit/test_dmm_trace.c).
 *  - a ray aimed at a micro-vertex from distance h: the float direction
 *    org - v misses the vertex by at most an ulp of the coordinates, and the
 *    surface around it has bounded slope under the ray, so the hit t is
 *    within 1e-5 of 1 (measured error ~1e-7); axis-parallel rays pass
 *    through the vertex exactly (zero shear), t within 4 ulps of
 *    org - v along the axis.
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

/* ---- bounds contain every micro-vertex */

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

/* ---- deformations */

static mr_vec3 affine_point(const mr_affine *m, mr_vec3 p)
{
    double r[3];
    for (int i = 0; i < 3; i++)
        r[i] = (double)m->m[4 * i] * p.x + (double)m->m[4 * i + 1] * p.y +
               (double)m->m[4 * i + 2] * p.z + (double)m->m[4 * i + 3];
    return mr_v3((float)r[0], (float)r[1], (float)r[2]);
}

static mr_vec3 affine_dir(const mr_affine *m, mr_vec3 d)
{
    double r[3];
    for (int i = 0; i < 3; i++)
        r[i] = (double)m->m[4 * i] * d.x + (double)m->m[4 * i + 1] * d.y +
               (double)m->m[4 * i + 2] * d.z;
    return mr_v3((float)r[0], (float)r[1], (float)r[2]);
}

/* Base mode of the same deformation: each corner skinned by its own matrix
 * (eq. 2-4), the state of the art the paper compares with. */
static mr_umesh_tri skin_tri(const mr_umesh_tri *rest, const mr_affine *mats)
{
    mr_umesh_tri t;
    for (int k = 0; k < 3; k++) {
        t.pos[k] = affine_point(&mats[k], rest->pos[k]);
        t.dir[k] = affine_dir(&mats[k], rest->dir[k]);
    }
    return t;
}

static const float DEG = 3.14159265f / 180.0f;

/* Hard matrix triples: 0 bends of 130 and 170 degrees; 1 twists of +-179.9
 * degrees (the blend passes through a near-singular matrix); 2 non-uniform
 * scale and shear (upper 3x3 far from orthonormal); 3 a flattening scale, a
 * reflection and a 150 degree bend with scale. */
static void hard_mats(int which, mr_affine m[3])
{
    const mr_vec3 one = mr_v3(1, 1, 1);
    switch (which) {
    case 0:
        m[0] = affine_trs(mr_v3(0, 0, 0), mr_v3(1, 0, 0), 0, one);
        m[1] = affine_trs(mr_v3(0.5f, 0, 0), mr_v3(0, 1, 0), 130 * DEG, one);
        m[2] = affine_trs(mr_v3(0, -0.3f, 0.2f), mr_v3(1, 1, 0), -170 * DEG, one);
        break;
    case 1:
        m[0] = affine_trs(mr_v3(0, 0, 0), mr_v3(0, 0, 1), 179.9f * DEG, one);
        m[1] = affine_trs(mr_v3(0, 0, 0), mr_v3(0, 0, 1), -179.9f * DEG, one);
        m[2] = affine_trs(mr_v3(0.1f, 0.2f, 0.3f), mr_v3(1, 0, 0), 90 * DEG, one);
        break;
    case 2: {
        const mr_affine a = {{1, 2.5f, 0, 0.3f, 0, 0.2f, 0, -1, 0.7f, 0, 3, 0.5f}};
        const mr_affine b = {{0.1f, 0, -1.5f, 0, 1.2f, 1, 0, 2, 0, -0.8f, 0.4f, 0}};
        m[0] = a;
        m[1] = b;
        m[2] = affine_trs(mr_v3(1, 1, 1), mr_v3(1, 2, 3), 60 * DEG, mr_v3(0.1f, 4, 1));
        break;
    }
    default:
        m[0] = affine_trs(mr_v3(0, 0, 0), mr_v3(0, 1, 0), 0, mr_v3(1, 1, 1e-4f));
        m[1] = affine_trs(mr_v3(0, 0, 1), mr_v3(0, 0, 1), 0, mr_v3(-1, 1, 1));
        m[2] = affine_trs(mr_v3(0, 0, 0), mr_v3(1, 0, 1), 150 * DEG, mr_v3(3, 0.2f, 1));
        break;
    }
}

/* ---- the battery every hard patch goes through */

/* Bounds hold every micro-vertex; random rays, rays at micro-vertices from
 * random directions and axis-parallel rays all agree with the brute force. */
static void run_patch(brute *bf, const mr_dmm_patch *p, uint64_t *s, uint32_t rays, int flags,
                      check_stats *cs)
{
    bounds_case(p);
    brute_init(bf, p);
    mr_vec3 lo, hi;
    assert_true(mr_dmm_patch_bounds(p, &lo, &hi));
    float radius = 1.5f * mr_v3_len(mr_v3_sub(hi, lo)) + 1e-3f;
    for (uint32_t i = 0; i < rays; i++) {
        mr_vec3 org, dir;
        float tmin, tmax;
        rnd_ray(bf, lo, hi, s, i, &org, &dir, &tmin, &tmax);
        check_ray(bf, p, org, dir, tmin, tmax, NULL, NULL, cs, flags);
    }
    /* micro-vertices: every one up to level 3, 64 random ones above */
    uint32_t nv = bf->nvert <= 45 ? bf->nvert : 64;
    for (uint32_t i = 0; i < nv; i++) {
        mr_vec3 v = bf->v[bf->nvert <= 45 ? i : rnd(s) % bf->nvert];
        mr_vec3 org = mr_v3_add(v, mr_v3_scale(rnd_unit(s), radius));
        mr_vec3 dir = mr_v3_sub(v, org);
        if (mr_v3_len(dir) > 0)
            check_ray(bf, p, org, dir, 0, INFINITY, NULL, NULL, cs, flags);
    }
    /* axis-parallel: one or two direction components exactly 0; the origin
     * shares the target's coordinates on those axes */
    for (uint32_t i = 0; i < rays / 2; i++) {
        mr_vec3 target = i % 2 ? rnd_surface_point(bf, s) : bf->v[rnd(s) % bf->nvert];
        float d[3] = {0, 0, 0};
        int k = (int)(i % 3);
        d[k] = rnd(s) % 2 ? 1.0f : -1.0f;
        if (i % 4 >= 2)
            d[(k + 1) % 3] = rndf(s, -1, 1);
        mr_vec3 dir = mr_v3(d[0], d[1], d[2]);
        mr_vec3 org = mr_v3_sub(target, mr_v3_scale(dir, radius));
        check_ray(bf, p, org, dir, 0, INFINITY, NULL, NULL, cs, flags);
    }
}

static void print_cs(const char *what, unsigned level, const check_stats *cs)
{
    printf("  %s level %u: %llu/%llu rays hit (%llu ties, %llu t off by winding only)\n", what,
           level, (unsigned long long)cs->hits, (unsigned long long)cs->rays,
           (unsigned long long)cs->tied, (unsigned long long)cs->rotated);
}

/* ---- bends beyond 120 degrees, non-uniform scale, shear */

static void test_bends(void **state)
{
    (void)state;
    uint64_t s = 0x243f6a8885a308d3ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * 4);
        assert_non_null(disp);
        random_disp(&s, disp, vc * 4, -0.3f, 0.5f);
        patch_set set;
        set_build(&set, level, 4, disp);
        check_stats cs = {0};
        for (int which = 0; which < 4; which++) {
            mr_umesh_tri rest = {{{0, 0, 0}, {1.5f, 0.1f, 0}, {0.2f, 1.4f, 0.1f}},
                                 {{0, 0, 1}, {0.2f, 0, 1}, {0, -0.3f, 1}}};
            mr_affine mats[3];
            hard_mats(which, mats);
            mr_dmm_patch p = set_patch(&set, (uint32_t)which, &rest, mats);
            run_patch(bf, &p, &s, 120, CHECK_TIES, &cs);
            mr_umesh_tri posed = skin_tri(&rest, mats);
            p = set_patch(&set, (uint32_t)which, &posed, NULL);
            run_patch(bf, &p, &s, 120, CHECK_TIES, &cs);
        }
        print_cs("bends", level, &cs);
        assert_true(cs.hits > cs.rays / 5);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- degenerate base triangles and directions */

static void test_degenerate_base(void **state)
{
    (void)state;
    uint64_t s = 0x13198a2e03707344ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const mr_vec3 shapes[][3] = {
        {{0, 0, 0}, {1, 0, 0}, {0.5f, 1e-6f, 0}},       /* sliver */
        {{0, 0, 0}, {1, 0, 0}, {1e-6f, 1e-6f, 1e-6f}},  /* needle */
        {{0, 0, 0}, {1, 0, 0}, {2, 0, 0}},              /* collinear: zero area */
        {{0, 1, 0}, {0, 1, 0}, {1, 0, 0}},              /* two corners coincide */
        {{0.3f, 0.3f, 0.3f}, {0.3f, 0.3f, 0.3f}, {0.3f, 0.3f, 0.3f}}, /* a point */
    };
    const mr_vec3 dirs[][3] = {
        {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}},
        {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}},   /* zero length: no displacement */
        {{0, 0, 1}, {0, 0, 0}, {0, 1, 1}},   /* one zero */
        {{0, 0, 1}, {0, 0, -1}, {0, 0, 1}},  /* n0 = -n1: the edge pinches */
        {{1, 0, 0}, {0, 1, 0}, {-1, 0, 0}},  /* tangential */
    };
    const unsigned levels[] = {0, 1, 3, 5};
    for (size_t li = 0; li < sizeof levels / sizeof *levels; li++) {
        unsigned level = levels[li];
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc);
        assert_non_null(disp);
        random_disp(&s, disp, vc, -0.5f, 0.5f);
        patch_set set;
        set_build(&set, level, 1, disp);
        check_stats cs = {0};
        for (size_t a = 0; a < sizeof shapes / sizeof *shapes; a++)
            for (size_t d = 0; d < sizeof dirs / sizeof *dirs; d++) {
                mr_umesh_tri tri;
                for (int k = 0; k < 3; k++)
                    tri.pos[k] = shapes[a][k], tri.dir[k] = dirs[d][k];
                mr_affine mats[3];
                for (int k = 0; k < 3; k++)
                    mats[k] = rnd_affine(&s, 1.0f);
                /* zero-area shapes: only robustness, no oracle (CHECK_LOOSE) */
                int flags = a >= 2 ? CHECK_LOOSE : CHECK_TIES;
                mr_dmm_patch p = set_patch(&set, 0, &tri, NULL);
                run_patch(bf, &p, &s, 40, flags, &cs);
                p = set_patch(&set, 0, &tri, mats);
                run_patch(bf, &p, &s, 40, flags, &cs);
            }
        print_cs("degenerate", level, &cs);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- displacements at the quantisation limits */

typedef enum { Q_ZERO, Q_MAX, Q_CHECKER, Q_HUGE, Q_HUGER, Q_TINY, Q_DENORMAL, Q_NARROW } q_kind;

static void quant_disp(q_kind kind, unsigned level, uint64_t *s, float *d)
{
    uint32_t vc = mr_umesh_vertex_count(level);
    for (uint32_t i = 0; i < 2 * vc; i++) {
        uint32_t a, b, tri = i / vc;
        mr_umesh_vertex_coords(level, i % vc, &a, &b);
        switch (kind) {
        case Q_ZERO: d[i] = 0; break;
        case Q_MAX: d[i] = tri ? 1.0f : 0.0f; break; /* triangle 1 all at 2^G - 1 */
        case Q_CHECKER: d[i] = ((a + b + tri) & 1) ? 1.0f : 0.0f; break;
        case Q_HUGE: d[i] = rndf(s, -1e15f, 1e15f); break;
        case Q_HUGER: d[i] = rndf(s, -1e30f, 1e30f); break;
        case Q_TINY: d[i] = rndf(s, 0, 1e-30f); break;
        case Q_DENORMAL: d[i] = (float)(rnd(s) % 64) * 1e-45f; break;
        default: d[i] = 1000.0f + rndf(s, 0, 1e-4f); break; /* range << bias */
        }
    }
}

static void test_quantisation_limits(void **state)
{
    (void)state;
    uint64_t s = 0xa4093822299f31d0ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const char *names[] = {"zero", "max", "checker", "huge", "huger", "tiny", "denormal",
                           "narrow"};
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * 2);
        assert_non_null(disp);
        for (int kind = Q_ZERO; kind <= Q_NARROW; kind++) {
            quant_disp((q_kind)kind, level, &s, disp);
            patch_set set;
            set_build(&set, level, 2, disp);
            if (kind == Q_MAX) {
                uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
                mr_dmm_default_bits(bits);
                for (uint32_t i = 0; i < vc; i++) {
                    assert_int_equal(set.values[i], 0);
                    assert_int_equal(set.values[vc + i], (1u << bits[0]) - 1u);
                }
            }
            check_stats cs = {0};
            for (uint32_t t = 0; t < 2; t++) {
                mr_umesh_tri tri = {{{0, 0, 0}, {1, 0, 0.2f}, {0.1f, 1, 0}},
                                    {{0, 0, 1}, {0.3f, 0, 0.95f}, {0, 0.6f, 0.8f}}};
                mr_affine mats[3];
                for (int k = 0; k < 3; k++)
                    mats[k] = rnd_affine(&s, 0.8f);
                /* huge displacements turn micro-triangles into needles */
                int flags = CHECK_TIES;
                if (kind != Q_HUGE && kind != Q_HUGER && kind != Q_CHECKER)
                    flags |= CHECK_FINE;
                mr_dmm_patch p = set_patch(&set, t, &tri, NULL);
                run_patch(bf, &p, &s, 60, flags, &cs);
                p = set_patch(&set, t, &tri, mats);
                run_patch(bf, &p, &s, 60, flags, &cs);
            }
            if (level == MR_UMESH_MAX_LEVEL)
                print_cs(names[kind], level, &cs);
            set_free(&set);
        }
        free(disp);
    }
    free(bf);
}

/* ---- grazing rays */

static void test_grazing(void **state)
{
    (void)state;
    uint64_t s = 0x082efa98ec4e6c89ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const float eps[] = {0.1f, 1e-3f, 1e-5f, 1e-7f, 0};
    const unsigned levels[] = {0, 3, 5};
    for (size_t li = 0; li < 3; li++) {
        unsigned level = levels[li];
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * 2);
        assert_non_null(disp);
        for (uint32_t i = 0; i < vc; i++)
            disp[i] = 0, disp[vc + i] = rndf(&s, -0.05f, 0.05f);
        patch_set set;
        set_build(&set, level, 2, disp);
        check_stats cs = {0};
        for (uint32_t t = 0; t < 2; t++)
            for (int mode = 0; mode < 2; mode++) {
                mr_umesh_tri tri = {{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}},
                                    {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}}};
                mr_affine m = rnd_affine(&s, 1.0f), mats[3] = {m, m, m}; /* rigid: flat */
                mr_dmm_patch p = set_patch(&set, t, &tri, mode ? mats : NULL);
                brute_init(bf, &p);
                mr_umesh_tri posed = mode ? skin_tri(&tri, mats) : tri;
                mr_vec3 e1 = mr_v3_sub(posed.pos[1], posed.pos[0]);
                mr_vec3 e2 = mr_v3_sub(posed.pos[2], posed.pos[0]);
                mr_vec3 n = mr_v3_normalize_or(mr_v3_cross(e1, e2), mr_v3(0, 0, 1));
                for (uint32_t i = 0; i < 300; i++) {
                    float w1 = (float)rnd01(&s), w2 = (float)rnd01(&s);
                    if (w1 + w2 > 1)
                        w1 = 1 - w1, w2 = 1 - w2;
                    mr_vec3 target = mr_v3_add(posed.pos[0], mr_v3_add(mr_v3_scale(e1, w1),
                                                                       mr_v3_scale(e2, w2)));
                    /* a tangent direction, tilted by eps towards the plane */
                    mr_vec3 tan = mr_v3_normalize_or(mr_v3_cross(n, rnd_unit(&s)), e1);
                    float e = eps[i % 5] * (i % 2 ? 1.0f : -1.0f);
                    mr_vec3 dir = mr_v3_add(mr_v3_scale(tan, cosf(e)), mr_v3_scale(n, -sinf(e)));
                    mr_vec3 org = mr_v3_sub(target, mr_v3_scale(dir, 3.0f));
                    check_ray(bf, &p, org, dir, 0, INFINITY, NULL, NULL, &cs, CHECK_TIES);
                }
                /* exactly in the plane z = 0 with zero z direction: the slab
                 * of a flat box is hit edge-on */
                if (!mode)
                    for (uint32_t i = 0; i < 50; i++) {
                        mr_vec3 org = mr_v3(rndf(&s, -1, 0), rndf(&s, 0, 1), 0);
                        mr_vec3 dir = mr_v3(1, rndf(&s, -1, 1), 0);
                        check_ray(bf, &p, org, dir, 0, INFINITY, NULL, NULL, &cs, CHECK_TIES);
                    }
            }
        print_cs("grazing", level, &cs);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- rays starting inside the bounds, inside the displaced shell, on the
 * surface */

static void test_origin_inside(void **state)
{
    (void)state;
    uint64_t s = 0x452821e638d01377ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const unsigned levels[] = {0, 1, 3, 5};
    for (size_t li = 0; li < 4; li++) {
        unsigned level = levels[li];
        uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
        float *disp = malloc(sizeof(float) * vc * 2);
        assert_non_null(disp);
        random_disp(&s, disp, vc * 2, -0.2f, 0.3f);
        patch_set set;
        set_build(&set, level, 2, disp);
        check_stats cs = {0};
        for (uint32_t t = 0; t < 2; t++)
            for (int mode = 0; mode < 2; mode++) {
                mr_umesh_tri tri = rnd_tri(&s);
                mr_affine mats[3];
                for (int k = 0; k < 3; k++)
                    mats[k] = rnd_affine(&s, 1.2f);
                mr_dmm_patch p = set_patch(&set, t, &tri, mode ? mats : NULL);
                brute_init(bf, &p);
                mr_vec3 lo, hi;
                assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
                float dmin = mr_dmm_value_to_float(set.enc, p.minv[0]);
                float dmax = mr_dmm_value_to_float(set.enc, p.maxv[0]);
                for (uint32_t i = 0; i < 300; i++) {
                    mr_vec3 org;
                    if (i % 3 == 0) { /* anywhere in the bounds */
                        org = mr_v3_add(lo, mr_v3_mul(mr_v3_sub(hi, lo), rnd_vec(&s, 0, 1)));
                    } else if (i % 3 == 1) { /* in the shell: a lattice point displaced
                                               * by d in [dmin, dmax] */
                        uint32_t b = rnd(&s) % (n + 1), a = rnd(&s) % (n + 1 - b);
                        float d = rndf(&s, dmin, dmax);
                        if (mode)
                            assert_int_equal(mr_umesh_eval_interpolated(&tri, p.mats, level, a,
                                                                        b, d, &org, NULL),
                                             MR_OK);
                        else
                            assert_int_equal(mr_umesh_eval(&tri, level, a, b, d, &org, NULL),
                                             MR_OK);
                    } else { /* on the surface: a micro-vertex */
                        org = bf->v[rnd(&s) % bf->nvert];
                    }
                    mr_vec3 dir = mr_v3_scale(rnd_unit(&s), rndf(&s, 0.5f, 2));
                    check_ray(bf, &p, org, dir, 0, INFINITY, NULL, NULL, &cs, CHECK_AIMED);
                    check_ray(bf, &p, org, dir, 1e-4f, INFINITY, NULL, NULL, &cs, CHECK_AIMED);
                }
            }
        print_cs("inside", level, &cs);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- two patches sharing an edge */

static bool v3_same_bits(mr_vec3 a, mr_vec3 b)
{
    return fbits(a.x) == fbits(b.x) && fbits(a.y) == fbits(b.y) && fbits(a.z) == fbits(b.z);
}

static void shared_edge_case(unsigned level, bool interpolated, uint64_t *s, brute *ba,
                             brute *bb, check_stats *cs)
{
    uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
    /* A = (p0, p1, p2), B = (p1, p0, p3): edge 0 of both, opposite ways */
    const mr_vec3 p0 = mr_v3(0.01f, -0.02f, 0.03f), p1 = mr_v3(1.03f, 0.02f, -0.01f);
    const mr_vec3 p2 = mr_v3(0.3f, 0.9f, 0.1f), p3 = mr_v3(0.6f, -0.9f, 0.3f);
    const mr_vec3 d0 = mr_v3(0.05f, -0.1f, 1), d1 = mr_v3(-0.1f, 0.05f, 0.98f);
    const mr_vec3 d2 = mr_v3(0, -0.2f, 1), d3 = mr_v3(0.05f, 0.25f, 0.96f);
    mr_umesh_tri ta = {{p0, p1, p2}, {d0, d1, d2}}, tb = {{p1, p0, p3}, {d1, d0, d3}};
    float *disp = malloc(sizeof(float) * 2 * vc), edge[33];
    assert_non_null(disp);
    /* small amplitude: the surface does not fold under rays within ~30
     * degrees of its normal (slopes stay below ~20 degrees at level 5) */
    for (uint32_t k = 0; k <= n; k++)
        edge[k] = rndf(s, -0.004f, 0.004f);
    for (uint32_t i = 0; i < vc; i++) {
        uint32_t a, b;
        mr_umesh_vertex_coords(level, i, &a, &b);
        disp[i] = b == 0 ? edge[a] : rndf(s, -0.004f, 0.004f);
        disp[vc + i] = b == 0 ? edge[n - a] : rndf(s, -0.004f, 0.004f);
    }
    patch_set set;
    set_build(&set, level, 2, disp);
    mr_affine m[4];
    for (int k = 0; k < 4; k++)
        m[k] = affine_trs(rnd_vec(s, -0.2f, 0.2f), rnd_unit(s), rndf(s, -0.25f, 0.25f),
                          rnd_vec(s, 0.9f, 1.1f));
    const mr_affine ma[3] = {m[0], m[1], m[2]}, mb[3] = {m[1], m[0], m[3]};
    mr_dmm_patch pa = set_patch(&set, 0, &ta, interpolated ? ma : NULL);
    mr_dmm_patch pb = set_patch(&set, 1, &tb, interpolated ? mb : NULL);
    brute_init(ba, &pa);
    brute_init(bb, &pb);
    bounds_case(&pa);
    bounds_case(&pb);
    /* precondition: the shared edge's micro-vertices are bit-identical */
    mr_vec3 ev[33];
    for (uint32_t k = 0; k <= n; k++) {
        ev[k] = mr_dmm_vertex(&pa, k, 0);
        assert_true(v3_same_bits(ev[k], mr_dmm_vertex(&pb, n - k, 0)));
    }
    mr_vec3 nrm = mr_v3_normalize_or(
        mr_v3_cross(mr_v3_sub(ev[n], ev[0]), mr_v3_sub(mr_dmm_vertex(&pa, 0, n), ev[0])),
        mr_v3(0, 0, 1));
    mr_vec3 along = mr_v3_normalize_or(mr_v3_sub(ev[n], ev[0]), mr_v3(1, 0, 0));
    mr_vec3 side = mr_v3_cross(nrm, along);
    const float dist[] = {2.0f, 1e3f, 1e5f};
    const float frac[] = {0, 0.5f, 1.0f / 3, 1e-3f, 1 - 1e-3f};
    uint64_t leaks = 0, required = 0;
    for (uint32_t k = 0; k <= n; k++)
        for (size_t fi = 0; fi < 5; fi++) {
            if (k == n && fi > 0)
                break;
            mr_vec3 target = fi == 0 ? ev[k] : mr_v3_lerp(ev[k], ev[k + 1], frac[fi]);
            float dc = fminf(mr_v3_len(mr_v3_sub(target, ev[0])),
                             mr_v3_len(mr_v3_sub(target, ev[n])));
            for (int di = 0; di < 6; di++)
                for (size_t oi = 0; oi < 3; oi++) {
                    /* from above and below along the normal, and tilted up to
                     * 25 degrees towards either side or along the edge */
                    float tilt = di < 2 ? 0 : rndf(s, -25, 25) * DEG;
                    mr_vec3 lateral = di % 3 == 0 ? along : side;
                    mr_vec3 u = mr_v3_add(mr_v3_scale(nrm, cosf(tilt)),
                                          mr_v3_scale(lateral, sinf(tilt)));
                    if (di % 2)
                        u = mr_v3_scale(u, -1);
                    mr_vec3 org = mr_v3_add(target, mr_v3_scale(u, dist[oi]));
                    mr_vec3 dir = mr_v3_sub(target, org);
                    bool ha =
                        check_ray(ba, &pa, org, dir, 0, INFINITY, NULL, NULL, cs, CHECK_AIMED);
                    bool hb =
                        check_ray(bb, &pb, org, dir, 0, INFINITY, NULL, NULL, cs, CHECK_AIMED);
                    /* the union is a disk around every point of the open
                     * edge: demand a hit where the float direction (off by
                     * ~2^-24 of the origin's distance) cannot take the ray
                     * past the patch corners' wedges */
                    if (dc > 16.0f * FLT_EPSILON * dist[oi] + 1e-6f) {
                        required++;
                        if (!(ha || hb)) {
                            leaks++;
                            print_error("leak: level %u %s, edge step %u + %g, origin at %g\n",
                                        level, interpolated ? "interpolated" : "base", k,
                                        (double)frac[fi], (double)dist[oi]);
                            print_ray(org, dir, 0, INFINITY);
                        }
                    }
                }
        }
    /* rays running along the edge, slightly above or below it */
    for (int i = 0; i < 40; i++) {
        float h = rndf(s, -0.01f, 0.01f);
        mr_vec3 org = mr_v3_add(mr_v3_sub(ev[0], mr_v3_scale(along, 0.5f)), mr_v3_scale(nrm, h));
        mr_vec3 dir = mr_v3_add(along, mr_v3_scale(side, rndf(s, -1e-3f, 1e-3f)));
        check_ray(ba, &pa, org, dir, 0, INFINITY, NULL, NULL, cs, CHECK_TIES);
        check_ray(bb, &pb, org, dir, 0, INFINITY, NULL, NULL, cs, CHECK_TIES);
    }
    if (leaks)
        fail_msg("%llu of %llu rays at the shared edge leaked (level %u, %s)",
                 (unsigned long long)leaks, (unsigned long long)required, level,
                 interpolated ? "interpolated" : "base");
    assert_true(required > 0);
    set_free(&set);
    free(disp);
}

static void test_shared_edge(void **state)
{
    (void)state;
    uint64_t s = 0xbe5466cf34e90c6cull;
    brute *ba = malloc(sizeof *ba), *bb = malloc(sizeof *bb);
    assert_true(ba && bb);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++)
        for (int mode = 0; mode < 2; mode++) {
            check_stats cs = {0};
            for (int rep = 0; rep < 2; rep++)
                shared_edge_case(level, mode != 0, &s, ba, bb, &cs);
            print_cs(mode ? "shared edge interpolated" : "shared edge base", level, &cs);
        }
    free(ba);
    free(bb);
}

/* ---- a ray at every micro-vertex */

static void vertex_rays(unsigned level, bool interpolated, uint64_t *s, brute *bf)
{
    uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
    float *disp = malloc(sizeof(float) * vc);
    assert_non_null(disp);
    random_disp(s, disp, vc, -0.004f, 0.004f);
    patch_set set;
    set_build(&set, level, 1, disp);
    /* nearly horizontal, directions near +z, mild deformation: the surface
     * is a height field over the xy plane and has no folds */
    mr_umesh_tri tri = {{{0, 0, 0}, {1, 0, 0.1f}, {0.1f, 1, -0.1f}},
                        {{0.1f, 0, 1}, {0, -0.15f, 1}, {-0.1f, 0.1f, 1}}};
    mr_affine mats[3];
    for (int k = 0; k < 3; k++)
        mats[k] = affine_trs(rnd_vec(s, -1, 1), rnd_unit(s), rndf(s, -0.3f, 0.3f),
                             rnd_vec(s, 0.85f, 1.15f));
    mr_dmm_patch p = set_patch(&set, 0, &tri, interpolated ? mats : NULL);
    brute_init(bf, &p);
    bounds_case(&p);
    check_stats cs = {0};
    double worst = 0;
    for (uint32_t b = 0; b <= n; b++)
        for (uint32_t a = 0; a + b <= n; a++) {
            mr_vec3 v = mr_dmm_vertex(&p, a, b);
            bool interior = a > 0 && b > 0 && a + b < n;
            /* axis-parallel from above and below: zero shear, the ray passes
             * through the vertex exactly, so even boundary vertices hit */
            for (int side = 0; side < 2; side++) {
                float zo = side ? v.z + 1.5f : v.z - 1.5f;
                mr_vec3 org = mr_v3(v.x, v.y, zo), dir = mr_v3(0, 0, side ? -1.0f : 1.0f);
                mr_dmm_hit h;
                if (!check_ray(bf, &p, org, dir, 0, INFINITY, &h, NULL, &cs, CHECK_AIMED)) {
                    print_error("axis-parallel ray missed micro-vertex (%u, %u)\n", a, b);
                    fail();
                }
                double expect = fabs((double)zo - (double)v.z);
                if (fabs(h.t - expect) > 4 * FLT_EPSILON * expect) {
                    print_error("vertex (%u, %u): t %a, expected %a\n", a, b, (double)h.t,
                                expect);
                    fail();
                }
            }
            /* oblique from above, unit distance: t = 1 at the vertex */
            mr_vec3 up = mr_v3_normalize_or(mr_v3(rndf(s, -0.4f, 0.4f), rndf(s, -0.4f, 0.4f), 1),
                                            mr_v3(0, 0, 1));
            mr_vec3 org = mr_v3_add(v, up), dir = mr_v3_sub(v, org);
            mr_dmm_hit h;
            bool hit = check_ray(bf, &p, org, dir, 0, INFINITY, &h, NULL, &cs, CHECK_AIMED);
            if (interior && !hit) {
                print_error("ray missed interior micro-vertex (%u, %u)\n", a, b);
                fail();
            }
            if (hit) {
                worst = fmax(worst, fabs(h.t - 1.0));
                if (fabs(h.t - 1.0) > 1e-5) {
                    print_error("vertex (%u, %u): t %.9g, expected 1\n", a, b, (double)h.t);
                    fail();
                }
            }
        }
    printf("  vertex rays level %u %s: %llu/%llu hit, worst |t - 1| %.2g\n", level,
           interpolated ? "interpolated" : "base", (unsigned long long)cs.hits,
           (unsigned long long)cs.rays, worst);
    set_free(&set);
    free(disp);
}

static void test_vertex_rays(void **state)
{
    (void)state;
    uint64_t s = 0xc0ac29b7c97c50ddull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const unsigned levels[] = {0, 3, 5};
    for (size_t li = 0; li < 3; li++)
        for (int mode = 0; mode < 2; mode++)
            for (int rep = 0; rep < 2; rep++)
                vertex_rays(levels[li], mode != 0, &s, bf);
    free(bf);
}

/* ---- axis-parallel rays through random patches */

static void test_axis_parallel(void **state)
{
    (void)state;
    uint64_t s = 0x3f84d5b5b5470917ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * 2);
        assert_non_null(disp);
        random_disp(&s, disp, vc * 2, -0.3f, 0.3f);
        patch_set set;
        set_build(&set, level, 2, disp);
        check_stats cs = {0};
        for (uint32_t t = 0; t < 2; t++)
            for (int mode = 0; mode < 2; mode++) {
                mr_umesh_tri tri = rnd_tri(&s);
                mr_affine mats[3];
                for (int k = 0; k < 3; k++)
                    mats[k] = rnd_affine(&s, 1.5f);
                mr_dmm_patch p = set_patch(&set, t, &tri, mode ? mats : NULL);
                brute_init(bf, &p);
                mr_vec3 lo, hi;
                assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
                for (uint32_t i = 0; i < 300; i++) {
                    mr_vec3 target = i % 2 ? rnd_surface_point(bf, &s) : bf->v[rnd(&s) % bf->nvert];
                    float d[3] = {0, 0, 0};
                    int k = (int)(rnd(&s) % 3);
                    d[k] = rnd(&s) % 2 ? 2.0f : -0.5f;
                    if (i % 3 == 1)
                        d[(k + 1) % 3] = rndf(&s, -1, 1);
                    mr_vec3 dir = mr_v3(d[0], d[1], d[2]);
                    mr_vec3 org = mr_v3_sub(target, mr_v3_scale(dir, 4.0f));
                    if (i % 5 == 0) {
                        /* origin exactly on a face plane of the bounds along
                         * a parallel axis */
                        int z = d[(k + 2) % 3] == 0 ? (k + 2) % 3 : (k + 1) % 3;
                        float *o = z == 0 ? &org.x : z == 1 ? &org.y : &org.z;
                        *o = comp(rnd(&s) % 2 ? lo : hi, z);
                    }
                    check_ray(bf, &p, org, dir, 0, INFINITY, NULL, NULL, &cs, CHECK_AIMED);
                }
            }
        print_cs("axis-parallel", level, &cs);
        assert_true(cs.hits > cs.rays / 3);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- rays from far away */

static void test_far_origin(void **state)
{
    (void)state;
    uint64_t s = 0x9216d5d98979fb1bull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    const float dist[] = {1e2f, 1e3f, 1e4f, 1e5f};
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level);
        float *disp = malloc(sizeof(float) * vc * 2);
        assert_non_null(disp);
        random_disp(&s, disp, vc * 2, -0.2f, 0.3f);
        patch_set set;
        set_build(&set, level, 2, disp);
        check_stats cs = {0};
        for (uint32_t t = 0; t < 2; t++)
            for (int mode = 0; mode < 2; mode++) {
                mr_umesh_tri tri = rnd_tri(&s);
                mr_affine mats[3];
                for (int k = 0; k < 3; k++)
                    mats[k] = rnd_affine(&s, 1.0f);
                mr_dmm_patch p = set_patch(&set, t, &tri, mode ? mats : NULL);
                brute_init(bf, &p);
                for (uint32_t i = 0; i < 300; i++) {
                    mr_vec3 target = i % 2 ? rnd_surface_point(bf, &s) : bf->v[rnd(&s) % bf->nvert];
                    mr_vec3 org = mr_v3_add(target, mr_v3_scale(rnd_unit(&s), dist[i % 4]));
                    check_ray(bf, &p, org, mr_v3_sub(target, org), 0, INFINITY, NULL, NULL, &cs,
                              CHECK_TIES);
                }
            }
        print_cs("far origin", level, &cs);
        set_free(&set);
        free(disp);
    }
    free(bf);
}

/* ---- overflowing geometry is refused by the bounds, not traced into NaN */

static void test_non_finite(void **state)
{
    (void)state;
    float disp[3] = {-3e38f, 3e38f, 0};
    patch_set set;
    set_build(&set, 0, 1, disp);
    mr_umesh_tri tri = {{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}}, {{0, 0, 10}, {0, 0, 10}, {0, 0, 10}}};
    mr_dmm_patch p = set_patch(&set, 0, &tri, NULL);
    mr_vec3 lo, hi;
    /* d * |dir| = 3e39 overflows float: the patch has no finite box and
     * the caller (the BVH build) must drop it */
    assert_false(mr_dmm_patch_bounds(&p, &lo, &hi));
    set_free(&set);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_bends),
        cmocka_unit_test(test_degenerate_base),
        cmocka_unit_test(test_quantisation_limits),
        cmocka_unit_test(test_grazing),
        cmocka_unit_test(test_origin_inside),
        cmocka_unit_test(test_shared_edge),
        cmocka_unit_test(test_vertex_rays),
        cmocka_unit_test(test_axis_parallel),
        cmocka_unit_test(test_far_origin),
        cmocka_unit_test(test_non_finite),
    };
    return cmocka_run_group_tests_name("dmm_hard", tests, NULL, NULL);
}
