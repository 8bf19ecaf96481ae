/*
 * test_hard_render.c - numerically hard cases for the triangle path: rays
 * with zero direction components, degenerate triangles, geometry far from
 * the origin, a camera looking along its up vector, grazing light (shadow
 * acne) and surfaces seen edge-on. Every film must stay free of NaN/Inf.
 * Each case reports its figures for `make hard` (hard_report.h).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "../support/scene_fixture.h"

#define HARD_KIND "mesh"
#include "../support/hard_report.h"

/* An n x n grid of quads spanning [-half, half]^2 in the XY plane at z = 0,
 * shifted by offset. */
static mr_asset *make_grid(int n, float half, mr_vec3 offset)
{
    uint32_t nv = (uint32_t)(n + 1) * (n + 1), nt = 2u * n * n;
    float *p = malloc(nv * 3 * sizeof(float));
    uint32_t *idx = malloc(nt * 3 * sizeof(uint32_t));
    assert_non_null(p);
    assert_non_null(idx);
    for (int y = 0; y <= n; y++)
        for (int x = 0; x <= n; x++) {
            float *v = p + 3 * (y * (n + 1) + x);
            v[0] = offset.x - half + 2 * half * x / n;
            v[1] = offset.y - half + 2 * half * y / n;
            v[2] = offset.z;
        }
    uint32_t *t = idx;
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            uint32_t a = y * (n + 1) + x, b = a + 1, c = a + n + 1, d = c + 1;
            *t++ = a; *t++ = b; *t++ = d;
            *t++ = a; *t++ = d; *t++ = c;
        }
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_from_mesh("grid", p, NULL, nv, idx, nt, &asset, &err) < 0)
        fail_msg("%s", err.msg);
    free(p);
    free(idx);
    return asset;
}

/* The centre ray is exactly (0, 0, -1): two of its components are zero, the
 * case where slab tests compute 0 * inf. It must hit the plane at exactly the
 * camera distance (the plane is at z = 0, vertices exactly representable). */
static void test_axis_aligned_rays(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_grid(4, 1, mr_v3(0, 0, 0)), mr_v3(0, 0, 3), mr_v3(0, 0, 0), 30, 33, 33, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    size_t c = 16 * 33 + 16;
    HARD_CHECK("leaks", f->object_id[c] != 1, "==", 0, "centre ray (0, 0, -1) missing the plane");
    /* tolerance: one float ulp of 3 */
    HARD_CHECK("error", fabsf(f->z[c] - 3.0f), "<=", 3.0f * 1.2e-7f, "|z - 3| of the centre ray");
    HARD_CHECK("error", fabsf(f->nz[c] - 1.0f), "==", 0, "|n.z - 1| of the centre ray");
    HARD_NONFINITE(film_nonfinite(f), "non-finite film values (33 x 33 x 8)");
    mr_film_free(f);
    fixture_free(&s);
}

/* Zero-area triangles (repeated and collinear vertices) next to a good one:
 * they must neither produce hits nor NaN normals (their area-weighted vertex
 * normals are zero). */
static void test_degenerate_triangles(void **state)
{
    (void)state;
    const float p[] = {-1, -1, 0, 1, -1, 0, 0, 1, 0,   /* a real triangle */
                       0, 0, 0.5f, 0, 0, 0.5f, 0, 0, 0.5f, /* a point */
                       -1, 0, 0.5f, 0, 0, 0.5f, 1, 0, 0.5f}; /* a line in front of the real one */
    const uint32_t idx[] = {0, 1, 2, 3, 4, 5, 6, 7, 8};
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_from_mesh("degenerate", p, NULL, 9, idx, 3, &a, &err) < 0)
        fail_msg("%s", err.msg);
    scene_fixture s;
    fixture_init(&s, a, mr_v3(0, 0, 4), mr_v3(0, 0, 0), 40, 41, 41, 2);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    size_t hits = 0, degenerate = 0;
    double z_err = 0;
    for (size_t i = 0; i < 41 * 41; i++) {
        if (f->object_id[i]) {
            hits++;
            degenerate += f->prim_id[i] != 0; /* only the real triangle is ever hit */
            z_err = hard_max(z_err, fabsf(f->z[i] - 4.0f));
        }
    }
    HARD_CHECK("other", degenerate, "==", 0, "pixels that hit a zero-area triangle");
    HARD_CHECK("error", z_err, "<", 0.5f, "largest |z - 4| of the %zu hits", hits);
    HARD_CHECK("other", hits, ">", 50, "pixels that hit the real triangle");
    HARD_NONFINITE(film_nonfinite(f), "non-finite film values (41 x 41 x 8)");
    mr_film_free(f);
    fixture_free(&s);
}

/* A plane 1e5 units from the origin seen from 10 units away. Embree's
 * intersection error scales with the coordinates' magnitude: 1e5 * 2^-23
 * ~ 0.012 absolute, so Z = 10 is checked to 0.05 and every pixel inside the
 * plane's footprint must hit (no cracks between the grid's triangles). */
static void test_far_from_origin(void **state)
{
    (void)state;
    mr_vec3 o = mr_v3(1e5f, -1e5f, 1e5f);
    scene_fixture s;
    fixture_init(&s, make_grid(8, 2, o), mr_v3(o.x, o.y, o.z + 10), o, 10, 32, 32, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    /* tan(5 deg) * 10 = 0.87 < 2: the whole image is inside the plane. */
    size_t missed = 0;
    double z_lo = INFINITY, z_hi = -INFINITY;
    for (size_t i = 0; i < 32 * 32; i++) {
        if (f->object_id[i] != 1 && missed++ == 0)
            print_error("pixel %zu missed the plane\n", i);
        z_lo = hard_min(z_lo, f->z[i]);
        z_hi = hard_max(z_hi, f->z[i]);
    }
    HARD_CHECK("leaks", missed, "==", 0, "pixels missing the plane at 1e5 (of 1024)");
    HARD_CHECK("error", z_lo, ">", 9.95f, "smallest z at 1e5 (the plane 10 away)");
    HARD_CHECK("error", z_hi, "<", 10.1f, "largest z at 1e5 (the plane 10 away)");
    HARD_NONFINITE(film_nonfinite(f), "non-finite film values (32 x 32 x 8)");
    /* Light at 45 degrees: with nothing else in the scene, shadow rays must
     * not find the plane they leave from, however far from the origin. */
    s.light.direction = mr_v3(0, -0.70710678f, -0.70710678f);
    mr_film *lit = fixture_render(&s, 0, &st);
    s.job.output.shadows = false;
    mr_film *unshadowed = fixture_render(&s, 0, &st);
    size_t acne = 0;
    for (size_t i = 0; i < 32 * 32; i++)
        if (lit->r[i] != unshadowed->r[i] && acne++ == 0)
            print_error("pixel %zu shadowed by its own surface at 1e5: %g vs %g\n", i, lit->r[i],
                        unshadowed->r[i]);
    HARD_CHECK("other", acne, "==", 0, "pixels shadowed by their own surface at 1e5");
    mr_film_free(lit);
    mr_film_free(unshadowed);
    mr_film_free(f);
    fixture_free(&s);
}

/* Looking straight down the up vector: the look-at frame must fall back to
 * another up instead of producing NaN (cross product of parallel vectors). */
static void test_camera_along_up(void **state)
{
    (void)state;
    mr_asset *a = make_grid(2, 1, mr_v3(0, 0, 0));
    scene_fixture s;
    /* the grid lies in XY; look at it from +Z with up = +Z (parallel to the view) */
    fixture_init(&s, a, mr_v3(0, 0, 5), mr_v3(0, 0, 0), 30, 17, 17, 1);
    s.job.camera.path.up = mr_v3(0, 0, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    /* the centre pixel of an odd-sized film looks straight at the origin */
    HARD_CHECK("leaks", f->object_id[8 * 17 + 8] != 1, "==", 0, "centre pixel missing the grid");
    HARD_CHECK("error", fabsf(f->z[8 * 17 + 8] - 5.0f), "<", 1e-5f, "|z - 5| of the centre pixel");
    HARD_NONFINITE(film_nonfinite(f), "non-finite film values (17 x 17 x 8)");
    mr_film_free(f);
    fixture_free(&s);
}

/* Grazing light (2 degrees above the surface) on a finely tessellated plane:
 * shadow rays leave from the surface and must not hit the triangle they
 * start on or its neighbours (shadow acne). With nothing else in the scene,
 * shadows on and off must give the same colours. */
static void test_no_shadow_acne_at_grazing_light(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_grid(64, 2, mr_v3(0, 0, 0)), mr_v3(0, 0, 3), mr_v3(0, 0, 0), 60, 64, 64, 1);
    float g = (float)(2 * M_PI / 180);
    s.light.direction = mr_v3(cosf(g), 0, -sinf(g)); /* travels along +X, slightly down onto z = 0 */
    mr_frame_stats st;
    mr_film *lit = fixture_render(&s, 0, &st);
    s.job.output.shadows = false;
    mr_film *unshadowed = fixture_render(&s, 0, &st);
    size_t hits = 0, acne = 0;
    for (size_t i = 0; i < 64 * 64; i++) {
        if (lit->object_id[i])
            hits++;
        if (lit->r[i] != unshadowed->r[i] && acne++ == 0)
            print_error("pixel %zu darkened by its own surface: %g vs %g\n", i, lit->r[i], unshadowed->r[i]);
    }
    HARD_CHECK("other", acne, "==", 0, "pixels darkened by their own surface (light 2 deg above it)");
    HARD_CHECK("other", hits, ">", 1000, "pixels that hit the plane (of 4096)");
    mr_film_free(lit);
    mr_film_free(unshadowed);
    fixture_free(&s);
}

/* A plane seen exactly edge-on: rays run inside the plane of the triangles.
 * Whatever they report, nothing may be NaN. */
static void test_edge_on_plane(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_grid(4, 1, mr_v3(0, 0, 0)), mr_v3(0, -5, 0), mr_v3(0, 0, 0), 30, 31, 31, 4);
    s.job.camera.path.up = mr_v3(0, 0, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    HARD_NONFINITE(film_nonfinite(f), "non-finite film values (31 x 31 x 8)");
    mr_film_free(f);
    fixture_free(&s);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_axis_aligned_rays),
        cmocka_unit_test(test_degenerate_triangles),
        cmocka_unit_test(test_far_from_origin),
        cmocka_unit_test(test_camera_along_up),
        cmocka_unit_test(test_no_shadow_acne_at_grazing_light),
        cmocka_unit_test(test_edge_on_plane),
    };
    return cmocka_run_group_tests_name("hard_render", tests, NULL, NULL);
}
