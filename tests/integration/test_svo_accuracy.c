/*
 * test_svo_accuracy.c - issue 5's accuracy contract: every svo method
 * against the skinned mesh rendered as triangles (the exact reference), on
 * a real animated character over its whole clip, through the real renderer
 * (Embree, the kind's user geometry and instancing).
 *
 * Scene: BCN_Epileptic.X (a real rig and clip) seen from the front, frames
 * spread evenly over the clip. For each method and depth the same job is
 * rendered twice, the object as kind "mesh" and as kind "svo"; per frame
 * the shared metrics (compare.h) are printed: coverage error, depth and
 * normal error, and holes (reference pixels, off its silhouette, that the
 * voxels miss).
 *
 * Asserted:
 *  - resize and emit leave no holes at any frame (the goal). Emit's
 *    cells cover every deformed box; resize's cells cover each box's centre
 *    region and neighbouring boxes overlap, so only the silhouette may
 *    erode (REFERENCE.md: <= 0.22 voxel), which "holes" does not count;
 *  - at the rest pose rigid, direct, resize and emit have no holes either;
 *  - coverage error below COVERAGE_PCT: voxels are up to a voxel thicker
 *    than the surface they enclose, deformed boxes are axis-aligned boxes
 *    around rotated voxels (up to sqrt(3) wider), resampling aligns them to
 *    a grid of cells at least as large as the box (up to one more cell), and
 *    screen-space selection keeps voxels of up to delta = 1 pixel whole. At
 *    480 x 360 the character covers ~8,000 pixels and a voxel of depth 8 is
 *    ~1 pixel, so the silhouette band is a few pixels wide: measured 7 %
 *    (rigid) to 33 % (emit, depth 7). 40 % still catches a limb in the
 *    wrong place (a mis-posed arm alone moves ~10 % of the pixels twice);
 *  - depth error (RMS over pixels both hit, relative to the scene diagonal
 *    of ~2.5 units) below DEPTH_RMSE: it is dominated by silhouette pixels
 *    where a fattened limb hides the body behind it; measured 5.5e-3 (rigid)
 *    to 4.6e-2 (emit, depth 7).
 * Direct boxes are reported, not asserted for holes when posed: the
 * thesis' direct output opens gaps where the deformation stretches
 * (measured: 5-10 hole pixels per frame at the worst pose).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include "../support/film_fixture.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "job_json.h"
#include "render/compare.h"
#include "render/device.h"
#include "render/renderer.h"

#define MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define FRAMES 8
#define COVERAGE_PCT 40.0
#define DEPTH_RMSE 0.06

static mr_job *make_job(const char *kind_fields, bool posed, double clip_duration)
{
    char times[512] = "", text[4096];
    for (int f = 0; f < FRAMES; f++) /* evenly over the whole clip */
        snprintf(times + strlen(times), sizeof times - strlen(times), "%s%.9g", f ? "," : "",
                 clip_duration * f / FRAMES);
    snprintf(text, sizeof text,
             "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},"
             "\"objects\":[{\"asset\":\"d\",%s%s}],"
             "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6]}],"
             "\"camera\":{\"yfov\":40,\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],"
             "\"target\":[0,0,-0.1]}]},"
             "\"frames\":{\"times\":[%s]},"
             "\"output\":{\"width\":480,\"height\":360,\"samples\":1}}",
             kind_fields, posed ? ",\"pose\":{\"clip\":0}" : "", times);
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(text, strlen(text), &job, &jerr) < 0)
        fail_msg("job: %s: %s", jerr.pointer, jerr.message);
    return job;
}

typedef struct frames {
    mr_film *film[FRAMES];
    double diagonal[FRAMES];
} frames;

static void render_all(mr_job *job, mr_asset *asset, frames *out)
{
    mr_device *dev = NULL;
    mr_renderer *r = NULL;
    mr_error err = {0};
    mr_asset *assets[1] = {asset};
    assert_int_equal(job->frame_count, FRAMES);
    if (mr_device_new(2, &dev, &err) < 0 || mr_renderer_new(dev, job, assets, NULL, &r, &err) < 0)
        fail_msg("renderer: %s", err.msg);
    for (size_t f = 0; f < FRAMES; f++) {
        mr_frame_stats st;
        assert_int_equal(mr_film_new(job->output.width, job->output.height, &out->film[f], &err),
                         MR_OK);
        if (mr_renderer_render(r, f, out->film[f], &st, &err) < 0)
            fail_msg("frame %zu: %s", f, err.msg);
        out->diagonal[f] = st.scene_diagonal;
    }
    mr_renderer_free(r);
    mr_device_free(dev);
}

static void free_frames(frames *f)
{
    for (size_t i = 0; i < FRAMES; i++)
        mr_film_free(f->film[i]);
}

static double clip_duration(const mr_asset *a)
{
    assert_true(a->clip_count > 0);
    return a->clips[0].duration > 0 ? a->clips[0].duration : 1.0;
}

static void check_method(mr_asset *asset, const frames *ref, const char *method, unsigned depth,
                         bool posed, bool want_no_holes)
{
    char fields[256];
    snprintf(fields, sizeof fields, "\"kind\":\"svo\",\"svo\":{\"depth\":%u,\"method\":\"%s\"}",
             depth, method);
    mr_job *job = make_job(fields, posed, clip_duration(asset));
    frames got = {0};
    render_all(job, asset, &got);
    size_t worst_holes = 0;
    double worst_cov = 0, worst_depth = 0;
    for (size_t f = 0; f < FRAMES; f++) {
        mr_compare_result c;
        mr_error err = {0};
        assert_int_equal(mr_film_compare(got.film[f], ref->film[f], ref->diagonal[f], &c, &err),
                         MR_OK);
        print_message("  %-6s depth %2u frame %zu: coverage %6.2f %%  depth rmse %.2e  normal "
                      "%5.1f deg  holes %zu (hit in either: %zu)\n",
                      method, depth, f, c.coverage_pct, c.depth_rmse, c.normal_mean_deg, c.holes,
                      c.hit_either);
        assert_true(c.hit_both > 0);
        worst_holes = c.holes > worst_holes ? c.holes : worst_holes;
        worst_cov = fmax(worst_cov, c.coverage_pct);
        worst_depth = fmax(worst_depth, c.depth_rmse);
    }
    print_message("%-6s depth %2u: worst coverage %.2f %%, depth rmse %.2e, holes %zu\n", method,
                  depth, worst_cov, worst_depth, worst_holes);
    if (want_no_holes)
        assert_int_equal(worst_holes, 0);
    assert_true(worst_cov < COVERAGE_PCT);
    assert_true(worst_depth < DEPTH_RMSE);
    free_frames(&got);
    mr_job_free(job);
}

static void test_methods_against_triangles(void **state)
{
    (void)state;
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &asset, &err) < 0)
        fail_msg("%s", err.msg);
    double dur = clip_duration(asset);

    mr_job *ref_job = make_job("\"kind\":\"mesh\"", true, dur);
    frames ref = {0};
    render_all(ref_job, asset, &ref);
    for (unsigned depth = 7; depth <= 8; depth++) {
        check_method(asset, &ref, "emit", depth, true, true);
        check_method(asset, &ref, "resize", depth, true, true);
        check_method(asset, &ref, "direct", depth, true, false);
    }
    free_frames(&ref);
    mr_job_free(ref_job);

    /* Rigid instances keep the rest pose: compare with the rest mesh (and
     * the deforming methods too, whose matrices are then the bind pose's). */
    mr_job *rest_job = make_job("\"kind\":\"mesh\"", false, dur);
    frames rest = {0};
    render_all(rest_job, asset, &rest);
    check_method(asset, &rest, "rigid", 8, false, true);
    check_method(asset, &rest, "direct", 8, false, true);
    check_method(asset, &rest, "resize", 8, false, true);
    check_method(asset, &rest, "emit", 8, false, true);
    free_frames(&rest);
    mr_job_free(rest_job);
    mr_asset_free(asset);
}

/* The public measurement hooks the benchmarks use (bench/bench_svo*.c):
 * the kind's per-frame fields, its creation figures on the renderer's
 * first frame only, the clip accessors and the exact triangle reference.
 * Exact relations (no timing is asserted beyond >= 0):
 *  - every selected voxel is a leaf or stands for at least one leaf below
 *    it, so selected <= the shared octree's leaves <= ... and deformed >=
 *    selected (every selected voxel was deformed on the way);
 *  - resize emits exactly 2 x 2 x 2 cells per deformed box, and its output
 *    octree (the frame's primitives) keeps at most the cells. */
static void test_stats_and_hooks(void **state)
{
    (void)state;
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &asset, &err) < 0)
        fail_msg("%s", err.msg);
    assert_int_equal(mr_asset_clip_count(asset), asset->clip_count);
    assert_true(mr_asset_clip_duration(asset, 0) == asset->clips[0].duration);
    assert_true(mr_asset_clip_duration(asset, asset->clip_count) == 0.0);
    assert_true(mr_asset_clip_duration(NULL, 0) == 0.0);

    char text[2048];
    snprintf(text, sizeof text,
             "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},"
             "\"objects\":[{\"asset\":\"d\",\"kind\":\"svo\",\"pose\":{\"clip\":0},"
             "\"svo\":{\"depth\":6,\"method\":\"resize\"}},{\"asset\":\"d\"}],"
             "\"camera\":{\"yfov\":40,\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],"
             "\"target\":[0,0,-0.1]}]},"
             "\"frames\":{\"times\":[0.5,1.0,1.5]},"
             "\"output\":{\"width\":96,\"height\":64,\"samples\":1}}");
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(text, strlen(text), &job, &jerr) < 0)
        fail_msg("job: %s: %s", jerr.pointer, jerr.message);
    mr_device *dev = NULL;
    mr_renderer *r = NULL;
    mr_film *film = NULL;
    mr_asset *assets[1] = {asset};
    if (mr_device_new(2, &dev, &err) < 0 || mr_renderer_new(dev, job, assets, NULL, &r, &err) < 0 ||
        mr_film_new(96, 64, &film, &err) < 0)
        fail_msg("renderer: %s", err.msg);
    double voxels = 0;
    for (size_t f = 0; f < 3; f++) {
        mr_frame_stats st;
        if (mr_renderer_render(r, f, film, &st, &err) < 0)
            fail_msg("frame %zu: %s", f, err.msg);
        double selected = fx_frame_extra(&st, "svo_selected"), cells = fx_frame_extra(&st, "svo_cells");
        if (f == 0) {
            voxels = fx_frame_extra(&st, "svo_voxels");
            assert_true(fx_frame_extra(&st, "svo_build_s") > 0);
        } else {
            assert_true(fx_frame_extra(&st, "svo_voxels") == voxels);
            assert_true(fx_frame_extra(&st, "svo_build_s") == 0); /* a creation figure: first frame only */
        }
        assert_true(fx_frame_extra(&st, "svo_skeleton_s") == 0 && fx_frame_extra(&st, "svo_bones") == 0);
        assert_true(selected > 0 && selected <= voxels);
        assert_true(fx_frame_extra(&st, "svo_deformed") >= selected);
        assert_true(cells == 8 * selected);
        /* the svo's output voxels plus the mesh object's triangles */
        assert_true((double)st.triangles <= cells + (double)asset->triangle_count);
        assert_true(fx_frame_extra(&st, "svo_octree_bytes") > 0);
        const char *const seconds[] = {"svo_pose_s", "svo_select_s", "svo_emit_s", "svo_rebuild_s"};
        for (int k = 0; k < 4; k++)
            assert_true(fx_frame_extra(&st, seconds[k]) >= 0);
    }
    /* the exact references: the skinned triangles of each object, at the
     * last frame's pose for the svo (posed), at rest for the mesh */
    for (size_t o = 0; o < 2; o++) {
        mr_trimesh m;
        if (mr_renderer_tessellate(r, o, &m, &err) < 0)
            fail_msg("tessellate %zu: %s", o, err.msg);
        assert_int_equal(m.triangle_count, asset->triangle_count);
        for (size_t i = 0; i < (size_t)m.triangle_count * 3; i++)
            assert_true(m.indices[i] < m.vertex_count);
        for (size_t i = 0; i < (size_t)m.vertex_count * 3; i++)
            assert_true(isfinite(m.positions[i]));
        mr_trimesh_free(&m);
    }
    mr_trimesh none;
    assert_int_equal(mr_renderer_tessellate(r, 2, &none, &err), MR_ERR_INVALID);
    assert_null(none.positions);
    mr_film_free(film);
    mr_renderer_free(r);
    mr_device_free(dev);
    mr_job_free(job);
    mr_asset_free(asset);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_stats_and_hooks),
        cmocka_unit_test(test_methods_against_triangles),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
