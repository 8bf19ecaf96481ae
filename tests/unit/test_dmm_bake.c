/*
 * test_dmm_bake.c - the first DMM baker stage (core/kinds/dmm/dmm_bake.h) on a
 * generated detailed mesh whose true surface is known in closed form: a
 * bumpy sphere r(u) = 1 + A (sin 4x cos 3y + 0.5 sin 5z), u = (x, y, z) unit,
 * tessellated as a cube sphere (6 faces of N x N quads, projected). The cube
 * faces share their border vertices only by position, which also exercises
 * the baker's weld.
 *
 * Tolerances are derived from the tessellation: the detailed mesh is a
 * piecewise-linear interpolant of the true surface, off it by at most the
 * sagitta kappa L^2 / 8 (L the longest detailed edge, kappa the largest
 * principal curvature). For this surface kappa <= 1/r + A * 40 / r^2 < 2.5
 * (|second derivatives of the bump| <= 16 + 9 + 12.5). A displacement is
 * measured along a direction of length >= 0.5 (checked) that meets the
 * surface at >= 60 degrees from tangent for these gentle bumps, so the
 * measured value may differ from the true one by sagitta / (|d| cos) <=
 * 4 * sagitta: tol = 4 * 2.5 * L^2 / 8.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/micromesh.h"

#define BUMP_A 0.03

static double radius_of(double x, double y, double z)
{
    return 1.0 + BUMP_A * (sin(4 * x) * cos(3 * y) + 0.5 * sin(5 * z));
}

typedef struct fixture {
    mr_mesh mesh;
    double max_edge;
} fixture;

static mr_vec3 sphere_point(float cx, float cy, float cz)
{
    double l = sqrt((double)cx * cx + (double)cy * cy + (double)cz * cz);
    double x = cx / l, y = cy / l, z = cz / l, r = radius_of(x, y, z);
    return mr_v3((float)(r * x), (float)(r * y), (float)(r * z));
}

static void make_sphere(fixture *f, uint32_t n)
{
    mr_mesh *m = &f->mesh;
    memset(f, 0, sizeof *f);
    m->name = "bumpy";
    m->vertex_count = 6 * (n + 1) * (n + 1);
    m->triangle_count = 6 * n * n * 2;
    m->positions = malloc(sizeof(float) * 3 * m->vertex_count);
    m->indices = malloc(sizeof(uint32_t) * 3 * m->triangle_count);
    m->joint_count = 3;
    m->joints = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(uint16_t));
    m->weights = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(float));
    assert_non_null(m->positions);
    assert_non_null(m->indices);
    assert_non_null(m->joints);
    assert_non_null(m->weights);
    uint32_t v = 0, t = 0;
    for (int face = 0; face < 6; face++) {
        int axis = face / 2;
        float sign = face % 2 ? -1.0f : 1.0f;
        uint32_t base = v;
        for (uint32_t j = 0; j <= n; j++)
            for (uint32_t i = 0; i <= n; i++) {
                /* the same integers give the same floats on every face, so
                 * border vertices of neighbouring faces coincide bitwise */
                float s = (float)(2 * (int)i - (int)n) / (float)n;
                float r = (float)(2 * (int)j - (int)n) / (float)n;
                float c[3];
                c[axis] = sign, c[(axis + 1) % 3] = s, c[(axis + 2) % 3] = r;
                mr_vec3 p = sphere_point(c[0], c[1], c[2]);
                m->positions[3 * v] = p.x, m->positions[3 * v + 1] = p.y;
                m->positions[3 * v + 2] = p.z;
                /* two influences, a function of position only */
                float w = 0.5f + 0.4f * p.z;
                m->joints[v * MR_MAX_INFLUENCES] = p.x > 0 ? 1 : 0;
                m->joints[v * MR_MAX_INFLUENCES + 1] = 2;
                m->weights[v * MR_MAX_INFLUENCES] = w;
                m->weights[v * MR_MAX_INFLUENCES + 1] = 1.0f - w;
                v++;
            }
        for (uint32_t j = 0; j < n; j++)
            for (uint32_t i = 0; i < n; i++) {
                uint32_t a = base + j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
                uint32_t q[6] = {a, b, d, a, d, c};
                for (int h = 0; h < 2; h++) {
                    uint32_t *ix = m->indices + 3 * t;
                    memcpy(ix, q + 3 * h, sizeof(uint32_t) * 3);
                    mr_vec3 p0 = mr_v3(m->positions[3 * ix[0]], m->positions[3 * ix[0] + 1],
                                       m->positions[3 * ix[0] + 2]);
                    mr_vec3 p1 = mr_v3(m->positions[3 * ix[1]], m->positions[3 * ix[1] + 1],
                                       m->positions[3 * ix[1] + 2]);
                    mr_vec3 p2 = mr_v3(m->positions[3 * ix[2]], m->positions[3 * ix[2] + 1],
                                       m->positions[3 * ix[2] + 2]);
                    mr_vec3 nn = mr_v3_cross(mr_v3_sub(p1, p0), mr_v3_sub(p2, p0));
                    if (mr_v3_dot(nn, p0) < 0) { /* wind outward */
                        uint32_t tmp = ix[1];
                        ix[1] = ix[2], ix[2] = tmp;
                    }
                    for (int e = 0; e < 3; e++) {
                        const float *pa = m->positions + 3 * ix[e];
                        const float *pb = m->positions + 3 * ix[(e + 1) % 3];
                        double dx = pa[0] - pb[0], dy = pa[1] - pb[1], dz = pa[2] - pb[2];
                        f->max_edge = fmax(f->max_edge, sqrt(dx * dx + dy * dy + dz * dz));
                    }
                    t++;
                }
            }
    }
}

static void free_sphere(fixture *f)
{
    free(f->mesh.positions);
    free(f->mesh.indices);
    free(f->mesh.joints);
    free(f->mesh.weights);
}

/* True displacement: the root of |p + t d| = r(direction) nearest to t = 0,
 * bracketed by a scan in steps of 1e-3 both ways and refined by bisection. */
static double g_of(mr_vec3 p, mr_vec3 d, double t)
{
    double x = p.x + t * d.x, y = p.y + t * d.y, z = p.z + t * d.z;
    double l = sqrt(x * x + y * y + z * z);
    return l - radius_of(x / l, y / l, z / l);
}

static double true_displacement(mr_vec3 p, mr_vec3 d)
{
    const double h = 1e-3;
    double g0 = g_of(p, d, 0);
    if (g0 == 0)
        return 0;
    for (int k = 1; k < 400; k++)
        for (int s = -1; s <= 1; s += 2) {
            double lo = s * (k - 1) * h, hi = s * k * h;
            if ((g_of(p, d, lo) < 0) != (g_of(p, d, hi) < 0)) {
                for (int it = 0; it < 60; it++) {
                    double mid = 0.5 * (lo + hi);
                    if ((g_of(p, d, mid) < 0) == (g_of(p, d, lo) < 0))
                        lo = mid;
                    else
                        hi = mid;
                }
                return 0.5 * (lo + hi);
            }
        }
    fail_msg("no root near the base point");
    return 0;
}

static mr_umesh_tri tri_of(const mr_dmm_bake *b, uint32_t t)
{
    mr_umesh_tri tri;
    for (int k = 0; k < 3; k++) {
        uint32_t v = b->base_indices[3 * t + k];
        tri.pos[k] = mr_v3(b->base_positions[3 * v], b->base_positions[3 * v + 1],
                           b->base_positions[3 * v + 2]);
        tri.dir[k] = mr_v3(b->base_directions[3 * v], b->base_directions[3 * v + 1],
                           b->base_directions[3 * v + 2]);
    }
    return tri;
}

static void check_bake(const fixture *f, const mr_dmm_bake *b)
{
    const mr_mesh *m = &f->mesh;
    double tol = 4.0 * 2.5 * f->max_edge * f->max_edge / 8.0;
    assert_int_equal(b->fallback_count, 0);
    assert_true(b->base_triangle_count > 0 && b->base_vertex_count >= 3);
    assert_int_equal(b->micro_vertex_count, mr_umesh_vertex_count(b->level));

    /* base vertices are detailed vertices: same position bits, same skin */
    for (uint32_t v = 0; v < b->base_vertex_count; v++) {
        uint32_t s = b->base_source[v];
        assert_true(s < m->vertex_count);
        assert_memory_equal(b->base_positions + 3 * v, m->positions + 3 * s, 3 * sizeof(float));
        assert_memory_equal(b->joints + v * MR_MAX_INFLUENCES, m->joints + s * MR_MAX_INFLUENCES,
                            MR_MAX_INFLUENCES * sizeof(uint16_t));
        assert_memory_equal(b->weights + v * MR_MAX_INFLUENCES, m->weights + s * MR_MAX_INFLUENCES,
                            MR_MAX_INFLUENCES * sizeof(float));
        /* unit directions (float normalisation: a few ulps) */
        const float *d = b->base_directions + 3 * v;
        assert_true(fabs(sqrt((double)d[0] * d[0] + (double)d[1] * d[1] + (double)d[2] * d[2]) - 1) <
                    1e-6);
    }

    /* displacements against the closed form */
    double worst = 0, sum2 = 0;
    size_t count = 0;
    for (uint32_t t = 0; t < b->base_triangle_count; t++) {
        mr_umesh_tri tri = tri_of(b, t);
        for (uint32_t i = 0; i < b->micro_vertex_count; i++) {
            uint32_t a, bb;
            mr_vec3 p, d;
            mr_umesh_vertex_coords(b->level, i, &a, &bb);
            assert_int_equal(mr_umesh_frame(&tri, b->level, a, bb, &p, &d, NULL), MR_OK);
            assert_true(mr_v3_len(d) >= 0.5f);
            double err = fabs(b->displacements[(size_t)t * b->micro_vertex_count + i] -
                              true_displacement(p, d));
            worst = fmax(worst, err);
            sum2 += err * err;
            count++;
        }
    }
    print_message("level %u: %u base triangles, displacement error max %.3g rms %.3g (tol %.3g); "
                  "surface distance rms %.3g max %.3g\n",
                  b->level, b->base_triangle_count, worst, sqrt(sum2 / (double)count), tol,
                  b->rms_distance, b->max_distance);
    assert_true(worst <= tol);

    /* the error report: micro-vertices are on the detailed mesh (up to float
     * rounding); a micro-triangle's centroid is off the true surface by at
     * most kappa/2 * sum w_i w_j |e_ij|^2 <= kappa Lm^2 / 6 (Lm its longest
     * edge) and the detailed mesh by its sagitta kappa L^2 / 8 more; a
     * factor 1.5 covers the curvature bound being taken at r = 1 */
    static mr_vec3 pts[561];
    double lm = 0;
    for (uint32_t t = 0; t < b->base_triangle_count; t++) {
        mr_umesh_tri tri = tri_of(b, t);
        assert_int_equal(mr_umesh_eval_all(&tri, b->level, 0,
                                           b->displacements + (size_t)t * b->micro_vertex_count,
                                           pts, NULL),
                         MR_OK);
        for (uint32_t k = 0; k < mr_umesh_triangle_count(b->level); k++) {
            uint32_t ix[3];
            mr_umesh_triangle(b->level, k, ix);
            for (int e = 0; e < 3; e++)
                lm = fmax(lm, mr_v3_len(mr_v3_sub(pts[ix[e]], pts[ix[(e + 1) % 3]])));
        }
    }
    double bound = 1.5 * 2.5 * (lm * lm / 6 + f->max_edge * f->max_edge / 8);
    print_message("surface distance bound %.3g (longest micro-edge %.3g)\n", bound, lm);
    assert_true(b->sample_count > 0);
    assert_true(b->rms_distance <= b->max_distance);
    assert_true(b->max_distance <= bound);
}

/* Micro-vertices on an edge shared by two base triangles get the same
 * displacement bits from both (the rays are bit-identical). */
static void check_shared_edges(const mr_dmm_bake *b)
{
    uint32_t n = mr_umesh_segments(b->level), pairs = 0;
    for (uint32_t t = 0; t < b->base_triangle_count; t++)
        for (int e = 0; e < 3; e++) {
            uint32_t u = b->base_indices[3 * t + e], w = b->base_indices[3 * t + (e + 1) % 3];
            for (uint32_t s = t + 1; s < b->base_triangle_count; s++)
                for (int f = 0; f < 3; f++) {
                    if (b->base_indices[3 * s + f] != w ||
                        b->base_indices[3 * s + (f + 1) % 3] != u)
                        continue;
                    pairs++;
                    for (uint32_t k = 0; k <= n; k++) {
                        uint32_t i1, i2, j = n - k;
                        i1 = e == 0   ? mr_umesh_vertex_index(b->level, k, 0)
                             : e == 1 ? mr_umesh_vertex_index(b->level, n - k, k)
                                      : mr_umesh_vertex_index(b->level, 0, n - k);
                        i2 = f == 0   ? mr_umesh_vertex_index(b->level, j, 0)
                             : f == 1 ? mr_umesh_vertex_index(b->level, n - j, j)
                                      : mr_umesh_vertex_index(b->level, 0, n - j);
                        assert_memory_equal(
                            b->displacements + (size_t)t * b->micro_vertex_count + i1,
                            b->displacements + (size_t)s * b->micro_vertex_count + i2,
                            sizeof(float));
                    }
                }
        }
    /* a closed manifold: every edge is shared (3 edges per triangle, 2 sides) */
    assert_int_equal(pairs * 2, b->base_triangle_count * 3);
}

static void test_bake_bumpy_sphere(void **state)
{
    (void)state;
    fixture f;
    make_sphere(&f, 40);
    mr_dmm_bake_params p = mr_dmm_bake_params_default();
    p.target_triangles = 400;
    p.level = 3;
    p.threads = 2;
    mr_error err = {0};
    mr_dmm_bake *b = NULL;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_OK);
    assert_non_null(b);
    assert_true(b->base_triangle_count <= 400);
    assert_true(b->base_triangle_count >= 200);
    check_bake(&f, b);
    check_shared_edges(b);
    assert_true(mr_dmm_bake_memory(b) > (size_t)b->base_triangle_count * b->micro_vertex_count * 4);

    /* same result on one thread, bit for bit */
    p.threads = 1;
    mr_dmm_bake *b1 = NULL;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b1, &err), MR_OK);
    assert_int_equal(b1->base_triangle_count, b->base_triangle_count);
    assert_memory_equal(b1->displacements, b->displacements,
                        (size_t)b->base_triangle_count * b->micro_vertex_count * sizeof(float));
    assert_true(b1->rms_distance == b->rms_distance && b1->max_distance == b->max_distance);
    mr_dmm_bake_free(b1);
    mr_dmm_bake_free(b);

    /* a target above the triangles there are keeps every one (meshopt
     * asserted on it: a worker's SIGABRT) */
    p.target_triangles = 1000000;
    p.level = 0;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_OK);
    assert_true(b->base_triangle_count > 400 && b->base_triangle_count <= f.mesh.triangle_count);
    mr_dmm_bake_free(b);

    /* level 0 by ratio: only the corners, which are detailed vertices, so
     * their displacement is 0 up to the ray's float rounding */
    p.target_triangles = 0;
    p.target_ratio = 0.02f;
    p.level = 0;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_OK);
    check_bake(&f, b);
    for (size_t i = 0; i < (size_t)b->base_triangle_count * 3; i++)
        assert_true(fabsf(b->displacements[i]) < 1e-5f);
    mr_dmm_bake_free(b);
    free_sphere(&f);
}

static void test_bad_input(void **state)
{
    (void)state;
    fixture f;
    make_sphere(&f, 4);
    mr_dmm_bake_params p = mr_dmm_bake_params_default();
    mr_error err = {0};
    mr_dmm_bake *b = (mr_dmm_bake *)&err; /* must be reset to NULL on failure */
    p.level = 6;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_ERR_INVALID);
    assert_null(b);
    p = mr_dmm_bake_params_default();
    p.target_ratio = 0;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_ERR_INVALID);
    p = mr_dmm_bake_params_default();
    f.mesh.positions[7] = NAN;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_ERR_INVALID);
    f.mesh.positions[7] = 0;
    f.mesh.indices[5] = f.mesh.vertex_count;
    assert_int_equal(mr_dmm_bake_run(&f.mesh, &p, &b, &err), MR_ERR_INVALID);
    assert_true(err.msg[0] != 0);
    f.mesh.indices[5] = 0;
    assert_int_equal(mr_dmm_bake_run(NULL, &p, &b, &err), MR_ERR_INVALID);
    /* a mesh of only degenerate triangles */
    mr_mesh d = f.mesh;
    uint32_t idx[3] = {0, 0, 1};
    d.indices = idx;
    d.triangle_count = 1;
    assert_int_equal(mr_dmm_bake_run(&d, &p, &b, &err), MR_ERR_INVALID);
    assert_null(b);
    free_sphere(&f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_bake_bumpy_sphere),
        cmocka_unit_test(test_bad_input),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
