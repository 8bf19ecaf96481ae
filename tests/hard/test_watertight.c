/*
 * test_watertight.c - the watertight ray/triangle test on known answers and
 * on the hard cases micro-meshes produce: rays through every vertex and
 * across every shared edge of a jittered height-field patch must hit it
 * (no leaks), axis-parallel rays, rays in the triangle's plane, degenerate
 * triangles, and the t range.
 *
 * Tolerances: t and barycentrics of exactly representable inputs within
 * 1e-6 (a few float ulps of O(1) values after one division).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdlib.h>

#include "math/watertight.h"

static void test_known_hit(void **state)
{
    (void)state;
    mr_vec3 a = mr_v3(0, 0, 0), b = mr_v3(1, 0, 0), c = mr_v3(0, 1, 0);
    mr_wt_ray r = mr_wt_ray_setup(mr_v3(0.25f, 0.25f, 5), mr_v3(0, 0, -1));
    mr_wt_hit h;
    assert_true(mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    assert_true(fabsf(h.t - 5) < 1e-6f);
    assert_true(fabsf(h.u - 0.25f) < 1e-6f); /* weight of b */
    assert_true(fabsf(h.v - 0.25f) < 1e-6f); /* weight of c */
    /* from below (no culling), with an unnormalised direction: t scales */
    r = mr_wt_ray_setup(mr_v3(0.5f, 0.25f, -2), mr_v3(0, 0, 4));
    assert_true(mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    assert_true(fabsf(h.t - 0.5f) < 1e-6f);
    assert_true(fabsf(h.u - 0.5f) < 1e-6f);
    /* the t range is honoured */
    assert_false(mr_wt_intersect(&r, a, b, c, 0, 0.49f, &h));
    assert_false(mr_wt_intersect(&r, a, b, c, 0.51f, 100, &h));
    /* outside the triangle */
    r = mr_wt_ray_setup(mr_v3(0.75f, 0.75f, 5), mr_v3(0, 0, -1));
    assert_false(mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    /* an oblique ray along a dominant x axis */
    r = mr_wt_ray_setup(mr_v3(-3, 0.2f, 0.3f), mr_v3(1, 0, 0));
    assert_true(mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(0, 1, 0), mr_v3(0, 0, 1), 0, 10, &h));
    assert_true(fabsf(h.t - 3) < 1e-6f);
}

static void test_degenerate_cases(void **state)
{
    (void)state;
    mr_wt_hit h;
    /* a ray lying in the triangle's plane */
    mr_wt_ray r = mr_wt_ray_setup(mr_v3(-1, 0.2f, 0), mr_v3(1, 0, 0));
    assert_false(mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0), 0, 10, &h));
    /* zero-area triangles: a point and a segment */
    r = mr_wt_ray_setup(mr_v3(0, 0, 5), mr_v3(0, 0, -1));
    assert_false(mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(0, 0, 0), mr_v3(0, 0, 0), 0, 10, &h));
    assert_false(mr_wt_intersect(&r, mr_v3(-1, 0, 0), mr_v3(0, 0, 0), mr_v3(1, 0, 0), 0, 10, &h));
    /* ray through a vertex exactly */
    assert_true(mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0), 0, 10, &h));
    assert_true(h.t == 5);
}

#define N 24 /* grid cells per side */

static mr_vec3 grid[N + 1][N + 1];

static float frand(unsigned *s)
{
    *s = *s * 1664525u + 1013904223u;
    return (float)(*s >> 8) * (1.0f / 16777216.0f);
}

/* True when the ray hits any triangle of the patch. */
static bool hits_patch(const mr_wt_ray *r)
{
    mr_wt_hit h;
    for (int y = 0; y < N; y++)
        for (int x = 0; x < N; x++) {
            mr_vec3 a = grid[y][x], b = grid[y][x + 1], c = grid[y + 1][x], d = grid[y + 1][x + 1];
            if (mr_wt_intersect(r, a, b, d, 0, 1e30f, &h) || mr_wt_intersect(r, a, d, c, 0, 1e30f, &h))
                return true;
        }
    return false;
}

/* A jittered, bumpy patch like a displaced micro-mesh: rays aimed at every
 * vertex and at points on every edge (from random origins above and below)
 * must all hit it. With a non-watertight test some slip through the cracks. */
static void test_no_leaks_through_shared_edges(void **state)
{
    (void)state;
    unsigned s = 12345;
    for (int y = 0; y <= N; y++)
        for (int x = 0; x <= N; x++) {
            float jx = (x == 0 || x == N) ? 0 : (frand(&s) - 0.5f) * 0.6f;
            float jy = (y == 0 || y == N) ? 0 : (frand(&s) - 0.5f) * 0.6f;
            grid[y][x] = mr_v3((x + jx) / N, (y + jy) / N, 0.05f * sinf(7.0f * x / N) * cosf(5.0f * y / N) +
                                                             0.01f * (frand(&s) - 0.5f));
        }
    size_t rays = 0, leaks = 0;
    for (int y = 1; y < N; y++)
        for (int x = 1; x < N; x++) {
            /* the vertex itself, and points on its right and upper edges */
            mr_vec3 targets[3] = {grid[y][x], mr_v3_lerp(grid[y][x], grid[y][x + 1], frand(&s)),
                                  mr_v3_lerp(grid[y][x], grid[y + 1][x], frand(&s))};
            for (int k = 0; k < 3; k++)
                for (int side = 0; side < 2; side++) {
                    mr_vec3 org = mr_v3(frand(&s), frand(&s), side ? 2.0f : -2.0f);
                    mr_wt_ray r = mr_wt_ray_setup(org, mr_v3_sub(targets[k], org));
                    rays++;
                    leaks += !hits_patch(&r);
                }
        }
    if (leaks)
        fail_msg("%zu of %zu rays leaked through the patch", leaks, rays);
    assert_true(rays > 3000);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_known_hit),
        cmocka_unit_test(test_degenerate_cases),
        cmocka_unit_test(test_no_leaks_through_shared_edges),
    };
    return cmocka_run_group_tests_name("watertight", tests, NULL, NULL);
}
