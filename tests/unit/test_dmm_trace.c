/*
 * test_dmm_trace.c - tessellation-free traversal of displaced micro-mesh
 * patches (core/kinds/dmm/dmm_trace.h; paper 000, Algorithms 1-4, eq. 5-13).
 *
 * The oracle is the tessellation itself: every micro-triangle of the patch
 * (mr_umesh_triangles order, vertices from mr_dmm_vertex) tested with the
 * same watertight test (mr_wtd_intersect), keeping the closest t. The
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
 * (tests/hard/test_dmm_hard.c; the harness is tests/support/dmm_patch_fixture.h) are documented
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

#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_trace.h"
#include "kinds/dmm/micromesh.h"
#include "math/watertight.h"

#include "../support/dmm_patch_fixture.h"

static float vmaxabs(mr_vec3 v) { return fmaxf(fabsf(v.x), fmaxf(fabsf(v.y), fabsf(v.z))); }


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

/* ---- 1b. traversal == the exact reference's per-triangle test (issue 17)
 *
 * mr_dmm_intersect_micro is what the dmm kind's watertight reference runs
 * per base triangle: every surviving micro-triangle of the tessellation,
 * same test, same vertex order, ties at equal t to the first in row order.
 * The traversal must return the same hit bit for bit (t, u, v, ng), also
 * for rays exactly through micro-vertices and micro-edge midpoints (where
 * several micro-triangles share the closest t), for decimated edges, for a
 * camera 1000 times the patch's size away (the double-precision test keeps
 * the boxes' pad ahead of its rounding) and when the hit lands exactly on
 * the incoming tmax (take_tmax decides who keeps it). No tolerance. */

static void same_hit(const char *what, bool a, const mr_dmm_hit *ha, float ta, bool b,
                     const mr_dmm_hit *hb, float tb)
{
    if (a != b || fbits(ta) != fbits(tb) ||
        (a && (fbits(ha->t) != fbits(hb->t) || fbits(ha->u) != fbits(hb->u) ||
               fbits(ha->v) != fbits(hb->v) || fbits(ha->ng.x) != fbits(hb->ng.x) ||
               fbits(ha->ng.y) != fbits(hb->ng.y) || fbits(ha->ng.z) != fbits(hb->ng.z))))
        fail_msg("%s: traversal %s t=%a u=%a v=%a, per-triangle %s t=%a u=%a v=%a", what,
                 a ? "hit" : "miss", (double)ha->t, (double)ha->u, (double)ha->v,
                 b ? "hit" : "miss", (double)hb->t, (double)hb->u, (double)hb->v);
}

/* The same rays through the patch as packets of up to 8
 * (mr_dmm_intersect_packet: what Embree's packets of primary rays get),
 * against each ray alone, bit for bit: closest hits from tmax = infinity,
 * then from each hit's own t as the incoming tmax with take_tmax
 * alternating by lane. */
static void packet_check(const mr_dmm_patch *p, const mr_dmm_ray *r, int n)
{
    float tmin[8] = {0}, t[8], *tmax[8];
    bool take[8];
    mr_dmm_hit h[8];
    const mr_dmm_ray *rp[8];
    for (int k = 0; k < n; k++)
        rp[k] = &r[k];
    for (int pass = 0; pass < 2; pass++) {
        float alone_t[8];
        mr_dmm_hit alone_h[8];
        bool alone[8];
        for (int k = 0; k < n; k++) {
            float t0 = INFINITY;
            mr_dmm_hit h0 = {0};
            if (pass == 1) /* the ray's closest hit (if any), now its incoming tmax */
                mr_dmm_intersect(p, &r[k], 0, &t0, true, false, &h0, NULL);
            take[k] = pass == 0 || k % 2;
            t[k] = alone_t[k] = t0;
            tmax[k] = &t[k];
            memset(&alone_h[k], 0, sizeof alone_h[k]);
            memset(&h[k], 0, sizeof h[k]);
            alone[k] = mr_dmm_intersect(p, &r[k], 0, &alone_t[k], take[k], false, &alone_h[k],
                                        NULL);
        }
        uint32_t m = mr_dmm_intersect_packet(p, n, rp, tmin, tmax, take, false, h, NULL);
        for (int k = 0; k < n; k++)
            same_hit(pass ? "packet, at tmax" : "packet", (m >> k & 1u) != 0, &h[k], t[k],
                     alone[k], &alone_h[k], alone_t[k]);
    }
    /* any hit (shadow rays): the same verdict as alone */
    for (int k = 0; k < n; k++) {
        t[k] = INFINITY;
        tmax[k] = &t[k];
        take[k] = true;
    }
    uint32_t m = mr_dmm_intersect_packet(p, n, rp, tmin, tmax, take, true, NULL, NULL);
    for (int k = 0; k < n; k++) {
        float ta = INFINITY;
        assert_int_equal((m >> k & 1u) != 0,
                         mr_dmm_intersect(p, &r[k], 0, &ta, true, true, NULL, NULL));
    }
}

static void test_traversal_equals_micro(void **state)
{
    (void)state;
    uint64_t s = 0x2545f4914f6cdd1dull;
    enum { PATCHES = 3, RAYS = 160 };
    uint64_t rays = 0, hits = 0, ties = 0, packets = 0;
    float *verts = malloc(sizeof(float) * 3 * MAX_VERTS);
    uint32_t *tris = malloc(sizeof(uint32_t) * 3 * MAX_TRIS);
    assert_true(verts && tris);
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level), n = mr_umesh_segments(level);
        float *disp = malloc(sizeof(float) * vc * PATCHES);
        assert_non_null(disp);
        random_disp(&s, disp, vc * PATCHES, -0.3f, 0.5f);
        patch_set set;
        set_build(&set, level, PATCHES, disp);
        for (uint32_t t = 0; t < PATCHES * 2; t++) {
            bool interpolated = t % 2;
            mr_umesh_tri tri = rnd_tri(&s);
            mr_affine mats[3];
            for (int k = 0; k < 3; k++)
                mats[k] = rnd_affine(&s, 1.6f);
            mr_dmm_patch p = set_patch(&set, t / 2, &tri, interpolated ? mats : NULL);
            p.decimate = level ? (unsigned)(rnd(&s) % 8) : 0;
            uint32_t count = mr_umesh_triangles(level, p.decimate, tris);
            for (uint32_t b = 0; b <= n; b++)
                for (uint32_t a = 0; a + b <= n; a++) {
                    mr_vec3 v = mr_dmm_vertex(&p, a, b);
                    float *o = verts + 3 * (size_t)mr_umesh_vertex_index(level, a, b);
                    o[0] = v.x, o[1] = v.y, o[2] = v.z;
                }
            mr_vec3 lo, hi;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            mr_vec3 c = mr_v3_scale(mr_v3_add(lo, hi), 0.5f);
            float size = mr_v3_len(mr_v3_sub(hi, lo)) + 1e-3f;
            mr_dmm_ray pack[8];
            int packed = 0;
            for (uint32_t i = 0; i < RAYS; i++) {
                /* aimed at a micro-vertex (i % 3 == 0), the midpoint of a
                 * micro-edge (1) or a random point of a micro-triangle */
                const uint32_t *k = tris + 3 * (size_t)(rnd(&s) % count);
                mr_vec3 x[3];
                for (int j = 0; j < 3; j++)
                    x[j] = mr_v3(verts[3 * k[j]], verts[3 * k[j] + 1], verts[3 * k[j] + 2]);
                mr_vec3 target = x[0];
                if (i % 3 == 1)
                    target = mr_v3_scale(mr_v3_add(x[0], x[1]), 0.5f);
                else if (i % 3 == 2) {
                    float w1 = (float)rnd01(&s), w2 = (float)rnd01(&s);
                    if (w1 + w2 > 1)
                        w1 = 1 - w1, w2 = 1 - w2;
                    target = mr_v3_add(mr_v3_scale(x[0], 1 - w1 - w2),
                                       mr_v3_add(mr_v3_scale(x[1], w1), mr_v3_scale(x[2], w2)));
                }
                float far = i % 4 == 3 ? 1000.0f : 1.5f; /* a distant camera now and then */
                mr_vec3 org = mr_v3_add(c, mr_v3_scale(rnd_unit(&s), far * size));
                mr_vec3 dir = mr_v3_sub(target, org);
                if (!(mr_v3_len(dir) > 0))
                    continue;
                mr_dmm_ray r = mr_dmm_ray_setup(org, dir);
                pack[packed++] = r;
                if (packed == 8 || i + 1 == RAYS) {
                    packet_check(&p, pack, packed);
                    packets++;
                    packed = 0;
                }
                float ta = INFINITY, tb = INFINITY;
                mr_dmm_hit ha = {0}, hb = {0};
                bool a = mr_dmm_intersect(&p, &r, 0, &ta, true, false, &ha, NULL);
                bool b = mr_dmm_intersect_micro(&p, verts, tris, count, &r, 0, &tb, true, false,
                                                &hb);
                same_hit("closest", a, &ha, ta, b, &hb, tb);
                rays++;
                hits += a;
                /* any hit: the same verdict */
                float aa = INFINITY, ab = INFINITY;
                assert_int_equal(mr_dmm_intersect(&p, &r, 0, &aa, true, true, NULL, NULL),
                                 mr_dmm_intersect_micro(&p, verts, tris, count, &r, 0, &ab, true,
                                                        true, NULL));
                if (!a)
                    continue;
                /* the hit exactly at the incoming tmax: taken or not, the same */
                for (int take = 0; take < 2; take++) {
                    float t1 = ha.t, t2 = ha.t;
                    mr_dmm_hit h1 = {0}, h2 = {0};
                    bool a1 = mr_dmm_intersect(&p, &r, 0, &t1, take, false, &h1, NULL);
                    bool b1 = mr_dmm_intersect_micro(&p, verts, tris, count, &r, 0, &t2, take,
                                                     false, &h2);
                    same_hit(take ? "at tmax, taken" : "at tmax, kept", a1, &h1, t1, b1, &h2, t2);
                    assert_int_equal(a1, take); /* taken: found again; kept: nothing closer */
                }
                /* several micro-triangles at that t: a tie the order decided */
                uint32_t at_t = 0;
                for (uint32_t m = 0; m < count; m++) {
                    mr_vec3 y[3];
                    for (int j = 0; j < 3; j++)
                        y[j] = mr_v3(verts[3 * tris[3 * m + j]], verts[3 * tris[3 * m + j] + 1],
                                     verts[3 * tris[3 * m + j] + 2]);
                    mr_wt_hit w;
                    at_t += mr_wtd_intersect(&r.wt, y[0], y[1], y[2], ha.t, ha.t, &w);
                }
                ties += at_t > 1;
            }
        }
        set_free(&set);
        free(disp);
    }
    printf("  %llu rays, %llu hit, %llu of them at a t several micro-triangles share: the same "
           "hit from both, and from %llu packets of them\n",
           (unsigned long long)rays, (unsigned long long)hits, (unsigned long long)ties,
           (unsigned long long)packets);
    /* the rays at vertices and edges must have made ties, or the order was not tested */
    assert_true(hits * 2 > rays && ties > 100);
    free(verts);
    free(tris);
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
            bounds_case(&p, NULL);
            p = set_patch(&set, t, &tri, mats);
            if (t % 2)
                mr_dmm_patch_pad(&p, p.pad);
            bounds_case(&p, NULL);
        }
        set_free(&set);
        free(disp);
    }
}

/* A base triangle whose corner directions oppose (+x at corner 0, -x at
 * corner 1, as across a thin part of a body), with the bake's kind of
 * displacements: a fixed distance (half the triangle's size) along the
 * direction interpolated to nearly nothing, so d reaches 8 times that where
 * the direction is smallest (exactly 0 at the midpoint of edge 01, a
 * lattice vertex at level 4, which takes the same 8). The box of the
 * corners' unit directions times [dmin, dmax] is over 4 times the triangle;
 * the patch's box must be the micro-vertices' own (widened by the patch's
 * pad, mr_dmm_patch_pad: within twice that, for the pad's own rounding),
 * still hold every micro-vertex, and the traversal must still equal the
 * brute force on rays aimed at it. Both modes. */
static void test_loose_bounds(void **state)
{
    (void)state;
    const unsigned level = 4;
    const uint32_t n = mr_umesh_segments(level), vc = mr_umesh_vertex_count(level);
    const float size = 0.02f, dist = 0.5f * size;
    mr_umesh_tri tri = {.pos = {mr_v3(0, 0, 0), mr_v3(size, 0, 0), mr_v3(0.3f * size, size, 0)},
                        .dir = {mr_v3(1, 0, 0), mr_v3(-1, 0, 0), mr_v3(0, 0, 1)}};
    float *disp = malloc(sizeof(float) * vc);
    assert_non_null(disp);
    for (uint32_t b = 0; b <= n; b++)
        for (uint32_t a = 0; a + b <= n; a++) {
            float w1 = (float)a / (float)n, w2 = (float)b / (float)n, w0 = 1 - w1 - w2;
            mr_vec3 d = mr_v3_add(mr_v3_scale(tri.dir[0], w0),
                                  mr_v3_add(mr_v3_scale(tri.dir[1], w1), mr_v3_scale(tri.dir[2], w2)));
            disp[mr_umesh_vertex_index(level, a, b)] = fminf(dist / mr_v3_len(d), 8.0f * dist);
        }
    patch_set set;
    set_build(&set, level, 1, disp);
    mr_affine mats[3];
    for (int k = 0; k < 3; k++) /* a little bend: interpolated matrices differ */
        mats[k] = affine_trs(mr_v3(0.1f * size * (float)k, 0, 0), mr_v3(0, 0, 1), 0.1f * (float)k,
                             mr_v3(1, 1, 1));
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    uint64_t s = 77;
    for (int interpolated = 0; interpolated < 2; interpolated++) {
        mr_dmm_patch p = set_patch(&set, 0, &tri, interpolated ? mats : NULL);
        bounds_case(&p, NULL);
        mr_vec3 lo, hi, vlo = mr_v3(INFINITY, INFINITY, INFINITY),
                        vhi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
        assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
        for (uint32_t b = 0; b <= n; b++)
            for (uint32_t a = 0; a + b <= n; a++) {
                mr_vec3 v = mr_dmm_vertex(&p, a, b);
                vlo = mr_v3(fminf(vlo.x, v.x), fminf(vlo.y, v.y), fminf(vlo.z, v.z));
                vhi = mr_v3(fmaxf(vhi.x, v.x), fmaxf(vhi.y, v.y), fmaxf(vhi.z, v.z));
            }
        float pad[3];
        mr_dmm_patch_pad(&p, pad);
        printf("  %s: box (%g %g %g)-(%g %g %g), micro-vertices (%g %g %g)-(%g %g %g)\n",
               interpolated ? "interpolated" : "base", (double)lo.x, (double)lo.y, (double)lo.z,
               (double)hi.x, (double)hi.y, (double)hi.z, (double)vlo.x, (double)vlo.y,
               (double)vlo.z, (double)vhi.x, (double)vhi.y, (double)vhi.z);
        for (int k = 0; k < 3; k++) {
            assert_true(comp(lo, k) >= comp(vlo, k) - 2 * pad[k]);
            assert_true(comp(hi, k) <= comp(vhi, k) + 2 * pad[k]);
        }
        brute_init(bf, &p);
        check_stats cs = {0};
        for (uint32_t i = 0; i < 400; i++) {
            mr_vec3 org, dir;
            float tmin, tmax;
            rnd_ray(bf, lo, hi, &s, i, &org, &dir, &tmin, &tmax);
            check_ray(bf, &p, org, dir, tmin, tmax, NULL, NULL, &cs, CHECK_FINE);
        }
        assert_true(cs.hits * 4 > cs.rays);
    }
    free(bf);
    set_free(&set);
    free(disp);
}

/* An encoding whose bias is large against some patches' displacements (one
 * encoding per mesh: Testwuson.X's reaches -11.3 on the belly seam's
 * patches, while its others displace by ~1e-5). Patch 0 spans [-11, 2]; the
 * other patches lie near the origin (so their pads, a bound on their own
 * coordinates times 2^-19, are ~1e-8) with displacements of a few 1e-5:
 * their grid values are near the top of the range, and bias + scale * V in
 * float cancels to an error of ~2^-24 * 11 = 6.6e-7, tens of pads. The
 * boxes must take the displacements as the micro-vertices do: every
 * micro-vertex in the patch's box and the traversal (whose node boxes use
 * the same bounds) equal to the brute force. With the float sum the first
 * patch's corner lay outside its box. */
static void test_cancelling_bias(void **state)
{
    (void)state;
    enum { PATCHES = 16 };
    const unsigned level = 3;
    const uint32_t vc = mr_umesh_vertex_count(level);
    uint64_t s = 0x2b992ddfa23249d6ull;
    float *disp = malloc(sizeof(float) * vc * PATCHES);
    assert_non_null(disp);
    random_disp(&s, disp, vc, -11.0f, 2.0f);
    for (uint32_t t = 1; t < PATCHES; t++)
        random_disp(&s, disp + (size_t)t * vc, vc, 1e-5f * (float)t, 1.5e-5f * (float)t);
    patch_set set;
    set_build(&set, level, PATCHES, disp);
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    check_stats cs = {0};
    for (uint32_t t = 1; t < PATCHES; t++) {
        const float size = 2e-3f;
        mr_umesh_tri tri;
        for (int k = 0; k < 3; k++) {
            tri.pos[k] = rnd_vec(&s, -size, size);
            tri.dir[k] = rnd_unit(&s);
        }
        mr_affine mats[3];
        for (int k = 0; k < 3; k++)
            mats[k] = affine_trs(rnd_vec(&s, -size, size), rnd_unit(&s), rndf(&s, -0.2f, 0.2f),
                                 mr_v3(1, 1, 1));
        for (int interpolated = 0; interpolated < 2; interpolated++) {
            mr_dmm_patch p = set_patch(&set, t, &tri, interpolated ? mats : NULL);
            bounds_case(&p, &cs);
            mr_vec3 lo, hi;
            assert_true(mr_dmm_patch_bounds(&p, &lo, &hi));
            brute_init(bf, &p);
            for (uint32_t i = 0; i < 200; i++) {
                mr_vec3 org, dir;
                float tmin, tmax;
                rnd_ray(bf, lo, hi, &s, i, &org, &dir, &tmin, &tmax);
                check_ray(bf, &p, org, dir, tmin, tmax, NULL, NULL, &cs, CHECK_FINE);
            }
        }
    }
    printf("  %llu rays, %llu hit; %llu micro-vertices, all inside their boxes\n",
           (unsigned long long)cs.rays, (unsigned long long)cs.hits,
           (unsigned long long)cs.vertices);
    assert_true(cs.hits * 4 > cs.rays);
    free(bf);
    set_free(&set);
    free(disp);
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

/* A pad and root children cached by the caller (mr_dmm_patch_pad,
 * mr_dmm_patch_root_children) give exactly the results of those computed
 * per call: same bounds, same hits bit for bit, one ray at a time and in
 * packets. Root children boxed far from the patch, where no ray of the
 * test points, lose every hit: the traversal reads them. */
static void test_caller_caches(void **state)
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
            float kids[MR_DMM_ROOT_CHILDREN_FLOATS], far[MR_DMM_ROOT_CHILDREN_FLOATS];
            assert_int_equal(mr_dmm_patch_root_children(&q, kids), level >= 2);
            for (int k = 0; k < MR_DMM_ROOT_CHILDREN_FLOATS; k++)
                far[k] = 1e30f; /* four boxes at (1e30, 1e30, 1e30) */
            mr_dmm_patch far_kids = q;
            if (level >= 2) {
                q.root_children = kids;
                far_kids.root_children = far;
            }
            unsigned hits = 0;
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
                bool a = mr_dmm_intersect(&p, &r, tmin, &t1, true, false, &h1, NULL);
                bool b = mr_dmm_intersect(&q, &r, tmin, &t2, true, false, &h2, NULL);
                assert_true(a == b && fbits(t1) == fbits(t2));
                assert_memory_equal(&h1, &h2, sizeof h1);
                hits += a;
                /* the same ray twice in a packet of three with the cache */
                const mr_dmm_ray other = mr_dmm_ray_setup(mr_v3(0, 0, 0), mr_v3(1, 1, 1));
                const mr_dmm_ray *rs[3] = {&r, &other, &r};
                float tm[3] = {tmin, tmin, tmin}, tx[3] = {tmax, tmax, tmax};
                float *txp[3] = {&tx[0], &tx[1], &tx[2]};
                const bool take[3] = {true, true, true};
                mr_dmm_hit hp[3];
                memset(hp, 0, sizeof hp);
                uint32_t m = mr_dmm_intersect_packet(&q, 3, rs, tm, txp, take, false, hp, NULL);
                assert_true((m & 1u) == a && (m >> 2 & 1u) == a);
                /* a hit's t, or tmax untouched by a miss */
                assert_true(fbits(tx[0]) == fbits(t1) && fbits(tx[2]) == fbits(t1));
                if (a) {
                    assert_memory_equal(&hp[0], &h1, sizeof h1);
                    assert_memory_equal(&hp[2], &h1, sizeof h1);
                }
                float t3 = tmax;
                if (level >= 2)
                    assert_false(mr_dmm_intersect(&far_kids, &r, tmin, &t3, true, false, NULL, NULL));
            }
            assert_true(hits > 10); /* most rays are aimed at the surface */
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
    assert_true(mr_dmm_intersect(&p, &r, 0, &tmax, true, false, &h, NULL));
    assert_true(h.t == 1.0f && tmax == 1.0f);
    assert_true(fabsf(h.u - 0.25f) < 1e-6f && fabsf(h.v - 0.25f) < 1e-6f);
    tmax = 0.5f; /* hit beyond tmax */
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, true, false, &h, NULL));
    assert_true(tmax == 0.5f);
    tmax = 0.5f; /* empty interval */
    assert_false(mr_dmm_intersect(&p, &r, 2.0f, &tmax, true, false, &h, NULL));
    tmax = NAN;
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, true, false, &h, NULL));
    tmax = 5;
    assert_false(mr_dmm_intersect(&p, &r, 1.5f, &tmax, true, false, &h, NULL)); /* behind tmin */
    assert_int_equal(mr_dmm_trace_leaf_sublevel(0), 0);
    assert_int_equal(mr_dmm_trace_leaf_sublevel(5), 4);
    assert_int_equal(mr_dmm_trace_pyramid_size(5), mr_dmm_pyramid_size(4));
    assert_int_equal(mr_dmm_trace_pyramid_size(0), 1);
    p.level = MR_UMESH_MAX_LEVEL + 1;
    tmax = 5;
    assert_false(mr_dmm_intersect(&p, &r, 0, &tmax, true, false, &h, NULL));
    set_free(&set);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_arguments),
        cmocka_unit_test(test_brute_base),
        cmocka_unit_test(test_brute_interpolated),
        cmocka_unit_test(test_traversal_equals_micro),
        cmocka_unit_test(test_bounds),
        cmocka_unit_test(test_loose_bounds),
        cmocka_unit_test(test_cancelling_bias),
        cmocka_unit_test(test_zero_base),
        cmocka_unit_test(test_zero_interpolated_bezier),
        cmocka_unit_test(test_equal_matrices),
        cmocka_unit_test(test_counters),
        cmocka_unit_test(test_caller_caches),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
