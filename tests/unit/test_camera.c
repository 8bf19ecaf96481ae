/*
 * test_camera.c - camera path interpolation at keyframes and between them,
 * and primary ray directions.
 *
 * Tolerance 1e-5: positions are O(10) floats through a cubic with four
 * weights (a few ulps of 10 ~ 1e-6 each); rotations go through slerp in double
 * and a float quaternion.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <cmocka.h>

#include "render/camera.h"

static void assert_near(double a, double b, double tol)
{
    if (!(fabs(a - b) <= tol))
        fail_msg("expected %.9g, got %.9g (tol %g)", b, a, tol);
}

static mr_vec3 forward_of(mr_quat q) { return mr_quat_rotate(q, mr_v3(0, 0, -1)); }

/* Three keys: x = 0, 2, 10 at t = 0, 1, 2, all looking at the origin from z = 5. */
static mr_camera_key keys3[3];
static mr_camera_path make_path(mr_interp interp)
{
    float xs[3] = {0, 2, 10};
    for (int i = 0; i < 3; i++)
        keys3[i] = (mr_camera_key){.t = i, .position = mr_v3(xs[i], 0, 5), .has_target = true,
                                   .target = mr_v3(0, 0, 0), .yfov = 0.5f + 0.25f * i};
    return (mr_camera_path){.interp = interp, .up = mr_v3(0, 1, 0), .key_count = 3, .keys = keys3};
}

static void test_keys_reproduced(void **state)
{
    (void)state;
    for (int mode = 0; mode < 2; mode++) {
        mr_camera_path p = make_path(mode ? MR_INTERP_CATMULL_ROM : MR_INTERP_LINEAR);
        for (int i = 0; i < 3; i++) {
            mr_camera c = mr_camera_path_eval(&p, i);
            assert_near(c.position.x, keys3[i].position.x, 1e-5);
            assert_near(c.position.z, 5, 1e-5);
            assert_near(c.yfov, keys3[i].yfov, 1e-6);
            /* Looks at the target: forward is parallel to target - position. */
            mr_vec3 want = mr_v3_normalize_or(mr_v3_sub(keys3[i].target, keys3[i].position), mr_v3(0, 0, 0));
            mr_vec3 f = forward_of(c.rotation);
            assert_near(mr_v3_dot(f, want), 1.0, 1e-5);
        }
    }
}

static void test_between_keys(void **state)
{
    (void)state;
    mr_camera_path lin = make_path(MR_INTERP_LINEAR);
    mr_camera c = mr_camera_path_eval(&lin, 0.25);
    assert_near(c.position.x, 0.5, 1e-6);
    assert_near(c.yfov, 0.5625, 1e-6);
    c = mr_camera_path_eval(&lin, 1.5);
    assert_near(c.position.x, 6.0, 1e-5);

    /* Uniform Catmull-Rom on the first segment with p0 = p1 (duplicated end):
     * x(u) = 0.5*((2*p1) + (-p0+p2)u + (2p0-5p1+4p2-p3)u^2 + (-p0+3p1-3p2+p3)u^3)
     * with p0=p1=0, p2=2, p3=10: x(0.5) = 0.5*(1 + (8-10)*0.25 + (-6+10)*0.125) = 0.5*(1-0.5+0.5) = 0.5. */
    mr_camera_path cr = make_path(MR_INTERP_CATMULL_ROM);
    c = mr_camera_path_eval(&cr, 0.5);
    assert_near(c.position.x, 0.5, 1e-5);
    /* Middle of the second segment: p0=0,p1=2,p2=10,p3=10:
     * 0.5*(4 + 10*0.5 + (0-10+40-10)*0.25 + (0+6-30+10)*0.125) = 0.5*(4+5+5-1.75) = 6.125. */
    c = mr_camera_path_eval(&cr, 1.5);
    assert_near(c.position.x, 6.125, 1e-5);

    /* Rotation halfway between two rotation keys is the slerp midpoint. */
    mr_camera_key rk[2] = {
        {.t = 0, .position = mr_v3(0, 0, 0), .rotation = mr_quat_identity(), .yfov = 1},
        {.t = 2, .position = mr_v3(0, 0, 0), .rotation = mr_quat_from_axis_angle(mr_v3(0, 1, 0), 1.5707963f), .yfov = 1},
    };
    mr_camera_path rp = {.interp = MR_INTERP_LINEAR, .up = mr_v3(0, 1, 0), .key_count = 2, .keys = rk};
    c = mr_camera_path_eval(&rp, 1.0);
    mr_vec3 f = forward_of(c.rotation);
    /* 45 degrees about +Y turns -Z towards -X. */
    assert_near(f.x, -sqrt(0.5), 1e-6);
    assert_near(f.z, -sqrt(0.5), 1e-6);
}

static void test_holds_outside_range(void **state)
{
    (void)state;
    mr_camera_path p = make_path(MR_INTERP_CATMULL_ROM);
    assert_near(mr_camera_path_eval(&p, -3).position.x, 0, 0);
    assert_near(mr_camera_path_eval(&p, 99).position.x, 10, 0);
}

static void test_ray_dirs(void **state)
{
    (void)state;
    mr_camera c = {mr_v3(0, 0, 0), mr_quat_identity(), 1.5707963f}; /* 90 degrees */
    /* Centre of the film looks straight ahead. */
    mr_vec3 d = mr_camera_ray_dir(&c, 200, 100, 100, 50);
    assert_near(d.z, -1, 1e-7);
    /* Top edge centre: 45 degrees up for a 90-degree vertical fov. */
    d = mr_camera_ray_dir(&c, 200, 100, 100, 0);
    assert_near(atan2(d.y, -d.z), M_PI / 4, 1e-6);
    /* Right edge: tan(h) = aspect * tan(45) = 2. */
    d = mr_camera_ray_dir(&c, 200, 100, 200, 50);
    assert_near(d.x / -d.z, 2.0, 1e-6);
}

/* The eight-wide directions the renderer's packets use are the scalar
 * ones bit for bit: an image must not depend on which of the two made a
 * ray. Pixel-centre, jittered (random in [0, 1) of a pixel) and far-off
 * film points under a turned camera; lanes compared by their bits. */
static void test_ray_dirs8(void **state)
{
    (void)state;
    mr_camera cam = {mr_v3(3, -2, 7), mr_quat_from_axis_angle(mr_v3(1, 2, 3), 0.9f), 0.7f};
    mr_camera_rays r = mr_camera_rays_setup(&cam, 1920, 1080);
    uint64_t z = 0x9e3779b97f4a7c15ull;
    size_t lanes = 0;
    for (int pass = 0; pass < 4096; pass++) {
        float px[8], py[8], dx[8], dy[8], dz[8];
        for (int i = 0; i < 8; i++) {
            z = z * 6364136223846793005ull + 1442695040888963407ull;
            float jx = (float)(z >> 40) / 16777216.0f, jy = (float)((z >> 16) & 0xffffff) / 16777216.0f;
            int x = (int)(z % 1920), y = (int)((z >> 20) % 1080);
            px[i] = pass % 3 == 0 ? (float)x + 0.5f : (float)x + jx;
            py[i] = pass % 3 == 2 ? (float)y * 37.0f - 20000.0f : (float)y + jy;
        }
        mr_camera_rays_dir8(&r, px, py, dx, dy, dz);
        for (int i = 0; i < 8; i++) {
            mr_vec3 d = mr_camera_rays_dir(&r, px[i], py[i]);
            if (memcmp(&d.x, &dx[i], 4) || memcmp(&d.y, &dy[i], 4) || memcmp(&d.z, &dz[i], 4))
                fail_msg("lane %d at (%.9g, %.9g): (%.9g %.9g %.9g) against the scalar (%.9g %.9g %.9g)",
                         i, px[i], py[i], dx[i], dy[i], dz[i], d.x, d.y, d.z);
            lanes++;
        }
    }
    assert_int_equal(lanes, 4096 * 8);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_keys_reproduced),
        cmocka_unit_test(test_between_keys),
        cmocka_unit_test(test_holds_outside_range),
        cmocka_unit_test(test_ray_dirs),
        cmocka_unit_test(test_ray_dirs8),
    };
    return cmocka_run_group_tests_name("camera", tests, NULL, NULL);
}
