/*
 * test_displaced_hard.c - the displaced kind's hard cases (issue 14), each
 * traced through Embree and the kind's traversal and compared with the
 * brute force over the exact tessellation (displaced_fixture.h: hit or
 * miss identical, t bit for bit):
 *  - zero UV area (all three texture coordinates equal, or collinear) and
 *    flipped (mirrored) texture coordinates;
 *  - texture coordinates spanning many repeats (40 periods of a 5 x 3
 *    texture against the brute force; 100,000 periods, too many to
 *    tessellate, against the bound the surface must lie in);
 *  - displacement larger than the triangle;
 *  - near-zero and opposing vertex normals (their interpolation passes
 *    through zero inside the triangle);
 *  - rays parallel to the base plane, grazing it, and starting inside the
 *    displaced shell (between the lowest and highest height);
 *  - 1x1 and non-power-of-two textures;
 *  - a skinned base (FBX/animation_with_skeleton.fbx, a bending bar with
 *    texture coordinates) over its clip and in extreme joint poses (joints
 *    twisted by up to 170 degrees and scaled by 0.05 and 20).
 * Each case reports for `make hard` (hard_report.h) the rays that disagree
 * with the brute force (hit, t bit for bit, occlusion) and its own figures.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <cmocka.h>

#include <float.h>
#include <math.h>

#include "../support/displaced_fixture.h"

#define HARD_KIND "displaced"
#include "../support/hard_report.h"

#define BAR "/usr/share/assimp/models/FBX/animation_with_skeleton.fbx"

/* A 4 x 4 vertex grid of 18 triangles on y = 0 (x, z in [-1, 1]) whose
 * texture coordinates come from uv(x, z). */
static mr_asset *grid_mesh(void (*uv)(int x, int z, float out[2]), const float *normal_of)
{
    enum { N = 4 };
    float P[N * N * 3], NR[N * N * 3], UV[N * N * 2];
    uint32_t I[(N - 1) * (N - 1) * 6];
    for (int z = 0; z < N; z++)
        for (int x = 0; x < N; x++) {
            int v = z * N + x;
            P[v * 3] = -1 + 2.0f * x / (N - 1), P[v * 3 + 1] = 0, P[v * 3 + 2] = -1 + 2.0f * z / (N - 1);
            for (int c = 0; c < 3; c++)
                NR[v * 3 + c] = normal_of ? normal_of[v * 3 + c] : (c == 1);
            uv(x, z, UV + v * 2);
        }
    int k = 0;
    for (int z = 0; z + 1 < N; z++)
        for (int x = 0; x + 1 < N; x++) {
            uint32_t a = (uint32_t)(z * N + x), b = a + 1, c = a + N, d = c + 1;
            uint32_t q[6] = {a, c, d, a, d, b};
            memcpy(I + k, q, sizeof q);
            k += 6;
        }
    return dfx_mesh(P, NR, UV, N * N, I, (N - 1) * (N - 1) * 2);
}

static void uv_plain(int x, int z, float o[2]) { o[0] = x / 3.0f, o[1] = z / 3.0f; }
static void uv_flipped(int x, int z, float o[2]) { o[0] = 1 - x / 3.0f, o[1] = z / 3.0f; }
/* the middle vertices collapse to one texture point: triangles around them
 * have zero or collinear UV area */
static void uv_degenerate(int x, int z, float o[2])
{
    bool mid = (x == 1 || x == 2) && (z == 1 || z == 2);
    o[0] = mid ? 0.5f : x / 3.0f;
    o[1] = mid ? 0.5f : (x == 0 ? 0.25f : z / 3.0f);
}
static void uv_repeats(int x, int z, float o[2]) { o[0] = 40 * x / 3.0f, o[1] = 40 * z / 3.0f; }
static void uv_huge(int x, int z, float o[2]) { o[0] = 1e5f * x / 3.0f, o[1] = 1e5f * z / 3.0f; }
/* grid coordinates past 2^63: their cells as integers were undefined */
static void uv_absurd(int x, int z, float o[2]) { o[0] = 1e25f * x / 3.0f, o[1] = 1e25f * z / 3.0f; }
static void uv_finer(int x, int z, float o[2]) { o[0] = 1e7f * x / 3.0f, o[1] = 1e7f * z / 3.0f; }

/* Random rays at the displaced mesh against the brute force: returns the
 * rays that disagree; the smallest share of rays that hit so far in
 * *hit_share. */
static int run(mr_asset *mesh, mr_asset *tex, float scale, float offset, uint64_t *seed, int rays,
               double *hit_share)
{
    dfx f = {0};
    dfx_params(&f, scale, offset);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    int bad = dfx_random_rays(&f, seed, rays);
    *hit_share = hard_min(*hit_share, (double)f.hits / rays);
    dfx_close(&f);
    mr_device_free(f.dev);
    return bad;
}

static void test_uv_cases(void **state)
{
    (void)state;
    uint64_t seed = 101;
    mr_asset *tex = dfx_texture(11, 6, MR_SAMPLE_U8, dfx_noise, &seed);
    void (*cases[])(int, int, float[2]) = {uv_plain, uv_flipped, uv_degenerate, uv_repeats};
    static const char *const NAMES[] = {"plain", "flipped", "degenerate (zero or collinear area)", "40-repeat"};
    double hit_share = 1;
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        mr_asset *mesh = grid_mesh(cases[k], NULL);
        int bad = run(mesh, tex, 0.25f, 0, &seed, 1500, &hit_share);
        HARD_CHECK("error", bad, "==", 0, "%s UVs: rays disagreeing with the brute force (of 1500)", NAMES[k]);
        mr_asset_free(mesh);
    }
    HARD_CHECK("other", hit_share, ">=", 0.1, "smallest share of rays that hit");
    mr_asset_free(tex);
}

/* 100,000 repeats: nothing to tessellate, but every downward ray must hit
 * between the lowest and highest surface. */
static void test_huge_repeats(void **state)
{
    (void)state;
    uint64_t seed = 5;
    mr_asset *tex = dfx_texture(5, 3, MR_SAMPLE_U8, dfx_noise, &seed);
    mr_asset *mesh = grid_mesh(uv_huge, NULL);
    dfx f = {0};
    dfx_params(&f, 0.1f, 0);
    /* no tessellation: open by hand */
    f.assets[0] = mesh, f.assets[1] = tex;
    f.desc = (mr_object_desc){.params = &f.par, .kind = &mr_kind_displaced};
    mr_kind_context ctx = {.assets = (const mr_asset *const *)f.assets, .asset_count = 2};
    mr_error err;
    assert_int_equal(mr_kind_displaced.create(mesh, &f.desc, &ctx, &f.geom, &err), MR_OK);
    assert_int_equal(mr_pose_new(mesh, &f.pose, &err), MR_OK);
    assert_int_equal(mr_pose_eval(f.pose, mesh, NULL, 0, &err), MR_OK);
    mr_mat4 id = mr_mat4_identity();
    mr_geom_frame fr = {0};
    assert_int_equal(mr_kind_displaced.update(f.geom, &fr, f.pose, &id, 2, &err), MR_OK);
    assert_int_equal(mr_device_new(2, &f.dev, &err), MR_OK);
    f.scene = rtcNewScene(mr_device_embree(f.dev));
    assert_int_equal(mr_kind_displaced.attach(f.geom, mr_device_embree(f.dev), f.scene, 0,
                                              RTC_BUILD_QUALITY_MEDIUM, &err), MR_OK);
    mr_kind_displaced.commit(f.geom);
    rtcCommitScene(f.scene);
    int bad = 0;
    for (int k = 0; k < 300; k++) {
        float x = rndf(&seed, -0.95f, 0.95f), z = rndf(&seed, -0.95f, 0.95f), t;
        mr_vec3 ng;
        bool hit = dfx_trace(&f, mr_v3(x, 1, z), mr_v3(0.01f, -1, 0.02f), 0, INFINITY, &t, &ng);
        /* heights in [0, 0.1]: t in [0.9, 1] (to rounding) */
        bad += !hit || t < 0.9f - 1e-4f || t > 1.0f + 1e-4f;
    }
    HARD_CHECK("leaks", bad, "==", 0,
               "downward rays missing the shell between the lowest and highest surface, or hitting outside it "
               "(of 300; 100,000 repeats)");
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    /* 10,000,000 repeats: cells finer than floats can place a micro-vertex
     * (a frame of such a plane ran for minutes): refused, naming what to
     * change */
    mr_asset *finer = grid_mesh(uv_finer, NULL);
    f.assets[0] = finer;
    mr_geom *g = NULL;
    err = (mr_error){0};
    int rc = mr_kind_displaced.create(finer, &f.desc, &ctx, &g, &err);
    HARD_CHECK("other", rc == MR_ERR_INVALID && !g && strstr(err.msg, "displaced.range") ? 0 : 1,
               "==", 0, "10^7 repeats refused with an error naming displaced.range (%s)", err.msg);
    mr_asset_free(finer);
    /* 10^25 repeats: cells beyond any integer, refused the same way (no
     * undefined conversion on the way: make hard runs under UBSan) */
    mr_asset *absurd = grid_mesh(uv_absurd, NULL);
    f.assets[0] = absurd;
    err = (mr_error){0};
    rc = mr_kind_displaced.create(absurd, &f.desc, &ctx, &g, &err);
    HARD_CHECK("other", rc == MR_ERR_INVALID && !g && strstr(err.msg, "displaced.range") ? 0 : 1,
               "==", 0, "10^25 repeats refused with an error naming displaced.range (%s)", err.msg);
    mr_asset_free(absurd);
    /* 100,000 repeats pre-tessellated: 10^11 cells, past the cap at once
     * (the tessellation sized a table for every cell of a base triangle's
     * box before counting: 13.8 GiB at range 4096 on a plane) */
    mesh = grid_mesh(uv_huge, NULL);
    f.assets[0] = mesh;
    f.par.method = MR_DISPLACED_TESSELLATED;
    err = (mr_error){0};
    rc = mr_kind_displaced.create(mesh, &f.desc, &ctx, &g, &err);
    HARD_CHECK("other", rc == MR_ERR_LIMIT && !g && strstr(err.msg, "micro-triangles") ? 0 : 1, "==", 0,
               "100,000 repeats pre-tessellated refused over the cap, not out of memory (%s)", err.msg);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

static void test_large_displacement_and_normals(void **state)
{
    (void)state;
    uint64_t seed = 202;
    mr_asset *tex = dfx_texture(9, 9, MR_SAMPLE_U16, dfx_noise, &seed);
    /* displacement 4x the triangles' size, both directions */
    mr_asset *mesh = grid_mesh(uv_plain, NULL);
    double hit_share = 1;
    HARD_CHECK("error", run(mesh, tex, 3.0f, -1.5f, &seed, 1500, &hit_share), "==", 0,
               "displacement 4x the triangles: rays disagreeing with the brute force (of 1500)");
    mr_asset_free(mesh);
    /* opposing normals (the interpolation passes through zero), near-zero
     * and sideways ones */
    float nrm[16 * 3];
    for (int v = 0; v < 16; v++) {
        mr_vec3 n = v % 3 == 0 ? mr_v3(0, 1, 0) : v % 3 == 1 ? mr_v3(0, -1, 0) : mr_v3(1e-12f, 1e-12f, 0);
        if (v == 5)
            n = mr_v3(1, 0, 0);
        nrm[v * 3] = n.x, nrm[v * 3 + 1] = n.y, nrm[v * 3 + 2] = n.z;
    }
    mesh = grid_mesh(uv_plain, nrm);
    HARD_CHECK("error", run(mesh, tex, 0.4f, 0.1f, &seed, 1500, &hit_share), "==", 0,
               "opposing, near-zero and sideways normals: rays disagreeing with the brute force (of 1500)");
    HARD_CHECK("other", hit_share, ">=", 0.1, "smallest share of rays that hit");
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

static void test_ray_directions(void **state)
{
    (void)state;
    uint64_t seed = 303;
    mr_asset *tex = dfx_texture(7, 5, MR_SAMPLE_F32, dfx_noise, &seed);
    mr_asset *mesh = grid_mesh(uv_plain, NULL);
    dfx f = {0};
    dfx_params(&f, 1.0f / 255.0f * 0.3f, 0.05f); /* heights 0.05 .. 0.35 */
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    int bad = 0;
    for (int k = 0; k < 1500; k++) {
        float x = rndf(&seed, -1.2f, 1.2f), z = rndf(&seed, -1.2f, 1.2f);
        float y = rndf(&seed, 0.0f, 0.4f);
        mr_vec3 d = rnd_unit(&seed);
        mr_vec3 flat = mr_v3(d.x, 0, d.z); /* parallel to the base plane */
        mr_vec3 graze = mr_v3(d.x, -1e-4f, d.z);
        bad += dfx_check_ray(&f, mr_v3(x, y, z), flat, 0, INFINITY);
        bad += dfx_check_ray(&f, mr_v3(x, y, z), graze, 0, INFINITY);
        /* from inside the shell, every direction */
        bad += dfx_check_ray(&f, mr_v3(x * 0.8f, y, z * 0.8f), d, 0, INFINITY);
        /* axis-parallel rays along the grid lines */
        bad += dfx_check_ray(&f, mr_v3(-2, y, (float)(k % 7 - 3) / 3.0f), mr_v3(1, 0, 0), 0, INFINITY);
    }
    HARD_CHECK("error", bad, "==", 0,
               "rays parallel to the base, grazing it, from inside the shell, along grid lines: disagreeing with "
               "the brute force (of %llu; %llu hit)", (unsigned long long)f.rays, (unsigned long long)f.hits);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

static double one(uint32_t x, uint32_t y, void *u)
{
    (void)x, (void)y, (void)u;
    return 200;
}

static void test_texture_sizes(void **state)
{
    (void)state;
    uint64_t seed = 404;
    static const uint32_t SIZES[][2] = {{1, 1}, {1, 13}, {13, 1}, {3, 7}, {31, 17}};
    double hit_share = 1;
    for (size_t k = 0; k < sizeof SIZES / sizeof SIZES[0]; k++) {
        mr_asset *tex = k == 0 ? dfx_texture(1, 1, MR_SAMPLE_U8, one, NULL)
                               : dfx_texture(SIZES[k][0], SIZES[k][1], MR_SAMPLE_U8, dfx_noise, &seed);
        mr_asset *mesh = grid_mesh(uv_plain, NULL);
        int bad = run(mesh, tex, 0.2f, 0, &seed, 1000, &hit_share);
        HARD_CHECK("error", bad, "==", 0, "%ux%u texture: rays disagreeing with the brute force (of 1000)",
                   SIZES[k][0], SIZES[k][1]);
        mr_asset_free(mesh);
        mr_asset_free(tex);
    }
    HARD_CHECK("other", hit_share, ">=", 0.1, "smallest share of rays that hit");
}

/* The bending bar: its clip, then joints twisted and scaled to extremes;
 * every pose traced against its own tessellation. */
static void test_skinned_extreme_poses(void **state)
{
    (void)state;
    mr_asset *bar = NULL;
    mr_error err;
    if (mr_asset_load(BAR, &bar, &err) != MR_OK)
        fail_msg("%s", err.msg);
    uint64_t seed = 505;
    mr_asset *tex = dfx_texture(24, 24, MR_SAMPLE_U8, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.02f, 0);
    f.par.level = 1;
    mr_pose_desc clip = {.has_clip = true, .clip_index = 0, .speed = 1, .loop = true};
    dfx_open(&f, bar, tex, &clip, NULL, 0);
    double dur = bar->clip_count ? bar->clips[0].duration : 1;
    int bad = 0;
    for (int k = 0; k < 4; k++) {
        dfx_repose(&f, &clip, NULL, dur * k / 4);
        bad += dfx_random_rays(&f, &seed, 150);
    }
    /* extreme joint transforms on every skinned joint */
    const mr_mesh *m = &bar->meshes[0];
    mr_joint_override ov[64];
    size_t n = m->joint_count < 64 ? m->joint_count : 64;
    static const float SCALES[] = {0.05f, 20.0f, 1.0f};
    for (int p = 0; p < 3; p++) {
        for (size_t j = 0; j < n; j++) {
            mr_quat q = mr_quat_from_axis_angle(rnd_unit(&seed), (float)(170 * M_PI / 180) * (p == 2 ? 1 : 0.5f));
            float s = SCALES[p];
            ov[j].joint = bar->nodes[m->joint_nodes[j]].name;
            ov[j].local = mr_mat4_from_trs(mr_v3(0, 0, 0), q, mr_v3(s, s, s));
        }
        mr_pose_desc extreme = {.joint_count = n, .joints = ov};
        dfx_repose(&f, &extreme, NULL, 0);
        bad += dfx_random_rays(&f, &seed, 150);
    }
    HARD_CHECK("error", bad, "==", 0,
               "rays disagreeing with the brute force over 4 clip poses and 3 extreme ones (of %llu; %llu hit)",
               (unsigned long long)f.rays, (unsigned long long)f.hits);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(bar);
    mr_asset_free(tex);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_uv_cases),
        cmocka_unit_test(test_huge_repeats),
        cmocka_unit_test(test_large_displacement_and_normals),
        cmocka_unit_test(test_ray_directions),
        cmocka_unit_test(test_texture_sizes),
        cmocka_unit_test(test_skinned_extreme_poses),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
