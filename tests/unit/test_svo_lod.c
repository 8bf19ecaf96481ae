/*
 * test_svo_lod.c - "tolerance_px" on svo objects (issue 16): the selecting
 * methods (direct, resize, emit) refine voxels until they project below
 * tolerance / sqrt(3) pixels, and report the selection's predicted error
 * (svo_lod_error_px: the most pixels a selected voxel's diagonal spans).
 *
 * A fly-through of the walking dancer (BCN_Epileptic.X, depth 8), the camera
 * flying in from 60 units to 3.2, 25 frames at 320x180 with reference
 * passes against the detailed mesh skinned directly (the ground truth):
 * methods emit and direct with tolerance_px 1, and emit without a
 * tolerance (delta 1) for comparison. Asserted: the prediction bounds the
 * measured error on every frame, and the frames within 1 px (see
 * test_flythrough).
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

static const char JOB[] =
    "{\"name\": \"svo-lod\", \"assets\": {\"dancer\": {\"path\": "
    "\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
    " \"objects\": [{\"name\": \"dancer\", \"asset\": \"dancer\", \"kind\": \"svo\","
    " \"pose\": {\"clip\": \"Epileptisch\", \"speed\": 1.0, \"loop\": true},"
    " \"svo\": {\"depth\": 8, \"method\": \"%s\"}, \"tolerance_px\": %s}],"
    " \"lights\": [{\"direction\": [-0.4, -0.8, -0.6], \"intensity\": 1.0}],"
    " \"camera\": {\"yfov\": 40, \"path\": [{\"t\": 0, \"position\": [0, 0.8, 60], \"target\": "
    "[0.1, 0.4, 0]}, {\"t\": 2, \"position\": [0.7, 0.7, 3.2], \"target\": [0.1, 0.4, 0]}]},"
    " \"frames\": {\"fps\": 12, \"start\": 0, \"end\": 2}, \"reference\": true,"
    " \"output\": {\"width\": 320, \"height\": 180, \"samples\": 1}}";

typedef struct flight {
    size_t frames, over;  /* frames, and those whose measured error passes 1 px */
    size_t leaf_limited;  /* frames that selected every leaf (the octree's depth is the limit) */
    double worst, worst_margin; /* largest measured surface_px; largest measured - predicted */
} flight;

/* The fly-through; tolerance: a JSON number or null. */
static flight flythrough(const char *method, const char *tolerance)
{
    char json[sizeof JOB + 64];
    snprintf(json, sizeof json, JOB, method, tolerance);
    mr_asset *dancer;
    assert_int_equal(lod_load_assets(json, &dancer, 1), 1);
    lod_run x;
    lod_open(&x, json, &dancer, NULL, 2);
    flight out = {.frames = x.job->frame_count, .worst_margin = -INFINITY};
    double all_leaves = 0;
    for (size_t i = 0; i < x.job->frame_count; i++) {
        mr_frame_stats st;
        mr_film_free(lod_frame(&x, i, &st));
        assert_int_equal(st.error_count, 1);
        assert_true(st.errors[0].reference == MR_REFERENCE_GROUND_TRUTH);
        double measured = st.errors[0].surface_px, predicted = fx_frame_extra(&st, "svo_lod_error_px");
        double selected = fx_frame_extra(&st, "svo_selected");
        if (i == 0)
            all_leaves = fx_frame_extra(&st, "svo_voxels");
        out.over += measured > 1.0;
        out.leaf_limited += selected == all_leaves;
        out.worst = fmax(out.worst, measured);
        if (strcmp(tolerance, "null")) {
            out.worst_margin = fmax(out.worst_margin, measured - predicted);
            /* the object's entry: the prediction and the deepest level
             * selected (the octree's depth, 8, when every leaf is) */
            assert_int_equal(st.lod_count, 1);
            assert_true(st.lod[0].object == 0 && st.lod[0].error_px == predicted);
            assert_true(st.lod[0].level <= 8 && (selected != all_leaves || st.lod[0].level == 8));
        } else {
            assert_true(predicted == 0 && st.lod_count == 0); /* no tolerance, no prediction */
        }
        print_message("%s, tolerance %s, frame %2zu: predicted %.3f px, measured %.3f px, %g of %g "
                      "voxels selected, %.1f ms\n", method, tolerance, i, predicted, measured,
                      selected, all_leaves, 1e3 * (st.pose_s + st.bvh_s + st.trace_s));
    }
    lod_close(&x);
    mr_asset_free(dancer);
    return out;
}

static void test_flythrough(void **state)
{
    (void)state;
    flight emit = flythrough("emit", "1"), plain = flythrough("emit", "null"),
           direct = flythrough("direct", "1");
    print_message("emit: %zu of %zu frames over 1 px with tolerance_px 1 (%zu limited by the "
                  "octree's depth; worst %.3f px), %zu without (delta 1; worst %.3f px); direct: "
                  "%zu over (worst %.3f px)\n", emit.over, emit.frames, emit.leaf_limited,
                  emit.worst, plain.over, plain.worst, direct.over, direct.worst);
    /* the prediction bounds what the reference pass measures, every frame
     * (measured: by 0.07 px at the least) */
    assert_true(emit.worst_margin <= 0 && direct.worst_margin <= 0);
    /* direct keeps every frame within the tolerance (worst 0.914 px); emit
     * misses where every leaf is selected (frame 24: the depth-8 octree's
     * leaves up close, predicted 1.85 px) and on one far frame where its
     * resampling grows a box by a cell (1.084 px): 2 of 25 frames, against
     * 19 of 25 at the default delta of 1 px */
    assert_int_equal(direct.over, 0);
    assert_true(emit.over <= 2 && emit.over < plain.over);
    assert_true(emit.leaf_limited >= 1);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_flythrough),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
