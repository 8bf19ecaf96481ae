/*
 * test_watertight.c - the watertight ray/triangle test on known answers and
 * on the hard cases micro-meshes produce: rays through every vertex and
 * across every shared edge of a jittered height-field patch must hit it
 * (no leaks), axis-parallel rays, rays in the triangle's plane, degenerate
 * triangles, and the t range.
 *
 * Tolerances: t and barycentrics of exactly representable inputs within
 * 1e-6 (a few float ulps of O(1) values after one division). Each case
 * reports its figures for `make hard` (tests/support/hard_report.h).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdlib.h>

#include "math/watertight.h"

#define HARD_KIND "mesh"
#include "../support/hard_report.h"

static void test_known_hit(void **state)
{
    (void)state;
    mr_vec3 a = mr_v3(0, 0, 0), b = mr_v3(1, 0, 0), c = mr_v3(0, 1, 0);
    mr_wt_ray r = mr_wt_ray_setup(mr_v3(0.25f, 0.25f, 5), mr_v3(0, 0, -1));
    mr_wt_hit h;
    int bad = 0;
    double t_err = 0, uv_err = 0;
    assert_true(mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    t_err = hard_max(t_err, fabsf(h.t - 5));
    uv_err = hard_max(uv_err, fabsf(h.u - 0.25f)); /* weight of b */
    uv_err = hard_max(uv_err, fabsf(h.v - 0.25f)); /* weight of c */
    /* from below (no culling), with an unnormalised direction: t scales */
    r = mr_wt_ray_setup(mr_v3(0.5f, 0.25f, -2), mr_v3(0, 0, 4));
    assert_true(mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    t_err = hard_max(t_err, fabsf(h.t - 0.5f));
    uv_err = hard_max(uv_err, fabsf(h.u - 0.5f));
    /* the t range is honoured */
    HARD_EXPECT(bad, !mr_wt_intersect(&r, a, b, c, 0, 0.49f, &h));
    HARD_EXPECT(bad, !mr_wt_intersect(&r, a, b, c, 0.51f, 100, &h));
    /* outside the triangle */
    r = mr_wt_ray_setup(mr_v3(0.75f, 0.75f, 5), mr_v3(0, 0, -1));
    HARD_EXPECT(bad, !mr_wt_intersect(&r, a, b, c, 0, 100, &h));
    /* an oblique ray along a dominant x axis */
    r = mr_wt_ray_setup(mr_v3(-3, 0.2f, 0.3f), mr_v3(1, 0, 0));
    assert_true(mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(0, 1, 0), mr_v3(0, 0, 1), 0, 10, &h));
    t_err = hard_max(t_err, fabsf(h.t - 3));
    HARD_CHECK("error", t_err, "<", 1e-6f, "largest |t - exact t| of 3 hits");
    HARD_CHECK("error", uv_err, "<", 1e-6f, "largest |barycentric - exact| of 2 hits");
    HARD_CHECK("other", bad, "==", 0, "hits outside the t range or the triangle (3 rays)");
}

static void test_degenerate_cases(void **state)
{
    (void)state;
    mr_wt_hit h;
    int phantom = 0;
    /* a ray lying in the triangle's plane */
    mr_wt_ray r = mr_wt_ray_setup(mr_v3(-1, 0.2f, 0), mr_v3(1, 0, 0));
    HARD_EXPECT(phantom, !mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0), 0, 10, &h));
    /* zero-area triangles: a point and a segment */
    r = mr_wt_ray_setup(mr_v3(0, 0, 5), mr_v3(0, 0, -1));
    HARD_EXPECT(phantom, !mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(0, 0, 0), mr_v3(0, 0, 0), 0, 10, &h));
    HARD_EXPECT(phantom, !mr_wt_intersect(&r, mr_v3(-1, 0, 0), mr_v3(0, 0, 0), mr_v3(1, 0, 0), 0, 10, &h));
    HARD_CHECK("other", phantom, "==", 0, "hits on an in-plane ray and zero-area triangles (3 rays)");
    /* ray through a vertex exactly */
    bool hit = mr_wt_intersect(&r, mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0), 0, 10, &h);
    HARD_CHECK("leaks", !hit, "==", 0, "miss of a ray through a vertex exactly");
    HARD_CHECK("error", fabsf(h.t - 5), "==", 0, "|t - 5| at the vertex");
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
    HARD_CHECK("leaks", leaks, "==", 0, "rays leaked through the jittered patch (of %zu)", rays);
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
