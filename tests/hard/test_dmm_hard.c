/*
 * test_dmm_hard.c - hard cases for the tessellation-free DMM traversal
 * (core/kinds/dmm/dmm_trace.h): extreme deformations, degenerate base triangles,
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
 * The harness (random numbers, patch sets, brute force, check_ray, bounds
 * check) is tests/support/dmm_patch_fixture.h, shared with
 * tests/unit/test_dmm_trace.c.
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
 *
 * Each case reports for `make hard` (hard_report.h, report_rays below) the
 * rays its check_ray calls failed on (0: the check stops at the first), the
 * non-finite hits, how far t lay above the brute force's (ulps), and where
 * it checks them the (u, v) and ng errors and micro-vertices outside the
 * bounds, plus its own figures.
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

#define HARD_KIND "dmm"
#include "../support/hard_report.h"

/* The figures of a battery of check_ray calls, under the case test. fine:
 * the rays were checked with CHECK_FINE ((u, v) and ng, 1e-3 each). */
static void report_rays(const char *test, const check_stats *cs, bool fine)
{
    hard_check(test, "error", (double)cs->mismatches, "==", 0,
               "rays disagreeing with the brute force (of %llu; %llu hit)",
               (unsigned long long)cs->rays, (unsigned long long)cs->hits);
    hard_check(test, "nan", (double)cs->nonfinite, "==", 0, "non-finite hits (t, u, v, ng)");
    hard_check(test, "error", cs->worst_t_ulps, "<=", 4,
               "largest t above the brute force's closest, ulps (ties at edges and vertices)");
    if (fine) {
        hard_check(test, "error", cs->worst_uv, "<=", 1e-3,
                   "largest (u, v) outside the micro-triangle hit, lattice units");
        hard_check(test, "error", cs->worst_ng, "<=", 1e-3,
                   "largest angle between ng and the micro-triangle's normal, sine");
    }
    if (cs->vertices)
        hard_check(test, "leaks", (double)cs->outside, "==", 0,
                   "micro-vertices outside the patch bounds (of %llu)",
                   (unsigned long long)cs->vertices);
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
    bounds_case(p, cs);
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
    check_stats all = {0};
    double hit_share = INFINITY; /* the smallest share of rays that hit, per level */
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
        hit_share = hard_min(hit_share, (double)cs.hits / (double)cs.rays);
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, false);
    HARD_CHECK("other", hit_share, ">", 0.2, "smallest share of rays that hit, over levels 0-5");
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
    check_stats all = {0};
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
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, false);
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
    check_stats all = {0};
    uint64_t off_grid = 0; /* Q_MAX values not at the grid's ends */
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
                    HARD_EXPECT(off_grid, set.values[i] == 0);
                    HARD_EXPECT(off_grid, set.values[vc + i] == (1u << bits[0]) - 1u);
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
            check_stats_add(&all, &cs);
            set_free(&set);
        }
        free(disp);
    }
    HARD_CHECK("other", off_grid, "==", 0, "displacements 0 and 1 not quantised to 0 and 2^bits - 1");
    report_rays(__func__, &all, true);
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
    check_stats all = {0};
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
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, false);
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
    check_stats all = {0};
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
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, true);
    free(bf);
}

/* ---- two patches sharing an edge */

static bool v3_same_bits(mr_vec3 a, mr_vec3 b)
{
    return fbits(a.x) == fbits(b.x) && fbits(a.y) == fbits(b.y) && fbits(a.z) == fbits(b.z);
}

/* Adds the rays that must hit the union of the two patches to *required
 * and those that missed both to *leaks. */
static void shared_edge_case(unsigned level, bool interpolated, uint64_t *s, brute *ba,
                             brute *bb, check_stats *cs, uint64_t *required_total,
                             uint64_t *leaks_total)
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
    bounds_case(&pa, cs);
    bounds_case(&pb, cs);
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
        print_error("%llu of %llu rays at the shared edge leaked (level %u, %s)\n",
                    (unsigned long long)leaks, (unsigned long long)required, level,
                    interpolated ? "interpolated" : "base");
    assert_true(required > 0);
    *required_total += required;
    *leaks_total += leaks;
    set_free(&set);
    free(disp);
}

static void test_shared_edge(void **state)
{
    (void)state;
    uint64_t s = 0xbe5466cf34e90c6cull;
    brute *ba = malloc(sizeof *ba), *bb = malloc(sizeof *bb);
    assert_true(ba && bb);
    check_stats all = {0};
    uint64_t required = 0, leaks = 0;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++)
        for (int mode = 0; mode < 2; mode++) {
            check_stats cs = {0};
            for (int rep = 0; rep < 2; rep++)
                shared_edge_case(level, mode != 0, &s, ba, bb, &cs, &required, &leaks);
            print_cs(mode ? "shared edge interpolated" : "shared edge base", level, &cs);
            check_stats_add(&all, &cs);
        }
    HARD_CHECK("leaks", leaks, "==", 0,
               "rays through the shared edge missing both patches (of %llu; levels 0-5, both modes)",
               (unsigned long long)required);
    report_rays(__func__, &all, true);
    free(ba);
    free(bb);
}

/* ---- a ray at every micro-vertex */

/* Worst figures into *t_err (|t - 1| of the oblique rays) and *axis_err
 * (|t - expected| / expected of the axis-parallel ones); rays that must hit
 * their micro-vertex and missed into *missed, of *aimed. */
static void vertex_rays(unsigned level, bool interpolated, uint64_t *s, brute *bf, check_stats *all,
                        double *t_err, double *axis_err, uint64_t *aimed, uint64_t *missed)
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
    check_stats cs = {0};
    bounds_case(&p, &cs);
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
                (*aimed)++;
                if (!check_ray(bf, &p, org, dir, 0, INFINITY, &h, NULL, &cs, CHECK_AIMED)) {
                    print_error("axis-parallel ray missed micro-vertex (%u, %u)\n", a, b);
                    (*missed)++;
                    continue;
                }
                double expect = fabs((double)zo - (double)v.z);
                *axis_err = hard_max(*axis_err, fabs(h.t - expect) / expect);
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
            *aimed += interior;
            if (interior && !hit) {
                print_error("ray missed interior micro-vertex (%u, %u)\n", a, b);
                (*missed)++;
            }
            if (hit) {
                worst = hard_max(worst, fabs(h.t - 1.0));
                if (fabs(h.t - 1.0) > 1e-5) {
                    print_error("vertex (%u, %u): t %.9g, expected 1\n", a, b, (double)h.t);
                    fail();
                }
            }
        }
    printf("  vertex rays level %u %s: %llu/%llu hit, worst |t - 1| %.2g\n", level,
           interpolated ? "interpolated" : "base", (unsigned long long)cs.hits,
           (unsigned long long)cs.rays, worst);
    *t_err = hard_max(*t_err, worst);
    check_stats_add(all, &cs);
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
    check_stats all = {0};
    double t_err = 0, axis_err = 0;
    uint64_t aimed = 0, missed = 0;
    for (size_t li = 0; li < 3; li++)
        for (int mode = 0; mode < 2; mode++)
            for (int rep = 0; rep < 2; rep++)
                vertex_rays(levels[li], mode != 0, &s, bf, &all, &t_err, &axis_err, &aimed, &missed);
    HARD_CHECK("leaks", missed, "==", 0,
               "rays missing the micro-vertex they aim at (of %llu: axis-parallel at every one, "
               "oblique at interior ones)", (unsigned long long)aimed);
    HARD_CHECK("error", t_err, "<=", 1e-5, "largest |t - 1| of oblique rays at micro-vertices");
    HARD_CHECK("error", axis_err, "<=", 4 * FLT_EPSILON,
               "largest relative t error of axis-parallel rays through micro-vertices");
    report_rays(__func__, &all, true);
    free(bf);
}

/* ---- axis-parallel rays through random patches */

static void test_axis_parallel(void **state)
{
    (void)state;
    uint64_t s = 0x3f84d5b5b5470917ull;
    brute *bf = malloc(sizeof *bf);
    assert_non_null(bf);
    check_stats all = {0};
    double hit_share = INFINITY;
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
        hit_share = hard_min(hit_share, (double)cs.hits / (double)cs.rays);
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, true);
    HARD_CHECK("other", hit_share, ">", 1.0 / 3, "smallest share of rays that hit, over levels 0-5");
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
    check_stats all = {0};
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
        check_stats_add(&all, &cs);
        set_free(&set);
        free(disp);
    }
    report_rays(__func__, &all, false);
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
    HARD_CHECK("nan", mr_dmm_patch_bounds(&p, &lo, &hi), "==", 0,
               "boxes given to a patch whose displacement overflows float (d |dir| = 3e39)");
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
