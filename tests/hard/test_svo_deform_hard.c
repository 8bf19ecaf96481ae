/*
 * test_svo_deform_hard.c - edge cases of selection, deformation and
 * resampling (core/kinds/svo/deform.h): the empty octree, a root leaf, a
 * zero-scale field (every box a point) and a flattening one (boxes with a
 * zero side, capped emission), a mirroring field (negative determinant), an
 * instance 1e5 away from the origin, non-finite matrices, an output of depth
 * 21, corrupt octrees; and a throughput printout on the BCN rig (depth 9,
 * or MR_SVO_DEFORM_BENCH_DEPTH; never asserted).
 *
 * Coverage is a point query with the library's ray caster (a zero-length
 * ray hits exactly the closed leaf boxes holding its origin), on float
 * points inside the float boxes: exact, no tolerance. Each case reports its
 * figures for `make hard` (hard_report.h): uncovered points, outputs off
 * their exact values, inputs accepted that must be refused.
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

#include "../support/bcn_fixture.h"
#include "anim/pose.h"
#include "kinds/svo/deform.h"
#include "kinds/svo/svo_build.h"
#include "kinds/svo/svo_trace.h"
#include "kinds/svo/voxelize.h"
#include "util/clock.h"
#include "../support/svo_rig.h"

#define HARD_KIND "svo"
#include "../support/hard_report.h"

static mr_svo *voxelize(const mr_asset *a, unsigned depth)
{
    mr_svo_voxelize_params p = {.depth = depth, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    mr_svo *s = NULL;
    mr_error err = {0};
    if (mr_svo_voxelize(a, &p, &s, &err) != MR_OK)
        fail_msg("voxelize: %s", err.msg);
    return s;
}

static void select_ok(const mr_svo *s, const mr_svo_extremes *e, const mr_svo_deformer *d, unsigned max_level,
                      mr_svo_selection *out)
{
    mr_error err = {0};
    if (mr_svo_select(s, e, d, NULL, max_level, 2, out, &err) != MR_OK)
        fail_msg("select: %s", err.msg);
}

static void resample_ok(const mr_svo_selection *sel, mr_svo_method m, unsigned depth, const mr_svo *src, mr_svo *out,
                        uint64_t *cells)
{
    mr_error err = {0};
    if (mr_svo_resample(sel, m, depth, src->palette, src->palette_count, 2, out, cells, &err) != MR_OK)
        fail_msg("resample: %s", err.msg);
}

static bool covered(const mr_svo *s, float x, float y, float z)
{
    return mr_svo_intersect(s, mr_v3(x, y, z), mr_v3(1, 1, 1), 0.0f, 0.0f, NULL);
}

/* Corners and centre of every box inside the output: the points that are
 * not (the first few printed) are counted into *uncovered, all into
 * *points. */
static void check_boxes_covered(const mr_svo *out, const mr_svo_selection *sel, uint64_t *points,
                                uint64_t *uncovered)
{
    for (size_t i = 0; i < sel->count; i++) {
        const float *b = &sel->box[i * 6];
        for (unsigned c = 0; c < 9; c++) {
            float p[3];
            for (int a = 0; a < 3; a++) {
                p[a] = c == 8 ? (float)(0.5 * ((double)b[a] + b[3 + a])) : ((c >> a) & 1) ? b[3 + a] : b[a];
                p[a] = p[a] < b[a] ? b[a] : p[a] > b[3 + a] ? b[3 + a] : p[a];
            }
            (*points)++;
            if (!covered(out, p[0], p[1], p[2]) && (*uncovered)++ < 5)
                print_error("box %zu [%.9g %.9g %.9g .. %.9g %.9g %.9g] point %u not covered\n", i, (double)b[0],
                            (double)b[1], (double)b[2], (double)b[3], (double)b[4], (double)b[5], c);
        }
    }
}

static const mr_svo_attr palette1[1] = {{{128, 128, 128}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}}};

/* ---- tiny octrees */

static void test_empty_octree(void **state)
{
    (void)state;
    mr_svo s;
    memset(&s, 0, sizeof s);
    s.depth = 4;
    s.size = 1.0f;
    s.palette = (mr_svo_attr *)palette1;
    s.palette_count = 1;
    mr_svo_extremes e;
    mr_error err = {0};
    int bad = 0;
    assert_int_equal(mr_svo_extremes_build(&s, &e, &err), MR_OK);
    HARD_EXPECT(bad, e.node_count == 0);
    const mr_affine I = affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0);
    mr_svo_deformer d = {.mesh_count = 1, .mesh = &I};
    mr_svo_selection sel = {0};
    select_ok(&s, &e, &d, 4, &sel);
    HARD_EXPECT(bad, sel.count == 0);
    HARD_EXPECT(bad, sel.visited == 0);
    for (int m = 0; m < 2; m++) {
        mr_svo out = {0};
        uint64_t cells = 99;
        resample_ok(&sel, m ? MR_SVO_EMIT : MR_SVO_RESIZE, 5, &s, &out, &cells);
        HARD_EXPECT(bad, cells == 0);
        HARD_EXPECT(bad, out.node_count == 0);
        HARD_EXPECT(bad, out.leaf_count == 0);
        HARD_EXPECT(bad, out.palette_count == 1);
        HARD_EXPECT(bad, !covered(&out, 0.5f, 0.5f, 0.5f));
        mr_svo_free(&out);
    }
    HARD_CHECK("other", bad, "==", 0,
               "outputs of the empty octree that are not empty (extremes, selection, resize and emit: 13)");
    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
}

static mr_affine shear_field(void *ctx, mr_vec3 p)
{
    (void)ctx;
    return affine_rows(1, 0.5f * p.z, 0, 3, 0, 1, 0, 0, 0, 0, 2, 0);
}

static void test_root_leaf(void **state)
{
    (void)state;
    mr_svo s;
    memset(&s, 0, sizeof s);
    mr_svo_leaf leaf = {{0, 0}, 0};
    mr_svo_normal_encode(mr_v3(0, 1, 0), leaf.normal);
    s.depth = 3;
    s.origin = mr_v3(-1, -1, -1);
    s.size = 2.0f;
    s.leaf_count = 1;
    s.leaves = &leaf;
    s.palette = (mr_svo_attr *)palette1;
    s.palette_count = 1;
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(&s, &e, &err), MR_OK);
    mr_svo_deformer d = {.field = shear_field};
    mr_svo_selection sel = {0};
    select_ok(&s, &e, &d, 3, &sel);
    assert_int_equal(sel.count, 1);
    assert_int_equal(sel.visited, 1);
    assert_int_equal(sel.level[0], 0);
    /* corners (+-1, +-1, +-1): the low one's matrix shears by -0.5, the
     * high one's by +0.5; x' = x + k y + 3 over both gives [1.5, 4.5],
     * z doubles */
    const float want[6] = {1.5f, -1, -2, 4.5f, 1, 2};
    double box_err = 0;
    for (int i = 0; i < 6; i++)
        box_err = hard_max(box_err, fabs((double)sel.box[i] - want[i]));
    HARD_CHECK("error", box_err, "==", 0, "largest |box bound - exact| of the sheared root leaf");
    uint64_t points = 0, uncovered = 0;
    for (int m = 0; m < 2; m++) {
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, m ? MR_SVO_EMIT : MR_SVO_RESIZE, 6, &s, &out, &cells);
        if (m)
            check_boxes_covered(&out, &sel, &points, &uncovered);
        else
            HARD_CHECK("other", cells, "==", 8, "resize: cells for the root leaf");
        mr_svo_free(&out);
    }
    HARD_CHECK("leaks", uncovered, "==", 0, "emit: box points not covered (of %llu)", (unsigned long long)points);
    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
}

/* ---- degenerate and mirrored fields on the real rig */

static mr_affine zero_field(void *ctx, mr_vec3 p)
{
    (void)ctx;
    (void)p;
    return affine_rows(0, 0, 0, 1.25f, 0, 0, 0, -2.5f, 0, 0, 0, 7.0f);
}

static mr_affine flat_field(void *ctx, mr_vec3 p)
{
    (void)ctx;
    (void)p;
    return affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0.5f); /* z collapsed onto 0.5 */
}

static mr_affine mirror_field(void *ctx, mr_vec3 p)
{
    (void)ctx;
    (void)p;
    return affine_rows(-1, 0, 0, 0.5f, 0, 1, 0, 0, 0, 0, 1, 0);
}

static void test_degenerate_fields(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 6;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);

    /* zero scale: every box is the point (1.25, -2.5, 7) */
    mr_svo_deformer zero = {.field = zero_field};
    mr_svo_selection sel = {0};
    select_ok(s, &e, &zero, D, &sel);
    assert_int_equal(sel.count, s->leaf_count);
    size_t off_point = 0, normal_lost = 0, wrong_cells = 0, uncovered_point = 0;
    for (size_t i = 0; i < sel.count; i++) {
        const float *b = &sel.box[i * 6];
        HARD_EXPECT(off_point,
                    b[0] == 1.25f && b[3] == 1.25f && b[1] == -2.5f && b[4] == -2.5f && b[2] == 7.0f && b[5] == 7.0f);
        /* the normal collapses: the bind normal is kept */
        HARD_EXPECT(normal_lost, memcmp(sel.leaf[i].normal, s->leaves[i].normal, 2) == 0);
    }
    HARD_CHECK("error", off_point, "==", 0, "zero scale: boxes that are not the point (1.25, -2.5, 7) (of %zu)",
               sel.count);
    HARD_CHECK("other", normal_lost, "==", 0, "zero scale: normals not kept from the bind pose");
    for (unsigned depth = 1; depth <= MR_SVO_MAX_DEPTH; depth += 10) {
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, MR_SVO_EMIT, depth, s, &out, &cells);
        HARD_EXPECT(wrong_cells, cells == sel.count); /* one finest cell each */
        HARD_EXPECT(wrong_cells, out.leaf_count == 1);
        HARD_EXPECT(uncovered_point, covered(&out, 1.25f, -2.5f, 7.0f));
        resample_ok(&sel, MR_SVO_RESIZE, depth, s, &out, &cells);
        HARD_EXPECT(wrong_cells, cells == 8 * sel.count);
        HARD_EXPECT(wrong_cells, out.leaf_count == 8); /* the same 8 finest cells each */
        HARD_EXPECT(uncovered_point, covered(&out, 1.25f, -2.5f, 7.0f));
        mr_svo_free(&out);
    }
    HARD_CHECK("other", wrong_cells, "==", 0,
               "zero scale: emit not 1 cell and voxel, resize not 8 (depths 1, 11, 21)");
    HARD_CHECK("leaks", uncovered_point, "==", 0, "zero scale: resampled octrees not covering the point");

    /* flat: boxes with a zero side; emit would want thousands of finest
     * cells per box and is capped by coarsening */
    mr_svo_deformer flat = {.field = flat_field};
    select_ok(s, &e, &flat, D, &sel);
    mr_svo out = {0};
    uint64_t cells = 0, points = 0, uncovered = 0;
    resample_ok(&sel, MR_SVO_EMIT, 10, s, &out, &cells);
    HARD_CHECK("other", cells, "<=", (double)MR_SVO_EMIT_MAX_CELLS * sel.count,
               "flat: emitted cells, capped at %d per box (%zu boxes)", (int)MR_SVO_EMIT_MAX_CELLS, sel.count);
    check_boxes_covered(&out, &sel, &points, &uncovered);
    print_message("flat: %zu boxes -> %llu cells -> %u voxels\n", sel.count, (unsigned long long)cells,
                  out.leaf_count);

    /* mirror in x: boxes stay ordered, normals stay outward (x flips) */
    mr_svo_deformer mirror = {.field = mirror_field};
    select_ok(s, &e, &mirror, D, &sel);
    assert_int_equal(sel.count, s->leaf_count);
    const double cell = (double)s->size * ldexp(1.0, -(int)D);
    size_t flipped = 0, disordered = 0;
    double widening = -INFINITY, normal_err = 0;
    for (size_t i = 0; i < sel.count; i++) {
        const float *b = &sel.box[i * 6];
        for (int ax = 0; ax < 3; ax++) {
            HARD_EXPECT(disordered, b[ax] <= b[3 + ax]);
            widening = hard_max(widening, (double)(b[3 + ax] - b[ax]) - cell);
        }
        const mr_vec3 n0 = mr_svo_normal_decode(s->leaves[i].normal), n1 = mr_svo_normal_decode(sel.leaf[i].normal);
        normal_err = hard_max(normal_err, fabsf(n1.x + n0.x));
        normal_err = hard_max(normal_err, fabsf(n1.y - n0.y));
        normal_err = hard_max(normal_err, fabsf(n1.z - n0.z));
        flipped += fabsf(n0.x) > 0.5f;
    }
    HARD_CHECK("other", disordered, "==", 0, "mirror: boxes with low > high (of %zu)", sel.count);
    /* outward rounding adds at most an ulp per side (coordinates < 4) */
    HARD_CHECK("error", widening, "<=", 0x1p-20, "mirror: largest box side beyond the voxel's");
    /* within the ~1 degree of the encoding, twice */
    HARD_CHECK("error", normal_err, "<", 0.05f, "mirror: largest normal component off the mirrored bind normal");
    HARD_CHECK("other", flipped, ">", 0, "mirror: normals with |x| > 0.5 (flipped)");
    resample_ok(&sel, MR_SVO_EMIT, D + 1, s, &out, &cells);
    check_boxes_covered(&out, &sel, &points, &uncovered);
    HARD_CHECK("leaks", uncovered, "==", 0, "flat and mirror: emitted box points not covered (of %llu)",
               (unsigned long long)points);
    mr_svo_free(&out);

    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* An instance 1e5 from the origin: floats there are 2^-7 apart, about a
 * voxel; boxes are still ordered and emit still covers them exactly. */
static void test_far_instance(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 7;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    rig r;
    rig_uniform(&r, a, affine_rows(1, 0, 0, 1e5f, 0, 1, 0, -1e5f, 0, 0, 1, 1e5f));
    mr_svo_selection sel = {0};
    select_ok(s, &e, &r.d, D, &sel);
    assert_int_equal(sel.count, s->leaf_count);
    size_t disordered = 0;
    for (size_t i = 0; i < sel.count; i++)
        for (int ax = 0; ax < 3; ax++)
            HARD_EXPECT(disordered, sel.box[i * 6 + ax] <= sel.box[i * 6 + 3 + ax]);
    HARD_CHECK("other", disordered, "==", 0, "boxes with low > high at 1e5 (of %zu)", sel.count);
    double origin_err = 0;
    uint64_t points = 0, uncovered = 0;
    for (int m = 0; m < 2; m++) {
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, m ? MR_SVO_EMIT : MR_SVO_RESIZE, D + 1, s, &out, &cells);
        origin_err = hard_max(origin_err, fabsf(out.origin.x - 1e5f));
        origin_err = hard_max(origin_err, fabsf(out.origin.y + 1e5f));
        if (m)
            check_boxes_covered(&out, &sel, &points, &uncovered);
        else
            HARD_CHECK("other", (double)cells - 8.0 * (double)sel.count, "==", 0,
                       "resize: cells minus 8 per voxel (%zu voxels)", sel.count);
        mr_svo_free(&out);
    }
    HARD_CHECK("error", origin_err, "<", 2.0f, "largest |output origin - (1e5, -1e5)| in x, y");
    HARD_CHECK("leaks", uncovered, "==", 0, "emit: box points not covered at 1e5 (of %llu)", (unsigned long long)points);
    mr_svo_selection_free(&sel);
    rig_free(&r);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- non-finite input */

static mr_affine nan_field(void *ctx, mr_vec3 p)
{
    const float lim = *(const float *)ctx;
    return affine_rows(1, 0, 0, p.x > lim ? NAN : 0.0f, 0, 1, 0, 0, 0, 0, 1, 0);
}

static void test_non_finite(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_svo *s = voxelize(a, 5);
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    rig r;
    rig_uniform(&r, a, affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0));
    mr_svo_selection sel = {0};
    int accepted = 0; /* non-finite deformations not refused as invalid */
    r.mesh[2].m[7] = NAN;
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 5, 2, &sel, &err) == MR_ERR_INVALID);
    print_message("NaN mesh matrix: %s\n", err.msg);
    r.mesh[2].m[7] = 0;
    r.joint[0][3].m[0] = INFINITY;
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 5, 2, &sel, &err) == MR_ERR_INVALID);
    r.joint[0][3].m[0] = 1;
    /* a field that goes bad over part of the shape */
    float lim = s->origin.x + 0.7f * s->size;
    mr_svo_deformer f = {.field = nan_field, .field_ctx = &lim};
    for (unsigned t = 1; t <= 2; t++) {
        HARD_EXPECT(accepted, mr_svo_select(s, &e, &f, NULL, 5, t, &sel, &err) == MR_ERR_INVALID);
        HARD_EXPECT(accepted, sel.count == 0);
        print_message("NaN field: %s\n", err.msg);
    }
    /* huge but finite matrices whose boxes leave the float range */
    rig_free(&r);
    rig_uniform(&r, a, affine_rows(3e38f, 3e38f, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0));
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 5, 2, &sel, &err) == MR_ERR_INVALID);
    print_message("overflow: %s\n", err.msg);
    HARD_CHECK("nan", accepted, "==", 0,
               "selections of NaN, Inf and overflowing deformations not refused (of 5; nothing selected)");
    rig_free(&r);
    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- depth 21 output */

static void test_depth21(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 6;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    /* the identity's boxes shrunk about their centres by 2^-14: tiny
     * voxels spread over the whole cube need levels near 21 */
    rig r;
    rig_uniform(&r, a, affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0));
    mr_svo_selection sel = {0};
    select_ok(s, &e, &r.d, D, &sel);
    for (size_t i = 0; i < sel.count; i++) {
        float *b = &sel.box[i * 6];
        for (int ax = 0; ax < 3; ax++) {
            const double c = 0.5 * ((double)b[ax] + b[3 + ax]), h = 0.5 * ((double)b[3 + ax] - b[ax]) * 0x1p-14;
            b[ax] = (float)(c - h);
            b[3 + ax] = (float)(c + h);
            assert_true(b[ax] <= b[3 + ax]);
        }
    }
    uint64_t points = 0, uncovered = 0;
    unsigned shallowest = MR_SVO_MAX_DEPTH;
    for (int m = 0; m < 2; m++) {
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, m ? MR_SVO_EMIT : MR_SVO_RESIZE, MR_SVO_MAX_DEPTH, s, &out, &cells);
        assert_int_equal(out.depth, MR_SVO_MAX_DEPTH);
        if (m)
            check_boxes_covered(&out, &sel, &points, &uncovered);
        else
            HARD_CHECK("other", (double)cells - 8.0 * (double)sel.count, "==", 0,
                       "resize: cells minus 8 per voxel (%zu voxels)", sel.count);
        /* levels reach deep into the octree */
        mr_svo_key *k = malloc(out.leaf_count * sizeof *k);
        assert_non_null(k);
        assert_int_equal(mr_svo_collect_keys(&out, k, NULL, &err), MR_OK);
        unsigned deepest = 0;
        for (uint32_t i = 0; i < out.leaf_count; i++)
            deepest = k[i].level > deepest ? k[i].level : deepest;
        print_message("depth 21 %s: %llu cells -> %u voxels, deepest level %u\n", m ? "emit" : "resize",
                      (unsigned long long)cells, out.leaf_count, deepest);
        shallowest = deepest < shallowest ? deepest : shallowest;
        free(k);
        mr_svo_free(&out);
    }
    HARD_CHECK("other", shallowest, ">=", 18, "deepest voxel level, smaller of resize and emit");
    HARD_CHECK("leaks", uncovered, "==", 0, "emit: box points not covered at depth 21 (of %llu)",
               (unsigned long long)points);
    rig_free(&r);
    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- corrupt octrees never crash */

static void test_corrupt_octree(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_svo *s = voxelize(a, 4);
    mr_svo_extremes e;
    mr_error err = {0};
    rig r;
    rig_uniform(&r, a, affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0));
    mr_svo_selection sel = {0};
    int accepted = 0; /* corrupt octrees not refused */
    /* an interior child index beyond the nodes */
    const uint32_t saved = s->first_node[0];
    s->first_node[0] = s->node_count;
    HARD_EXPECT(accepted, mr_svo_extremes_build(s, &e, &err) < 0);
    HARD_EXPECT(accepted, mr_svo_extremes_build(s, &(mr_svo_extremes){0}, &err) == MR_ERR_FORMAT);
    s->first_node[0] = saved;
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    /* corrupted after the extremes were built: the selection notices */
    s->first_leaf[s->node_count - 1] = s->leaf_count;
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 4, 2, &sel, &err) == MR_ERR_INVALID);
    print_message("corrupt: %s\n", err.msg);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    s = voxelize(a, 4);
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    /* a child pointing back to its parent (a cycle) */
    s->first_node[1] = 0;
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 4, 2, &sel, &err) == MR_ERR_INVALID);
    mr_svo_voxelize_free(s);
    s = voxelize(a, 4);
    /* a leaf naming a palette entry that does not exist */
    s->leaves[5].attr = (uint16_t)s->palette_count;
    HARD_EXPECT(accepted, mr_svo_select(s, &e, &r.d, NULL, 4, 2, &sel, &err) == MR_ERR_INVALID);
    print_message("bad attr: %s\n", err.msg);
    /* bad masks */
    s->leaves[5].attr = 0;
    s->child_mask[0] = 0;
    HARD_EXPECT(accepted, mr_svo_extremes_build(s, &(mr_svo_extremes){0}, &err) < 0);
    /* reading out of bounds stops the program under ASan (make hard) */
    HARD_CHECK("other", accepted, "==", 0,
               "corrupt octrees (child index out of range, a cycle, a bad palette entry, bad masks) not "
               "refused (of 6 calls)");
    rig_free(&r);
    mr_svo_selection_free(&sel);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- throughput (printed only) */

/* Depth 9 by default, to keep the suite quick; MR_SVO_DEFORM_BENCH_DEPTH=10
 * gives the figures of the task (the BCN rig at depth 10). */
static void test_throughput(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const char *env = getenv("MR_SVO_DEFORM_BENCH_DEPTH");
    const unsigned D = env && atoi(env) >= 1 && atoi(env) <= 11 ? (unsigned)atoi(env) : 9;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    mr_error err = {0};
    assert_int_equal(mr_svo_extremes_build(s, &e, &err), MR_OK);
    /* the clip's pose (object at the identity) */
    mr_pose *pose = NULL;
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    mr_pose_desc desc;
    memset(&desc, 0, sizeof desc);
    desc.has_clip = true;
    desc.has_time = true;
    desc.time = 0.5 * a->clips[0].duration;
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_OK);
    mr_svo_skin r;
    const mr_mat4 I = mr_mat4_identity();
    assert_int_equal(mr_svo_skin_init(&r, a, &err), MR_OK);
    mr_svo_skin_pose(&r, a, pose, &I);
    /* the second call, as per frame: the selection's buffers are reused */
    mr_svo_selection sel = {0};
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, D, 2, &sel, &err), MR_OK);
    double t0 = mr_now();
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, D, 2, &sel, &err), MR_OK);
    const double ts = mr_now() - t0;
    /* the speed is printed, never asserted; what is: the clip's pose selects
     * every voxel */
    HARD_CHECK("other", (double)sel.count - (double)s->leaf_count, "==", 0,
               "voxels the posed rig selects minus the octree's %u (depth %u)", s->leaf_count, D);
    print_message("BCN depth %u, 2 threads: select %zu voxels (%llu deformed) in %.1f ms: %.1f M voxels/s\n", D,
                  sel.count, (unsigned long long)sel.visited, ts * 1e3, (double)sel.visited / ts * 1e-6);
    for (int m = 0; m < 2; m++) {
        mr_svo out = {0};
        uint64_t cells = 0;
        t0 = mr_now();
        assert_int_equal(mr_svo_resample(&sel, m ? MR_SVO_EMIT : MR_SVO_RESIZE, D, s->palette, s->palette_count, 2,
                                         &out, &cells, &err),
                         MR_OK);
        const double tr = mr_now() - t0;
        print_message("  %s at depth %u: %llu cells -> %u voxels in %.1f ms: %.1f M cells/s\n",
                      m ? "emit" : "resize", D, (unsigned long long)cells, out.leaf_count, tr * 1e3,
                      (double)cells / tr * 1e-6);
        mr_svo_free(&out);
    }
    mr_svo_selection_free(&sel);
    mr_svo_skin_free(&r);
    mr_pose_free(pose);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_empty_octree),    cmocka_unit_test(test_root_leaf),
        cmocka_unit_test(test_degenerate_fields), cmocka_unit_test(test_far_instance),
        cmocka_unit_test(test_non_finite),      cmocka_unit_test(test_depth21),
        cmocka_unit_test(test_corrupt_octree),  cmocka_unit_test(test_throughput),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
