/*
 * test_springmass_grid.c - the node grid of the spring-mass kind (paper
 * 001, 3.1): which lattice points lie inside a mesh (closed, with holes,
 * overlapping and nested shells, a real model), the spacing found for a
 * target node count, the 18-neighbourhood, surface and one-node-thin nodes,
 * and the refusals.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <stdio.h>

#include "../support/springmass_fixture.h"
#include "asset/asset.h"

/* The exact answer for a sphere of radius r at c, for points farther than
 * `margin` from its surface (the UV sphere's facets lie up to
 * r (1 - cos(pi / 32)) = 4.8e-3 r inside the true sphere). */
static int sphere_truth(const double p[3], const double c[3], double r, double margin)
{
    double d = sqrt((p[0] - c[0]) * (p[0] - c[0]) + (p[1] - c[1]) * (p[1] - c[1]) + (p[2] - c[2]) * (p[2] - c[2]));
    if (fabs(d - r) <= margin)
        return -1;
    return d < r;
}

static void lattice_point(const sm_lattice *lat, size_t idx, double p[3])
{
    size_t i = idx % lat->n[0], j = (idx / lat->n[0]) % lat->n[1], k = idx / ((size_t)lat->n[0] * lat->n[1]);
    p[0] = lat->origin[0] + lat->h * (double)i;
    p[1] = lat->origin[1] + lat->h * (double)j;
    p[2] = lat->origin[2] + lat->h * (double)k;
}

static sm_lattice cube_lattice(double half, double h)
{
    sm_lattice lat = {.h = h};
    uint32_t n = (uint32_t)llround(2 * half / h) + 1;
    for (int a = 0; a < 3; a++) {
        lat.n[a] = n;
        lat.origin[a] = -half + 0.013 * h * (a + 1); /* off the sphere's symmetry planes */
    }
    return lat;
}

static void test_inside_closed_sphere(void **state)
{
    (void)state;
    sm_mesh m;
    sm_mesh_sphere(&m, 0, 0, 0, 1.0, 32, 64);
    sm_lattice lat = cube_lattice(1.3, 0.05);
    size_t n = (size_t)lat.n[0] * lat.n[1] * lat.n[2];
    uint8_t *in = malloc(n);
    sm_inside_info info;
    mr_error err;
    assert_int_equal(sm_inside_lattice(m.pos, m.tri, m.triangle_count, &lat, 2, in, &info, &err), MR_OK);
    size_t checked = 0;
    double c[3] = {0, 0, 0}, p[3];
    for (size_t i = 0; i < n; i++) {
        lattice_point(&lat, i, p);
        int truth = sphere_truth(p, c, 1.0, 0.01);
        if (truth < 0)
            continue;
        checked++;
        if (in[i] != truth)
            fail_msg("point (%g, %g, %g): inside %d, truth %d", p[0], p[1], p[2], in[i], truth);
    }
    assert_true(checked > n * 9 / 10);
    /* a watertight sphere: every line votes, no point needs the fallback */
    assert_int_equal(info.abstained, 0);
    assert_int_equal(info.winding, 0);
    assert_int_equal(info.lines, 3 * (size_t)lat.n[0] * lat.n[0]);
    free(in);
    sm_mesh_free(&m);
}

/* Small holes cost the lines through them their vote, not the answer. */
static void test_inside_sphere_with_holes(void **state)
{
    (void)state;
    sm_mesh m;
    sm_mesh_sphere(&m, 0, 0, 0, 1.0, 32, 64);
    uint32_t before = m.triangle_count;
    sm_mesh_punch(&m, 100, 331, 12); /* 12 triangles spread over the sphere */
    assert_int_equal(m.triangle_count, before - 12);
    sm_lattice lat = cube_lattice(1.3, 0.05);
    size_t n = (size_t)lat.n[0] * lat.n[1] * lat.n[2];
    uint8_t *in = malloc(n);
    sm_inside_info info;
    mr_error err;
    assert_int_equal(sm_inside_lattice(m.pos, m.tri, m.triangle_count, &lat, 2, in, &info, &err), MR_OK);
    assert_true(info.abstained > 0); /* some lines did pass through holes */
    double c[3] = {0, 0, 0}, p[3];
    for (size_t i = 0; i < n; i++) {
        lattice_point(&lat, i, p);
        int truth = sphere_truth(p, c, 1.0, 0.01);
        if (truth >= 0 && in[i] != truth)
            fail_msg("with holes, point (%g, %g, %g): inside %d, truth %d", p[0], p[1], p[2], in[i], truth);
    }
    free(in);
    sm_mesh_free(&m);
}

/* Two overlapping spheres are their union (winding, not parity); a sphere
 * inside another with inward normals is a hollow shell. */
static void test_inside_shells(void **state)
{
    (void)state;
    sm_mesh a, b;
    sm_mesh_sphere(&a, -0.4, 0, 0, 0.8, 24, 48);
    sm_mesh_sphere(&b, 0.4, 0, 0, 0.8, 24, 48);
    sm_mesh u;
    sm_mesh_alloc(&u, a.vertex_count + b.vertex_count, a.triangle_count + b.triangle_count);
    memcpy(u.pos, a.pos, (size_t)a.vertex_count * 3 * sizeof *u.pos);
    memcpy(u.pos + (size_t)a.vertex_count * 3, b.pos, (size_t)b.vertex_count * 3 * sizeof *u.pos);
    memcpy(u.tri, a.tri, (size_t)a.triangle_count * 3 * sizeof *u.tri);
    for (size_t k = 0; k < (size_t)b.triangle_count * 3; k++)
        u.tri[(size_t)a.triangle_count * 3 + k] = b.tri[k] + a.vertex_count;
    sm_lattice lat = cube_lattice(1.3, 0.05);
    size_t n = (size_t)lat.n[0] * lat.n[1] * lat.n[2];
    uint8_t *in = malloc(n);
    mr_error err;
    assert_int_equal(sm_inside_lattice(u.pos, u.tri, u.triangle_count, &lat, 1, in, NULL, &err), MR_OK);
    double ca[3] = {-0.4, 0, 0}, cb[3] = {0.4, 0, 0}, p[3];
    for (size_t i = 0; i < n; i++) {
        lattice_point(&lat, i, p);
        int ta = sphere_truth(p, ca, 0.8, 0.01), tb = sphere_truth(p, cb, 0.8, 0.01);
        if (ta < 0 || tb < 0)
            continue;
        if (in[i] != (ta || tb))
            fail_msg("union, point (%g, %g, %g): inside %d", p[0], p[1], p[2], in[i]);
    }
    /* hollow: outer radius 1, inner 0.5 turned inside out */
    sm_mesh outer, inner;
    sm_mesh_sphere(&outer, 0, 0, 0, 1.0, 24, 48);
    sm_mesh_sphere(&inner, 0, 0, 0, 0.5, 24, 48);
    for (uint32_t t = 0; t < inner.triangle_count; t++) {
        uint32_t s = inner.tri[t * 3 + 1];
        inner.tri[t * 3 + 1] = inner.tri[t * 3 + 2];
        inner.tri[t * 3 + 2] = s;
    }
    sm_mesh h;
    sm_mesh_alloc(&h, outer.vertex_count + inner.vertex_count, outer.triangle_count + inner.triangle_count);
    memcpy(h.pos, outer.pos, (size_t)outer.vertex_count * 3 * sizeof *h.pos);
    memcpy(h.pos + (size_t)outer.vertex_count * 3, inner.pos, (size_t)inner.vertex_count * 3 * sizeof *h.pos);
    memcpy(h.tri, outer.tri, (size_t)outer.triangle_count * 3 * sizeof *h.tri);
    for (size_t k = 0; k < (size_t)inner.triangle_count * 3; k++)
        h.tri[(size_t)outer.triangle_count * 3 + k] = inner.tri[k] + outer.vertex_count;
    assert_int_equal(sm_inside_lattice(h.pos, h.tri, h.triangle_count, &lat, 2, in, NULL, &err), MR_OK);
    double c0[3] = {0, 0, 0};
    for (size_t i = 0; i < n; i++) {
        lattice_point(&lat, i, p);
        int to = sphere_truth(p, c0, 1.0, 0.01), ti = sphere_truth(p, c0, 0.5, 0.01);
        if (to < 0 || ti < 0)
            continue;
        if (in[i] != (to && !ti))
            fail_msg("hollow, point (%g, %g, %g): inside %d", p[0], p[1], p[2], in[i]);
    }
    free(in);
    sm_mesh_free(&a);
    sm_mesh_free(&b);
    sm_mesh_free(&u);
    sm_mesh_free(&outer);
    sm_mesh_free(&inner);
    sm_mesh_free(&h);
}

/* The generalised winding number: 1 inside, 0 outside (tolerance 1e-9:
 * solid angles of a closed mesh sum to 4 pi up to rounding), about 1/2
 * with half the sphere gone. */
static void test_winding_number(void **state)
{
    (void)state;
    sm_mesh m;
    sm_mesh_sphere(&m, 0, 0, 0, 1.0, 16, 32);
    double in[3] = {0.1, 0.2, -0.3}, out[3] = {1.5, 0.2, 0.1}, far[3] = {1e6, 0, 0};
    assert_true(fabs(sm_winding_number(m.pos, m.tri, m.triangle_count, in) - 1) < 1e-9);
    assert_true(fabs(sm_winding_number(m.pos, m.tri, m.triangle_count, out)) < 1e-9);
    assert_true(fabs(sm_winding_number(m.pos, m.tri, m.triangle_count, far)) < 1e-9);
    /* the upper hemisphere only (triangles of the top 8 rings): an open cup */
    double centre[3] = {0, 0, 0};
    uint32_t keep = 32 + 32 + 2 * 32 * 7; /* the caps come first, two per segment */
    uint32_t half = 0;
    for (uint32_t t = 0; t < keep && t < m.triangle_count; t++) {
        const double *v = m.pos + (size_t)m.tri[t * 3] * 3;
        if (v[1] >= -1e-12)
            memmove(m.tri + (size_t)half++ * 3, m.tri + (size_t)t * 3, 3 * sizeof *m.tri);
    }
    double w = sm_winding_number(m.pos, m.tri, half, centre);
    assert_true(w > 0.3 && w < 0.7);
    sm_mesh_free(&m);
}

static void test_neighbours(void **state)
{
    (void)state;
    int axis = 0, diag = 0;
    for (int d = 0; d < 18; d++) {
        int nz = 0;
        for (int a = 0; a < 3; a++)
            nz += sm_neighbour_dir[d][a] != 0;
        if (d < 6)
            assert_int_equal(nz, 1);
        else
            assert_int_equal(nz, 2);
        axis += nz == 1;
        diag += nz == 2;
        for (int e = 0; e < 18; e++) { /* distinct, and every direction's opposite is there */
            bool same = true, opposite = true;
            for (int a = 0; a < 3; a++) {
                same &= sm_neighbour_dir[d][a] == sm_neighbour_dir[e][a];
                opposite &= sm_neighbour_dir[d][a] == -sm_neighbour_dir[e][a];
            }
            assert_false(same && d != e);
            (void)opposite;
        }
    }
    assert_int_equal(axis, 6);
    assert_int_equal(diag, 12);
}

static void test_grid_sphere(void **state)
{
    (void)state;
    sm_mesh m;
    sm_mesh_sphere(&m, 0.3, -0.2, 0.1, 1.0, 32, 64);
    sm_grid g;
    mr_error err;
    /* a target count: within 5 % */
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 0, 3000, 0, 2, &g, &err), MR_OK);
    assert_true(fabs((double)g.nodes / 3000 - 1) <= 0.05);
    /* a spacing: the lattice points inside, close to the volume over h^3 */
    double h = 0.1;
    sm_grid_free(&g);
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, h, 0, 0, 2, &g, &err), MR_OK);
    assert_true(g.h == h);
    double expect = 4.0 / 3.0 * M_PI / (h * h * h);
    assert_true(fabs(g.nodes / expect - 1) < 0.05);
    /* padding: no node within SM_GRID_PAD cells of the array's faces */
    size_t surface = 0, count = 0;
    for (uint32_t k = 0; k < g.n[2]; k++)
        for (uint32_t j = 0; j < g.n[1]; j++)
            for (uint32_t i = 0; i < g.n[0]; i++) {
                size_t c = sm_grid_cell(&g, i, j, k);
                if (!g.active[c])
                    continue;
                count++;
                assert_true(i >= SM_GRID_PAD && j >= SM_GRID_PAD && k >= SM_GRID_PAD);
                assert_true(i + SM_GRID_PAD < g.n[0] && j + SM_GRID_PAD < g.n[1] && k + SM_GRID_PAD < g.n[2]);
                bool open = false;
                for (int d = 0; d < 6; d++)
                    open |= !g.active[(size_t)((ptrdiff_t)c + sm_grid_offset(&g, sm_neighbour_dir[d]))];
                assert_int_equal(open, (g.flags[c] & SM_NODE_SURFACE) != 0);
                surface += open;
                assert_false(g.flags[c] & SM_NODE_THIN); /* a ball has no one-node-thin part */
            }
    assert_int_equal(count, g.nodes);
    assert_int_equal(surface, g.surface_nodes);
    assert_int_equal(g.thin_nodes, 0);
    sm_grid_free(&g);
    sm_mesh_free(&m);
}

/* A slab thinner than the spacing still gets its middle layer (the
 * lattice is centred on the box), and every node of it is one node thin. */
static void test_grid_thin_sheet(void **state)
{
    (void)state;
    sm_mesh m;
    double lo[3] = {-1, -0.02, -1}, hi[3] = {1, 0.02, 1};
    sm_mesh_box(&m, lo, hi);
    sm_grid g;
    mr_error err;
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 0.1, 0, 0, 2, &g, &err), MR_OK);
    assert_true(g.nodes > 300);
    assert_int_equal(g.thin_nodes, g.nodes);
    assert_int_equal(g.surface_nodes, g.nodes);
    sm_grid_free(&g);
    sm_mesh_free(&m);
}

static void test_grid_refusals(void **state)
{
    (void)state;
    sm_mesh m;
    sm_mesh_sphere(&m, 0, 0, 0, 1.0, 16, 32);
    sm_grid g;
    mr_error err;
    /* more cells than allowed */
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 1e-3, 0, 0, 1, &g, &err),
                     MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "a spacing of 0.001 makes a grid of more than"));
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 0, 3000, 1000, 1, &g, &err),
                     MR_ERR_LIMIT);
    /* a spacing larger than the sphere: the middle node is inside */
    assert_int_equal(sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 5, 0, 0, 1, &g, &err), MR_OK);
    assert_int_equal(g.nodes, 1);
    sm_grid_free(&g);
    /* an open mesh: one triangle has no inside */
    sm_mesh_punch(&m, 1, 1, m.triangle_count);
    assert_int_equal(m.triangle_count, 1);
    int rc = sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 0.1, 0, 0, 1, &g, &err);
    assert_true(rc == MR_ERR_INVALID || rc == MR_ERR_LIMIT);
    sm_mesh_free(&m);
    /* nothing at all */
    assert_int_equal(sm_grid_build(NULL, 0, NULL, 0, 0.1, 0, 0, 1, &g, &err), MR_ERR_INVALID);
}

/* A real model (assimp's Wuson, a PLY of 3,732 triangles with each face
 * its own vertices): the inside is found for a target count. */
static void test_grid_real_model(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err;
    assert_int_equal(mr_asset_load("/usr/share/assimp/models/PLY/Wuson.ply", &a, &err), MR_OK);
    const mr_mesh *mesh = &a->meshes[0];
    double *pos = malloc((size_t)mesh->vertex_count * 3 * sizeof *pos);
    for (size_t k = 0; k < (size_t)mesh->vertex_count * 3; k++)
        pos[k] = mesh->positions[k];
    sm_grid g;
    assert_int_equal(sm_grid_build(pos, mesh->vertex_count, mesh->indices, mesh->triangle_count, 0, 5000, 0, 2, &g,
                                   &err),
                     MR_OK);
    assert_true(fabs((double)g.nodes / 5000 - 1) <= 0.05);
    assert_true(g.surface_nodes > 0 && g.surface_nodes < g.nodes);
    printf("Wuson: %zu nodes at h = %.4f, %zu surface, %zu thin, %zu lines abstained, %zu by winding number\n",
           g.nodes, g.h, g.surface_nodes, g.thin_nodes, g.inside.abstained, g.inside.winding);
    sm_grid_free(&g);
    free(pos);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_inside_closed_sphere), cmocka_unit_test(test_inside_sphere_with_holes),
        cmocka_unit_test(test_inside_shells),        cmocka_unit_test(test_winding_number),
        cmocka_unit_test(test_neighbours),           cmocka_unit_test(test_grid_sphere),
        cmocka_unit_test(test_grid_thin_sheet),      cmocka_unit_test(test_grid_refusals),
        cmocka_unit_test(test_grid_real_model),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
