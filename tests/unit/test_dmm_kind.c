/*
 * test_dmm_kind.c - the `dmm` geometry kind in mode `tessellated`
 * (core/kinds/dmm/dmm_kind.c), rendered through the real renderer:
 *  - a bumpy sphere baked to a DMM renders like the detailed mesh, within
 *    coverage and depth bounds derived from the bake's reported distance;
 *  - level 0 with zero displacement renders exactly like the base mesh;
 *  - a skinned, refined real character (BCN_Epileptic.X) animates, and 1 and
 *    2 threads give bit-identical films;
 *  - parameters the kind cannot honour are refused;
 *  - with a cache directory, a bake is stored once and reused: the second
 *    create is a hit (the file is not rewritten, and a doctored but valid
 *    file shows through), with a tessellation bit-identical to a fresh
 *    bake, static and skinned; another level is another file; a corrupt or
 *    truncated file still renders and is rewritten; an unusable directory
 *    only costs the cache.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <cmocka.h>

#include <dirent.h>
#include <math.h>
#include <sys/stat.h>
#include <unistd.h>

#include "../support/bcn_fixture.h"
#include "../support/grid_fixture.h"
#include "../support/scene_fixture.h"
#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_file.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/kind.h"
#include "render/compare.h"

/* A create context without a disk cache (bake threads: all cores). */
static const mr_kind_context NO_CACHE = {.cache_dir = NULL, .threads = 0};


/* Unit icosphere subdivided `rounds` times, every vertex moved radially to
 * 1 + amp * sin(f x) sin(f y) sin(f z): smooth bumps the bake can follow. */
static mr_asset *make_bumpy_sphere(unsigned rounds, float amp, float f)
{
    const float t = 1.6180339887f;
    float v0[12][3] = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0}, {0, -1, t}, {0, 1, t},
                       {0, -1, -t}, {0, 1, -t}, {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
    uint32_t f0[20][3] = {{0, 11, 5}, {0, 5, 1}, {0, 1, 7}, {0, 7, 10}, {0, 10, 11},
                          {1, 5, 9}, {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                          {3, 9, 4}, {3, 4, 2}, {3, 2, 6}, {3, 6, 8}, {3, 8, 9},
                          {4, 9, 5}, {2, 4, 11}, {6, 2, 10}, {8, 6, 7}, {9, 8, 1}};
    size_t nt = 20, nv = 12;
    for (unsigned r = 0; r < rounds; r++)
        nt *= 4;
    size_t cap_v = nt * 3 + 12; /* midpoints are duplicated per triangle, then welded by the baker */
    float *p = malloc(cap_v * 3 * sizeof(float));
    uint32_t *idx = malloc(nt * 3 * sizeof(uint32_t));
    uint32_t *tmp = malloc(nt * 3 * sizeof(uint32_t));
    assert_true(p && idx && tmp);
    for (size_t i = 0; i < 12; i++)
        memcpy(p + i * 3, v0[i], sizeof v0[i]);
    memcpy(idx, f0, sizeof f0);
    size_t cur = 20;
    for (unsigned r = 0; r < rounds; r++) {
        size_t out = 0;
        for (size_t k = 0; k < cur; k++) {
            uint32_t a = idx[k * 3], b = idx[k * 3 + 1], c = idx[k * 3 + 2], m[3];
            uint32_t e[3][2] = {{a, b}, {b, c}, {c, a}};
            for (int j = 0; j < 3; j++) {
                /* Midpoint from the sorted pair: bit-identical on both sides. */
                uint32_t lo = e[j][0] < e[j][1] ? e[j][0] : e[j][1];
                uint32_t hi = e[j][0] ^ e[j][1] ^ lo;
                for (int q = 0; q < 3; q++)
                    p[nv * 3 + q] = 0.5f * (p[lo * 3 + q] + p[hi * 3 + q]);
                m[j] = (uint32_t)nv++;
            }
            uint32_t ch[4][3] = {{a, m[0], m[2]}, {m[0], b, m[1]}, {m[2], m[1], c}, {m[0], m[1], m[2]}};
            memcpy(tmp + out * 3, ch, sizeof ch);
            out += 4;
        }
        memcpy(idx, tmp, out * 3 * sizeof(uint32_t));
        cur = out;
    }
    for (size_t i = 0; i < nv; i++) {
        float *q = p + i * 3;
        float len = sqrtf(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
        float x = q[0] / len, y = q[1] / len, z = q[2] / len;
        float rad = 1.0f + amp * sinf(f * x) * sinf(f * y) * sinf(f * z);
        q[0] = x * rad;
        q[1] = y * rad;
        q[2] = z * rad;
    }
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_from_mesh("bumpy", p, NULL, (uint32_t)nv, idx, (uint32_t)cur, &asset, &err) < 0)
        fail_msg("asset: %s", err.msg);
    free(p);
    free(idx);
    free(tmp);
    return asset;
}

/* The largest distance of the rendered DMM surface to the detailed mesh that
 * the bake vouches for: its reported max distance (before quantisation) plus
 * the encoder's largest quantisation error (directions are at most unit
 * length, so a displacement error is at most that many model units). */
static double bake_bound(const mr_asset *a, const mr_dmm_params *d)
{
    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = d->level;
    bp.target_ratio = d->base_ratio;
    bp.target_triangles = d->base_triangles;
    mr_dmm_bake *b = NULL;
    mr_dmm_encoded *enc = NULL;
    mr_dmm_encode_stats st;
    mr_error err = {0};
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    assert_int_equal(mr_dmm_bake_run(&a->meshes[0], &bp, &b, &err), MR_OK);
    assert_int_equal(mr_dmm_encode(b->level, bits, b->base_triangle_count, b->tri_info, b->displacements, &enc,
                                   &st, &err),
                     MR_OK);
    double bound = b->max_distance + st.max_error;
    print_message("bake: %u base triangles, level %u, rms %.3g max %.3g, quantisation max %.3g\n",
                  b->base_triangle_count, b->level, b->rms_distance, b->max_distance, st.max_error);
    mr_dmm_encoded_free(enc);
    mr_dmm_bake_free(b);
    return bound;
}

static void test_matches_detailed_mesh(void **state)
{
    (void)state;
    const int W = 256, H = 256;
    mr_dmm_params d = {.level = 3, .base_ratio = 0.05f, .mode = MR_DMM_TESSELLATED};
    scene_fixture ref, dmm;
    /* Camera 4 units away, yfov 35 deg: the unit sphere is ~100 pixels in
     * radius, i.e. about 100 pixels per model unit at the silhouette. */
    fixture_init(&ref, make_bumpy_sphere(5, 0.06f, 6.0f), mr_v3(0.3f, 0.5f, 4), mr_v3(0, 0, 0), 35,
                 W, H, 1);
    fixture_init(&dmm, make_bumpy_sphere(5, 0.06f, 6.0f), mr_v3(0.3f, 0.5f, 4), mr_v3(0, 0, 0), 35,
                 W, H, 1);
    dmm.object.kind = &mr_kind_dmm;
    dmm.object.params = &d;
    double D = bake_bound(dmm.asset, &d);
    assert_true(D > 0 && D < 0.05);
    mr_frame_stats st;
    mr_film *fr = fixture_render(&ref, 0, &st);
    mr_film *fd = fixture_render(&dmm, 0, &st);
    assert_true(st.triangles % 64 == 0); /* 4^3 micro-triangles per base triangle */
    assert_film_finite(fd);
    mr_compare_result cmp;
    mr_error err = {0};
    assert_int_equal(mr_film_compare(fd, fr, 1.0, &cmp, &err), MR_OK);
    print_message("dmm vs detailed: coverage %.3f%% depth rmse %.3g max %.3g, normal mean %.2f deg\n",
                  cmp.coverage_pct, cmp.depth_rmse, cmp.depth_max, cmp.normal_mean_deg);
    assert_true(cmp.hit_both > 20000);
    /* Coverage: a pixel's (single) sample can only disagree when it passes
     * between the two silhouettes, which are at most D apart in space: a band
     * of about D * 100 pixels along a silhouette of 2 pi 100 pixels, against
     * pi 100^2 pixels covered. The bumps lengthen the silhouette a little and
     * the band is counted on both sides, hence factor 4:
     * coverage_pct <= 100 * 4 * 2 pi 100 (100 D) / (pi 100^2) = 800 D (%),
     * plus one pixel's worth of slack per silhouette pixel would be far more
     * than the bound allows, so this also catches cracks and holes. */
    double cov_bound = 800.0 * D;
    assert_true(cmp.coverage_pct <= cov_bound);
    /* Depth: along a view ray meeting the surface at angle theta the depth
     * gap is at most D / cos(theta); over a sphere's disk seen from outside,
     * the RMS of 1 / cos(theta) cut off one pixel from the rim is about 2,
     * so RMS depth <= 4 D leaves a factor 2 of margin. */
    assert_true(cmp.depth_rmse <= 4.0 * D);
    mr_film_free(fr);
    mr_film_free(fd);
    fixture_free(&ref);
    fixture_free(&dmm);
}

/* A flat 9x9-vertex grid in the z = 0 plane, interior vertices jittered
 * within the plane (so the base triangles are not all alike). */
static mr_asset *make_flat_grid(void)
{
    enum { N = 9 };
    float p[N * N * 3];
    uint32_t idx[(N - 1) * (N - 1) * 6];
    for (int y = 0; y < N; y++)
        for (int x = 0; x < N; x++) {
            bool inner = x > 0 && y > 0 && x < N - 1 && y < N - 1;
            float jx = inner ? 0.3f * sinf(7.0f * (float)(x * N + y)) : 0;
            float jy = inner ? 0.3f * cosf(5.0f * (float)(x + y * N)) : 0;
            p[(y * N + x) * 3] = ((float)x + jx) / (N - 1) * 2 - 1;
            p[(y * N + x) * 3 + 1] = ((float)y + jy) / (N - 1) * 2 - 1;
            p[(y * N + x) * 3 + 2] = 0;
        }
    const uint32_t nt = grid_triangles(N, N, idx);
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_from_mesh("grid", p, NULL, N * N, idx, nt, &asset, &err) < 0)
        fail_msg("asset: %s", err.msg);
    return asset;
}

/* Level 0, base_ratio 1: the base mesh is the (welded) detailed mesh and the
 * dmm surface is base + d * n at the corners. Renders the base mesh as `mesh`
 * and the detail as `dmm` and returns the largest depth difference over
 * pixels (coverage must agree exactly); *max_disp gets the largest |d|. */
static float level0_vs_base(mr_asset *detail, mr_vec3 eye, float *max_disp)
{
    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = 0;
    bp.target_ratio = 1.0f;
    mr_dmm_bake *b = NULL;
    mr_error err = {0};
    assert_int_equal(mr_dmm_bake_run(&detail->meshes[0], &bp, &b, &err), MR_OK);
    *max_disp = 0;
    for (size_t i = 0; i < (size_t)b->base_triangle_count * b->micro_vertex_count; i++)
        *max_disp = fmaxf(*max_disp, fabsf(b->displacements[i]));
    mr_asset *base = NULL;
    assert_int_equal(mr_asset_from_mesh("base", b->base_positions, NULL, b->base_vertex_count,
                                        b->base_indices, b->base_triangle_count, &base, &err),
                     MR_OK);
    mr_dmm_bake_free(b);

    scene_fixture ref, dmm;
    fixture_init(&ref, base, eye, mr_v3(0, 0, 0), 35, 160, 120, 1);
    fixture_init(&dmm, detail, eye, mr_v3(0, 0, 0), 35, 160, 120, 1);
    mr_dmm_params d = {.level = 0, .base_ratio = 1.0f, .mode = MR_DMM_TESSELLATED};
    dmm.object.kind = &mr_kind_dmm;
    dmm.object.params = &d;
    mr_frame_stats st;
    mr_film *fr = fixture_render(&ref, 0, &st);
    mr_film *fd = fixture_render(&dmm, 0, &st);
    size_t n = (size_t)fr->width * fr->height, hits = 0;
    float worst = 0;
    for (size_t i = 0; i < n; i++) {
        assert_int_equal(fr->object_id[i] != 0, fd->object_id[i] != 0);
        assert_true(fr->a[i] == fd->a[i]);
        worst = fmaxf(worst, fabsf(fr->z[i] - fd->z[i]));
        hits += fr->object_id[i] != 0;
    }
    assert_true(hits > n / 10);
    mr_film_free(fr);
    mr_film_free(fd);
    fixture_free(&ref);
    fixture_free(&dmm);
    return worst;
}

static void test_level0_is_base_mesh(void **state)
{
    (void)state;
    float d, z;
    /* A flat mesh: the baker's rays start on the surface, so every
     * displacement is exactly 0 and the dmm must BE the base mesh: identical
     * coverage and bit-identical depth (shading differs: dmm shades with
     * geometric normals, mesh with vertex normals). */
    z = level0_vs_base(make_flat_grid(), mr_v3(0.4f, -1.5f, 3), &d);
    assert_true(d == 0.0f);
    assert_true(z == 0.0f);
    /* A curved mesh: rays from a vertex hit its own triangles at t ~ 1e-9
     * rather than exactly 0 (Embree's rounding), so positions may move by
     * that much: depth within 1e-6 (10x the displacement bound measured on
     * a unit-size object, at our view angles), coverage still identical. */
    z = level0_vs_base(make_bumpy_sphere(2, 0.06f, 6.0f), mr_v3(0.3f, 0.5f, 4), &d);
    assert_true(d < 1e-7f);
    assert_true(z <= 1e-6f);
}

/* Shading normals of a rigidly placed object. With one matrix for every
 * base vertex the interpolated matrix is that matrix, and the cofactor of an
 * affine map sends a rest triangle's normal to the normal of the mapped
 * triangle: "matrix" normals must equal the micro-triangles' geometric
 * normals in direction, here under rotation plus non-uniform scale (where a
 * plain M n would tilt them). Tolerance: 1e-4 in the unit vectors' cosine,
 * float rounding of a cross product of micro-edges a few ulps long relative
 * to the object. Every mode (tessellated primitive ids and tessellation-free
 * base-triangle ids) is checked at every micro-triangle centre. */
static void test_matrix_normals_match_geometric_when_rigid(void **state)
{
    (void)state;
    mr_asset *a = make_bumpy_sphere(1, 0.05f, 5.0f);
    const mr_kind *ops = &mr_kind_dmm;
    mr_mat4 t = mr_mat4_from_trs(mr_v3(0.3f, -2.0f, 1.0f),
                                 mr_quat_from_axis_angle(mr_v3(1, 2, 3), 0.7f),
                                 mr_v3(2.0f, 0.5f, 1.3f));
    const mr_dmm_mode modes[3] = {MR_DMM_TESSELLATED, MR_DMM_BASE, MR_DMM_INTERPOLATED};
    for (int m = 0; m < 3; m++) {
        mr_geom *geo[2] = {NULL, NULL};
        for (int k = 0; k < 2; k++) {
            mr_dmm_params d = {.level = 2, .base_ratio = 0.5f, .mode = modes[m],
                               .deform = modes[m] == MR_DMM_INTERPOLATED ? MR_DMM_DEFORM_INTERPOLATED
                                                                         : MR_DMM_DEFORM_BASE,
                               .normals = k ? MR_DMM_NORMALS_MATRIX : MR_DMM_NORMALS_GEOMETRIC};
            mr_object_desc o = {.kind = &mr_kind_dmm, .params = &d};
            mr_error err = {0};
            assert_int_equal(ops->create(a, &o, &NO_CACHE, &geo[k], &err), MR_OK);
            assert_int_equal(ops->update(geo[k], NULL, NULL, &t, 1, &err), MR_OK);
        }
        uint64_t prims = modes[m] == MR_DMM_TESSELLATED ? ops->primitives(geo[0]) : 0;
        /* tessellation-free: base triangles, sampled at micro-triangle centres */
        uint32_t base = (uint32_t)(ops->primitives(geo[0]) / 16), n = 4;
        uint64_t checked = 0;
        double worst = 1;
        for (uint64_t prim = 0; prim < (prims ? prims : base); prim++)
            for (uint32_t cell = 0; cell < (prims ? 1u : n * n); cell++) {
                float u = 1.0f / 3, v = 1.0f / 3;
                if (!prims) {
                    uint32_t ia = cell % n, ib = cell / n;
                    if (ia + ib >= n)
                        continue;
                    u = ((float)ia + 1.0f / 3) / (float)n;
                    v = ((float)ib + 1.0f / 3) / (float)n;
                }
                mr_vec3 g = mr_v3_normalize_or(ops->normal(geo[0], (unsigned)prim, u, v, mr_v3(0, 0, 0)),
                                               mr_v3(0, 0, 0));
                mr_vec3 x = mr_v3_normalize_or(ops->normal(geo[1], (unsigned)prim, u, v, mr_v3(0, 0, 0)),
                                               mr_v3(0, 0, 0));
                double c = mr_v3_dot(g, x);
                worst = c < worst ? c : worst;
                checked++;
            }
        assert_true(checked > 100);
        if (!(worst > 1.0 - 1e-4))
            fail_msg("mode %d: matrix vs geometric normal cosine %.7f", (int)modes[m], worst);
        ops->free(geo[0]);
        ops->free(geo[1]);
    }
    mr_asset_free(a);
}

/* Normals "smooth" (issue 13): continuous across base edges, closer to the
 * true surface's normals than the micro-triangles' own, moved with the
 * object, and their shading point lifts hits off a convex surface.
 * A sphere of radius 1 (no bumps) refined 4 times (5120 triangles), baked
 * with a quarter as base triangles at level 2, rotated and scaled
 * non-uniformly. Tolerances: across a base edge both triangles interpolate
 * the same two coarse normals with weights from the same dyadic edge
 * parameter, so the normals agree to float rounding (cosine within 1e-6;
 * measured 1 - 4e-7); against the ellipsoid's analytic normal the smooth
 * ones must be off by less than 0.6x the geometric ones on average
 * (measured 0.59 vs 1.17 degrees: the coarse lattice here is a level above
 * the micro-triangles, so its interpolation error is what remains). */
static void test_smooth_normals(void **state)
{
    (void)state;
    mr_asset *a = make_bumpy_sphere(4, 0.0f, 1.0f);
    const mr_kind *ops = &mr_kind_dmm;
    mr_vec3 scale = mr_v3(2.0f, 0.5f, 1.3f);
    mr_quat rot = mr_quat_from_axis_angle(mr_v3(1, 2, 3), 0.7f);
    mr_mat4 t = mr_mat4_from_trs(mr_v3(0.3f, -2.0f, 1.0f), rot, scale);
    mr_mat4 inv_rot = mr_mat4_from_trs(mr_v3(0, 0, 0), (mr_quat){-rot.x, -rot.y, -rot.z, rot.w},
                                       mr_v3(1, 1, 1));
    mr_geom *geo[2] = {NULL, NULL};
    for (int k = 0; k < 2; k++) {
        mr_dmm_params d = {.level = 2, .base_ratio = 0.25f, .mode = MR_DMM_BASE,
                           .deform = MR_DMM_DEFORM_BASE,
                           .normals = k ? MR_DMM_NORMALS_SMOOTH : MR_DMM_NORMALS_GEOMETRIC};
        mr_object_desc o = {.kind = &mr_kind_dmm, .params = &d};
        mr_error err = {0};
        assert_int_equal(ops->create(a, &o, &NO_CACHE, &geo[k], &err), MR_OK);
        assert_int_equal(ops->update(geo[k], NULL, NULL, &t, 1, &err), MR_OK);
    }
    /* base triangle corners from the tessellation (one block of 15
     * micro-vertices per base triangle at level 2: corners at 0, 4, 14) */
    mr_trimesh tm;
    mr_error err = {0};
    assert_int_equal(ops->tessellate(geo[1], &tm, &err), MR_OK);
    uint32_t nb = tm.vertex_count / 15;
    const uint32_t corner[3] = {0, 4, 14};
    double sum[2] = {0, 0};
    size_t samples = 0, edges = 0;
    double worst_edge = 1;
    for (uint32_t b = 0; b < nb; b++) {
        /* against the ellipsoid's normal at the hit's direction: the rest
         * point x on the unit sphere maps to T x; the normal is R S^-1 x */
        for (int cell = 0; cell < 6; cell++) {
            float u = (float)(cell % 3 + 0.5) / 4, v = (float)(cell / 3 + 0.5) / 4;
            mr_vec3 p = mr_v3(0, 0, 0);
            const float *c0 = tm.positions + 3 * ((size_t)b * 15 + corner[0]);
            const float *c1 = tm.positions + 3 * ((size_t)b * 15 + corner[1]);
            const float *c2 = tm.positions + 3 * ((size_t)b * 15 + corner[2]);
            for (int q = 0; q < 3; q++)
                (&p.x)[q] = (1 - u - v) * c0[q] + u * c1[q] + v * c2[q];
            /* back to the rest sphere: undo translation, rotation, scale */
            mr_vec3 r = mr_mat4_dir(&inv_rot, mr_v3_sub(p, mr_v3(0.3f, -2.0f, 1.0f)));
            r = mr_v3_normalize_or(mr_v3(r.x / scale.x, r.y / scale.y, r.z / scale.z),
                                   mr_v3(0, 0, 1));
            mr_mat4 rs = mr_mat4_from_trs(mr_v3(0, 0, 0), rot, mr_v3(1, 1, 1));
            mr_vec3 truth = mr_v3_normalize_or(
                mr_mat4_dir(&rs, mr_v3(r.x / scale.x, r.y / scale.y, r.z / scale.z)),
                mr_v3(0, 0, 0));
            for (int k = 0; k < 2; k++) {
                mr_vec3 n = mr_v3_normalize_or(ops->normal(geo[k], b, u, v, mr_v3(0, 0, 0)), mr_v3(0, 0, 0));
                sum[k] += acos(fmin(1.0, fabs((double)mr_v3_dot(n, truth)))) * 180 / M_PI;
            }
            samples++;
            /* a convex surface: the shading point stands off it, outwards */
            mr_vec3 lifted;
            assert_true(ops->shading_point(geo[1], b, u, v, p, &lifted));
            mr_vec3 n = ops->normal(geo[1], b, u, v, mr_v3(0, 0, 0));
            assert_true(mr_v3_dot(mr_v3_sub(lifted, p), n) >= 0);
        }
        /* every edge shared with a later triangle, sampled from both sides */
        for (uint32_t o = b + 1; o < nb; o++)
            for (int e = 0; e < 3; e++)
                for (int f = 0; f < 3; f++) {
                    const float *b0 = tm.positions + 3 * ((size_t)b * 15 + corner[e]);
                    const float *b1 = tm.positions + 3 * ((size_t)b * 15 + corner[(e + 1) % 3]);
                    const float *o0 = tm.positions + 3 * ((size_t)o * 15 + corner[f]);
                    const float *o1 = tm.positions + 3 * ((size_t)o * 15 + corner[(f + 1) % 3]);
                    if (memcmp(b0, o1, 12) != 0 || memcmp(b1, o0, 12) != 0)
                        continue;
                    edges++;
                    for (int j = 1; j < 8; j++) {
                        float sp = (float)j / 8, so = 1 - sp;
                        float ub[2] = {e == 0 ? sp : e == 1 ? 1 - sp : 0, e == 1 ? sp : e == 2 ? 1 - sp : 0};
                        float uo[2] = {f == 0 ? so : f == 1 ? 1 - so : 0, f == 1 ? so : f == 2 ? 1 - so : 0};
                        mr_vec3 nb_ = mr_v3_normalize_or(ops->normal(geo[1], b, ub[0], ub[1], mr_v3(0, 0, 0)), mr_v3(0, 0, 0));
                        mr_vec3 no = mr_v3_normalize_or(ops->normal(geo[1], o, uo[0], uo[1], mr_v3(0, 0, 0)), mr_v3(0, 0, 0));
                        double c = mr_v3_dot(nb_, no);
                        worst_edge = c < worst_edge ? c : worst_edge;
                    }
                }
    }
    print_message("smooth normals: %zu samples, mean error %.3f deg (geometric %.3f); %zu shared "
                  "edges, worst cosine across them %.8f\n",
                  samples, sum[1] / samples, sum[0] / samples, edges, worst_edge);
    assert_true(edges * 2 >= nb * 3 - 3); /* a closed surface: (almost) every edge found */
    assert_true(worst_edge > 1.0 - 1e-6);
    assert_true(sum[1] < 0.6 * sum[0]);
    mr_trimesh_free(&tm);
    ops->free(geo[0]);
    ops->free(geo[1]);
    mr_asset_free(a);
}

/* World bounds of the asset in its rest pose. */
static void rest_bounds(const mr_asset *a, mr_vec3 *lo, mr_vec3 *hi)
{
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    assert_int_equal(mr_pose_eval(pose, a, NULL, 0, &err), MR_OK);
    *lo = mr_v3(INFINITY, INFINITY, INFINITY);
    *hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    for (size_t m = 0; m < a->mesh_count; m++) {
        float *p = malloc((size_t)a->meshes[m].vertex_count * 3 * sizeof(float) + 1);
        assert_non_null(p);
        mr_skin_mesh(a, m, pose, NULL, p, NULL, 1);
        for (uint32_t v = 0; v < a->meshes[m].vertex_count; v++) {
            mr_vec3 q = mr_v3(p[v * 3], p[v * 3 + 1], p[v * 3 + 2]);
            *lo = mr_v3_min(*lo, q);
            *hi = mr_v3_max(*hi, q);
        }
        free(p);
    }
    mr_pose_free(pose);
}

static void test_skinned_animates_deterministically(void **state)
{
    (void)state;
    mr_refine_params rp = {.rounds = 1, .amplitude = 0.0f};
    mr_asset *a = bcn_load_refined(&rp);
    assert_true(a->clip_count > 0);
    double duration = a->clips[0].duration;
    mr_vec3 lo, hi;
    rest_bounds(a, &lo, &hi);
    mr_vec3 c = mr_v3_scale(mr_v3_add(lo, hi), 0.5f);
    float r = 0.5f * mr_v3_len(mr_v3_sub(hi, lo));
    scene_fixture s;
    fixture_init(&s, a, mr_v3_add(c, mr_v3(0.4f * r, 0.3f * r, 2.8f * r)), c, 45, 96, 96, 1);
    mr_dmm_params d = {.level = 2, .base_ratio = 0.25f, .mode = MR_DMM_TESSELLATED};
    s.object.kind = &mr_kind_dmm;
    s.object.params = &d;
    mr_pose_desc pd = {.has_clip = true, .clip_index = 0, .speed = 1, .loop = true};
    s.object.pose_count = 1;
    s.object.poses = &pd;
    mr_frame_stats st;
    s.time = 0;
    mr_film *f0 = fixture_render(&s, 1, &st);
    s.time = 0.5 * duration;
    mr_film *f1 = fixture_render(&s, 1, &st);
    mr_film *f2 = fixture_render(&s, 2, &st);
    assert_film_finite(f1);
    size_t n = (size_t)f0->width * f0->height, differ = 0, hits = 0;
    for (size_t i = 0; i < n; i++) {
        differ += f0->z[i] != f1->z[i];
        hits += f1->object_id[i] != 0;
    }
    print_message("skinned dmm: %zu of %zu pixels hit, %zu depths differ between frames\n", hits,
                  n, differ);
    assert_true(hits > n / 50);
    assert_true(differ > 0); /* it moves */
    /* Any thread count gives the same frame, bit for bit. */
    assert_memory_equal(f1->z, f2->z, n * sizeof(float));
    assert_memory_equal(f1->r, f2->r, n * sizeof(float));
    assert_memory_equal(f1->nx, f2->nx, n * sizeof(float));
    assert_memory_equal(f1->prim_id, f2->prim_id, n * sizeof(uint32_t));
    mr_film_free(f0);
    mr_film_free(f1);
    mr_film_free(f2);
    fixture_free(&s);
}

static void test_refused(void **state)
{
    (void)state;
    mr_asset *a = make_bumpy_sphere(1, 0.0f, 1.0f);
    /* mode base deforms the base mesh; a request to interpolate matrices
     * with it is contradictory and refused rather than silently ignored */
    mr_dmm_params d = {.level = 3, .base_ratio = 0.5f, .mode = MR_DMM_BASE,
                       .deform = MR_DMM_DEFORM_INTERPOLATED};
    mr_object_desc o = {.kind = &mr_kind_dmm, .params = &d};
    mr_geom *g = NULL;
    mr_error err = {0};
    const mr_kind *ops = mr_kind_find("dmm");
    assert_non_null(ops);
    assert_string_equal(ops->name, "dmm");
    assert_int_equal(ops->create(a, &o, &NO_CACHE, &g, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "cannot use deformation"));
    assert_null(g);
    d.deform = MR_DMM_DEFORM_BASE;
    d.mode = MR_DMM_TESSELLATED;
    d.level = 6;
    assert_int_equal(ops->create(a, &o, &NO_CACHE, &g, &err), MR_ERR_INVALID);
    d.level = 1;
    d.base_ratio = 0;
    assert_int_equal(ops->create(a, &o, &NO_CACHE, &g, &err), MR_ERR_INVALID);
    d.base_ratio = 1;
    assert_int_equal(ops->create(a, &o, &NO_CACHE, &g, &err), MR_OK);
    /* 80 triangles at ratio 1 give 80 base triangles, 4 micro-triangles each. */
    assert_int_equal(ops->primitives(g), 80 * 4);
    assert_true(ops->memory(g) > 80 * 4 * 3 * sizeof(uint32_t));
    ops->free(g);
    mr_asset_free(a);
}

/* ---- the disk cache of bakes */

/* The object's exact tessellation after create (bakes cached in cache_dir,
 * or none when NULL) and one update at time t (clip 0 when the asset has
 * clips). Fails the test if create fails. */
static mr_trimesh tessellate_at(const mr_asset *a, const mr_dmm_params *d, const char *cache_dir,
                                double t)
{
    const mr_kind *ops = &mr_kind_dmm;
    mr_dmm_params params = *d;
    mr_object_desc o = {.kind = &mr_kind_dmm, .params = &params};
    mr_geom *g = NULL;
    mr_pose *pose = NULL;
    mr_error err = {0};
    if (ops->create(a, &o, &(mr_kind_context){.cache_dir = cache_dir}, &g, &err) < 0)
        fail_msg("create: %s", err.msg);
    mr_pose_desc pd = {.has_clip = a->clip_count > 0, .clip_index = 0, .speed = 1, .loop = true};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    assert_int_equal(mr_pose_eval(pose, a, &pd, t, &err), MR_OK);
    mr_mat4 id = mr_mat4_identity();
    if (ops->update(g, NULL, pose, &id, 1, &err) < 0)
        fail_msg("update: %s", err.msg);
    mr_trimesh m;
    if (ops->tessellate(g, &m, &err) < 0)
        fail_msg("tessellate: %s", err.msg);
    mr_pose_free(pose);
    ops->free(g);
    return m;
}

static void assert_same_mesh(const mr_trimesh *x, const mr_trimesh *y)
{
    assert_int_equal(x->vertex_count, y->vertex_count);
    assert_int_equal(x->triangle_count, y->triangle_count);
    assert_memory_equal(x->positions, y->positions, (size_t)x->vertex_count * 3 * sizeof(float));
    assert_memory_equal(x->indices, y->indices, (size_t)x->triangle_count * 3 * sizeof(uint32_t));
}

/* The one .dmm file in dir (fails unless there are exactly `want`). */
static void cache_file(const char *dir, size_t want, char *path, size_t n)
{
    DIR *dd = opendir(dir);
    assert_non_null(dd);
    size_t found = 0;
    for (struct dirent *e; (e = readdir(dd));) {
        size_t len = strlen(e->d_name);
        if (len > 4 && strcmp(e->d_name + len - 4, ".dmm") == 0) {
            found++;
            snprintf(path, n, "%s/%s", dir, e->d_name);
        }
        assert_null(strstr(e->d_name, ".tmp")); /* no temporary file left behind */
    }
    closedir(dd);
    assert_int_equal(found, want);
}

static void file_id(const char *path, struct stat *st) { assert_int_equal(stat(path, st), 0); }

static bool same_file(const struct stat *a, const struct stat *b)
{
    return a->st_ino == b->st_ino && a->st_mtim.tv_sec == b->st_mtim.tv_sec &&
           a->st_mtim.tv_nsec == b->st_mtim.tv_nsec && a->st_size == b->st_size;
}

/* Fresh bake, miss (stores), hit: one tessellation, bit for bit; and a
 * doctored but valid cache file shows through, which only a hit can do. */
static void check_hit(const mr_asset *a, mr_dmm_params d, double t, const char *dir)
{
    mr_trimesh fresh = tessellate_at(a, &d, NULL, t);
    mr_trimesh miss = tessellate_at(a, &d, dir, t);
    char path[512];
    cache_file(dir, 1, path, sizeof path);
    struct stat st0, st1;
    file_id(path, &st0);
    mr_trimesh hit = tessellate_at(a, &d, dir, t);
    file_id(path, &st1);
    assert_true(same_file(&st0, &st1)); /* not rewritten */
    assert_same_mesh(&fresh, &miss);
    assert_same_mesh(&fresh, &hit);

    /* shift every mesh's displacement grid: valid, same key, other surface */
    mr_dmm_file *f = NULL;
    mr_error err = {0};
    assert_int_equal(mr_dmm_file_read_path(path, &f, &err), MR_OK);
    for (uint32_t i = 0; i < f->mesh_count; i++)
        if (f->meshes[i].encoded)
            f->meshes[i].encoded->bias += 0.01f;
    assert_int_equal(mr_dmm_file_write_path(f, path, &err), MR_OK);
    mr_dmm_file_free(f);
    mr_trimesh doctored = tessellate_at(a, &d, dir, t);
    assert_int_equal(doctored.vertex_count, fresh.vertex_count);
    assert_true(memcmp(doctored.positions, fresh.positions,
                       (size_t)fresh.vertex_count * 3 * sizeof(float)) != 0);
    unlink(path);
    mr_trimesh_free(&doctored);
    mr_trimesh_free(&fresh);
    mr_trimesh_free(&miss);
    mr_trimesh_free(&hit);
}

static void make_temp_dir(char *dir, size_t n)
{
    snprintf(dir, n, "/tmp/mr-dmm-cache-XXXXXX");
    assert_non_null(mkdtemp(dir));
}

static void remove_dir(const char *dir)
{
    char cmd[600];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
    assert_int_equal(system(cmd), 0);
}

static void test_cache_hit_is_bit_identical(void **state)
{
    (void)state;
    char root[64], dir[128];
    make_temp_dir(root, sizeof root);
    snprintf(dir, sizeof dir, "%s/not/yet", root); /* created on the first store */

    mr_asset *sphere = make_bumpy_sphere(4, 0.06f, 6.0f);
    check_hit(sphere, (mr_dmm_params){.level = 3, .base_ratio = 0.05f, .mode = MR_DMM_TESSELLATED},
              0, dir);
    struct stat st;
    assert_int_equal(stat(dir, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0755);
    check_hit(sphere, (mr_dmm_params){.level = 2, .base_ratio = 0.1f, .mode = MR_DMM_BASE}, 0, dir);
    mr_asset_free(sphere);

    /* skinned, three meshes, posed mid-clip, matrices interpolated: the
     * stored joints and weights drive the same skinning */
    mr_asset *bcn = bcn_load();
    assert_true(bcn->clip_count > 0);
    check_hit(bcn,
              (mr_dmm_params){.level = 2, .base_ratio = 0.25f, .mode = MR_DMM_INTERPOLATED,
                              .deform = MR_DMM_DEFORM_INTERPOLATED,
                              .normals = MR_DMM_NORMALS_MATRIX},
              0.5 * bcn->clips[0].duration, dir);
    mr_asset_free(bcn);
    remove_dir(root);
}

static void test_cache_keys_corruption_and_failures(void **state)
{
    (void)state;
    char dir[64];
    make_temp_dir(dir, sizeof dir);
    mr_asset *a = make_bumpy_sphere(3, 0.06f, 6.0f);
    mr_dmm_params d = {.level = 2, .base_ratio = 0.1f, .mode = MR_DMM_TESSELLATED};
    mr_trimesh fresh = tessellate_at(a, &d, NULL, 0);
    const char *cache_dir = dir;
    mr_trimesh m = tessellate_at(a, &d, cache_dir, 0);
    mr_trimesh_free(&m);
    char path[512];
    cache_file(dir, 1, path, sizeof path);

    /* another level (or ratio) is another bake and another file */
    d.level = 3;
    m = tessellate_at(a, &d, cache_dir, 0);
    mr_trimesh_free(&m);
    cache_file(dir, 2, path, sizeof path);
    d.level = 2;
    d.base_ratio = 0.2f;
    m = tessellate_at(a, &d, cache_dir, 0);
    mr_trimesh_free(&m);
    cache_file(dir, 3, path, sizeof path);
    remove_dir(dir);
    make_temp_dir(dir, sizeof dir);
    d.base_ratio = 0.1f;
    m = tessellate_at(a, &d, cache_dir, 0);
    mr_trimesh_free(&m);
    cache_file(dir, 1, path, sizeof path);

    /* corrupt, then truncated, then garbage: each still renders the fresh
     * bake and is replaced by a valid file (a new inode: renamed in) */
    struct stat st;
    file_id(path, &st);
    off_t size = st.st_size;
    for (int round = 0; round < 3; round++) {
        FILE *f = fopen(path, "r+b");
        assert_non_null(f);
        if (round == 0) {
            fseek(f, size / 2, SEEK_SET);
            int c = fgetc(f);
            fseek(f, size / 2, SEEK_SET);
            fputc(c ^ 0x10, f);
        } else if (round == 1) {
            assert_int_equal(ftruncate(fileno(f), size - 7), 0);
        } else {
            assert_int_equal(ftruncate(fileno(f), 0), 0);
            fputs("not a dmm file at all", f);
        }
        fclose(f);
        struct stat bad;
        file_id(path, &bad);
        m = tessellate_at(a, &d, cache_dir, 0);
        assert_same_mesh(&fresh, &m);
        mr_trimesh_free(&m);
        struct stat now;
        file_id(path, &now);
        assert_true(now.st_ino != bad.st_ino);
        assert_int_equal(now.st_size, size);
        mr_dmm_file *ok = NULL;
        mr_error err = {0};
        if (mr_dmm_file_read_path(path, &ok, &err) != MR_OK)
            fail_msg("round %d: the rewritten file does not read: %s", round, err.msg);
        mr_dmm_file_free(ok);
    }

    /* a cache directory that cannot exist (below a regular file) or a
     * directory in the file's place: the job renders, uncached */
    char below[600];
    snprintf(below, sizeof below, "%s/dmm", path);
    cache_dir = below;
    m = tessellate_at(a, &d, cache_dir, 0);
    assert_same_mesh(&fresh, &m);
    mr_trimesh_free(&m);
    cache_dir = dir;
    assert_int_equal(unlink(path), 0);
    assert_int_equal(mkdir(path, 0755), 0);
    m = tessellate_at(a, &d, cache_dir, 0);
    assert_same_mesh(&fresh, &m);
    mr_trimesh_free(&m);
    mr_trimesh_free(&fresh);
    mr_asset_free(a);
    remove_dir(dir);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_cache_hit_is_bit_identical),
        cmocka_unit_test(test_cache_keys_corruption_and_failures),
        cmocka_unit_test(test_refused),
        cmocka_unit_test(test_matrix_normals_match_geometric_when_rigid),
        cmocka_unit_test(test_smooth_normals),
        cmocka_unit_test(test_level0_is_base_mesh),
        cmocka_unit_test(test_matches_detailed_mesh),
        cmocka_unit_test(test_skinned_animates_deterministically),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
