/*
 * test_displaced_lod.c - levels of detail of the displaced kind
 * ("tolerance_px", issue 16): a height texture's mip levels, each with its
 * distance to mip level 0 (mr_dgrid_distance), picked per frame by the
 * projected distance.
 *
 *  - the distance of two grids is the largest height difference anywhere:
 *    checked against dense sampling of both height fields (8 x 8 points per
 *    texel of level 0), equal for sides the level's factor divides, and for
 *    odd sides how much denser sampling finds beyond it (printed);
 *  - examples/lod-displaced.json (the displaced sphere, Wrinkles.jpg at
 *    1024 x 683, the camera flying in from 40 units to 2.4, tolerance_px
 *    1) at 320x180 with reference passes:
 *    every frame's surface_px against the ground truth (mip level 0
 *    tessellated) within the tolerance, levels coarse far away and level 0
 *    up close, a frame alone on one thread the same pixels;
 *  - the same fly-through with method "tessellated" picks the same levels
 *    and covers the same pixels (the traversal is exact at every level);
 *  - a procedural source's levels (its range halved): the distance of two
 *    ranges (mr_dproc_distance) against dense sampling of both height
 *    fields, and examples/displaced-ground.json flown over from far to
 *    near with reference passes, every frame within 1 px of its ground
 *    truth (twice the range, tessellated), coarse ranges far away.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "../support/displaced_fixture.h"
#include "../support/film_fixture.h"
#include "../support/lod_fixture.h"
#include "job_json.h"
#include "kinds/displaced/dgrid.h"
#include "kinds/displaced/dsurf.h"
#include "kinds/displaced/tiling.h"

/* ---- the distance of two grids ---- */

static double dense_distance(const mr_dgrid *a, const mr_dgrid *b)
{
    const mr_dheights ha = mr_dgrid_heights(a), hb = mr_dgrid_heights(b);
    const int sub = 8;
    double worst = 0;
    for (uint32_t y = 0; y < a->h * sub; y++)
        for (uint32_t x = 0; x < a->w * sub; x++) {
            double u = (double)x / sub / a->w, v = (double)y / sub / a->h;
            double d = mr_dsurf_height_at(&ha, u * a->w, v * a->h) -
                       mr_dsurf_height_at(&hb, u * b->w, v * b->h);
            worst = fmax(worst, fabs(d));
        }
    return worst;
}

static void test_grid_distance(void **state)
{
    (void)state;
    static const uint32_t SIZES[][2] = {{64, 64}, {48, 40}, {45, 37}};
    uint64_t seed = 7;
    for (size_t s = 0; s < sizeof SIZES / sizeof SIZES[0]; s++) {
        mr_asset *tex = dfx_texture(SIZES[s][0], SIZES[s][1], MR_SAMPLE_U8, dfx_noise, &seed);
        mr_dgrid fine;
        mr_error err;
        assert_int_equal(mr_dgrid_init(&fine, tex->image, 0, 0.3, -0.1, 2, &err), MR_OK);
        assert_true(mr_dgrid_distance(&fine, &fine, 2) == 0);
        for (unsigned k = 1; k <= 3; k++) {
            mr_dgrid coarse;
            assert_int_equal(mr_dgrid_init(&coarse, tex->image, k, 0.3, -0.1, 2, &err), MR_OK);
            double d = mr_dgrid_distance(&fine, &coarse, 2);
            assert_true(d == mr_dgrid_distance(&coarse, &fine, 2)); /* symmetric */
            double dense = dense_distance(&fine, &coarse);
            bool divides = SIZES[s][0] % (1u << k) == 0 && SIZES[s][1] % (1u << k) == 0;
            print_message("%ux%u level %u: distance %.6f, dense sampling %.6f%s\n", SIZES[s][0],
                          SIZES[s][1], k, d, dense, divides ? "" : " (sides not divisible)");
            /* dense sampling holds every sample of both grids when the
             * sides divide (8 points per texel of level 0; the level's
             * samples are level 0 samples): it cannot find less, and
             * finding more would be a crossing the figure misses. 1e-12:
             * the rounding of heights about 0.3 in double. */
            if (divides)
                assert_true(fabs(d - dense) <= 1e-12);
            assert_true(d > 0.05); /* noise: a coarse level strays by a fair part of 0.3 */
            mr_dgrid_free(&coarse);
        }
        mr_dgrid_free(&fine);
        mr_asset_free(tex);
    }
}

/* ---- the fly-through ---- */

/* examples/lod-displaced.json at 320x180 with reference passes, its
 * object traced by the given method. */
static char *flythrough_json(const char *method)
{
    cJSON *o = lod_example("lod-displaced", 320, 180);
    cJSON *obj = cJSON_GetArrayItem(cJSON_GetObjectItem(o, "objects"), 0);
    cJSON_AddStringToObject(cJSON_GetObjectItem(obj, "displaced"), "method", method);
    char *s = cJSON_PrintUnformatted(o);
    cJSON_Delete(o);
    return s;
}

#define MAX_FRAMES 64

static void test_flythrough(void **state)
{
    (void)state;
    char *json = flythrough_json("tessellation_free"), *tess_json = flythrough_json("tessellated");
    mr_asset *assets[2];
    mr_error err;
    assert_int_equal(lod_load_assets(json, assets, 2), 2); /* the sphere and the texture */
    lod_run x, t;
    lod_open(&x, json, assets, NULL, 2);
    lod_open(&t, tess_json, assets, NULL, 2);
    size_t frames = x.job->frame_count, probe = frames * 3 / 5;
    assert_true(frames >= 20 && frames <= MAX_FRAMES);
    mr_film *kept = NULL;
    double worst = 0, levels[MAX_FRAMES] = {0};
    size_t mismatched = 0, pixels = 0;
    double worst_dz = 0;
    for (size_t i = 0; i < frames; i++) {
        mr_frame_stats st, ts;
        mr_film *f = lod_frame(&x, i, &st), *g = lod_frame(&t, i, &ts);
        levels[i] = fx_frame_extra(&st, "displaced_lod_level");
        double predicted = fx_frame_extra(&st, "displaced_lod_error_px");
        /* the tessellated object picks by the same rule from the same
         * figures: the same level */
        assert_true(fx_frame_extra(&ts, "displaced_lod_level") == levels[i]);
        assert_true(predicted <= 1.0);
        /* the object's own entry says the same */
        assert_int_equal(st.lod_count, 1);
        assert_true(st.lod[0].object == 0 && st.lod[0].level == levels[i] &&
                    st.lod[0].error_px == predicted);
        assert_int_equal(st.error_count, 2);
        for (uint32_t e = 0; e < st.error_count; e++) {
            const mr_frame_error *fe = &st.errors[e];
            if (fe->reference == MR_REFERENCE_TESSELLATED) { /* the picked level tessellated */
                assert_true(fe->coverage_error_pct == 0 && fe->holes == 0);
                continue;
            }
            /* the ground truth is mip level 0 tessellated: the level's
             * whole error. The goal: within the tolerance on 99 % of
             * frames, i.e. all of these 25. */
            worst = fmax(worst, fe->surface_px);
            if (fe->surface_px > 1.0)
                fail_msg("frame %zu: level %g predicted %.3f px, measured %.3f px (coverage %.3f %%)",
                         i, levels[i], predicted, fe->surface_px, fe->coverage_error_pct);
        }
        /* tessellation-free against the same level tessellated: the same
         * pixels covered (no holes, nothing hit by one only) */
        mr_compare_result c;
        assert_int_equal(mr_film_compare(f, g, st.scene_diagonal, &c, &err), MR_OK);
        if (c.hit_one || c.holes)
            fail_msg("frame %zu (level %g): %zu pixels hit by one only, %zu holes", i, levels[i],
                     c.hit_one, c.holes);
        pixels += c.hit_both;
        for (int p = 0; p < f->width * f->height; p++)
            if (f->object_id[p]) {
                double dz = fabs((double)f->z[p] - g->z[p]) / st.scene_diagonal;
                worst_dz = fmax(worst_dz, dz);
                mismatched += dz > 1e-5;
            }
        print_message("frame %2zu: mip level %g, predicted %.3f px, measured %.3f px; %.1f ms "
                      "(tessellated %.1f ms)\n", i, levels[i], predicted,
                      st.errors[0].reference == MR_REFERENCE_GROUND_TRUTH ? st.errors[0].surface_px
                                                                          : st.errors[1].surface_px,
                      1e3 * (st.pose_s + st.bvh_s + st.trace_s),
                      1e3 * (ts.pose_s + ts.bvh_s + ts.trace_s));
        mr_film_free(g);
        if (i == probe)
            kept = f;
        else
            mr_film_free(f);
    }
    print_message("%zu frames, mip levels %g .. %g, worst surface_px against mip level 0 %.3f; "
                  "against the level tessellated: %zu pixels, coverage error 0, %zu deeper than "
                  "1e-5 of the diagonal apart (worst %.2e)\n",
                  frames, levels[0], levels[frames - 1], worst, pixels, mismatched, worst_dz);
    assert_true(levels[0] >= 4);          /* 40 units away: a coarse mip level */
    assert_true(levels[frames - 1] == 0); /* 2.4 units away, texels of a few pixels */
    for (size_t i = 1; i < frames; i++)   /* the camera only comes closer */
        assert_true(levels[i] <= levels[i - 1]);
    /* Embree's own triangle test lets a ray slip between micro-triangles
     * now and then (test_displaced_accuracy explains each such pixel by
     * brute force): a handful of pixels in all, not a level's worth */
    assert_true(mismatched <= 16);
    lod_close(&t);
    lod_close(&x);

    lod_assert_frame_alone(json, assets, probe, kept);
    for (size_t i = 0; i < 2; i++)
        mr_asset_free(assets[i]);
    cJSON_free(json);
    cJSON_free(tess_json);
}

/* ---- a procedural source's levels ---- */

/* mr_dproc_distance against dense sampling (16 x 16 points per fine cell)
 * of both height fields over a triangle of grid space, ranges 16 against
 * 8, 4 and 2: dense sampling holds every fine grid point, where the
 * distance is attained, so it finds the same (to 1e-12: heights about 0.3
 * in double), and nothing beyond it. */
static void test_proc_distance(void **state)
{
    (void)state;
    uint64_t seed = 11;
    mr_asset *ex = dfx_texture(64, 64, MR_SAMPLE_U8, dfx_noise, &seed);
    mr_error err;
    mr_dproc fine;
    assert_int_equal(mr_dproc_init(&fine, ex->image, 0.5, 0.5, 1.0, 0.25, 3, 16, 0.3, -0.1, 2, &err),
                     MR_OK);
    const double tri[6] = {-3.5, -2.25, 21.0, 1.5, 4.75, 19.0}; /* grid space of range 16 */
    const mr_dheights hf = mr_dproc_heights(&fine);
    for (uint32_t range = 8; range >= 2; range /= 2) {
        mr_dproc coarse;
        assert_int_equal(mr_dproc_init(&coarse, ex->image, 0.5, 0.5, 1.0, 0.25, 3, range, 0.3, -0.1,
                                       2, &err), MR_OK);
        const mr_dheights hc = mr_dproc_heights(&coarse);
        double d = mr_dproc_distance(&fine, &coarse, tri, 1, 2), dense = 0;
        const double k = 16.0 / range;
        for (int y = -4 * 16; y <= 20 * 16; y++)
            for (int x = -4 * 16; x <= 22 * 16; x++) {
                double gx = x / 16.0, gy = y / 16.0;
                /* inside the triangle's box, as the distance scans */
                if (gx < -3.5 || gx > 21.0 || gy < -2.25 || gy > 19.0)
                    continue;
                double e = mr_dsurf_height_at(&hf, gx, gy) - mr_dsurf_height_at(&hc, gx / k, gy / k);
                dense = fmax(dense, fabs(e));
            }
        print_message("range 16 against %u: distance %.6f, dense sampling %.6f\n", range, d, dense);
        assert_true(dense <= d + 1e-12);
        assert_true(d > 0.02); /* noise: a coarser range strays */
        mr_dproc_free(&coarse);
    }
    mr_dproc_free(&fine);
    mr_asset_free(ex);
}

/* examples/displaced-ground.json (the procedural ground, range 64) at
 * 320x180 with reference passes and tolerance_px 1, the camera flying
 * down at the ground from 30 units to its own 2.8: every frame within 1 px
 * of the ground truth (range 128 tessellated), predicted within it where a
 * coarser range is picked (up close the object's own range is predicted
 * above 1 px: the bound is the largest difference anywhere on the ground,
 * projected at its nearest point), the tessellated pass at the same level
 * covering the same pixels; far away a coarse range, close up the
 * object's own. */
static void test_proc_flythrough(void **state)
{
    (void)state;
    cJSON *o = lod_example("displaced-ground", 320, 180);
    cJSON_AddNumberToObject(o, "tolerance_px", 1.0);
    cJSON *frames = cJSON_CreateObject(); /* the example renders one time */
    cJSON_ReplaceItemInObject(o, "frames", frames);
    cJSON_AddNumberToObject(frames, "fps", 6);
    cJSON_AddNumberToObject(frames, "start", 0);
    cJSON_AddNumberToObject(frames, "end", 2);
    cJSON *cam = cJSON_CreateObject(), *keys = cJSON_AddArrayToObject(cam, "path");
    cJSON_AddNumberToObject(cam, "yfov", 40);
    for (int k = 0; k <= 12; k++) {
        /* the example's camera moved out along its own line of sight, from
         * 30 / 2.8 times as far down to its own place */
        double scale = pow(30.0 / 2.8, 1.0 - k / 12.0);
        const double p[3] = {0.0, 1.4 * scale, 2.4 * scale}, target[3] = {0.0, 0.0, 0.0};
        cJSON *key = cJSON_CreateObject();
        cJSON_AddNumberToObject(key, "t", k / 6.0);
        cJSON_AddItemToObject(key, "position", cJSON_CreateDoubleArray(p, 3));
        cJSON_AddItemToObject(key, "target", cJSON_CreateDoubleArray(target, 3));
        cJSON_AddItemToArray(keys, key);
    }
    cJSON_ReplaceItemInObject(o, "camera", cam);
    char *json = cJSON_PrintUnformatted(o);
    cJSON_Delete(o);
    mr_asset *assets[2];
    assert_int_equal(lod_load_assets(json, assets, 2), 2); /* the plane and the example */
    lod_run x;
    lod_open(&x, json, assets, NULL, 2);
    size_t frames_n = x.job->frame_count;
    double levels[MAX_FRAMES] = {0}, worst = 0;
    for (size_t i = 0; i < frames_n; i++) {
        mr_frame_stats st;
        mr_film *f = lod_frame(&x, i, &st);
        levels[i] = fx_frame_extra(&st, "displaced_lod_level");
        double predicted = fx_frame_extra(&st, "displaced_lod_error_px"), measured = -1;
        /* the object's own range strays from twice it by more than 1 px
         * up close: nothing finer to pick, it is traced and said */
        assert_true(predicted <= 1.0 || levels[i] == 0);
        assert_int_equal(st.error_count, 2);
        for (uint32_t e = 0; e < st.error_count; e++) {
            const mr_frame_error *fe = &st.errors[e];
            if (fe->reference == MR_REFERENCE_TESSELLATED)
                assert_true(fe->coverage_error_pct == 0 && fe->holes == 0);
            else
                measured = fe->surface_px;
        }
        print_message("frame %2zu: range / 2^%g, predicted %.3f px, measured %.3f px\n", i,
                      levels[i], predicted, measured);
        worst = fmax(worst, measured);
        if (!(measured <= 1.0))
            fail_msg("frame %zu: range / 2^%g measured %.3f px", i, levels[i], measured);
        mr_film_free(f);
    }
    print_message("%zu frames, worst surface_px against twice the range %.3f\n", frames_n, worst);
    assert_true(levels[0] >= 2);            /* far: at most a quarter of the range */
    assert_true(levels[frames_n - 1] <= 1); /* at the example's own camera: fine */
    lod_close(&x);
    for (size_t i = 0; i < 2; i++)
        mr_asset_free(assets[i]);
    cJSON_free(json);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_grid_distance),
        cmocka_unit_test(test_flythrough),
        cmocka_unit_test(test_proc_distance),
        cmocka_unit_test(test_proc_flythrough),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
