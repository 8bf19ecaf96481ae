/*
 * dmm_patch_fixture.h - the harness shared by the DMM traversal tests
 * (tests/unit/test_dmm_trace.c, tests/hard/test_dmm_hard.c): deterministic
 * random numbers, patch sets (displacements encoded, decoded and their
 * pyramids allocated with exactly the traversal's prefix, so AddressSanitizer
 * catches a read past it), the brute force over every micro-triangle of the
 * tessellation (mr_dmm_vertex + the same watertight test), check_ray (the
 * traversal against the brute force: hit/miss exactly, t bit for bit under
 * STRICT_T, hit fields sane) and the bounds check. Header-only, included
 * once per test program after cmocka.h; functions are static inline so a
 * program that uses only some of them compiles without warnings.
 */
#ifndef MR_TEST_DMM_PATCH_FIXTURE_H
#define MR_TEST_DMM_PATCH_FIXTURE_H

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_trace.h"
#include "kinds/dmm/micromesh.h"
#include "math/watertight.h"

#define MAX_VERTS 561u  /* mr_umesh_vertex_count(5) */
#define MAX_TRIS 1024u  /* mr_umesh_triangle_count(5) */
#ifndef STRICT_T
#define STRICT_T 1
#endif

#include "rng_fixture.h"

static inline uint32_t fbits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

static inline bool v3_finite(mr_vec3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

static inline float comp(mr_vec3 v, int k) { return k == 0 ? v.x : k == 1 ? v.y : v.z; }


/* ---- affine matrices (row-major 3x4, mr_math.h) */

static inline mr_affine affine_of(const mr_mat4 *m)
{
    mr_affine a;
    memcpy(a.m, m->m, sizeof a.m);
    return a;
}

/* Translation * rotation * (non-uniform) scale. */
static inline mr_affine affine_trs(mr_vec3 t, mr_vec3 axis, float angle, mr_vec3 s)
{
    mr_quat q = mr_quat_from_axis_angle(mr_v3_normalize_or(axis, mr_v3(0, 0, 1)), angle);
    mr_mat4 m = mr_mat4_from_trs(t, q, s);
    return affine_of(&m);
}

static inline mr_affine rnd_affine(uint64_t *s, float max_angle)
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
static inline void set_build(patch_set *s, unsigned level, uint32_t count, const float *disp)
{
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    mr_error err = {0};
    memset(s, 0, sizeof *s);
    s->level = level;
    s->count = count;
    int rc = mr_dmm_encode(level, bits, count, NULL, disp, &s->enc, NULL, &err);
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

static inline void set_free(patch_set *s)
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
static inline mr_dmm_patch set_patch(const patch_set *s, uint32_t t, const mr_umesh_tri *tri,
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

static inline void brute_init(brute *bf, const mr_dmm_patch *p)
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

static inline bool brute_tri(const brute *bf, const mr_wtd_ray *r, uint32_t k, float tmin, float tmax,
                      mr_wt_hit *h)
{
    const uint32_t *i = bf->idx + 3 * k;
    return mr_wtd_intersect(r, bf->v[i[0]], bf->v[i[1]], bf->v[i[2]], tmin, tmax, h);
}

/* Closest hit over every micro-triangle; *tri gets the first one at that t.
 * Every micro-triangle's verdict is kept in bf->hits, bf->t. */
static inline bool brute_hit(brute *bf, const mr_wtd_ray *r, float tmin, float tmax, float *t,
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
static inline void lattice_bary(const brute *bf, uint32_t k, double x, double y, double w[3])
{
    const uint32_t *i = bf->idx + 3 * k;
    double ax = bf->a[i[0]], ay = bf->b[i[0]], bx = bf->a[i[1]], by = bf->b[i[1]];
    double cx = bf->a[i[2]], cy = bf->b[i[2]];
    double det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
    w[1] = ((x - ax) * (cy - ay) - (cx - ax) * (y - ay)) / det;
    w[2] = ((bx - ax) * (y - ay) - (x - ax) * (by - ay)) / det;
    w[0] = 1.0 - w[1] - w[2];
}

static inline mr_vec3 tri_normal(const brute *bf, uint32_t k)
{
    const uint32_t *i = bf->idx + 3 * k;
    return mr_v3_cross(mr_v3_sub(bf->v[i[1]], bf->v[i[0]]), mr_v3_sub(bf->v[i[2]], bf->v[i[0]]));
}

/* Whether micro-triangle k has watertight t = t exactly: with its vertices
 * in the tessellation's order, or (rotated) started at another corner of
 * the same winding. Rotation keeps the edge functions (the same floats, so
 * the same hit/miss) but sums det and the scaled t in another order. */
static inline bool tri_has_t(const brute *bf, const mr_wtd_ray *r, uint32_t k, float tmin, float tmax,
                      float t, bool rotated)
{
    const uint32_t *i = bf->idx + 3 * k;
    for (int s = rotated ? 1 : 0; s < (rotated ? 3 : 1); s++) {
        mr_wt_hit h;
        if (mr_wtd_intersect(r, bf->v[i[s]], bf->v[i[(s + 1) % 3]], bf->v[i[(s + 2) % 3]], tmin,
                            tmax, &h) &&
            fbits(h.t) == fbits(t))
            return true;
    }
    return false;
}

/* Some micro-triangle's t, in tessellation order (0), only rotated (1), or
 * no micro-triangle's (-1); r is the ray of the last brute_hit. */
static inline int source_of(const brute *bf, const mr_wtd_ray *r, float tmin, float tmax, float t)
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
    double worst_t_ulps; /* largest t above the brute force's closest, in ulps */
    uint64_t mismatches; /* rays the check failed on (it stops at the first) */
    uint64_t nonfinite;  /* hits with a non-finite field (t, u, v, ng) */
    uint64_t vertices, outside; /* micro-vertices checked against the bounds, outside */
} check_stats;

/* Sums b's counts into a, keeps the worst of the worst figures. */
static inline void check_stats_add(check_stats *a, const check_stats *b)
{
    a->rays += b->rays;
    a->hits += b->hits;
    a->rotated += b->rotated;
    a->tied += b->tied;
    a->worst_uv = fmax(a->worst_uv, b->worst_uv);
    a->worst_ng = fmax(a->worst_ng, b->worst_ng);
    a->worst_t_ulps = fmax(a->worst_t_ulps, b->worst_t_ulps);
    a->mismatches += b->mismatches;
    a->nonfinite += b->nonfinite;
    a->vertices += b->vertices;
    a->outside += b->outside;
}

/* How many floats lie above b up to a (negative: below). */
static inline int64_t ulps_between(float b, float a)
{
    uint32_t ua = fbits(a), ub = fbits(b);
    int64_t oa = ua >> 31 ? -(int64_t)(ua & 0x7fffffffu) : (int64_t)ua;
    int64_t ob = ub >> 31 ? -(int64_t)(ub & 0x7fffffffu) : (int64_t)ub;
    return oa - ob;
}

/* check_ray flags */
enum {
    CHECK_FINE = 1, /* (u, v) in the micro-triangle hit, ng parallel to its normal */
    CHECK_TIES = 2, /* accept t a few ulps above the closest (see check_ray) */
    CHECK_LOOSE = 4, /* zero-area micro-triangles: no brute-force agreement (see check_ray) */
    CHECK_AIMED = CHECK_TIES | CHECK_FINE, /* rays aimed exactly at vertices and edges */
};

static inline void print_ray(mr_vec3 org, mr_vec3 dir, float tmin, float tmax)
{
    print_error("ray org (%a, %a, %a) dir (%a, %a, %a) tmin %a tmax %a\n", (double)org.x,
                (double)org.y, (double)org.z, (double)dir.x, (double)dir.y, (double)dir.z,
                (double)tmin, (double)tmax);
}

static inline float ulps_up(float t, int n)
{
    for (int i = 0; i < n; i++)
        t = nextafterf(t, INFINITY);
    return t;
}

static inline void fail_ray(const char *what, const mr_dmm_patch *p, mr_vec3 org, mr_vec3 dir,
                     float tmin, float tmax, check_stats *cs)
{
    if (cs)
        cs->mismatches++;
    print_error("level %u %s: %s\n", p->level, p->mats[0] ? "interpolated" : "base", what);
    print_ray(org, dir, tmin, tmax);
    fail();
}

static inline bool hit_finite(const mr_dmm_hit *h)
{
    return isfinite(h->t) && isfinite(h->u) && isfinite(h->v) && v3_finite(h->ng);
}

/* (u, v) in some micro-triangle hit at (practically) t, ng parallel to its
 * normal; mr_dmm_locate names that micro-triangle or, on its boundary, a
 * neighbour. Several candidates at an edge or a vertex. */
static inline void check_fine(const brute *bf, const mr_dmm_patch *p, const mr_dmm_ray *r,
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
                 tmax, cs);
    }
    uint32_t la[3], lb[3];
    mr_dmm_locate(p->level, p->decimate, h->u, h->v, la, lb);
    const uint32_t *ti = bf->idx + 3 * best;
    int same = 0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            same += la[i] == bf->a[ti[j]] && lb[i] == bf->b[ti[j]];
    double w[3];
    lattice_bary(bf, best, x, y, w);
    if (!(same == 3 || fmin(w[0], fmin(w[1], w[2])) < 1e-3))
        fail_ray("mr_dmm_locate names another micro-triangle", p, r->org, r->dir, tmin, tmax, cs);
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
static inline bool check_ray(brute *bf, const mr_dmm_patch *p, mr_vec3 org, mr_vec3 dir,
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
    bool hit = mr_dmm_intersect(p, &r, tmin, &tm, true, false, &h, st);
    bool loose = (flags & CHECK_LOOSE) != 0;
    char msg[200];
    if (cs) {
        cs->rays++;
        cs->hits += hit;
    }
    if (hit != bhit && !loose) {
        snprintf(msg, sizeof msg, "traversal %s t=%a, brute force %s t=%a (micro-triangle %u)",
                 hit ? "hit" : "miss", (double)h.t, bhit ? "hit" : "miss", (double)bt, btri);
        fail_ray(msg, p, org, dir, tmin, tmax, cs);
    }
    if (!hit) {
        assert_true(fbits(tm) == fbits(tmax)); /* untouched on a miss */
    } else {
        if (!hit_finite(&h)) {
            if (cs)
                cs->nonfinite++;
            snprintf(msg, sizeof msg, "non-finite hit t=%g u=%g v=%g ng=(%g, %g, %g)",
                     (double)h.t, (double)h.u, (double)h.v, (double)h.ng.x, (double)h.ng.y,
                     (double)h.ng.z);
            fail_ray(msg, p, org, dir, tmin, tmax, cs);
        }
        if (!(h.t >= tmin && h.t <= tmax)) {
            snprintf(msg, sizeof msg, "hit t=%a outside [tmin, tmax]", (double)h.t);
            fail_ray(msg, p, org, dir, tmin, tmax, cs);
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
        if (cs && !loose)
            cs->worst_t_ulps = fmax(cs->worst_t_ulps, (double)ulps_between(bt, h.t));
        if (src < 0 || (src == 1 && STRICT_T) ||
            (!loose && !(h.t >= bottom && h.t <= top))) {
            snprintf(msg, sizeof msg, "traversal t=%a, brute force t=%a (micro-triangle %u)%s",
                     (double)h.t, (double)bt, btri,
                     src == 1 ? ": the traversal's t is a micro-triangle's t with its vertices "
                                "rotated (winding started at another corner)"
                     : src < 0 ? ": no micro-triangle has that t"
                               : "");
            fail_ray(msg, p, org, dir, tmin, tmax, cs);
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
    bool any = mr_dmm_intersect(p, &r, tmin, &ta, true, true, &ah, NULL);
    if (any != bhit && !loose) {
        snprintf(msg, sizeof msg, "any-hit %s, brute force %s", any ? "hit" : "miss",
                 bhit ? "hit" : "miss");
        fail_ray(msg, p, org, dir, tmin, tmax, cs);
    }
    if (any) {
        if (!(hit_finite(&ah) && fbits(ta) == fbits(ah.t) && ta >= tmin && ta <= tmax)) {
            if (cs && !hit_finite(&ah))
                cs->nonfinite++;
            snprintf(msg, sizeof msg, "any-hit t=%a u=%g v=%g: not finite or outside the "
                     "interval", (double)ah.t, (double)ah.u, (double)ah.v);
            fail_ray(msg, p, org, dir, tmin, tmax, cs);
        }
        int src = source_of(bf, &r.wt, tmin, tmax, ta);
        if (src < 0 || (src == 1 && STRICT_T)) {
            snprintf(msg, sizeof msg, "any-hit t=%a is %s", (double)ta,
                     src < 0 ? "no micro-triangle's t"
                             : "a micro-triangle's t only with its vertices rotated");
            fail_ray(msg, p, org, dir, tmin, tmax, cs);
        }
    }
    return hit;
}

/* Point at barycentrics (w1, w2) of a random micro-triangle of the
 * tessellation. */
static inline mr_vec3 rnd_surface_point(const brute *bf, uint64_t *s)
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
static inline void rnd_ray(const brute *bf, mr_vec3 lo, mr_vec3 hi, uint64_t *s, uint32_t i,
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

static inline void random_disp(uint64_t *s, float *d, uint32_t n, float lo, float hi)
{
    for (uint32_t i = 0; i < n; i++)
        d[i] = rndf(s, lo, hi);
}

static inline mr_umesh_tri rnd_tri(uint64_t *s)
{
    mr_umesh_tri t;
    for (int k = 0; k < 3; k++) {
        t.pos[k] = rnd_vec(s, -2, 2);
        t.dir[k] = mr_v3_scale(rnd_unit(s), rndf(s, 0.3f, 1.5f));
    }
    return t;
}

static inline bool inside(mr_vec3 v, mr_vec3 lo, mr_vec3 hi)
{
    return v.x >= lo.x && v.y >= lo.y && v.z >= lo.z && v.x <= hi.x && v.y <= hi.y &&
           v.z <= hi.z;
}

/* ---- bounds contain every micro-vertex (counted into cs, if given) */

static inline void bounds_case(const mr_dmm_patch *p, check_stats *cs)
{
    mr_vec3 lo, hi;
    assert_true(mr_dmm_patch_bounds(p, &lo, &hi));
    uint32_t n = mr_umesh_segments(p->level);
    for (uint32_t b = 0; b <= n; b++)
        for (uint32_t a = 0; a + b <= n; a++) {
            mr_vec3 v = mr_dmm_vertex(p, a, b);
            if (cs)
                cs->vertices++;
            if (!inside(v, lo, hi)) {
                if (cs)
                    cs->outside++;
                print_error("level %u vertex (%u, %u) = (%a, %a, %a) outside (%a %a %a)-(%a %a "
                            "%a)\n",
                            p->level, a, b, (double)v.x, (double)v.y, (double)v.z,
                            (double)lo.x, (double)lo.y, (double)lo.z, (double)hi.x,
                            (double)hi.y, (double)hi.z);
                fail();
            }
        }
}

#endif
