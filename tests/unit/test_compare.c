/*
 * test_compare.c - error metrics between two films (compare.h).
 *
 * Small hand-built films whose answers follow in closed form. Inputs are
 * chosen exactly representable in float, so the only error left is double
 * rounding in sqrt/acos/log10; the tolerance 1e-12 (relative to values of
 * order 1..100) is many orders above that and far below any real defect.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "render/compare.h"
#include "render/film.h"

#define TOL 1e-12

static mr_film *film(int w, int h)
{
    mr_film *f = NULL;
    mr_error err = {0};
    assert_int_equal(mr_film_new(w, h, &f, &err), MR_OK);
    return f;
}

/* Marks pixel i as a hit with depth z and normal n. */
static void hit(mr_film *f, size_t i, float z, float nx, float ny, float nz)
{
    f->object_id[i] = 1;
    f->prim_id[i] = (uint32_t)i;
    f->z[i] = z;
    f->nx[i] = nx;
    f->ny[i] = ny;
    f->nz[i] = nz;
}

static void test_identical(void **state)
{
    mr_film *a = film(5, 4), *b = film(5, 4);
    mr_compare_result r;
    mr_error err = {0};
    size_t i;
    (void)state;

    for (i = 0; i < 20; i++) {
        a->r[i] = 0.05f * (float)i;
        a->g[i] = 0.5f;
        a->b[i] = 1.0f - 0.04f * (float)i;
        if (i % 3)
            hit(a, i, 2.0f + (float)i, 0.0f, 0.6f, 0.8f);
    }
    memcpy(b->r, a->r, 20 * sizeof(float));
    memcpy(b->g, a->g, 20 * sizeof(float));
    memcpy(b->b, a->b, 20 * sizeof(float));
    memcpy(b->z, a->z, 20 * sizeof(float));
    memcpy(b->nx, a->nx, 20 * sizeof(float));
    memcpy(b->ny, a->ny, 20 * sizeof(float));
    memcpy(b->nz, a->nz, 20 * sizeof(float));
    memcpy(b->object_id, a->object_id, 20 * sizeof(uint32_t));

    assert_int_equal(mr_film_compare(a, b, 3.0, &r, &err), MR_OK);
    assert_int_equal(r.pixels, 20);
    assert_int_equal(r.hit_either, 13);
    assert_int_equal(r.hit_both, 13);
    assert_int_equal(r.hit_one, 0);
    assert_true(r.coverage_pct == 0.0);
    assert_true(r.depth_rmse == 0.0 && r.depth_max == 0.0);
    /* acos(1) is exactly 0. */
    assert_true(r.normal_mean_deg == 0.0 && r.normal_max_deg == 0.0);
    assert_true(r.psnr_rgb == MR_PSNR_IDENTICAL);
    mr_film_free(a);
    mr_film_free(b);
}

static void test_coverage(void **state)
{
    mr_film *a = film(4, 4), *b = film(4, 4);
    mr_compare_result r;
    mr_error err = {0};
    (void)state;

    /* Neither frame hits anything: coverage error is defined as 0. */
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.hit_either, 0);
    assert_true(r.coverage_pct == 0.0);
    assert_true(r.psnr_rgb == MR_PSNR_IDENTICAL);

    /* Three pixels hit in both, one only in b: 1 of 4 -> exactly 25 %. */
    hit(a, 0, 1.0f, 0, 0, 1);
    hit(a, 5, 1.0f, 0, 0, 1);
    hit(a, 10, 1.0f, 0, 0, 1);
    hit(b, 0, 1.0f, 0, 0, 1);
    hit(b, 5, 1.0f, 0, 0, 1);
    hit(b, 10, 1.0f, 0, 0, 1);
    hit(b, 15, 1.0f, 0, 0, 1);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.hit_either, 4);
    assert_int_equal(r.hit_both, 3);
    assert_int_equal(r.hit_one, 1);
    assert_true(r.coverage_pct == 25.0);
    /* Symmetric. */
    assert_int_equal(mr_film_compare(b, a, 1.0, &r, &err), MR_OK);
    assert_true(r.coverage_pct == 25.0);

    /* One more pixel only in a: 2 of 5 -> 40 %. A hit means object_id != 0,
     * whatever the other planes say. */
    a->object_id[3] = 77;
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.hit_one, 2);
    assert_int_equal(r.hit_either, 5);
    assert_true(fabs(r.coverage_pct - 40.0) <= TOL);

    /* Disjoint hits: 100 %. Nothing hit in both -> depth/normal stay 0. */
    mr_film_clear(a);
    mr_film_clear(b);
    hit(a, 1, 1.0f, 0, 0, 1);
    hit(b, 2, 9.0f, 1, 0, 0);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(r.coverage_pct == 100.0);
    assert_int_equal(r.hit_both, 0);
    assert_true(r.depth_rmse == 0.0 && r.depth_max == 0.0);
    assert_true(r.normal_mean_deg == 0.0 && r.normal_max_deg == 0.0);
    mr_film_free(a);
    mr_film_free(b);
}

static void test_depth(void **state)
{
    mr_film *a = film(3, 2), *b = film(3, 2);
    mr_compare_result r;
    mr_error err = {0};
    (void)state;

    /* |dZ| over pixels hit in both: 0, 3, 4, 0 -> RMSE sqrt(25 / 4) = 2.5,
     * max 4; relative to a diagonal of 10: 0.25 and 0.4. */
    hit(a, 0, 5.0f, 0, 0, 1);
    hit(b, 0, 5.0f, 0, 0, 1);
    hit(a, 1, 5.0f, 0, 0, 1);
    hit(b, 1, 8.0f, 0, 0, 1);
    hit(a, 2, 10.0f, 0, 0, 1);
    hit(b, 2, 6.0f, 0, 0, 1);
    hit(a, 3, 2.5f, 0, 0, 1);
    hit(b, 3, 2.5f, 0, 0, 1);
    /* Hit in one frame only: its (huge) depth must not count. */
    hit(a, 4, 1000.0f, 0, 0, 1);
    /* Missed in both: ignored even though Z differs. */
    a->z[5] = 50.0f;

    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_int_equal(r.hit_both, 4);
    assert_true(fabs(r.depth_rmse - 0.25) <= TOL);
    assert_true(fabs(r.depth_max - 0.4) <= TOL);

    /* Scales inversely with the diagonal. */
    assert_int_equal(mr_film_compare(a, b, 0.5, &r, &err), MR_OK);
    assert_true(fabs(r.depth_rmse - 5.0) <= TOL);
    assert_true(fabs(r.depth_max - 8.0) <= TOL);
    mr_film_free(a);
    mr_film_free(b);
}

static void test_normals(void **state)
{
    mr_film *a = film(2, 2), *b = film(2, 2);
    mr_compare_result r;
    mr_error err = {0};
    (void)state;

    /* One pixel at 90 degrees, one identical: mean 45, max 90. */
    hit(a, 0, 1.0f, 0, 0, 1);
    hit(b, 0, 1.0f, 1, 0, 0);
    hit(a, 1, 1.0f, 0, 1, 0);
    hit(b, 1, 1.0f, 0, 1, 0);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(fabs(r.normal_max_deg - 90.0) <= TOL);
    assert_true(fabs(r.normal_mean_deg - 45.0) <= TOL);

    /* Opposite normals: 180, so the mean over three pixels is 90. */
    hit(a, 2, 1.0f, 0, 0, 1);
    hit(b, 2, 1.0f, 0, 0, -1);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(fabs(r.normal_max_deg - 180.0) <= TOL);
    assert_true(fabs(r.normal_mean_deg - 90.0) <= TOL);

    mr_film_clear(a);
    mr_film_clear(b);
    {
        /* A 60 degree pair, (0,0,1) vs (0, sqrt3/2, 1/2): sqrt3/2 is rounded
         * to float, so the exact reference is that float vector's angle. */
        float s = (float)(sqrt(3.0) / 2.0);
        double len = sqrt((double)s * s + 0.25);
        double want = acos(0.5 / len) * 180.0 / 3.14159265358979323846;
        hit(a, 0, 1.0f, 0, 0, 1);
        hit(b, 0, 1.0f, 0, s, 0.5f);
        assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
        assert_true(fabs(r.normal_max_deg - want) <= TOL);
        assert_true(fabs(r.normal_max_deg - 60.0) <= 1e-5); /* float input */
    }

    /* Length does not matter, only direction. */
    hit(a, 0, 1.0f, 2, 0, 0);
    hit(b, 0, 1.0f, 1, 0, 0);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(r.normal_max_deg == 0.0);
    mr_film_free(a);
    mr_film_free(b);
}

static void test_psnr(void **state)
{
    mr_film *a = film(4, 2), *b = film(4, 2);
    mr_compare_result r;
    mr_error err = {0};
    size_t i;
    (void)state;

    /* R differs by 0.5 everywhere, G and B equal: MSE = 0.25 / 3,
     * PSNR = 10 log10(12). Hits play no part in colour. */
    for (i = 0; i < 8; i++) {
        a->r[i] = 0.5f;
        b->r[i] = 1.0f;
        a->g[i] = b->g[i] = 0.25f;
    }
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(fabs(r.psnr_rgb - 10.0 * log10(12.0)) <= TOL);

    /* One channel of one pixel off by 1 (0 vs 1) out of 24 samples:
     * MSE = 1/24, PSNR = 10 log10(24). */
    for (i = 0; i < 8; i++)
        b->r[i] = 0.5f;
    b->b[7] = 1.0f;
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(fabs(r.psnr_rgb - 10.0 * log10(24.0)) <= TOL);

    /* Clamped to [0, 1] first: 5 vs 1 and -3 vs 0 are no difference, and
     * a NaN reads as 0. Alpha is not part of the metric. */
    b->b[7] = 0.0f;
    a->r[0] = 5.0f;
    b->r[0] = 1.0f;
    a->g[1] = -3.0f;
    b->g[1] = 0.0f;
    a->b[2] = NAN;
    b->b[2] = 0.0f;
    a->a[3] = 1.0f;
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_true(r.psnr_rgb == MR_PSNR_IDENTICAL);
    mr_film_free(a);
    mr_film_free(b);
}

/* Holes: misses inside the reference's silhouette, not on its edge. */
static void test_holes(void **state)
{
    (void)state;
    mr_film *a = film(5, 5), *b = film(5, 5);
    mr_compare_result r;
    mr_error err = {0};
    for (int p = 0; p < 25; p++)
        hit(b, p, 1.0f, 0, 0, 1); /* the reference covers everything */
    for (int p = 0; p < 25; p++)
        if (p != 12 && p != 0 && p != 7)
            hit(a, p, 1.0f, 0, 0, 1);
    /* 12 (centre) and 7 (its neighbour above) are interior: holes; 0 is a
     * corner of the image, never interior. */
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.holes, 2);
    /* The reference missing a neighbour of 12 puts 12 on its silhouette. */
    b->object_id[13] = 0;
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.holes, 0); /* 7's neighbours include 13 too */
    /* Not symmetric: against a full reference an empty frame has the 3 x 3
     * interior as holes; against an empty reference nothing is a hole. */
    mr_film_clear(b);
    for (int p = 0; p < 25; p++)
        hit(a, p, 1.0f, 0, 0, 1);
    assert_int_equal(mr_film_compare(b, a, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.holes, 9);
    assert_int_equal(r.strays, 0);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.holes, 0);
    assert_int_equal(r.strays, 9); /* the converse: a full frame against nothing */
    mr_film_free(a);
    mr_film_free(b);
}

/* Strays: hits beside the reference's silhouette, more than one pixel
 * away from it. */
static void test_strays(void **state)
{
    (void)state;
    mr_film *a = film(7, 5), *b = film(7, 5);
    mr_compare_result r;
    mr_error err = {0};
    /* the reference hits column 1 only */
    for (int y = 0; y < 5; y++)
        hit(b, y * 7 + 1, 1.0f, 0, 0, 1);
    /* a hits the same, plus (2, 2) beside the outline and (4, 2) two
     * columns away; (6, 2) is on the frame border */
    for (int y = 0; y < 5; y++)
        hit(a, y * 7 + 1, 1.0f, 0, 0, 1);
    hit(a, 2 * 7 + 2, 1.0f, 0, 0, 1);
    hit(a, 2 * 7 + 4, 1.0f, 0, 0, 1);
    hit(a, 2 * 7 + 6, 1.0f, 0, 0, 1);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.strays, 1);  /* (4, 2); (2, 2) touches column 1 */
    assert_int_equal(r.holes, 0);
    assert_int_equal(r.hit_one, 3);
    /* the reference reaching (3, 1) puts (4, 2) next to its silhouette */
    hit(b, 1 * 7 + 3, 1.0f, 0, 0, 1);
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_OK);
    assert_int_equal(r.strays, 0);
    mr_film_free(a);
    mr_film_free(b);
}

static void test_invalid(void **state)
{
    mr_film *a = film(4, 3), *b = film(3, 4), *c = film(4, 3);
    mr_compare_result r;
    mr_error err = {0};
    (void)state;

    r.pixels = 123;
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, &err), MR_ERR_INVALID);
    assert_int_equal(err.code, MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "4x3"));
    assert_non_null(strstr(err.msg, "3x4"));
    assert_int_equal(r.pixels, 0); /* result cleared on failure */

    assert_int_equal(mr_film_compare(a, c, 0.0, &r, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "scene_diagonal"));
    assert_int_equal(mr_film_compare(a, c, -1.0, &r, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(a, c, NAN, &r, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(a, c, INFINITY, &r, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(NULL, c, 1.0, &r, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(a, NULL, 1.0, &r, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(a, c, 1.0, NULL, &err), MR_ERR_INVALID);
    /* A NULL error pointer is allowed. */
    assert_int_equal(mr_film_compare(a, b, 1.0, &r, NULL), MR_ERR_INVALID);
    assert_int_equal(mr_film_compare(a, c, 1e-30, &r, NULL), MR_OK);
    mr_film_free(a);
    mr_film_free(b);
    mr_film_free(c);
}

/* Fills the film with one object of grey level v. */
static void fill(mr_film *f, uint32_t object, float v)
{
    for (size_t i = 0; i < (size_t)f->width * (size_t)f->height; i++) {
        f->object_id[i] = object;
        f->r[i] = f->g[i] = f->b[i] = v;
    }
}

/* The isolated-dark-pixel metric: exactly the pixels below 0.6x the
 * median of eight neighbours on one object. Grey levels make luminance the
 * level itself (the weights sum to 1 within float rounding, hence the
 * margins of 1e-3 around the 0.6 threshold). */
static void test_speckles(void **state)
{
    (void)state;
    mr_film *f = film(5, 5);
    mr_speckle_result s;
    fill(f, 1, 1.0f);
    mr_film_speckles(f, &s);
    assert_int_equal(s.interior, 9); /* the 3x3 inside the border */
    assert_int_equal(s.speckles, 0);
    assert_true(s.speckle_pct == 0.0);

    f->r[12] = f->g[12] = f->b[12] = 0.599f; /* the centre, just below 0.6 */
    mr_film_speckles(f, &s);
    assert_int_equal(s.speckles, 1);
    assert_true(fabs(s.speckle_pct - 100.0 / 9.0) < 1e-9);
    f->r[12] = f->g[12] = f->b[12] = 0.601f; /* just above: not a speckle */
    mr_film_speckles(f, &s);
    assert_int_equal(s.speckles, 0);
    f->r[12] = f->g[12] = f->b[12] = NAN; /* a NaN pixel is one */
    mr_film_speckles(f, &s);
    assert_int_equal(s.speckles, 1);

    /* the median, not the mean: of the eight neighbours of a 3x3 film,
     * three dark ones leave it at 1, four pull it to (0.1 + 1) / 2 = 0.55 */
    mr_speckle_result only;
    mr_film *g = film(3, 3);
    const float centre[3] = {0.5f, 0.5f, 0.3f};
    const int dark[3] = {3, 4, 4};
    const size_t expect[3] = {1, 0, 1}; /* 0.5 < 0.6; 0.5 >= 0.33; 0.3 < 0.33 */
    for (int c = 0; c < 3; c++) {
        fill(g, 1, 1.0f);
        const size_t ring[8] = {0, 1, 2, 3, 5, 6, 7, 8};
        for (int k = 0; k < dark[c]; k++)
            g->r[ring[k]] = g->g[ring[k]] = g->b[ring[k]] = 0.1f;
        g->r[4] = g->g[4] = g->b[4] = centre[c];
        mr_film_speckles(g, &only);
        assert_int_equal(only.interior, 1);
        assert_int_equal(only.speckles, expect[c]);
    }

    /* a pinhole (the pixel misses, the background shows) inside an object
     * is one; a pixel whose neighbours hit two objects is not interior */
    fill(g, 1, 1.0f);
    g->object_id[4] = 0;
    g->r[4] = g->g[4] = g->b[4] = 0.0f;
    mr_film_speckles(g, &only);
    assert_int_equal(only.speckles, 1);
    fill(g, 1, 1.0f);
    g->object_id[0] = 2;
    g->r[4] = g->g[4] = g->b[4] = 0.0f;
    mr_film_speckles(g, &only);
    assert_int_equal(only.interior, 0);
    assert_int_equal(only.speckles, 0);
    mr_film_free(g);
    mr_film_free(f);
}

/* The definition of a speckle, pixel by pixel and plainly (a full sort
 * of the eight neighbours' luminances): what mr_film_speckles must count,
 * whatever shortcuts it takes and however it splits the film. */
static int cmp_float(const void *a, const void *b)
{
    float x = *(const float *)a, y = *(const float *)b;
    return (x > y) - (x < y);
}

static float plain_luminance(const mr_film *f, size_t p)
{
    float y = 0.2126f * f->r[p] + 0.7152f * f->g[p] + 0.0722f * f->b[p];
    return y == y ? y : 0.0f;
}

static mr_speckle_result plain_speckles(const mr_film *f)
{
    mr_speckle_result r = {0};
    const int w = f->width;
    for (int y = 1; y + 1 < f->height; y++)
        for (int x = 1; x + 1 < w; x++) {
            size_t p = (size_t)y * (size_t)w + (size_t)x;
            size_t q[8] = {p - w - 1, p - w, p - w + 1, p - 1, p + 1, p + w - 1, p + w, p + w + 1};
            bool inside = f->object_id[q[0]] != 0;
            float lum[8];
            for (int k = 0; k < 8; k++) {
                inside = inside && f->object_id[q[k]] == f->object_id[q[0]];
                lum[k] = plain_luminance(f, q[k]);
            }
            if (!inside)
                continue;
            qsort(lum, 8, sizeof lum[0], cmp_float);
            r.interior++;
            r.speckles += plain_luminance(f, p) < (float)MR_SPECKLE_RATIO * (0.5f * (lum[3] + lum[4]));
        }
    return r;
}

/* Random films against the definition: objects in patches with misses
 * between them, colours from dark to bright, with ties (a few levels), or
 * nearly even with dark pixels around the threshold; negative values, NaN
 * and infinities, on sizes that leave a partial last
 * chunk of rows. Exact counts: the test fails on one pixel counted
 * differently. */
static void test_speckles_random(void **state)
{
    (void)state;
    uint64_t seed = 0x9e3779b97f4a7c15ull;
    const int sizes[4][2] = {{3, 3}, {67, 41}, {300, 53}, {129, 200}};
    size_t speckles = 0;
    for (int round = 0; round < 24; round++) {
        int w = sizes[round % 4][0], h = sizes[round % 4][1];
        mr_film *f = film(w, h);
        for (size_t i = 0; i < (size_t)w * (size_t)h; i++) {
            seed = seed * 6364136223846793005ull + 1442695040888963407ull;
            uint32_t bits = (uint32_t)(seed >> 32);
            int px = (int)(i % (size_t)w), py = (int)(i / (size_t)w);
            f->object_id[i] = (bits & 63u) == 0 ? 0u : 1u + (uint32_t)((px / 9 + py / 7) % 3);
            float u = (float)(bits >> 8 & 0xffffu) / 65535.0f, v = u;
            if (round % 3 == 1)
                v = (float)(bits >> 8 & 3u) * 0.4f; /* ties */
            else if (round % 3 == 2) /* a smooth surface, dark pixels near the threshold */
                v = (bits >> 24 & 7u) ? 0.95f + 0.05f * u : 0.5f + 0.15f * u;
            switch (bits >> 28) {
            case 0: v = NAN; break;
            case 1: v = -v; break;
            case 2: v = bits & 1u ? INFINITY : -INFINITY; break;
            default: break;
            }
            f->r[i] = v;
            f->g[i] = (bits >> 24 & 1u) ? v : 0.5f * v;
            f->b[i] = v;
        }
        mr_speckle_result want = plain_speckles(f), got;
        mr_film_speckles(f, &got);
        assert_int_equal(got.interior, want.interior);
        assert_int_equal(got.speckles, want.speckles);
        speckles += want.speckles;
        mr_film_free(f);
    }
    assert_true(speckles > 100); /* the films do have speckles to count */
}

/* A 40x30 film whose camera sees a pixel as 1/40 of a unit at depth 1
 * (tan(yfov / 2) = 0.375), with a square of hits x in [10, 25), y in
 * [8, 20) at depth z. */
static mr_film *square(float z, int shift_x)
{
    mr_film *f = film(40, 30);
    f->has_camera = true;
    f->yfov = (float)(2.0 * atan(0.375));
    for (int y = 8; y < 20; y++)
        for (int x = 10 + shift_x; x < 25 + shift_x; x++)
            hit(f, (size_t)y * 40 + (size_t)x, z, 0, 0, 1);
    return f;
}

/* surface_px: how far apart two surfaces are on screen, in closed form. At
 * depth 8 a unit spans 1 / (8 * 2 * 0.375 / 30) = 5 pixels. The only error
 * is float yfov and double rounding: 1e-5 px. */
static void test_surface_px(void **state)
{
    (void)state;
    mr_compare_result r;
    mr_error err = {0};
    mr_film *a = square(8.0f, 0);

    mr_film *b = square(8.0f, 0); /* equal films: 0 */
    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_true(r.surface_px == 0.0);
    mr_film_free(b);

    /* moved 3 pixels sideways: the 3 uncovered columns of either are 3
     * pixels from the other's nearest hit, less the half pixel the edge
     * sits between centres */
    b = square(8.0f, 3);
    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_float_equal(r.surface_px, 2.5, 1e-5);
    mr_film_free(b);

    /* moved 0.4 away along the view: 0.4 * 5 = 2 pixels at a's depth (and
     * 0.4 / (8.4 * 0.025) = 1.905 at b's: the larger counts), where depth_max
     * gives the same 0.4 whatever the distance */
    b = square(8.4f, 0);
    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_float_equal(r.surface_px, 0.4 * 5.0, 1e-5);
    mr_film_free(b);

    /* a surface at a grazing angle (depth steps by 1 a pixel) moved 0.5
     * along the view: within the depths its pixels span, so not counted,
     * where depth_max reads 0.5 */
    mr_film *g = square(8.0f, 0), *h = square(8.0f, 0);
    for (int y = 8; y < 20; y++)
        for (int x = 10; x < 25; x++) {
            g->z[y * 40 + x] = 8.0f + (float)(x - 10);
            h->z[y * 40 + x] = 8.5f + (float)(x - 10);
        }
    assert_int_equal(mr_film_compare(g, h, 1.0, &r, &err), MR_OK);
    assert_true(r.surface_px == 0.0);
    assert_float_equal(r.depth_max, 0.5, TOL);
    /* ... but 3 steps off is not: h(x) = g(x + 3). A pixel whose
     * neighbour column of h matches within the spans reads half a pixel;
     * g's first column has none: its own pixel of h is 3 - (1 + 1) = 1
     * unit beyond the spans, at depth 8: 5 pixels, the largest */
    for (int y = 8; y < 20; y++)
        for (int x = 10; x < 25; x++)
            h->z[y * 40 + x] = 11.0f + (float)(x - 10);
    assert_int_equal(mr_film_compare(g, h, 1.0, &r, &err), MR_OK);
    assert_float_equal(r.surface_px, 5.0, 1e-5);
    mr_film_free(g);
    mr_film_free(h);

    /* a hit with nothing of the other within the window (8 pixels) counts
     * the window plus one */
    b = square(8.0f, 0);
    hit(b, 2 * 40 + 38, 8.0f, 0, 0, 1); /* (38, 2): 13 columns from the square */
    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_true(r.surface_px == MR_SURFACE_WINDOW + 1);

    /* films without a camera: no way to place the points; 0 */
    a->has_camera = b->has_camera = false;
    assert_int_equal(mr_film_compare(a, b, 10.0, &r, &err), MR_OK);
    assert_true(r.surface_px == 0.0);
    mr_film_free(b);
    mr_film_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_identical), cmocka_unit_test(test_coverage),
        cmocka_unit_test(test_depth),     cmocka_unit_test(test_normals),
        cmocka_unit_test(test_psnr),      cmocka_unit_test(test_invalid),
        cmocka_unit_test(test_holes),     cmocka_unit_test(test_strays),     cmocka_unit_test(test_speckles),
        cmocka_unit_test(test_speckles_random),
        cmocka_unit_test(test_surface_px),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
