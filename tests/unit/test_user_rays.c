/*
 * test_user_rays.c - the box test a user geometry's callbacks run on the
 * packet Embree hands them (user_rays.h, mr_rays_in_box): it may keep rays
 * that miss the box (it is a filter), never drop one that meets it.
 *
 * The reference is the same slab test in double, exact to ~2^-52 against
 * the filter's float test, which widens its distances by 2^-20 of
 * themselves: wherever the double test finds the ray's [tnear, tfar]
 * entering the box, even by a hair, the filter must keep it. Rays are
 * aimed at random points inside boxes with tfar the distance to that point
 * (the case of a hit on a surface the box bounds, the one that matters),
 * then random rays around them; exact ties are built on purpose (rays in a
 * face's plane, parallel to axes with the origin on a face, tfar the
 * entry distance to the bit). Every packet width Embree uses (1, 4, 8, 16)
 * gives the lanes the one-ray path gives, and invalid lanes are never
 * kept. And it filters: a ray that passes the box by a thousandth of its
 * size is dropped, or the test would be a no-op.
 */
#include <float.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <cmocka.h>

#include "kinds/user_rays.h"

#include "../support/rng_fixture.h"

typedef struct one_ray {
    float o[3], d[3], tnear, tfar;
} one_ray;

/* The packet of N rays (SoA, as Embree lays it out: user_rays.h). */
static void pack(const one_ray *r, unsigned N, float *soa)
{
    memset(soa, 0, sizeof(float) * MR_RAY_FIELDS * 16);
    for (unsigned i = 0; i < N; i++) {
        for (unsigned a = 0; a < 3; a++) {
            *mr_ray_f(soa, N, MR_RAY_ORG + a, i) = r[i].o[a];
            *mr_ray_f(soa, N, MR_RAY_DIR + a, i) = r[i].d[a];
        }
        *mr_ray_f(soa, N, MR_RAY_TNEAR, i) = r[i].tnear;
        *mr_ray_f(soa, N, MR_RAY_TFAR, i) = r[i].tfar;
    }
}

/* The slab test in double: whether [tnear, tfar] of r meets the box. */
static bool meets(const one_ray *r, const float lo[3], const float hi[3])
{
    double entry = r->tnear, exit = r->tfar;
    for (int a = 0; a < 3; a++) {
        if (r->d[a] == 0) {
            if (r->o[a] < lo[a] || r->o[a] > hi[a])
                return false;
            continue;
        }
        double t1 = ((double)lo[a] - r->o[a]) / r->d[a], t2 = ((double)hi[a] - r->o[a]) / r->d[a];
        entry = fmax(entry, fmin(t1, t2));
        exit = fmin(exit, fmax(t1, t2));
    }
    return entry <= exit;
}

/* Whether the filter keeps ray r: asked one ray at a time (the scalar
 * code) and as every lane of packets of 4, 8 and 16 (SSE), which must
 * agree. */
static uint32_t kept_one(const one_ray *r, const float lo[3], const float hi[3])
{
    float soa[MR_RAY_FIELDS * 16];
    one_ray same[16];
    int valid[16];
    for (int i = 0; i < 16; i++)
        same[i] = *r, valid[i] = -1;
    pack(r, 1, soa);
    const uint32_t one = mr_rays_in_box(soa, 1, valid, lo, hi);
    for (unsigned N = 4; N <= 16; N *= 2) {
        pack(same, N, soa);
        const uint32_t all = (1u << N) - 1u;
        assert_int_equal(mr_rays_in_box(soa, N, valid, lo, hi), one ? all : 0u);
    }
    return one;
}

static void random_box(uint64_t *s, float lo[3], float hi[3])
{
    float scale = powf(10.0f, rndf(s, -3, 3)); /* boxes from 1e-3 to 1e3 across */
    for (int a = 0; a < 3; a++) {
        float c = rndf(s, -1, 1) * scale * 4, h = rndf(s, 0, 1) * scale;
        if (rnd(s) % 8 == 0)
            h = 0; /* a flat box: a triangle in an axis plane */
        lo[a] = c - h;
        hi[a] = c + h;
    }
}

/* A ray from a random origin to point p inside the box, tfar the float
 * distance to p along the unnormalised direction (1: p = o + d). */
static one_ray ray_to(uint64_t *s, const float p[3], float spread)
{
    one_ray r;
    for (int a = 0; a < 3; a++) {
        r.o[a] = p[a] + rndf(s, -1, 1) * spread;
        r.d[a] = p[a] - r.o[a];
    }
    if (rnd(s) % 4 == 0)
        r.d[rnd(s) % 3] = 0, r.o[0] = p[0], r.o[1] = p[1], r.o[2] = p[2]; /* parallel, from the point */
    r.tnear = 0;
    r.tfar = 1.0f;
    if (r.d[0] == 0 && r.d[1] == 0 && r.d[2] == 0)
        r.d[0] = 1;
    return r;
}

static void test_rays_meeting_the_box_are_kept(void **state)
{
    (void)state;
    uint64_t s = 0x5eed0001;
    unsigned kept_misses = 0, misses = 0;
    for (int n = 0; n < 200000; n++) {
        float lo[3], hi[3];
        random_box(&s, lo, hi);
        float p[3], size = 0;
        for (int a = 0; a < 3; a++) {
            p[a] = lo[a] + (hi[a] - lo[a]) * (float)rnd01(&s);
            if (rnd(&s) % 4 == 0) /* on a face, an edge or a corner */
                p[a] = rnd(&s) % 2 ? lo[a] : hi[a];
            size = fmaxf(size, hi[a] - lo[a]);
        }
        one_ray r = ray_to(&s, p, fmaxf(size, 1e-3f) * 10);
        if (meets(&r, lo, hi))
            assert_int_equal(kept_one(&r, lo, hi), 1u);
        /* the same ray, stopped where it enters (t from the double test,
         * rounded both ways) and started where it leaves */
        one_ray q = r;
        q.tfar = nextafterf(q.tfar, 0) * 0.5f;
        if (meets(&q, lo, hi))
            assert_int_equal(kept_one(&q, lo, hi), 1u);
        /* random rays around the box */
        for (int a = 0; a < 3; a++) {
            q.o[a] = p[a] + rndf(&s, -1, 1) * fmaxf(size, 1e-3f) * 3;
            q.d[a] = rndf(&s, -1, 1);
        }
        q.tnear = rndf(&s, 0, 1), q.tfar = q.tnear + rndf(&s, 0, 20) * fmaxf(size, 1e-3f);
        if (meets(&q, lo, hi))
            assert_int_equal(kept_one(&q, lo, hi), 1u);
        else {
            misses++;
            kept_misses += kept_one(&q, lo, hi);
        }
    }
    /* a filter, not a pass: of the random rays that miss, it keeps only
     * those within its 2^-20 widening (measured: none of ~100,000) */
    assert_true(misses > 50000);
    assert_true(kept_misses * 1000u < misses);
}

/* Rays through a box's edges and corners from afar: the two or three
 * slabs' distances then agree in exact arithmetic, and their float
 * roundings, each its own, put entry after exit by an ulp about half the
 * time the double test has them meet. Without the widening the filter
 * drops those. */
static void test_edges_and_corners_from_afar(void **state)
{
    (void)state;
    uint64_t s = 0x5eed0003;
    unsigned ties = 0;
    for (int n = 0; n < 100000; n++) {
        float lo[3], hi[3];
        random_box(&s, lo, hi);
        float p[3];
        int on = 2 + (int)(rnd(&s) % 2); /* an edge, or a corner */
        int free_axis = (int)(rnd(&s) % 3);
        for (int a = 0; a < 3; a++)
            p[a] = (on == 2 && a == free_axis) ? lo[a] + (hi[a] - lo[a]) * (float)rnd01(&s)
                                               : (rnd(&s) % 2 ? lo[a] : hi[a]);
        one_ray r;
        mr_vec3 d = rnd_unit(&s);
        r.d[0] = d.x, r.d[1] = d.y, r.d[2] = d.z;
        float k = rndf(&s, 1, 1000) * fmaxf(fabsf(p[0]) + fabsf(p[1]) + fabsf(p[2]), 1);
        for (int a = 0; a < 3; a++)
            r.o[a] = p[a] - k * r.d[a];
        r.tnear = 0;
        r.tfar = rnd(&s) % 2 ? INFINITY : k * 2;
        if (meets(&r, lo, hi)) {
            ties++;
            assert_int_equal(kept_one(&r, lo, hi), 1u);
        }
    }
    assert_true(ties > 10000);
}

/* Ties built to the bit: the ray in the plane of a face, parallel to an
 * axis with its origin on a face, and tfar equal to the entry distance. */
static void test_exact_ties_are_kept(void **state)
{
    (void)state;
    const float lo[3] = {-1, 2, 0.1f}, hi[3] = {3, 2.5f, 0.7f};
    /* along x in the face y = lo.y, z = hi.z (an edge of the box) */
    one_ray r = {{-10, 2, 0.7f}, {1, 0, 0}, 0, 100};
    assert_int_equal(kept_one(&r, lo, hi), 1u);
    /* stopping exactly at the entry x = -1: t = 9 */
    r.tfar = 9;
    assert_int_equal(kept_one(&r, lo, hi), 1u);
    /* and one ulp before it: the double test misses, the filter may keep */
    r.tfar = nextafterf(9, 0);
    assert_false(meets(&r, lo, hi));
    /* starting exactly at the exit x = 3: t = 13 */
    r.tnear = 13, r.tfar = 20;
    assert_int_equal(kept_one(&r, lo, hi), 1u);
    /* a touching corner, diagonally: from (-2, 1, -0.9) to (-1, 2, 0.1) */
    one_ray c = {{-2, 1, -0.9f}, {1, 1, 1}, 0, 1};
    assert_int_equal(kept_one(&c, lo, hi), 1u);
    /* parallel to two axes just outside a face: dropped */
    one_ray out = {{0, nextafterf(2.5f, 3), 0.5f}, {1, 0, 0}, 0, 100};
    assert_int_equal(kept_one(&out, lo, hi), 0u);
    /* passing a thousandth of the box beyond a face: dropped */
    one_ray past = {{-10, 2.5f + 0.004f, 0.5f}, {1, 0, 0}, 0, 100};
    assert_int_equal(kept_one(&past, lo, hi), 0u);
    /* a NaN lane is kept (the callback's own checks refuse it) */
    one_ray nan = {{NAN, 2, 0.5f}, {1, 0, 0}, 0, 100};
    assert_int_equal(kept_one(&nan, lo, hi), 1u);
}

/* Packets of 4, 8 and 16: lane by lane what the one-ray path says, and
 * nothing for the lanes Embree marks invalid. */
static void test_packets_agree_with_single_rays(void **state)
{
    (void)state;
    uint64_t s = 0x5eed0002;
    const unsigned widths[3] = {4, 8, 16};
    for (int n = 0; n < 20000; n++) {
        float lo[3], hi[3];
        random_box(&s, lo, hi);
        const unsigned N = widths[n % 3];
        one_ray r[16];
        int valid[16];
        uint32_t want = 0;
        for (unsigned i = 0; i < N; i++) {
            float p[3];
            for (int a = 0; a < 3; a++)
                p[a] = lo[a] + (hi[a] - lo[a]) * rndf(&s, -1, 2);
            r[i] = ray_to(&s, p, 1000);
            r[i].tnear = rndf(&s, 0, 0.5f);
            valid[i] = rnd(&s) % 5 ? -1 : 0;
            if (valid[i] == -1)
                want |= kept_one(&r[i], lo, hi) << i;
        }
        float soa[MR_RAY_FIELDS * 16];
        pack(r, N, soa);
        assert_int_equal(mr_rays_in_box(soa, N, valid, lo, hi), want);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_rays_meeting_the_box_are_kept),
        cmocka_unit_test(test_edges_and_corners_from_afar),
        cmocka_unit_test(test_exact_ties_are_kept),
        cmocka_unit_test(test_packets_agree_with_single_rays),
    };
    return cmocka_run_group_tests_name("user_rays", tests, NULL, NULL);
}
