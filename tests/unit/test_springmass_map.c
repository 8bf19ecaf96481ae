/*
 * test_springmass_map.c - the mappings of the spring-mass kind (paper 001,
 * 3.2-3.3; core/kinds/springmass/map.h): every mapping reproduces the rest
 * mesh and moves it rigidly under a rigid motion of the nodes (positions
 * within 1e-5 of the mesh size, normals turned with it), on a sphere and on
 * a real model; the curvature-corrected mapping falls back to the constant
 * basis on a one-node-thin sheet; a grid of one node moves the mesh by
 * translation; results do not depend on the thread count.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <stdio.h>

#include "../support/springmass_fixture.h"
#include "asset/asset.h"

static const int MAPPINGS[] = {MR_SPRINGMASS_ONE_TO_ONE, MR_SPRINGMASS_TRIANGLE_BASIS,
                               MR_SPRINGMASS_TRIANGLE_CURVATURE, MR_SPRINGMASS_TRILINEAR};
static const char *const NAMES[] = {"one_to_one", "triangle_basis", "triangle_basis_curvature", "trilinear"};

typedef struct setup {
    sm_mesh mesh;
    double size; /* bounding-box diagonal */
    mr_springmass_params p;
    mr_springmass_pin pin;
    mr_springmass_pin_key keys[2];
    sm_sim *sim;
} setup;

static void setup_sim(setup *s, double spacing, uint32_t nodes)
{
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (uint32_t v = 0; v < s->mesh.vertex_count; v++)
        for (int a = 0; a < 3; a++) {
            lo[a] = fmin(lo[a], s->mesh.pos[v * 3 + a]);
            hi[a] = fmax(hi[a], s->mesh.pos[v * 3 + a]);
        }
    s->size = sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
                   (hi[2] - lo[2]) * (hi[2] - lo[2]));
    s->p = sm_default_params();
    /* every node on one rigid path: turned by 60 degrees about a tilted
     * axis around a pivot off the centre, and moved */
    s->keys[0] = (mr_springmass_pin_key){0, {0, 0, 0}, {0, 0, 0, 1}};
    mr_quat q = mr_quat_from_axis_angle(mr_v3_normalize_or(mr_v3(0.3f, 1, -0.2f), mr_v3(0, 1, 0)),
                                        (float)(M_PI / 3));
    s->keys[1] = (mr_springmass_pin_key){1, {0.7f, -0.3f, 0.45f}, q};
    s->pin = (mr_springmass_pin){.box_min = {-1e9f, -1e9f, -1e9f}, .box_max = {1e9f, 1e9f, 1e9f},
                                 .pivot = {0.2f, 0.1f, -0.15f}, .has_pivot = true, .path = s->keys, .path_count = 2};
    s->p.pins = &s->pin;
    s->p.pin_count = 1;
    sm_grid g;
    mr_error err;
    if (sm_grid_build(s->mesh.pos, s->mesh.vertex_count, s->mesh.tri, s->mesh.triangle_count, spacing, nodes, 0, 2,
                      &g, &err) < 0)
        fail_msg("grid: %s", err.msg);
    if (sm_sim_new(&g, &s->p, 2, &s->sim, &err) < 0)
        fail_msg("sim: %s", err.msg);
}

/* The rigid motion of the path at the end (t = 1). */
static void rigid(const setup *s, const float *v, float *out, bool direction)
{
    mr_vec3 d = direction ? mr_v3(v[0], v[1], v[2]) : mr_v3(v[0] - s->pin.pivot.x, v[1] - s->pin.pivot.y, v[2] - s->pin.pivot.z);
    mr_vec3 r = mr_quat_rotate(s->keys[1].rotation, d);
    if (!direction)
        r = mr_v3(r.x + s->pin.pivot.x + s->keys[1].translation.x, r.y + s->pin.pivot.y + s->keys[1].translation.y,
                  r.z + s->pin.pivot.z + s->keys[1].translation.z);
    out[0] = r.x;
    out[1] = r.y;
    out[2] = r.z;
}

static double max_angle(const float *a, const float *b, uint32_t n)
{
    double worst = 0;
    for (uint32_t v = 0; v < n; v++) {
        const float *x = a + (size_t)v * 3, *y = b + (size_t)v * 3;
        double d = (double)x[0] * y[0] + (double)x[1] * y[1] + (double)x[2] * y[2];
        double lx = sqrt((double)x[0] * x[0] + (double)x[1] * x[1] + (double)x[2] * x[2]);
        double ly = sqrt((double)y[0] * y[0] + (double)y[1] * y[1] + (double)y[2] * y[2]);
        worst = fmax(worst, acos(fmin(1, fmax(-1, d / (lx * ly)))));
    }
    return worst;
}

/* At rest and after the rigid motion, for every mapping. */
static void check_rigid(setup *s, const char *what)
{
    uint32_t nv = s->mesh.vertex_count;
    size_t n3 = (size_t)nv * 3;
    float *pos = malloc(n3 * 4 + 4), *nrm = malloc(n3 * 4 + 4), *rest_pos = malloc(n3 * 4 + 4),
          *rest_nrm = malloc(n3 * 4 + 4), *want = malloc(n3 * 4 + 4), *want_n = malloc(n3 * 4 + 4);
    mr_error err;
    for (size_t k = 0; k < sizeof MAPPINGS / sizeof *MAPPINGS; k++) {
        sm_sim_reset(s->sim, 2);
        sm_map *m = NULL;
        if (sm_map_new(s->sim, MAPPINGS[k], s->mesh.fpos, s->mesh.nrm, nv, 2, &m, &err) < 0)
            fail_msg("%s: %s", NAMES[k], err.msg);
        sm_map_apply(m, s->sim, rest_pos, rest_nrm, 2);
        if (MAPPINGS[k] != MR_SPRINGMASS_ONE_TO_ONE) {
            /* the rest mesh itself (float rounding of offsets in a basis) */
            double e = sm_max_diff(rest_pos, s->mesh.fpos, n3) / s->size, a = max_angle(rest_nrm, s->mesh.nrm, nv);
            if (!(e < 1e-6 && a < 1e-3))
                fail_msg("%s, %s at rest: position error %.3g of the size, normal %.3g rad", what, NAMES[k], e, a);
        }
        /* t = 1: the rigid motion's end */
        if (sm_sim_advance(s->sim, (uint64_t)llround(1.0 / s->p.dt), 2, &err) < 0)
            fail_msg("advance: %s", err.msg);
        sm_map_apply(m, s->sim, pos, nrm, 2);
        for (uint32_t v = 0; v < nv; v++) {
            rigid(s, rest_pos + (size_t)v * 3, want + (size_t)v * 3, false);
            rigid(s, rest_nrm + (size_t)v * 3, want_n + (size_t)v * 3, true);
        }
        double e = sm_max_diff(pos, want, n3) / s->size, a = max_angle(nrm, want_n, nv);
        printf("%-12s %-26s rigid motion: max position error %.2e of the size, normals %.2e rad "
               "(constant fallback %zu, translation only %zu, ghosts %zu)\n",
               what, NAMES[k], e, a, sm_map_get_info(m)->constant_fallback, sm_map_get_info(m)->translation_only,
               sm_map_get_info(m)->ghost_corners);
        if (!(e < 1e-5 && a < 1e-4))
            fail_msg("%s, %s: rigid motion off by %.3g of the size, normals by %.3g rad", what, NAMES[k], e, a);
        sm_map_free(m);
    }
    free(pos);
    free(nrm);
    free(rest_pos);
    free(rest_nrm);
    free(want);
    free(want_n);
}

static void test_rigid_sphere(void **state)
{
    (void)state;
    setup s = {0};
    sm_mesh_sphere(&s.mesh, 0.1, 0.2, -0.1, 1.0, 48, 96);
    setup_sim(&s, 0, 2000);
    check_rigid(&s, "sphere");
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

/* A real model: assimp's Wuson, every face its own three vertices. */
static void test_rigid_real_model(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err;
    assert_int_equal(mr_asset_load("/usr/share/assimp/models/PLY/Wuson.ply", &a, &err), MR_OK);
    const mr_mesh *mesh = &a->meshes[0];
    setup s = {0};
    sm_mesh_alloc(&s.mesh, mesh->vertex_count, mesh->triangle_count);
    for (size_t k = 0; k < (size_t)mesh->vertex_count * 3; k++) {
        s.mesh.pos[k] = mesh->positions[k];
        s.mesh.nrm[k] = mesh->normals[k];
    }
    memcpy(s.mesh.tri, mesh->indices, (size_t)mesh->triangle_count * 3 * sizeof *s.mesh.tri);
    sm_mesh_sync(&s.mesh);
    setup_sim(&s, 0, 3000);
    check_rigid(&s, "Wuson");
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
    mr_asset_free(a);
}

/* A slab one node thin: the approximate normals lie in the sheet (3.5),
 * so the curvature mapping keeps the vertices of its faces on the constant
 * basis, and still reproduces the rigid motion. */
static void test_thin_sheet(void **state)
{
    (void)state;
    setup s = {0};
    double lo[3] = {-1, -0.02, -1}, hi[3] = {1, 0.02, 1};
    sm_mesh_box(&s.mesh, lo, hi);
    setup_sim(&s, 0.25, 0);
    assert_int_equal(sm_sim_grid(s.sim)->thin_nodes, sm_sim_grid(s.sim)->nodes);
    sm_map *m = NULL;
    mr_error err;
    assert_int_equal(sm_map_new(s.sim, MR_SPRINGMASS_TRIANGLE_CURVATURE, s.mesh.fpos, s.mesh.nrm,
                                s.mesh.vertex_count, 1, &m, &err),
                     MR_OK);
    /* the 8 vertices of the sheet's two faces (normals +-y, across it) at
     * least; its rim's nodes have normals pointing out of the rim */
    size_t across = 0;
    for (uint32_t v = 0; v < s.mesh.vertex_count; v++)
        across += fabsf(s.mesh.nrm[v * 3 + 1]) > 0.5f;
    assert_int_equal(across, 8);
    assert_true(sm_map_get_info(m)->constant_fallback >= across);
    sm_map_free(m);
    check_rigid(&s, "thin sheet");
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

/* One node: no triangle, no neighbour. The triangle mappings follow it by
 * translation, trilinear extrapolates from it alone; rest is reproduced
 * and a pure translation carried exactly. */
static void test_single_node(void **state)
{
    (void)state;
    setup s = {0};
    sm_mesh_sphere(&s.mesh, 0, 0, 0, 1.0, 16, 32);
    setup_sim(&s, 5.0, 0);
    assert_int_equal(sm_sim_grid(s.sim)->nodes, 1);
    s.keys[1].rotation = mr_quat_identity(); /* a translation only */
    check_rigid(&s, "one node");
    sm_map *m = NULL;
    mr_error err;
    assert_int_equal(sm_map_new(s.sim, MR_SPRINGMASS_TRIANGLE_BASIS, s.mesh.fpos, s.mesh.nrm, s.mesh.vertex_count, 1,
                                &m, &err),
                     MR_OK);
    assert_int_equal(sm_map_get_info(m)->translation_only, s.mesh.vertex_count);
    sm_map_free(m);
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

/* The same bits for 1 and 3 threads, after a deforming simulation. */
static void test_threads(void **state)
{
    (void)state;
    setup s = {0};
    sm_mesh_sphere(&s.mesh, 0, 0, 0, 1.0, 48, 96);
    setup_sim(&s, 0, 2000);
    mr_springmass_probe_key pk[2] = {{0, {0, 1.4f, 0}}, {0.2f, {0, 0.6f, 0.1f}}};
    mr_springmass_probe probe = {0.4f, pk, 2};
    s.pin.box_max.y = -0.6f; /* the bottom held, the top probed */
    s.pin.path_count = 0;
    s.p.probes = &probe;
    s.p.probe_count = 1;
    mr_error err;
    assert_int_equal(sm_sim_advance(s.sim, 60, 2, &err), MR_OK);
    size_t n3 = (size_t)s.mesh.vertex_count * 3;
    for (size_t k = 0; k < sizeof MAPPINGS / sizeof *MAPPINGS; k++) {
        float *out[2][2];
        for (int run = 0; run < 2; run++) {
            sm_map *m = NULL;
            out[run][0] = malloc(n3 * 4);
            out[run][1] = malloc(n3 * 4);
            assert_int_equal(sm_map_new(s.sim, MAPPINGS[k], s.mesh.fpos, s.mesh.nrm, s.mesh.vertex_count,
                                        run ? 3 : 1, &m, &err),
                             MR_OK);
            sm_map_apply(m, s.sim, out[run][0], out[run][1], run ? 3 : 1);
            sm_map_free(m);
        }
        assert_memory_equal(out[0][0], out[1][0], n3 * 4);
        assert_memory_equal(out[0][1], out[1][1], n3 * 4);
        for (int run = 0; run < 2; run++) {
            free(out[run][0]);
            free(out[run][1]);
        }
    }
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_rigid_sphere), cmocka_unit_test(test_rigid_real_model),
        cmocka_unit_test(test_thin_sheet),   cmocka_unit_test(test_single_node),
        cmocka_unit_test(test_threads),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
