/*
 * test_springmass_lod.c - "tolerance_px" on spring-mass objects (issue
 * 16): each frame maps the detailed mesh by the cheapest of triangle_basis,
 * triangle_basis_curvature and trilinear whose distance to the trilinear
 * mapping (the ground truth), measured at every 16th vertex and projected
 * at the mesh's nearest depth, stays below the tolerance.
 *
 * examples/springmass-probe.json (Wuson refined to 59,712 faces over 8,000
 * nodes, a probe pressing along its back) with the camera flying in from
 * 40 units to the example's own 4.6, 19 frames at 320x180, tolerance_px 1,
 * reference passes: the ground truth is the same simulation mapped
 * trilinearly.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "../support/film_fixture.h"
#include "../support/lod_fixture.h"

/* The example at 320x180 over 1.5 s at 12 fps, reference passes, the
 * tolerance, and a camera flying in along its own line of sight. */
static char *example(void)
{
    cJSON *o = lod_example("springmass-probe", 320, 180);
    cJSON_AddNumberToObject(o, "tolerance_px", 1);
    cJSON_ReplaceItemInObject(o, "frames", cJSON_Parse("{\"fps\": 12, \"start\": 0, \"end\": 1.5}"));
    /* the example's camera key, moved back along its line of sight */
    cJSON *key = cJSON_GetArrayItem(cJSON_GetObjectItem(cJSON_GetObjectItem(o, "camera"), "path"), 0);
    double p[3], t[3];
    for (int a = 0; a < 3; a++) {
        p[a] = cJSON_GetArrayItem(cJSON_GetObjectItem(key, "position"), a)->valuedouble;
        t[a] = cJSON_GetArrayItem(cJSON_GetObjectItem(key, "target"), a)->valuedouble;
    }
    double d = sqrt((p[0] - t[0]) * (p[0] - t[0]) + (p[1] - t[1]) * (p[1] - t[1]) +
                    (p[2] - t[2]) * (p[2] - t[2]));
    char path_json[512];
    snprintf(path_json, sizeof path_json,
             "[{\"t\": 0, \"position\": [%.6f, %.6f, %.6f], \"target\": [%.6f, %.6f, %.6f]},"
             " {\"t\": 1.5, \"position\": [%.6f, %.6f, %.6f], \"target\": [%.6f, %.6f, %.6f]}]",
             t[0] + (p[0] - t[0]) * 40 / d, t[1] + (p[1] - t[1]) * 40 / d,
             t[2] + (p[2] - t[2]) * 40 / d, t[0], t[1], t[2], p[0], p[1], p[2], t[0], t[1], t[2]);
    cJSON_ReplaceItemInObject(cJSON_GetObjectItem(o, "camera"), "path", cJSON_Parse(path_json));
    char *s = cJSON_PrintUnformatted(o);
    cJSON_Delete(o);
    return s;
}

static void test_flythrough(void **state)
{
    (void)state;
    char *json = example();
    mr_asset *asset;
    assert_int_equal(lod_load_assets(json, &asset, 1), 1);
    lod_run x;
    lod_open(&x, json, &asset, NULL, 2);
    const mr_job *job = x.job;
    double worst = 0;
    uint32_t first = 0, last = 0;
    for (size_t i = 0; i < job->frame_count; i++) {
        mr_frame_stats st;
        mr_film_free(lod_frame(&x, i, &st));
        assert_int_equal(st.lod_count, 1);
        const mr_object_lod *l = &st.lod[0];
        assert_true(l->level <= 2);
        assert_true(l->error_px <= 1.0 && (l->level > 0 || l->error_px == 0));
        double measured = -1;
        for (uint32_t e = 0; e < st.error_count; e++)
            if (st.errors[e].reference == MR_REFERENCE_GROUND_TRUTH)
                measured = st.errors[e].surface_px;
            else /* the object itself: picks the same mapping */
                assert_true(st.errors[e].coverage_error_pct == 0 && st.errors[e].surface_px == 0);
        assert_true(measured >= 0);
        worst = fmax(worst, measured);
        print_message("frame %2zu: mapping level %u, predicted %.3f px, measured %.3f px, map %.2f "
                      "ms\n", i, l->level, l->error_px, measured, 1e3 * fx_frame_extra(&st, "map_s"));
        if (measured > 1.0)
            fail_msg("frame %zu: level %u predicted %.3f px, measured %.3f px", i, l->level,
                     l->error_px, measured);
        if (i == 0)
            first = l->level;
        last = l->level;
    }
    print_message("%zu frames, mapping levels %u .. %u, worst surface_px against trilinear %.3f\n",
                  job->frame_count, first, last, worst);
    assert_int_equal(first, 2); /* 40 units away: triangle_basis */
    lod_close(&x);
    mr_asset_free(asset);
    cJSON_free(json);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_flythrough),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
