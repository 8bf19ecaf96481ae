/*
 * test_math.c - quaternion slerp, matrix inverse, tangent fitting and friends against values
 * known in closed form.
 *
 * Tolerance: 1e-6 absolute on O(1) values, a few float32 ulps (2^-23 ~ 1.2e-7)
 * times the handful of operations each result goes through; 1e-5 where acos /
 * sin in float amplify rounding near the ends of their range.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include <float.h>
#include <math.h>

#include "math/mr_math.h"

#define PI_F 3.14159265358979f

static void assert_near(double a, double b, double tol)
{
    if (!(fabs(a - b) <= tol))
        fail_msg("expected %.9g, got %.9g (tol %g)", b, a, tol);
}

static void assert_quat_same_rotation(mr_quat a, mr_quat b, double tol)
{
    /* q and -q are the same rotation */
    double d = fabs((double)a.x * b.x + (double)a.y * b.y + (double)a.z * b.z + (double)a.w * b.w);
    assert_near(d, 1.0, tol);
}

static void test_slerp_known_values(void **state)
{
    (void)state;
    mr_quat id = mr_quat_identity();
    mr_quat z90 = mr_quat_from_axis_angle(mr_v3(0, 0, 1), PI_F / 2);
    /* Halfway between 0 and 90 degrees about Z is 45 degrees: (0,0,sin 22.5, cos 22.5). */
    mr_quat h = mr_quat_slerp(id, z90, 0.5f);
    assert_near(h.x, 0, 1e-6);
    assert_near(h.y, 0, 1e-6);
    assert_near(h.z, sin(M_PI / 8), 1e-6);
    assert_near(h.w, cos(M_PI / 8), 1e-6);
    /* A quarter of the way: 22.5 degrees. */
    mr_quat q = mr_quat_slerp(id, z90, 0.25f);
    assert_near(q.z, sin(M_PI / 16), 1e-6);
    assert_near(q.w, cos(M_PI / 16), 1e-6);
    /* End points are reproduced. */
    assert_quat_same_rotation(mr_quat_slerp(id, z90, 0.0f), id, 1e-6);
    assert_quat_same_rotation(mr_quat_slerp(id, z90, 1.0f), z90, 1e-6);
    /* Shortest path: -z90 is the same rotation, the midpoint must still be 45 degrees. */
    mr_quat neg = {-z90.x, -z90.y, -z90.z, -z90.w};
    assert_quat_same_rotation(mr_quat_slerp(id, neg, 0.5f), h, 1e-6);
    /* Constant angular speed: rotating X by slerp(0..180 deg about Y) at t=1/3 gives 60 deg. */
    mr_quat y180 = mr_quat_from_axis_angle(mr_v3(0, 1, 0), PI_F * 0.999f);
    mr_vec3 v = mr_quat_rotate(mr_quat_slerp(id, y180, 1.0f / 3.0f), mr_v3(1, 0, 0));
    assert_near(acos(v.x) * 180 / M_PI, 60 * 0.999, 1e-3);
    /* Nearly identical inputs take the lerp branch and stay unit length. */
    mr_quat tiny = mr_quat_from_axis_angle(mr_v3(1, 0, 0), 1e-5f);
    mr_quat m = mr_quat_slerp(id, tiny, 0.5f);
    assert_near(sqrt(m.x * m.x + m.y * m.y + m.z * m.z + m.w * m.w), 1.0, 1e-6);
    assert_near(m.x, sin(0.25e-5), 1e-7);
}

static void test_mat4_inverse_known(void **state)
{
    (void)state;
    /* A matrix with a known integer inverse. */
    mr_mat4 a = {{2, 0, 0, 1,
                  0, 4, 0, 2,
                  0, 0, 8, 3,
                  0, 0, 0, 1}};
    mr_mat4 inv;
    assert_true(mr_mat4_inverse(&a, &inv));
    const float expect[16] = {0.5f, 0, 0, -0.5f,
                              0, 0.25f, 0, -0.5f,
                              0, 0, 0.125f, -0.375f,
                              0, 0, 0, 1};
    for (int i = 0; i < 16; i++)
        assert_near(inv.m[i], expect[i], 1e-7);
    /* A general (shear + projective row) matrix: A * A^-1 = I. */
    mr_mat4 g = {{1, 2, 3, 4,
                  0, 1, 4, 5,
                  5, 6, 0, 7,
                  1, 0, 2, 1}};
    assert_true(mr_mat4_inverse(&g, &inv));
    mr_mat4 p = mr_mat4_mul(&g, &inv);
    for (int i = 0; i < 16; i++)
        assert_near(p.m[i], (i % 5 == 0) ? 1.0 : 0.0, 1e-5);
    /* A large translation does not make a rotation singular (with the scale
     * taken over all entries, 1e4^4 swamped det = 1). Round trip within the
     * float32 spacing of 1e4 (~1e-3). */
    mr_mat4 far = mr_mat4_from_trs(mr_v3(1e4f, -3e3f, 2e3f), mr_quat_from_axis_angle(mr_v3(0, 1, 0), 0.3f),
                                   mr_v3(1, 1, 1));
    assert_true(mr_mat4_inverse(&far, &inv));
    mr_vec3 back = mr_mat4_point(&inv, mr_mat4_point(&far, mr_v3(1, 2, 3)));
    assert_near(back.x, 1, 2e-3); assert_near(back.y, 2, 2e-3); assert_near(back.z, 3, 2e-3);
    /* Small uniform scale far from the origin is still invertible. */
    mr_mat4 tiny = mr_mat4_from_trs(mr_v3(500, 0, 0), mr_quat_identity(), mr_v3(1e-3f, 1e-3f, 1e-3f));
    assert_true(mr_mat4_inverse(&tiny, &inv));
    assert_near(inv.m[0], 1e3, 1e-2);
    assert_near(inv.m[3], -5e5, 1.0);
    /* Singular: rank 3. */
    mr_mat4 s = {{1, 2, 3, 0, 2, 4, 6, 0, 0, 0, 1, 0, 0, 0, 0, 1}};
    assert_false(mr_mat4_inverse(&s, &inv));
    mr_mat4 z = {{0}};
    assert_false(mr_mat4_inverse(&z, &inv));
}

static void test_trs_roundtrip(void **state)
{
    (void)state;
    mr_quat r = mr_quat_from_axis_angle(mr_v3(1, 2, 3), 0.7f);
    mr_mat4 m = mr_mat4_from_trs(mr_v3(1, -2, 3), r, mr_v3(2, 3, 4));
    mr_vec3 t, s;
    mr_quat r2;
    assert_true(mr_mat4_to_trs(&m, &t, &r2, &s));
    assert_near(t.x, 1, 1e-6); assert_near(t.y, -2, 1e-6); assert_near(t.z, 3, 1e-6);
    assert_near(s.x, 2, 1e-5); assert_near(s.y, 3, 1e-5); assert_near(s.z, 4, 1e-5);
    assert_quat_same_rotation(r, r2, 1e-6);
    /* Scale first, then rotate, then translate: (1,0,0) -> 2*R(1,0,0) + t. */
    mr_vec3 p = mr_mat4_point(&m, mr_v3(1, 0, 0));
    mr_vec3 e = mr_v3_add(mr_quat_rotate(r, mr_v3(2, 0, 0)), mr_v3(1, -2, 3));
    assert_near(p.x, e.x, 1e-5); assert_near(p.y, e.y, 1e-5); assert_near(p.z, e.z, 1e-5);
}

static void test_normal_matrix_keeps_perpendicular(void **state)
{
    (void)state;
    /* Non-uniform scale: a 45-degree plane normal must stay perpendicular to
     * the transformed plane's tangents. */
    mr_mat4 m = mr_mat4_from_trs(mr_v3(0, 0, 0), mr_quat_from_axis_angle(mr_v3(0, 0, 1), 0.3f),
                                 mr_v3(1, 5, 1));
    mr_vec3 n = mr_v3(1, 1, 0), tangent = mr_v3(1, -1, 0), tangent2 = mr_v3(0, 0, 1);
    mr_mat4 nm = mr_mat4_normal_matrix(&m);
    mr_vec3 n2 = mr_v3_normalize_or(mr_mat4_dir(&nm, n), mr_v3(0, 0, 0));
    assert_near(mr_v3_dot(n2, mr_v3_normalize_or(mr_mat4_dir(&m, tangent), n2)), 0, 1e-6);
    assert_near(mr_v3_dot(n2, mr_v3_normalize_or(mr_mat4_dir(&m, tangent2), n2)), 0, 1e-6);
}

static void test_look_rotation(void **state)
{
    (void)state;
    /* Looking down -Z with +Y up is the identity. */
    assert_quat_same_rotation(mr_quat_look_rotation(mr_v3(0, 0, -1), mr_v3(0, 1, 0)),
                              mr_quat_identity(), 1e-6);
    /* Looking along +X: camera -Z maps to +X, +Y stays up. */
    mr_quat q = mr_quat_look_rotation(mr_v3(1, 0, 0), mr_v3(0, 1, 0));
    mr_vec3 f = mr_quat_rotate(q, mr_v3(0, 0, -1)), u = mr_quat_rotate(q, mr_v3(0, 1, 0));
    assert_near(f.x, 1, 1e-6); assert_near(f.y, 0, 1e-6); assert_near(f.z, 0, 1e-6);
    assert_near(u.y, 1, 1e-6);
    /* Straight down (parallel to up) still gives a valid orthonormal frame. */
    q = mr_quat_look_rotation(mr_v3(0, -1, 0), mr_v3(0, 1, 0));
    f = mr_quat_rotate(q, mr_v3(0, 0, -1));
    assert_near(f.y, -1, 1e-6);
}

/* mr_v3_tangent_to: the part across n, unit; close to n's direction it is
 * still orthogonal to n to rounding (1e-6: the second Gram-Schmidt step;
 * one step leaves about 1e-7 / sin(angle) of n in it); along n, lost. */
static void test_tangent_to(void **state)
{
    (void)state;
    mr_vec3 n = mr_v3_normalize_or(mr_v3(0.3f, -0.5f, 0.8f), mr_v3(0, 0, 1));
    mr_vec3 t = mr_v3_tangent_to(mr_v3(2, 0, 0), mr_v3(0, 0, 1), false);
    assert_true(t.x == 1 && t.y == 0 && t.z == 0);
    mr_vec3 side = mr_v3_normalize_or(mr_v3_cross(n, mr_v3(1, 0, 0)), mr_v3(0, 1, 0));
    for (int k = 0; k < 6; k++) {
        float angle = 0.5f * powf(0.25f, (float)k); /* 0.5 .. 5e-4 rad from n, the last under the 1e-3 bound */
        mr_vec3 in = mr_v3_scale(mr_v3_add(mr_v3_scale(n, cosf(angle)), mr_v3_scale(side, sinf(angle))), 3.0f);
        mr_vec3 out = mr_v3_tangent_to(in, n, false);
        if (angle < 1e-3f) {
            assert_true(out.x == 0 && out.y == 0 && out.z == 0);
            mr_vec3 any = mr_v3_tangent_to(in, n, true);
            assert_true(fabsf(mr_v3_len(any) - 1) < 1e-6f && fabsf(mr_v3_dot(any, n)) < 1e-6f);
            continue;
        }
        if (!(fabsf(mr_v3_len(out) - 1) < 1e-6f && fabsf(mr_v3_dot(out, n)) < 1e-6f &&
              mr_v3_dot(out, side) > 0.99999f))
            fail_msg("%g rad from n: (%g %g %g), . n %g", (double)angle, (double)out.x, (double)out.y,
                     (double)out.z, (double)mr_v3_dot(out, n));
    }
    /* nothing, or not finite: lost */
    mr_vec3 z = mr_v3_tangent_to(mr_v3(0, 0, 0), n, false);
    assert_true(z.x == 0 && z.y == 0 && z.z == 0);
    z = mr_v3_tangent_to(mr_v3(NAN, 1, 0), n, false);
    assert_true(z.x == 0 && z.y == 0 && z.z == 0);
    z = mr_v3_tangent_to(mr_v3(INFINITY, 1, 0), n, true);
    assert_true(fabsf(mr_v3_len(z) - 1) < 1e-6f && fabsf(mr_v3_dot(z, n)) < 1e-6f);
    /* the fixed choice: the same bits for the same n */
    mr_vec3 a = mr_v3_any_orthogonal(n), b = mr_v3_any_orthogonal(n);
    assert_memory_equal(&a, &b, sizeof a);
}

static void test_catmull_rom_interpolates(void **state)
{
    (void)state;
    mr_vec3 p0 = mr_v3(0, 0, 0), p1 = mr_v3(1, 0, 0), p2 = mr_v3(2, 1, 0), p3 = mr_v3(3, 1, 0);
    mr_vec3 a = mr_catmull_rom(p0, p1, p2, p3, 0.0f), b = mr_catmull_rom(p0, p1, p2, p3, 1.0f);
    assert_near(a.x, 1, 1e-7); assert_near(a.y, 0, 1e-7);
    assert_near(b.x, 2, 1e-7); assert_near(b.y, 1, 1e-7);
    /* Midpoint: 0.5*(p1+p2) + 0.125*((p1-p0)+(p2-p3))... closed form -> (1.5, 0.5). */
    mr_vec3 m = mr_catmull_rom(p0, p1, p2, p3, 0.5f);
    assert_near(m.x, 1.5, 1e-6); assert_near(m.y, 0.5, 1e-6);
    /* Collinear evenly spaced points: the curve is the straight line. */
    mr_vec3 q = mr_catmull_rom(mr_v3(0, 0, 0), mr_v3(1, 1, 1), mr_v3(2, 2, 2), mr_v3(3, 3, 3), 0.3f);
    assert_near(q.x, 1.3, 1e-6); assert_near(q.z, 1.3, 1e-6);
}

/* mr_float_down / mr_float_up: the float bound on the named side of a
 * double, exact when the double is a float; the bit-pattern step checked
 * against nextafterf on both signs, at zero and at the ends of the range. */
static void test_float_bounds(void **state)
{
    (void)state;
    const double vs[] = {1.0, -1.0, 0.1, -0.1, 1.0 / 3.0, -1.0 / 3.0, 1e-50, -1e-50, 0.0, -0.0,
                         3.4028235677973366e38 /* above FLT_MAX, rounds to it */, 1e39, -1e39,
                         1.0 + 0x1p-30, 1.0 - 0x1p-30, -1.0 + 0x1p-30, 16777217.0};
    for (size_t i = 0; i < sizeof vs / sizeof vs[0]; i++) {
        const double v = vs[i];
        const float f = (float)v, lo = mr_float_down(v), hi = mr_float_up(v);
        assert_true((double)lo <= v && (double)hi >= v);
        assert_true(lo == ((double)f > v ? nextafterf(f, -INFINITY) : f));
        assert_true(hi == ((double)f < v ? nextafterf(f, INFINITY) : f));
    }
    assert_true(mr_float_down(-1e-50) == -FLT_TRUE_MIN && mr_float_up(1e-50) == FLT_TRUE_MIN);
    assert_true(mr_float_down(1.0) == 1.0f && mr_float_up(-2.5) == -2.5f);
    assert_true(mr_float_down(1e39) == FLT_MAX && isinf(mr_float_up(1e39)));
    assert_true(isnan(mr_float_down(NAN)) && isnan(mr_float_up(NAN)));
}

/* mr_popcount32 against a bit-by-bit count: every 16-bit value (the
 * renderer's packet masks) and a stream of 32-bit ones from a fixed
 * generator, with the edges (0, all ones, single bits). */
static unsigned count_bits(uint32_t v)
{
    unsigned n = 0;
    for (int b = 0; b < 32; b++)
        n += v >> b & 1u;
    return n;
}

static void test_popcount32(void **state)
{
    (void)state;
    for (uint32_t v = 0; v <= 0xffffu; v++)
        assert_int_equal(mr_popcount32(v), count_bits(v));
    assert_int_equal(mr_popcount32(0xffffffffu), 32);
    for (int b = 0; b < 32; b++) {
        assert_int_equal(mr_popcount32(1u << b), 1);
        assert_int_equal(mr_popcount32(~(1u << b)), 31);
    }
    uint64_t x = 0x9e3779b97f4a7c15ull;
    for (int k = 0; k < 100000; k++) {
        x ^= x << 13, x ^= x >> 7, x ^= x << 17;
        const uint32_t v = (uint32_t)(x >> 16);
        assert_int_equal(mr_popcount32(v), count_bits(v));
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_slerp_known_values),
        cmocka_unit_test(test_mat4_inverse_known),
        cmocka_unit_test(test_trs_roundtrip),
        cmocka_unit_test(test_normal_matrix_keeps_perpendicular),
        cmocka_unit_test(test_look_rotation),
        cmocka_unit_test(test_catmull_rom_interpolates),
        cmocka_unit_test(test_tangent_to),
        cmocka_unit_test(test_float_bounds),
        cmocka_unit_test(test_popcount32),
    };
    return cmocka_run_group_tests_name("math", tests, NULL, NULL);
}
