/*
 * test_springmass_map.c - the mappings of the spring-mass kind (paper 001,
 * 3.2-3.3; core/kinds/springmass/map.h): every mapping reproduces the rest
 * mesh and moves it rigidly under a rigid motion of the nodes (positions
 * within 1e-5 of the mesh size, normals turned with it, tangents (3.3.4)
 * within 1e-5 of the turned rest ones), on a sphere and on a real model;
 * the curvature-corrected mapping falls back to the constant basis on a
 * one-node-thin sheet; a grid of one node moves the mesh by translation;
 * tangents stay unit and orthogonal to the carried normal while the mesh
 * bends; results (tangents too) do not depend on the thread count.
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

/* The parameters: every node on one rigid path (a test that deforms the
 * mesh changes them before build_sim: the sim resolves its pins when it
 * is made). */
static void setup_params(setup *s)
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
}

static void build_sim(setup *s, double spacing, uint32_t nodes)
{
    sm_grid g;
    mr_error err;
    if (sm_grid_build(s->mesh.pos, s->mesh.vertex_count, s->mesh.tri, s->mesh.triangle_count, spacing, nodes, 0, 2,
                      &g, &err) < 0)
        fail_msg("grid: %s", err.msg);
    if (sm_sim_new(&g, &s->p, 2, &s->sim, &err) < 0)
        fail_msg("sim: %s", err.msg);
}

static void setup_sim(setup *s, double spacing, uint32_t nodes)
{
    setup_params(s);
    build_sim(s, spacing, nodes);
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

/* Largest |1 - |t|| and |t . n| over the vertices with a tangent. */
static void tangent_frame_error(const float *t, const float *n, uint32_t count, double *unit, double *ortho)
{
    *unit = *ortho = 0;
    for (uint32_t v = 0; v < count; v++) {
        const float *x = t + (size_t)v * 3, *y = n + (size_t)v * 3;
        double l = sqrt((double)x[0] * x[0] + (double)x[1] * x[1] + (double)x[2] * x[2]);
        *unit = fmax(*unit, fabs(1 - l));
        *ortho = fmax(*ortho, fabs((double)x[0] * y[0] + (double)x[1] * y[1] + (double)x[2] * y[2]));
    }
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

/* At rest and after the rigid motion, for every mapping. Tangents (when
 * the mesh has them) are held to the positions' 1e-5 (absolute, on unit
 * vectors): in the triangle mappings a unit tangent goes through the same
 * float products with the same basis as an offset of at most the mesh's
 * size, and one_to_one adds one Gram-Schmidt step against a node normal
 * made of unit vectors, so its rounding error, in units of its length, is
 * of the positions' in units of the size (measured: up to 6.8e-6 on Wuson).
 * trilinear's tangent is a derivative of the map (its Jacobian: node
 * displacements differenced across a cell of h, about a 25th of the size),
 * so the float rounding of the node positions (1e-7 of the size) grows by
 * size / h in it, as it does in the normals (the cofactor of that
 * Jacobian), which are held to 1e-4 rad for that reason: so are its
 * tangents (measured: 3.0e-5 on Wuson, normals 4.4e-5). */
static void check_rigid(setup *s, const char *what)
{
    uint32_t nv = s->mesh.vertex_count;
    size_t n3 = (size_t)nv * 3;
    const bool tangents = s->mesh.tan != NULL;
    float *pos = malloc(n3 * 4 + 4), *nrm = malloc(n3 * 4 + 4), *rest_pos = malloc(n3 * 4 + 4),
          *rest_nrm = malloc(n3 * 4 + 4), *want = malloc(n3 * 4 + 4), *want_n = malloc(n3 * 4 + 4),
          *tan = malloc(n3 * 4 + 4), *rest_tan = malloc(n3 * 4 + 4), *want_t = malloc(n3 * 4 + 4);
    mr_error err;
    for (size_t k = 0; k < sizeof MAPPINGS / sizeof *MAPPINGS; k++) {
        sm_sim_reset(s->sim, 2);
        sm_map *m = NULL;
        if (sm_map_new(s->sim, MAPPINGS[k], s->mesh.fpos, s->mesh.nrm, s->mesh.tan, nv, 2, &m, &err) < 0)
            fail_msg("%s: %s", NAMES[k], err.msg);
        sm_map_apply(m, s->sim, rest_pos, rest_nrm, rest_tan, 2);
        double et_rest = 0, unit = 0, ortho = 0;
        if (tangents)
            tangent_frame_error(rest_tan, rest_nrm, nv, &unit, &ortho);
        if (MAPPINGS[k] != MR_SPRINGMASS_ONE_TO_ONE) {
            /* the rest mesh itself (float rounding of offsets in a basis) */
            double e = sm_max_diff(rest_pos, s->mesh.fpos, n3) / s->size, a = max_angle(rest_nrm, s->mesh.nrm, nv);
            if (tangents)
                et_rest = sm_max_diff(rest_tan, s->mesh.tan, n3);
            if (!(e < 1e-6 && a < 1e-3 && et_rest < 1e-5))
                fail_msg("%s, %s at rest: position error %.3g of the size, normal %.3g rad, tangent %.3g", what,
                         NAMES[k], e, a, et_rest);
        }
        if (!(unit < 1e-5 && ortho < 1e-5))
            fail_msg("%s, %s at rest: tangents off unit length by %.3g, off the normal's plane by %.3g", what,
                     NAMES[k], unit, ortho);
        /* t = 1: the rigid motion's end */
        if (sm_sim_advance(s->sim, (uint64_t)llround(1.0 / s->p.dt), 2, &err) < 0)
            fail_msg("advance: %s", err.msg);
        sm_map_apply(m, s->sim, pos, nrm, tan, 2);
        for (uint32_t v = 0; v < nv; v++) {
            rigid(s, rest_pos + (size_t)v * 3, want + (size_t)v * 3, false);
            rigid(s, rest_nrm + (size_t)v * 3, want_n + (size_t)v * 3, true);
            rigid(s, rest_tan + (size_t)v * 3, want_t + (size_t)v * 3, true);
        }
        double e = sm_max_diff(pos, want, n3) / s->size, a = max_angle(nrm, want_n, nv);
        double et = tangents ? sm_max_diff(tan, want_t, n3) : 0;
        printf("%-12s %-26s rigid motion: max position error %.2e of the size, normals %.2e rad, tangents %.2e "
               "(at rest %.2e) (constant fallback %zu, translation only %zu, ghosts %zu)\n",
               what, NAMES[k], e, a, et, et_rest, sm_map_get_info(m)->constant_fallback,
               sm_map_get_info(m)->translation_only, sm_map_get_info(m)->ghost_corners);
        double et_bound = MAPPINGS[k] == MR_SPRINGMASS_TRILINEAR ? 1e-4 : 1e-5;
        if (!(e < 1e-5 && a < 1e-4 && et < et_bound))
            fail_msg("%s, %s: rigid motion off by %.3g of the size, normals by %.3g rad, tangents by %.3g", what,
                     NAMES[k], e, a, et);
        sm_map_free(m);
    }
    free(pos);
    free(nrm);
    free(rest_pos);
    free(rest_nrm);
    free(want);
    free(want_n);
    free(tan);
    free(rest_tan);
    free(want_t);
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

/* A real model: assimp's Wuson, every face its own three vertices, with
 * its texture coordinates' tangents (asset.h, mr_mesh_tangents). */
static void test_rigid_real_model(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err;
    assert_int_equal(mr_asset_load("/usr/share/assimp/models/PLY/Wuson.ply", &a, &err), MR_OK);
    const mr_mesh *mesh = &a->meshes[0];
    assert_non_null(mesh->tangents);
    setup s = {0};
    sm_mesh_alloc(&s.mesh, mesh->vertex_count, mesh->triangle_count);
    s.mesh.tan = malloc((size_t)mesh->vertex_count * 3 * sizeof *s.mesh.tan + 4);
    for (size_t k = 0; k < (size_t)mesh->vertex_count * 3; k++) {
        s.mesh.pos[k] = mesh->positions[k];
        s.mesh.nrm[k] = mesh->normals[k];
        s.mesh.tan[k] = mesh->tangents[k / 3 * 4 + k % 3];
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
    sm_mesh_fit_tangents(&s.mesh, mr_v3(0.6f, 0.3f, 0.2f));
    setup_sim(&s, 0.25, 0);
    assert_int_equal(sm_sim_grid(s.sim)->thin_nodes, sm_sim_grid(s.sim)->nodes);
    sm_map *m = NULL;
    mr_error err;
    assert_int_equal(sm_map_new(s.sim, MR_SPRINGMASS_TRIANGLE_CURVATURE, s.mesh.fpos, s.mesh.nrm, s.mesh.tan,
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
    assert_int_equal(sm_map_new(s.sim, MR_SPRINGMASS_TRIANGLE_BASIS, s.mesh.fpos, s.mesh.nrm, s.mesh.tan,
                                s.mesh.vertex_count, 1, &m, &err),
                     MR_OK);
    assert_int_equal(sm_map_get_info(m)->translation_only, s.mesh.vertex_count);
    sm_map_free(m);
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

/* The same bits for 1 and 3 threads, after a deforming simulation:
 * positions, normals and tangents. */
static void test_threads(void **state)
{
    (void)state;
    setup s = {0};
    sm_mesh_sphere(&s.mesh, 0, 0, 0, 1.0, 48, 96);
    setup_params(&s);
    mr_springmass_probe_key pk[2] = {{0, {0, 1.4f, 0}}, {0.2f, {0, 0.6f, 0.1f}}};
    mr_springmass_probe probe = {0.4f, pk, 2};
    s.pin.box_max.y = -0.6f; /* the bottom held, the top probed */
    s.pin.path_count = 0;
    s.p.probes = &probe;
    s.p.probe_count = 1;
    build_sim(&s, 0, 2000);
    mr_error err;
    const float *rest[3], *now[3];
    sm_sim_rest(s.sim, rest);
    assert_int_equal(sm_sim_advance(s.sim, 60, 2, &err), MR_OK);
    sm_sim_positions(s.sim, now);
    double moved = 0; /* the simulation did deform the grid */
    for (size_t c = 0; c < sm_sim_grid(s.sim)->cells; c++)
        if (sm_sim_grid(s.sim)->active[c])
            moved = fmax(moved, fabs((double)now[1][c] - rest[1][c]));
    assert_true(moved > 0.1);
    size_t n3 = (size_t)s.mesh.vertex_count * 3;
    for (size_t k = 0; k < sizeof MAPPINGS / sizeof *MAPPINGS; k++) {
        float *out[2][3];
        for (int run = 0; run < 2; run++) {
            sm_map *m = NULL;
            for (int q = 0; q < 3; q++)
                out[run][q] = malloc(n3 * 4);
            assert_int_equal(sm_map_new(s.sim, MAPPINGS[k], s.mesh.fpos, s.mesh.nrm, s.mesh.tan, s.mesh.vertex_count,
                                        run ? 3 : 1, &m, &err),
                             MR_OK);
            sm_map_apply(m, s.sim, out[run][0], out[run][1], out[run][2], run ? 3 : 1);
            sm_map_free(m);
        }
        for (int q = 0; q < 3; q++)
            if (memcmp(out[0][q], out[1][q], n3 * 4) != 0)
                fail_msg("%s: the %s differ between 1 and 3 threads", NAMES[k],
                         q == 0 ? "positions" : q == 1 ? "normals" : "tangents");
        for (int run = 0; run < 2; run++)
            for (int q = 0; q < 3; q++)
                free(out[run][q]);
    }
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
}

/* Bending and probing (a real model, Wuson with its texture coordinates'
 * tangents: its bottom held, a probe pushed a tenth of its height into its
 * top, which dents and bends it): every
 * mapping's tangents stay unit and orthogonal to the normal it carries,
 * within 1e-5 (float rounding: the triangle mappings turn the rest pair
 * with one orthonormal basis, one_to_one and trilinear end in a
 * Gram-Schmidt step; a few ulps of each of about ten operations), while
 * they do turn (the deformation moves them). */
static void test_tangents_deformed(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err;
    assert_int_equal(mr_asset_load("/usr/share/assimp/models/PLY/Wuson.ply", &a, &err), MR_OK);
    const mr_mesh *mesh = &a->meshes[0];
    setup s = {0};
    sm_mesh_alloc(&s.mesh, mesh->vertex_count, mesh->triangle_count);
    s.mesh.tan = malloc((size_t)mesh->vertex_count * 3 * sizeof *s.mesh.tan + 4);
    for (size_t k = 0; k < (size_t)mesh->vertex_count * 3; k++) {
        s.mesh.pos[k] = mesh->positions[k];
        s.mesh.nrm[k] = mesh->normals[k];
        s.mesh.tan[k] = mesh->tangents[k / 3 * 4 + k % 3];
    }
    memcpy(s.mesh.tri, mesh->indices, (size_t)mesh->triangle_count * 3 * sizeof *s.mesh.tri);
    sm_mesh_sync(&s.mesh);
    setup_params(&s);
    /* the probe: from above the top down into it */
    double lo = INFINITY, hi = -INFINITY;
    for (uint32_t v = 0; v < s.mesh.vertex_count; v++) {
        lo = fmin(lo, s.mesh.pos[v * 3 + 1]);
        hi = fmax(hi, s.mesh.pos[v * 3 + 1]);
    }
    mr_springmass_probe_key pk[2] = {{0, {0, (float)(hi + 0.3 * (hi - lo)), 0}},
                                     {0.25f, {0, (float)(hi - 0.1 * (hi - lo)), 0.05f}}};
    mr_springmass_probe probe = {(float)(0.2 * (hi - lo)), pk, 2};
    s.pin.box_max.y = (float)(lo + 0.2 * (hi - lo)); /* the bottom held */
    s.pin.path_count = 0;
    s.p.probes = &probe;
    s.p.probe_count = 1;
    s.p.gravity = (mr_vec3){0, 0, 0}; /* the probe alone (gravity folds the floppy model over) */
    build_sim(&s, 0, 1500);
    uint32_t nv = s.mesh.vertex_count;
    size_t n3 = (size_t)nv * 3;
    float *pos = malloc(n3 * 4 + 4), *nrm = malloc(n3 * 4 + 4), *tan = malloc(n3 * 4 + 4),
          *rest_tan = malloc(n3 * 4 + 4);
    for (size_t k = 0; k < sizeof MAPPINGS / sizeof *MAPPINGS; k++) {
        sm_sim_reset(s.sim, 2);
        sm_map *m = NULL;
        assert_int_equal(sm_map_new(s.sim, MAPPINGS[k], s.mesh.fpos, s.mesh.nrm, s.mesh.tan, nv, 2, &m, &err), MR_OK);
        sm_map_apply(m, s.sim, pos, nrm, rest_tan, 2);
        assert_int_equal(sm_sim_advance(s.sim, (uint64_t)llround(0.25 / s.p.dt), 2, &err), MR_OK);
        sm_map_apply(m, s.sim, pos, nrm, tan, 2);
        double unit, ortho, turned = max_angle(tan, rest_tan, nv);
        tangent_frame_error(tan, nrm, nv, &unit, &ortho);
        printf("Wuson probed %-26s tangents: off unit length by %.2e, off the normal's plane by %.2e; turned by "
               "up to %.2f rad\n",
               NAMES[k], unit, ortho, turned);
        if (!(unit < 1e-5 && ortho < 1e-5))
            fail_msg("%s: tangents off unit length by %.3g, off the normal's plane by %.3g", NAMES[k], unit, ortho);
        if (!(turned > 0.1))
            fail_msg("%s: the probe turned no tangent by more than %.3g rad", NAMES[k], turned);
        sm_map_free(m);
    }
    free(pos);
    free(nrm);
    free(tan);
    free(rest_tan);
    sm_sim_free(s.sim);
    sm_mesh_free(&s.mesh);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_rigid_sphere), cmocka_unit_test(test_rigid_real_model),
        cmocka_unit_test(test_thin_sheet),   cmocka_unit_test(test_single_node),
        cmocka_unit_test(test_threads),      cmocka_unit_test(test_tangents_deformed),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
