/*
 * test_dmm_lod.c - the dmm kind's levels of detail ("tolerance_px", issue 16;
 * core/kinds/dmm/dmm_kind.c, dmm_lod.h) on a real model (BCN_Epileptic.X).
 *
 *  - the bounds are what they say: each base triangle's share of the baked
 *    surface's two-sided distance to the detailed mesh, whose largest is
 *    that distance recomputed by brute force with another closest-point
 *    routine (svo's mr_tri_closest_point); the per-level bounds never
 *    shrink towards coarser levels; without a tolerance nothing is
 *    measured; mr_dmm_lod_coarsening (how far a coarser level strays from
 *    the baked one, under any decimation) against dense sampling on a
 *    random lattice: never beyond it, and reaching it;
 *  - examples/dmm-skinned.json flown through from far to near with
 *    "reference": true, the dancer still and walking: the measured error
 *    against the ground truth (surface_px) within the tolerance on at
 *    least 99 % of frames and the prediction within it, the tessellated
 *    reference (at the levels the object picked) exact, level 0 everywhere
 *    far away and the finest level in places close up while most base
 *    triangles stay coarser; per frame the finest and mean level, the
 *    predicted and measured pixels and the frame time against the finest
 *    level alone are printed;
 *  - the tessellation-free object and its exact reference (mode
 *    "tessellated", intersector "watertight") with the same tolerance pick
 *    the same levels and render the same pixels, on frames with different
 *    mixes of levels;
 *  - the bounds through the derived-data cache (dmm_lod.h): the first
 *    object measures and stores them, a second reads them (a valid file
 *    with another bound shows it is the file that answers), damaged files
 *    are measured again and stored as before, other parameters are another
 *    key.
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

/* the fly-through: frames a second, seconds, the camera's first distance */
#define FPS 12
#define DURATION 2
#define FAR 20.0
/* Where each fly-through ends: where the baked level still fits 1 px at
 * 320x180. The still dancer's baked surface strays from the detailed mesh
 * by up to 3.4e-3 units at rest: at 1.13 units the last frame traces level
 * 3 in places, predicted 0.996 px. Walking, it strays by up to 1.9e-2
 * units at the joints in the poses of its clip: those fit down to about
 * 6.5 units. */
#define STILL_NEAR 1.13
#define WALKING_NEAR 6.5
#define TMP_DIR_TEMPLATE "/tmp/mr-dmm-lod-XXXXXX"
#include "../support/bcn_fixture.h"
#include "../support/file_fixture.h"
#include "../support/film_fixture.h"
#include "../support/lod_fixture.h"
#include "job_json.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/dmm/dmm_lod.h"
#include "kinds/dmm/micromesh.h"
#include "kinds/kind.h"
#include "kinds/svo/voxelize.h"
#include "render/renderer.h"
#include "util/crc32.h"
#include "util/file_io.h"
#include "util/le.h"

/* ---- each level's error ---- */

/* The two-sided distance of dmm_lod.h, brute force: every vertex of the
 * detailed mesh (duplicates at one position give the same distance)
 * against the level; every micro-vertex a micro-triangle uses and every
 * micro-triangle's centroid against the detailed mesh. */
static double brute_error(const mr_asset *a, const mr_trimesh *level)
{
    double worst = 0;
    for (size_t i = 0; i < a->mesh_count; i++)
        for (uint32_t v = 0; v < a->meshes[i].vertex_count; v++) {
            double p[3];
            lod_point(a->meshes[i].positions, v, p);
            worst = fmax(worst, lod_brute_distance(level->positions, level->indices, level->triangle_count, p));
        }
    uint8_t *used = calloc(level->vertex_count, 1);
    assert_non_null(used);
    for (size_t e = 0; e < (size_t)level->triangle_count * 3; e++)
        used[level->indices[e]] = 1;
    for (uint32_t k = 0; k < level->vertex_count + level->triangle_count; k++) {
        double p[3];
        if (k < level->vertex_count) {
            if (!used[k])
                continue;
            lod_point(level->positions, k, p);
        } else {
            const uint32_t *t = level->indices + 3 * (size_t)(k - level->vertex_count);
            double c[3][3];
            for (int j = 0; j < 3; j++)
                lod_point(level->positions, t[j], c[j]);
            for (int j = 0; j < 3; j++)
                p[j] = (c[0][j] + c[1][j] + c[2][j]) / 3.0;
        }
        double d = INFINITY;
        for (size_t i = 0; i < a->mesh_count; i++)
            d = fmin(d, lod_brute_distance(a->meshes[i].positions, a->meshes[i].indices,
                                    a->meshes[i].triangle_count, p));
        worst = fmax(worst, d);
    }
    free(used);
    return worst;
}

static mr_geom *create(const mr_asset *a, mr_dmm_params *p, double tolerance_px)
{
    mr_object_desc o = {.kind = &mr_kind_dmm, .params = p, .tolerance_px = tolerance_px};
    mr_geom *g = NULL;
    mr_error err;
    if (mr_kind_dmm.create(a, &o, &(mr_kind_context){.cache_dir = tmp_dir}, &g, &err) < 0)
        fail_msg("create: %s", err.msg);
    return g;
}

/* The plain dancer (5k triangles) at level 2 over 1/16 of its triangles:
 * small enough for a brute force over every pair. Tolerance 1e-6 of the
 * dancer's size (about 2 units): both compute in double from the same
 * float points, the two closest-point routines round differently. */
static void test_error_is_the_distance(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_dmm_params p = {.level = 2, .base_ratio = 0.0625f, .mode = MR_DMM_BASE,
                       .deform = MR_DMM_DEFORM_BASE, .normals = MR_DMM_NORMALS_GEOMETRIC};
    mr_geom *g = create(a, &p, 1.0);
    assert_int_equal(mr_kind_dmm.geometry_ids(g), 1);
    mr_dmm_lod_table tab;
    assert_true(mr_dmm_lod_bounds(g, &tab));
    const uint32_t nt = tab.triangles;
    const double *bound = tab.error;
    double fine = 0;
    for (uint32_t t = 0; t < nt; t++)
        fine = fmax(fine, tab.fine[t]);
    mr_trimesh m;
    mr_error err;
    if (mr_dmm_rest_triangles(g, &m, &err) < 0)
        fail_msg("%s", err.msg);
    double brute = brute_error(a, &m);
    printf("baked level 2: %u micro-triangles, error %.9g, brute force %.9g\n", m.triangle_count,
           fine, brute);
    assert_float_equal(fine, brute, 1e-6);
    assert_true(brute > 0);
    mr_trimesh_free(&m);
    /* per base triangle: a coarser level never promises better, level 0
     * strays somewhere, every bound is finite, and a level without
     * decimation is within the bound that allows it */
    double worst[3] = {0, 0, 0};
    for (uint32_t t = 0; t < nt; t++) {
        const double *e = bound + (size_t)t * (MR_UMESH_MAX_LEVEL + 1);
        for (int l = 0; l < 3; l++) {
            assert_true(isfinite(e[l]) && e[l] >= 0);
            assert_true(l == 2 || e[l] >= e[l + 1]);
            assert_true(tab.whole[(size_t)t * (MR_UMESH_MAX_LEVEL + 1) + l] <= e[l]);
            worst[l] = fmax(worst[l], e[l]);
        }
    }
    printf("%u base triangles: largest bound %.3g / %.3g / %.3g at levels 0 / 1 / 2\n", nt,
           worst[0], worst[1], worst[2]);
    assert_true(worst[0] > worst[1] && worst[1] > 0);
    mr_kind_dmm.free(g);
    /* without a tolerance: no levels of detail, nothing measured */
    g = create(a, &p, 0);
    assert_false(mr_dmm_lod_bounds(g, &tab));
    assert_int_equal(mr_kind_dmm.geometry_ids(g), 1);
    mr_kind_dmm.free(g);
    mr_asset_free(a);
}

/* ---- how far a coarser level of one base triangle strays ---- */

/* Lattice weights of (x, y) (level-fine lattice units) in the triangle
 * with lattice corners (A[k], B[k]). */
static void weights_in(const double A[3], const double B[3], double x, double y, double w[3])
{
    double d1a = A[1] - A[0], d1b = B[1] - B[0], d2a = A[2] - A[0], d2b = B[2] - B[0];
    double det = d1a * d2b - d1b * d2a, px = x - A[0], py = y - B[0];
    w[1] = (px * d2b - py * d2a) / det;
    w[2] = (d1a * py - d1b * px) / det;
    w[0] = 1.0 - w[1] - w[2];
}

/* The surface of the count micro-triangles tris of level `level` over the
 * level-fine lattice pos at (x, y) (fine lattice units): the triangle that
 * holds it best (largest smallest weight), interpolated. */
static void surface_at(unsigned fine, const float *pos, unsigned level, const uint32_t *tris,
                       uint32_t count, double x, double y, double out[3])
{
    double best = -INFINITY, w[3], bw[3] = {0, 0, 0};
    uint32_t bi[3] = {0, 0, 0};
    unsigned up = fine - level;
    for (uint32_t k = 0; k < count; k++) {
        double A[3], B[3];
        uint32_t idx[3];
        for (int j = 0; j < 3; j++) {
            uint32_t a, b;
            mr_umesh_vertex_coords(level, tris[3 * k + j], &a, &b);
            A[j] = (double)(a << up), B[j] = (double)(b << up);
            idx[j] = mr_umesh_vertex_index(fine, a << up, b << up);
        }
        weights_in(A, B, x, y, w);
        double least = fmin(w[0], fmin(w[1], w[2]));
        if (least > best) {
            best = least;
            memcpy(bw, w, sizeof w);
            memcpy(bi, idx, sizeof idx);
        }
    }
    for (int i = 0; i < 3; i++)
        out[i] = bw[0] * pos[3 * bi[0] + i] + bw[1] * pos[3 * bi[1] + i] + bw[2] * pos[3 * bi[2] + i];
}

/* mr_dmm_lod_coarsening against dense sampling: a level-3 lattice of
 * random heights (and sideways jitter) on the unit triangle, every coarser
 * level and decimation mask; 20,000 random domain points plus every
 * lattice vertex and edge midpoint. It is exact: no sample exceeds it (up
 * to 1e-12, double rounding of values about 1), and the samples come
 * within 2 % of it (they miss the polygon corners where it is attained by
 * little at this density). Level 3 against itself, undecimated: 0. */
static void test_coarsening_exact(void **state)
{
    (void)state;
    const unsigned fine = 3;
    const uint32_t nv = mr_umesh_vertex_count(fine), n = mr_umesh_segments(fine);
    float pos[3 * 45];
    uint32_t seed = 12345;
    for (uint32_t i = 0; i < nv; i++) {
        uint32_t a, b;
        mr_umesh_vertex_coords(fine, i, &a, &b);
        float r[3];
        for (int k = 0; k < 3; k++) {
            seed = seed * 1664525u + 1013904223u;
            r[k] = (float)(seed >> 8) / 16777216.0f - 0.5f;
        }
        pos[3 * i] = (float)a / (float)n + 0.02f * r[0];
        pos[3 * i + 1] = (float)b / (float)n + 0.02f * r[1];
        pos[3 * i + 2] = 0.1f * r[2];
    }
    mr_umesh_topology topo;
    mr_error err;
    assert_int_equal(mr_umesh_topology_init(&topo, fine, &err), MR_OK);
    assert_true(mr_dmm_lod_coarsening(fine, pos, fine, topo.tris[fine][0], topo.count[fine][0]) == 0);
    double lowest_ratio = 1;
    for (unsigned l = 0; l <= fine; l++)
        for (unsigned m = 0; m < (l ? 8u : 1u); m++) {
            if (l == fine && m == 0)
                continue;
            const uint32_t *tris = topo.tris[l][m], count = topo.count[l][m];
            double bound = mr_dmm_lod_coarsening(fine, pos, l, tris, count), seen = 0;
            for (uint32_t s = 0; s < 20000 + 4 * (n + 1) * (n + 1); s++) {
                double x, y;
                if (s < 20000) {
                    seed = seed * 1664525u + 1013904223u;
                    x = (double)(seed >> 8) / 16777216.0 * n;
                    seed = seed * 1664525u + 1013904223u;
                    y = (double)(seed >> 8) / 16777216.0 * n;
                    if (x + y > n)
                        x = n - x, y = n - y;
                } else { /* lattice vertices and half-steps */
                    uint32_t q = s - 20000;
                    x = 0.5 * (q % (2 * n + 2)), y = 0.5 * (q / (2 * n + 2));
                    if (x + y > n)
                        continue;
                }
                double f[3], c[3];
                surface_at(fine, pos, fine, topo.tris[fine][0], topo.count[fine][0], x, y, f);
                surface_at(fine, pos, l, tris, count, x, y, c);
                double d = sqrt((f[0] - c[0]) * (f[0] - c[0]) + (f[1] - c[1]) * (f[1] - c[1]) +
                                (f[2] - c[2]) * (f[2] - c[2]));
                if (d > bound + 1e-12)
                    fail_msg("level %u mask %u: %.9g at (%g, %g) beyond the bound %.9g", l, m, d, x,
                             y, bound);
                seen = fmax(seen, d);
            }
            lowest_ratio = fmin(lowest_ratio, seen / bound);
            if (m == 0 || m == 7)
                printf("level %u mask %u: bound %.6f, sampled %.6f\n", l, m, bound, seen);
        }
    printf("sampled / bound: at least %.4f\n", lowest_ratio);
    assert_true(lowest_ratio > 0.98);
    mr_umesh_topology_free(&topo);
}

/* A surface with one triangle more: S's triangles and a copy of its first
 * triangle moved by `shift` along x (new vertices appended). */
static void with_extra(const mr_trimesh *s, float shift, float **pos, uint32_t **idx)
{
    *pos = malloc(((size_t)s->vertex_count + 3) * 3 * sizeof(float));
    *idx = malloc(((size_t)s->triangle_count + 1) * 3 * sizeof(uint32_t));
    assert_true(*pos && *idx);
    memcpy(*pos, s->positions, (size_t)s->vertex_count * 3 * sizeof(float));
    memcpy(*idx, s->indices, (size_t)s->triangle_count * 3 * sizeof(uint32_t));
    for (int k = 0; k < 3; k++) {
        const float *v = s->positions + 3 * (size_t)s->indices[k];
        float *o = *pos + 3 * ((size_t)s->vertex_count + k);
        o[0] = v[0] + shift, o[1] = v[1], o[2] = v[2];
        (*idx)[3 * (size_t)s->triangle_count + k] = s->vertex_count + k;
    }
}

/* Both sides count: a surface against itself with a triangle more (a
 * spike the level lost, or one it grew) is as far as that triangle's
 * farthest sample, brute force; measured one way each. */
static void test_both_sides(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_dmm_params p = {.level = 0, .base_ratio = 0.0625f, .mode = MR_DMM_BASE,
                       .deform = MR_DMM_DEFORM_BASE, .normals = MR_DMM_NORMALS_GEOMETRIC};
    mr_geom *g = create(a, &p, 0);
    mr_trimesh s;
    mr_error err;
    if (mr_dmm_rest_triangles(g, &s, &err) < 0)
        fail_msg("%s", err.msg);
    float *pos;
    uint32_t *idx;
    with_extra(&s, 0.1f, &pos, &idx);
    uint32_t nv = s.vertex_count + 3, nt = s.triangle_count + 1;
    /* the moved triangle's corners and centroid, brute force against S */
    double spike = 0, c[3] = {0, 0, 0};
    for (uint32_t k = 0; k < 3; k++) {
        double q[3];
        lod_point(pos, s.vertex_count + k, q);
        spike = fmax(spike, lod_brute_distance(s.positions, s.indices, s.triangle_count, q));
        for (int j = 0; j < 3; j++)
            c[j] += q[j] / 3.0;
    }
    double lost = spike; /* the truth's extra vertices against S */
    spike = fmax(spike, lod_brute_distance(s.positions, s.indices, s.triangle_count, c));
    assert_true(lost > 0.01);
    /* the truth has the extra triangle: only the truth-to-level side sees it */
    mr_dmm_lod_truth t;
    double d = 0;
    assert_int_equal(mr_dmm_lod_truth_init(&t, pos, nv, idx, nt, "test", &err), MR_OK);
    assert_int_equal(mr_dmm_lod_distance(&t, s.positions, s.vertex_count, s.indices, s.triangle_count,
                                         NULL, 1, 2, "test", &d, &err), MR_OK);
    printf("truth with a triangle more: %.9g (brute force %.9g)\n", d, lost);
    assert_float_equal(d, lost, 1e-9);
    mr_dmm_lod_truth_free(&t);
    /* the level has it: only the level-to-truth side sees it */
    assert_int_equal(mr_dmm_lod_truth_init(&t, s.positions, s.vertex_count, s.indices,
                                           s.triangle_count, "test", &err), MR_OK);
    d = 0;
    assert_int_equal(mr_dmm_lod_distance(&t, pos, nv, idx, nt, NULL, 1, 2, "test", &d, &err), MR_OK);
    printf("level with a triangle more: %.9g (brute force %.9g)\n", d, spike);
    assert_float_equal(d, spike, 1e-9);
    mr_dmm_lod_truth_free(&t);
    free(pos);
    free(idx);
    mr_trimesh_free(&s);
    mr_kind_dmm.free(g);
    mr_asset_free(a);
}

/* ---- the example flown through ---- */

static cJSON *json_vec3(double x, double y, double z)
{
    const double v[3] = {x, y, z};
    return cJSON_CreateDoubleArray(v, 3);
}

/* examples/dmm-skinned.json (the refined dancer, level 3, interpolated;
 * still: without its clip) at 320x180 and 12 frames a second over 2 s, the
 * camera flying straight at its chest from 20 units away to `near`, the
 * distance shrinking by the same factor every frame (a key per frame);
 * tolerance: its "tolerance_px" (0: none); reference passes when asked;
 * mode: the object's (NULL: the example's), with the intersector given. */
static char *example(bool still, double near, double tolerance, bool reference, const char *mode,
                     const char *intersector)
{
    cJSON *o = lod_example("dmm-skinned", 320, 180);
    if (!reference)
        cJSON_DeleteItemFromObject(o, "reference");
    cJSON *frames = cJSON_GetObjectItem(o, "frames");
    cJSON_ReplaceItemInObject(frames, "fps", cJSON_CreateNumber(FPS));
    cJSON_ReplaceItemInObject(frames, "end", cJSON_CreateNumber(DURATION));
    cJSON *cam = cJSON_CreateObject(), *keys = cJSON_AddArrayToObject(cam, "path");
    cJSON_AddNumberToObject(cam, "yfov", 40);
    for (int k = 0; k <= FPS * DURATION; k++) {
        double t = (double)k / FPS, z = FAR * pow(near / FAR, t / DURATION);
        cJSON *key = cJSON_CreateObject();
        cJSON_AddNumberToObject(key, "t", t);
        cJSON_AddItemToObject(key, "position", json_vec3(0.0, 0.0, z));
        cJSON_AddItemToObject(key, "target", json_vec3(0.0, 0.0, 0.0));
        cJSON_AddItemToArray(keys, key);
    }
    cJSON_ReplaceItemInObject(o, "camera", cam);
    if (tolerance > 0)
        cJSON_AddNumberToObject(o, "tolerance_px", tolerance);
    cJSON *obj = cJSON_GetArrayItem(cJSON_GetObjectItem(o, "objects"), 0);
    if (still)
        cJSON_DeleteItemFromObject(obj, "pose");
    cJSON *dmm = cJSON_GetObjectItem(obj, "dmm");
    if (mode) {
        cJSON_ReplaceItemInObject(dmm, "mode", cJSON_CreateString(mode));
        cJSON_AddStringToObject(dmm, "deformation", "interpolated");
        cJSON_AddStringToObject(dmm, "intersector", intersector);
    }
    char *s = cJSON_PrintUnformatted(o);
    cJSON_Delete(o);
    return s;
}

static mr_asset *dancer_load(void)
{
    /* examples/dmm-skinned.json's "refine" (flythrough checks it) */
    mr_refine_params rp = {.rounds = 2, .amplitude = 0.006f, .frequency = 12, .octaves = 3, .seed = 1};
    return bcn_load_refined(&rp);
}

#define FRAMES (FPS * DURATION + 1)

/* The example flown through to `near` with tolerance_px 1 and reference
 * passes: every frame's tessellated reference (the object at the level it
 * picked, traced triangle by triangle) exact, the predicted error within
 * the tolerance (the path ends where the finest level still fits), and the
 * error measured against the ground truth within it on at least 99 % of
 * frames; then the same frames at the finest level alone (no tolerance) for
 * time. Prints a row per frame; level[] gets the levels traced. */
static void flythrough(mr_asset *dancer, bool still, double near, double level[FRAMES],
                       double mean[FRAMES])
{
    char *json = example(still, near, 1.0, true, NULL, NULL);
    const mr_renderer_options opt = {.cache_dir = tmp_dir}; /* the bakes, once */
    lod_run x;
    lod_open(&x, json, &dancer, &opt, 2);
    const mr_asset_desc *ad = &x.job->assets[0];
    assert_true(ad->refine && ad->refine_params.rounds == 2 && ad->refine_params.amplitude == 0.006f &&
                ad->refine_params.seed == 1);
    double tolerance = x.job->objects[0].tolerance_px;
    assert_true(tolerance == 1.0);
    size_t frames = x.job->frame_count, over = 0;
    assert_int_equal(frames, FRAMES);
    double predicted[FRAMES], measured[FRAMES], seconds[FRAMES], finest_s[FRAMES];
    size_t unfit = 0;
    for (size_t i = 0; i < frames; i++) {
        mr_frame_stats st;
        mr_film_free(lod_frame(&x, i, &st));
        assert_int_equal(st.error_count, 2);
        for (uint32_t e = 0; e < st.error_count; e++) {
            const mr_frame_error *fe = &st.errors[e];
            if (fe->reference == MR_REFERENCE_TESSELLATED) {
                if (!(fe->coverage_error_pct == 0 && fe->surface_px == 0 &&
                      fe->psnr_rgb_db == MR_PSNR_IDENTICAL))
                    fail_msg("frame %zu: the tessellated reference differs (coverage %g %%, "
                             "surface %g px, psnr %g dB)", i, fe->coverage_error_pct,
                             fe->surface_px, fe->psnr_rgb_db);
                continue;
            }
            measured[i] = fe->surface_px;
        }
        level[i] = fx_frame_extra(&st, "dmm_lod_level");
        mean[i] = fx_frame_extra(&st, "dmm_lod_level_mean");
        predicted[i] = fx_frame_extra(&st, "dmm_lod_error_px");
        assert_int_equal(st.lod_count, 1); /* the object's own entry: the same */
        assert_true(st.lod[0].object == 0 && st.lod[0].level == level[i] &&
                    st.lod[0].error_px == predicted[i]);
        if (i == 0)
            printf("frame 0: geometry %.1f MiB (coarser levels %.1f MiB), bakes %.2f s, measuring "
                   "the levels %.2f s\n", (double)st.geometry_bytes / 1048576.0,
                   fx_frame_extra(&st, "dmm_lod_bytes") / 1048576.0,
                   fx_frame_extra(&st, "dmm_bake_s"), fx_frame_extra(&st, "dmm_lod_build_s"));
        seconds[i] = st.total_s;
        over += measured[i] > tolerance;
        unfit += !(predicted[i] <= tolerance);
    }
    lod_close(&x);
    cJSON_free(json);

    json = example(still, near, 0, false, NULL, NULL);
    lod_run y;
    lod_open(&y, json, &dancer, &opt, 2);
    for (size_t i = 0; i < frames; i++) {
        mr_frame_stats st;
        mr_film_free(lod_frame(&y, i, &st));
        assert_true(fx_frame_extra(&st, "dmm_lod_level") == 3);
        assert_true(fx_frame_extra(&st, "dmm_lod_error_px") == 0);
        assert_int_equal(st.lod_count, 0); /* no tolerance: no entry */
        assert_true(fx_frame_extra(&st, "dmm_lod_bytes") == 0);
        if (i == 0)
            printf("finest level alone, frame 0: geometry %.1f MiB\n",
                   (double)st.geometry_bytes / 1048576.0);
        finest_s[i] = st.total_s;
    }
    lod_close(&y);
    cJSON_free(json);
    double sum = 0, sum_finest = 0;
    printf("%s: frame level mean predicted_px surface_px seconds finest_s ratio\n", still ? "still" : "walking");
    for (size_t i = 0; i < frames; i++) {
        printf("%5zu %5g %5.2f %12.3f %10.3f %7.4f %8.4f %5.2f\n", i, level[i], mean[i], predicted[i],
               measured[i], seconds[i], finest_s[i], seconds[i] / finest_s[i]);
        if (i > 0) { /* frame 0 carries the set-up */
            sum += seconds[i];
            sum_finest += finest_s[i];
        }
    }
    printf("frames 1..%zu: %.3f s against %.3f s at the finest level (%.2fx); %zu of %zu frames "
           "over %g px\n", frames - 1, sum, sum_finest, sum / sum_finest, over, frames, tolerance);
    /* at least 99 % of frames within the tolerance: with 25 frames, all;
     * and every frame predicted within it (the path ends where the baked
     * level still fits) */
    assert_true(over <= (size_t)(0.01 * (double)frames));
    assert_int_equal(unfit, 0);
}

/* The dancer without its clip: its bounds are measured in the rest pose
 * it stands in. Far away every base triangle traces level 0; close up the
 * finest level appears where the surface needs it, while most triangles
 * stay coarser (a uniform level would trace them all at it). */
static void test_flythrough_still(void **state)
{
    (void)state;
    mr_asset *dancer = dancer_load();
    double level[FRAMES], mean[FRAMES];
    flythrough(dancer, true, STILL_NEAR, level, mean);
    assert_true(level[0] == 0 && mean[0] == 0); /* 20 units away */
    assert_true(level[FRAMES - 1] == 3);          /* close up: the finest somewhere */
    assert_true(mean[FRAMES - 1] > 0 && mean[FRAMES - 1] < 1); /* most triangles coarser */
    mr_asset_free(dancer);
}

/* The walking dancer: where a base triangle spans a joint, the
 * interpolated deformation and the detailed mesh's own skinning part in
 * the poses of its clip, so those triangles need finer levels (or none
 * fits) while the rest stay coarse: per base triangle, the coarse levels
 * stay wherever they fit. */
static void test_flythrough_walking(void **state)
{
    (void)state;
    mr_asset *dancer = dancer_load();
    double level[FRAMES], mean[FRAMES];
    flythrough(dancer, false, WALKING_NEAR, level, mean);
    assert_true(level[0] == 0 && mean[0] == 0);
    assert_true(level[FRAMES - 1] >= 2);                           /* at the joints */
    assert_true(mean[FRAMES - 1] > 0 && mean[FRAMES - 1] < 0.5);   /* the rest coarse */
    mr_asset_free(dancer);
}

/* The tessellation-free object (mode "interpolated") and its exact
 * reference (mode "tessellated", intersector "watertight") with the same
 * tolerance: they measure the same bounds on the same micro-triangles and
 * place every base triangle by the same box, so they pick the same levels
 * (the same finest and mean level every frame), and trace them to the same
 * pixels (0 differing, every plane), on frames of the still fly-through
 * with different mixes of levels. */
static void test_reference_picks_the_same_level(void **state)
{
    (void)state;
    mr_asset *dancer = dancer_load();
    char *free_json = example(true, STILL_NEAR, 1.0, false, NULL, NULL);
    char *ref_json = example(true, STILL_NEAR, 1.0, false, "tessellated", "watertight");
    const mr_renderer_options opt = {.cache_dir = tmp_dir};
    lod_run x, y;
    lod_open(&x, free_json, &dancer, &opt, 2);
    lod_open(&y, ref_json, &dancer, &opt, 2);
    const size_t frames[] = {0, FRAMES - 14, FRAMES - 3, FRAMES - 1};
    double mixes_seen = 0, last = -1;
    for (size_t k = 0; k < sizeof frames / sizeof *frames; k++) {
        mr_frame_stats a, b;
        mr_film *fa = lod_frame(&x, frames[k], &a), *fb = lod_frame(&y, frames[k], &b);
        double la = fx_frame_extra(&a, "dmm_lod_level"), lb = fx_frame_extra(&b, "dmm_lod_level");
        double ma = fx_frame_extra(&a, "dmm_lod_level_mean"), mb = fx_frame_extra(&b, "dmm_lod_level_mean");
        printf("frame %zu: levels up to %g, mean %.4f (tessellation-free) and up to %g, mean %.4f "
               "(tessellated)\n", frames[k], la, ma, lb, mb);
        assert_true(la == lb && ma == mb);
        assert_true(fx_frame_extra(&a, "dmm_lod_error_px") == fx_frame_extra(&b, "dmm_lod_error_px"));
        char what[64];
        snprintf(what, sizeof what, "frame %zu at levels up to %g", frames[k], la);
        fx_assert_same_pixels(fa, fb, what);
        mixes_seen += ma != last;
        last = ma;
        mr_film_free(fa);
        mr_film_free(fb);
    }
    assert_true(mixes_seen >= 3); /* at least three different mixes */
    lod_close(&x);
    lod_close(&y);
    cJSON_free(free_json);
    cJSON_free(ref_json);
    mr_asset_free(dancer);
}

/* The one file in dir whose name ends in ext other than `skip` (NULL:
 * any), malloc'ed path; NULL when there is none. */
static char *find_file(const char *dir, const char *ext, const char *skip)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    char *found = NULL;
    const size_t el = strlen(ext);
    for (struct dirent *e; (e = readdir(d)) && !found;) {
        const size_t n = strlen(e->d_name);
        if (n > el && strcmp(e->d_name + n - el, ext) == 0 && (!skip || !strstr(skip, e->d_name))) {
            found = malloc(strlen(dir) + n + 2);
            assert_non_null(found);
            sprintf(found, "%s/%s", dir, e->d_name);
        }
    }
    closedir(d);
    return found;
}

/* The bounds table (dmm_lod.h's file holds it) of an object with a
 * tolerance, created with cache folder `cache`: base triangle 0's fine
 * bound into *fine0, the whole table's figures summed into *sum. */
static void bounds_of(const mr_asset *a, mr_dmm_params *p, const char *cache, double *fine0,
                      double *sum)
{
    mr_object_desc o = {.kind = &mr_kind_dmm, .params = p, .tolerance_px = 1.0};
    mr_geom *g = NULL;
    mr_error err;
    if (mr_kind_dmm.create(a, &o, &(mr_kind_context){.cache_dir = cache}, &g, &err) < 0)
        fail_msg("create: %s", err.msg);
    mr_dmm_lod_table tab;
    assert_true(mr_dmm_lod_bounds(g, &tab));
    *fine0 = tab.fine[0];
    *sum = 0;
    for (uint32_t t = 0; t < tab.triangles; t++) {
        *sum += tab.fine[t];
        for (uint32_t l = 0; l < MR_DMM_LOD_LEVELS; l++)
            *sum += tab.error[t * MR_DMM_LOD_LEVELS + l] + tab.whole[t * MR_DMM_LOD_LEVELS + l];
    }
    mr_kind_dmm.free(g);
}

/* Both CRCs of a bounds file of size bytes after an edit. */
static void reseal(uint8_t *file, size_t size)
{
    mr_le_put_u32(file + 56, mr_crc32(file + 64, size - 64));
    mr_le_put_u32(file + 60, mr_crc32(file, 60));
}

static void test_errors_cached(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    char cache[128];
    snprintf(cache, sizeof cache, "%s/errors", tmp_dir);
    mr_dmm_params p = {.level = 2, .base_ratio = 0.0625f, .mode = MR_DMM_INTERPOLATED,
                       .deform = MR_DMM_DEFORM_INTERPOLATED, .normals = MR_DMM_NORMALS_GEOMETRIC};
    double fine0, sum, fine0_again, sum_again;
    bounds_of(a, &p, cache, &fine0, &sum);
    assert_true(fine0 > 0 && sum > 0);
    char *path = find_file(cache, ".mrdle", NULL);
    assert_non_null(path);
    size_t size;
    uint8_t *bytes = file_get(path, &size);
    const uint32_t nt = mr_le_get_u32(bytes + 16);
    assert_int_equal(mr_le_get_u32(bytes + 8), 2);       /* version */
    assert_int_equal(mr_le_get_u32(bytes + 20), 6);      /* levels per triangle */
    assert_int_equal(size, 64 + (size_t)nt * 13 * 8);   /* 13 f64 per base triangle */
    bounds_of(a, &p, cache, &fine0_again, &sum_again);
    assert_true(fine0_again == fine0 && sum_again == sum);
    /* a valid file with another fine bound for triangle 0: read, not
     * measured */
    uint8_t *other = malloc(size);
    assert_non_null(other);
    memcpy(other, bytes, size);
    mr_le_put_f64(other + 64, fine0 * 0.5);
    reseal(other, size);
    file_put(path, other, size);
    bounds_of(a, &p, cache, &fine0_again, &sum_again);
    assert_true(fine0_again == fine0 * 0.5);
    /* damaged ones, measured again and stored as they were: a byte of a
     * bound flipped (the payload CRC left); a coarser level's bound below
     * a finer one's (both CRCs right) */
    other[66] ^= 0x10;
    file_put(path, other, size);
    bounds_of(a, &p, cache, &fine0_again, &sum_again);
    assert_true(fine0_again == fine0 && sum_again == sum);
    memcpy(other, bytes, size);
    mr_le_put_f64(other + 64 + 8, 0.5 * mr_le_get_f64(other + 64 + 16)); /* level 0 < level 1 */
    reseal(other, size);
    file_put(path, other, size);
    bounds_of(a, &p, cache, &fine0_again, &sum_again);
    assert_true(fine0_again == fine0 && sum_again == sum);
    size_t size2;
    uint8_t *restored = file_get(path, &size2);
    assert_int_equal(size2, size);
    assert_memory_equal(restored, bytes, size);
    /* other parameters: another key, another file */
    p.base_ratio = 0.125f;
    bounds_of(a, &p, cache, &fine0_again, &sum_again);
    char *path2 = find_file(cache, ".mrdle", path);
    assert_non_null(path2);
    free(path2);
    free(restored);
    free(other);
    free(bytes);
    free(path);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_error_is_the_distance),
        cmocka_unit_test(test_coarsening_exact),
        cmocka_unit_test(test_both_sides),
        cmocka_unit_test(test_flythrough_still),
        cmocka_unit_test(test_flythrough_walking),
        cmocka_unit_test(test_reference_picks_the_same_level),
        cmocka_unit_test(test_errors_cached),
    };
    return cmocka_run_group_tests(tests, file_fixture_setup, file_fixture_teardown);
}
