/*
 * test_svo_voxelize.c - mesh -> SVO voxelisation (core/kinds/svo/voxelize.h):
 * the triangle/box overlap test against brute-force sampling and hand-made
 * separating cases, closest points, weight quantisation, conservative
 * surface voxelisation of a cube and a UV sphere (coverage, no spurious
 * voxels, counts against analytic expectations), solid volume, a real
 * skinned model's palette, thread-count independence, leaf keys dropped
 * unless kept, and bad input.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "asset/asset.h"
#include "util/morton.h"
#include "kinds/svo/voxelize.h"

#define MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define PI 3.14159265358979323846

/* Deterministic LCG so failures reproduce. */
static uint64_t rng_state = 12345;
static double rnd(void)
{
    rng_state = rng_state * 6364136223846793005ull + 1442695040888963407ull;
    return (double)(rng_state >> 11) / 9007199254740992.0;
}

/* ---------------------------------------------------------------------- */
/* Overlap test                                                           */

static bool sample_hit(const double c[3], const double h[3], const double *v[3], int steps,
                       double grow)
{
    for (int i = 0; i <= steps; i++)
        for (int j = 0; j <= steps - i; j++) {
            double u = (double)i / steps, w = (double)j / steps, t = 1 - u - w;
            bool in = true;
            for (int k = 0; k < 3 && in; k++) {
                double p = t * v[0][k] + u * v[1][k] + w * v[2][k];
                in = fabs(p - c[k]) <= h[k] + grow;
            }
            if (in)
                return true;
        }
    return false;
}

/* Random triangles against a box; a triangle sample inside the box means
 * SAT must report overlap (no false negatives). Conversely a reported overlap
 * must be confirmed by a sample within the box grown by the sample spacing
 * times the longest edge (the farthest a true overlap point can lie from the
 * nearest sample): catches a SAT that is too permissive. */
static void test_overlap_vs_brute_force(void **state)
{
    (void)state;
    const int steps = 120;
    int hits = 0, misses = 0;
    for (int it = 0; it < 3000; it++) {
        double c[3] = {0, 0, 0}, h[3] = {0.5 + rnd(), 0.5 + rnd(), 0.5 + rnd()};
        double a[3], b[3], d[3];
        double sc = it % 3 == 0 ? 1.0 : 3.0;
        for (int k = 0; k < 3; k++) {
            a[k] = (rnd() - 0.5) * 4 * sc;
            b[k] = a[k] + (rnd() - 0.5) * 3 * sc;
            d[k] = a[k] + (rnd() - 0.5) * 3 * sc;
        }
        const double *v[3] = {a, b, d};
        bool sat = mr_tri_box_overlap(c, h, a, b, d);
        if (sample_hit(c, h, v, steps, 0.0))
            assert_true(sat);
        if (sat) {
            double e = 0;
            for (int k = 0; k < 3; k++)
                e = fmax(e, fmax(fabs(a[k] - b[k]), fmax(fabs(b[k] - d[k]), fabs(d[k] - a[k]))));
            assert_true(sample_hit(c, h, v, steps, 2.0 * e / steps + 1e-12));
            hits++;
        } else {
            misses++;
        }
    }
    /* Both outcomes must be exercised for the test to mean anything. */
    assert_true(hits > 300 && misses > 300);
}

static void test_overlap_known_cases(void **state)
{
    (void)state;
    double c[3] = {0, 0, 0}, h[3] = {1, 1, 1};
    /* Parallel to a face, just outside / touching. */
    double a[3] = {-2, -2, 1.000001}, b[3] = {2, -2, 1.000001}, d[3] = {0, 2, 1.000001};
    assert_false(mr_tri_box_overlap(c, h, a, b, d));
    a[2] = b[2] = d[2] = 1.0;
    assert_true(mr_tri_box_overlap(c, h, a, b, d));
    /* Separated only by an edge x axis direction: segment-like triangle near
     * the (+x, +y) box edge, line x + y = 2.5 (corner has x + y = 2). */
    double e0[3] = {2, 0.5, -0.5}, e1[3] = {0.5, 2, -0.5}, e2[3] = {0.5, 2, 0.5};
    assert_false(mr_tri_box_overlap(c, h, e0, e1, e2));
    double f0[3] = {1.4, 0.5, -0.5}, f1[3] = {0.5, 1.4, -0.5}, f2[3] = {0.5, 1.4, 0.5};
    assert_true(mr_tri_box_overlap(c, h, f0, f1, f2));
    /* Separated only by the triangle normal: plane x + y + z = 3.2 cuts the
     * box's bounding planes but misses the corner (1,1,1) (sum 3). */
    double g0[3] = {3.2, 0, 0}, g1[3] = {0, 3.2, 0}, g2[3] = {0, 0, 3.2};
    assert_false(mr_tri_box_overlap(c, h, g0, g1, g2));
    g0[0] = 2.9, g1[1] = 2.9, g2[2] = 2.9;
    assert_true(mr_tri_box_overlap(c, h, g0, g1, g2));
    /* Triangle fully containing the box's cross-section. */
    double big0[3] = {-1e30, -1e30, 0}, big1[3] = {1e30, -1e30, 0}, big2[3] = {0, 1e30, 0};
    assert_true(mr_tri_box_overlap(c, h, big0, big1, big2));
    big0[2] = big1[2] = big2[2] = 5;
    assert_false(mr_tri_box_overlap(c, h, big0, big1, big2));
    /* Float extremes must not overflow to inf - inf = NaN. */
    double m0[3] = {-3.4e38, -3.4e38, 0.5}, m1[3] = {3.4e38, -3.4e38, 0.5},
           m2[3] = {0, 3.4e38, 0.5};
    assert_true(mr_tri_box_overlap(c, h, m0, m1, m2));
    /* Non-finite input, negative extent. */
    double n0[3] = {NAN, 0, 0};
    assert_false(mr_tri_box_overlap(c, h, n0, f1, f2));
    double inf0[3] = {INFINITY, 0, 0};
    assert_false(mr_tri_box_overlap(c, h, inf0, f1, f2));
    double hn[3] = {-1, 1, 1};
    assert_false(mr_tri_box_overlap(c, hn, f0, f1, f2));
}

static void test_overlap_degenerate(void **state)
{
    (void)state;
    double c[3] = {0, 0, 0}, h[3] = {1, 1, 1};
    /* Points. */
    double p_in[3] = {0.3, -0.9, 1.0}, p_out[3] = {0.3, -0.9, 1.01};
    assert_true(mr_tri_box_overlap(c, h, p_in, p_in, p_in));
    assert_false(mr_tri_box_overlap(c, h, p_out, p_out, p_out));
    /* Segments (repeated vertex and collinear), passing the corner. */
    double s0[3] = {2, 0.5, 0}, s1[3] = {0.5, 2, 0}, mid[3] = {1.25, 1.25, 0};
    assert_false(mr_tri_box_overlap(c, h, s0, s1, s1));
    assert_false(mr_tri_box_overlap(c, h, s0, mid, s1));
    double t0[3] = {1.4, 0.5, 0}, t1[3] = {0.5, 1.4, 0}, tm[3] = {0.95, 0.95, 0};
    assert_true(mr_tri_box_overlap(c, h, t0, t1, t1));
    assert_true(mr_tri_box_overlap(c, h, t0, tm, t1));
    /* Random degenerate triangles vs brute force. */
    for (int it = 0; it < 2000; it++) {
        double a[3], b[3], d[3];
        double t = rnd() * 2 - 0.5;
        for (int k = 0; k < 3; k++) {
            a[k] = (rnd() - 0.5) * 5;
            b[k] = a[k] + (rnd() - 0.5) * 4;
            d[k] = a[k] + t * (b[k] - a[k]); /* collinear */
        }
        const double *v[3] = {a, b, d};
        bool sat = mr_tri_box_overlap(c, h, a, b, d);
        /* Sampling the segment hull: a sample inside forces overlap. */
        if (sample_hit(c, h, v, 200, 0.0))
            assert_true(sat);
        if (sat)
            assert_true(sample_hit(c, h, v, 200, 0.05 * 3));
    }
}

/* Closest point: squared distance equals the brute-force minimum over a
 * dense sample grid up to the sample spacing (<= 1e-2 for these sizes), and
 * is never larger than it. */
static void test_closest_point(void **state)
{
    (void)state;
    for (int it = 0; it < 500; it++) {
        double a[3], b[3], d[3], p[3], w[3];
        for (int k = 0; k < 3; k++) {
            a[k] = rnd() * 2 - 1, b[k] = rnd() * 2 - 1, d[k] = rnd() * 2 - 1;
            p[k] = rnd() * 4 - 2;
        }
        if (it % 5 == 0)
            memcpy(d, b, sizeof d); /* degenerate */
        double d2 = mr_tri_closest_point(p, a, b, d, w);
        assert_true(w[0] >= 0 && w[1] >= 0 && w[2] >= 0);
        assert_true(fabs(w[0] + w[1] + w[2] - 1) < 1e-9);
        double best = 1e300;
        const int steps = 200;
        for (int i = 0; i <= steps; i++)
            for (int j = 0; j <= steps - i; j++) {
                double u = (double)i / steps, v = (double)j / steps, t = 1 - u - v, s = 0;
                for (int k = 0; k < 3; k++) {
                    double q = t * a[k] + u * b[k] + v * d[k] - p[k];
                    s += q * q;
                }
                best = fmin(best, s);
            }
        assert_true(d2 <= best + 1e-12);
        assert_true(sqrt(best) - sqrt(d2) < 2e-2);
    }
}

static void test_quantize_weights(void **state)
{
    (void)state;
    uint8_t q[4];
    float w1[4] = {0.5f, 0.25f, 0.25f, 0};
    mr_svo_quantize_weights(w1, 4, 1, q);
    /* 127.5, 63.75, 63.75: floors 127+63+63 = 253, the two largest
     * remainders (0.75, 0.75) get the 2 left. */
    assert_int_equal(q[0], 127);
    assert_int_equal(q[1], 64);
    assert_int_equal(q[2], 64);
    assert_int_equal(q[3], 0);
    float w2[4] = {1.0f / 3, 1.0f / 3, 1.0f / 3, 0};
    mr_svo_quantize_weights(w2, 4, 1, q);
    assert_int_equal(q[0] + q[1] + q[2] + q[3], 255);
    assert_int_equal(q[0], 85);
    float z[4] = {0, 0, 0, 0};
    mr_svo_quantize_weights(z, 4, 1, q);
    assert_int_equal(q[0] | q[1] | q[2] | q[3], 0);
    float bad[4] = {NAN, 1, 0, 0};
    mr_svo_quantize_weights(bad, 4, 1, q);
    assert_int_equal(q[0] | q[1] | q[2] | q[3], 0);
    for (int it = 0; it < 2000; it++) {
        float w[4];
        for (int k = 0; k < 4; k++)
            w[k] = (float)(rnd() < 0.2 ? 0 : rnd());
        static const unsigned steps[] = {1, 3, 5, 15, 17, 51, 85, 255};
        unsigned step = steps[it % 8];
        mr_svo_quantize_weights(w, 4, step, q);
        unsigned sum = 0;
        for (int k = 0; k < 4; k++) {
            sum += q[k];
            assert_int_equal(q[k] % step, 0);
        }
        if (w[0] + w[1] + w[2] + w[3] > 0) {
            assert_int_equal(sum, 255);
            /* Largest remainder: each within one step of its exact share. */
            float s = w[0] + w[1] + w[2] + w[3];
            for (int k = 0; k < 4; k++)
                assert_true(fabs(q[k] - w[k] / s * 255) < step + 1e-3);
        }
    }
}

/* ---------------------------------------------------------------------- */
/* Octree helpers                                                         */

/* Leaf index holding finest cell (x, y, z), or -1. */
static long find_leaf(const mr_svo *s, uint32_t x, uint32_t y, uint32_t z)
{
    if (s->node_count == 0)
        return s->leaf_count == 1 ? 0 : -1;
    uint32_t node = 0;
    for (unsigned l = 0; l < s->depth; l++) {
        unsigned bit = s->depth - 1 - l;
        unsigned ch = ((x >> bit) & 1) | (((y >> bit) & 1) << 1) | (((z >> bit) & 1) << 2);
        unsigned cm = s->child_mask[node], lm = s->leaf_mask[node];
        if (!(cm >> ch & 1))
            return -1;
        unsigned below = (1u << ch) - 1;
        if (lm >> ch & 1)
            return (long)s->first_leaf[node] + __builtin_popcount(lm & below);
        node = s->first_node[node] + (uint32_t)__builtin_popcount(cm & ~lm & below);
    }
    return -1;
}

typedef struct grid_map {
    double o[3], scale;
} grid_map;

static grid_map grid_of(const mr_svo *s)
{
    grid_map g = {{s->origin.x, s->origin.y, s->origin.z}, (double)(1u << s->depth) / s->size};
    return g;
}

static void to_grid(const grid_map *g, const float *p, double out[3])
{
    for (int k = 0; k < 3; k++)
        out[k] = (p[k] - g->o[k]) * g->scale;
}

/* Every leaf overlaps some triangle of mesh 0 (grown by 1e-3 cell: the
 * voxeliser grows cells by 1e-4 to stay conservative under rounding). */
static void check_leaves_overlap(const mr_svo *s, const mr_mesh *m)
{
    grid_map g = grid_of(s);
    double *gv = malloc((size_t)m->vertex_count * 3 * sizeof *gv);
    assert_non_null(gv);
    for (uint32_t v = 0; v < m->vertex_count; v++)
        to_grid(&g, &m->positions[v * 3], &gv[v * 3]);
    assert_non_null(s->leaf_keys);
    for (uint32_t i = 0; i < s->leaf_count; i++) {
        uint32_t x, y, z;
        assert_int_equal(s->leaf_keys[i].level, s->depth);
        mr_morton_decode(s->leaf_keys[i].code, &x, &y, &z);
        double c[3] = {x + 0.5, y + 0.5, z + 0.5}, h[3] = {0.501, 0.501, 0.501};
        bool any = false;
        for (uint32_t t = 0; t < m->triangle_count && !any; t++) {
            const uint32_t *ti = &m->indices[t * 3];
            bool far = false; /* bounding-box reject keeps this O(leaves x triangles) cheap */
            for (int k = 0; k < 3 && !far; k++)
                far = fmin(gv[ti[0] * 3 + k], fmin(gv[ti[1] * 3 + k], gv[ti[2] * 3 + k])) > c[k] + 1 ||
                      fmax(gv[ti[0] * 3 + k], fmax(gv[ti[1] * 3 + k], gv[ti[2] * 3 + k])) < c[k] - 1;
            if (!far)
                any = mr_tri_box_overlap(c, h, &gv[m->indices[t * 3] * 3],
                                     &gv[m->indices[t * 3 + 1] * 3], &gv[m->indices[t * 3 + 2] * 3]);
        }
        if (!any)
            fail_msg("leaf %u (%u %u %u) overlaps no triangle", i, x, y, z);
    }
    free(gv);
}

/* Dense samples on every triangle (barycentric grid of 1/steps, finer than
 * a cell here) each land in a present voxel: conservative coverage. */
static void check_surface_covered(const mr_svo *s, const mr_mesh *m, int steps)
{
    grid_map g = grid_of(s);
    for (uint32_t t = 0; t < m->triangle_count; t++) {
        double v[3][3];
        for (int q = 0; q < 3; q++)
            to_grid(&g, &m->positions[m->indices[t * 3 + q] * 3], v[q]);
        for (int i = 0; i <= steps; i++)
            for (int j = 0; j <= steps - i; j++) {
                double u = (double)i / steps, w = (double)j / steps, r = 1 - u - w;
                uint32_t c[3];
                for (int k = 0; k < 3; k++)
                    c[k] = (uint32_t)floor(r * v[0][k] + u * v[1][k] + w * v[2][k]);
                if (find_leaf(s, c[0], c[1], c[2]) < 0)
                    fail_msg("triangle %u sample (%d,%d) in cell %u %u %u: no voxel", t, i, j,
                             c[0], c[1], c[2]);
            }
    }
}

static void check_palette(const mr_svo *s, const mr_asset *a)
{
    for (uint32_t i = 0; i < s->leaf_count; i++)
        assert_true(s->leaves[i].attr < s->palette_count);
    for (uint32_t k = 0; k < s->palette_count; k++) {
        const mr_svo_attr *p = &s->palette[k];
        assert_true(p->mesh < a->mesh_count);
        const mr_mesh *m = &a->meshes[p->mesh];
        unsigned sum = 0;
        for (unsigned j = 0; j < MR_SVO_INFLUENCES; j++) {
            sum += p->weights[j];
            if (p->weights[j])
                assert_true(p->joints[j] < m->joint_count);
            if (j > 0)
                assert_true(p->weights[j] <= p->weights[j - 1]);
        }
        assert_true(sum == 255 || (sum == 0 && m->joint_count == 0) || sum == 0);
        if (m->joint_count == 0)
            assert_int_equal(sum, 0);
    }
}

/* ---------------------------------------------------------------------- */
/* Fixtures                                                               */

static mr_asset *make_cube(void)
{
    static const float p[8 * 3] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0,
                                   0, 0, 1, 1, 0, 1, 0, 1, 1, 1, 1, 1};
    static const uint32_t idx[12 * 3] = {0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4,
                                         2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6, 1, 3, 5, 3, 7, 5};
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_from_mesh("cube", p, NULL, 8, idx, 12, &a, &err), MR_OK);
    return a;
}

/* Watertight UV sphere of radius r at the origin (poles shared). */
static mr_asset *make_sphere(double r, int slices, int stacks)
{
    uint32_t nv = 2 + (uint32_t)(slices * (stacks - 1));
    uint32_t nt = (uint32_t)(2 * slices * (stacks - 1));
    float *p = malloc(nv * 3 * sizeof *p), *n = malloc(nv * 3 * sizeof *n);
    uint32_t *idx = malloc(nt * 3 * sizeof *idx);
    assert_true(p && n && idx);
    uint32_t v = 0;
    p[0] = 0, p[1] = 0, p[2] = (float)r;
    v = 1;
    for (int i = 1; i < stacks; i++)
        for (int j = 0; j < slices; j++, v++) {
            double th = PI * i / stacks, ph = 2 * PI * j / slices;
            p[v * 3] = (float)(r * sin(th) * cos(ph));
            p[v * 3 + 1] = (float)(r * sin(th) * sin(ph));
            p[v * 3 + 2] = (float)(r * cos(th));
        }
    p[v * 3] = 0, p[v * 3 + 1] = 0, p[v * 3 + 2] = (float)-r;
    for (uint32_t k = 0; k < nv; k++)
        for (int q = 0; q < 3; q++)
            n[k * 3 + q] = (float)(p[k * 3 + q] / r);
    uint32_t t = 0, south = nv - 1;
#define RING(i, j) (1 + (uint32_t)((i) - 1) * (uint32_t)slices + (uint32_t)((j) % slices))
    for (int j = 0; j < slices; j++) {
        idx[t * 3] = 0, idx[t * 3 + 1] = RING(1, j), idx[t * 3 + 2] = RING(1, j + 1), t++;
        idx[t * 3] = south, idx[t * 3 + 1] = RING(stacks - 1, j + 1),
                idx[t * 3 + 2] = RING(stacks - 1, j), t++;
    }
    for (int i = 1; i < stacks - 1; i++)
        for (int j = 0; j < slices; j++) {
            idx[t * 3] = RING(i, j), idx[t * 3 + 1] = RING(i + 1, j),
                    idx[t * 3 + 2] = RING(i + 1, j + 1), t++;
            idx[t * 3] = RING(i, j), idx[t * 3 + 1] = RING(i + 1, j + 1),
                    idx[t * 3 + 2] = RING(i, j + 1), t++;
        }
#undef RING
    assert_int_equal(t, nt);
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_from_mesh("sphere", p, n, nv, idx, nt, &a, &err), MR_OK);
    free(p);
    free(n);
    free(idx);
    return a;
}

/* Keeps the leaf keys: the checks below read each leaf's cell from them. */
static mr_svo *voxelize(const mr_asset *a, unsigned depth, mr_svo_voxelize_mode mode,
                        unsigned threads)
{
    mr_svo_voxelize_params p = {.depth = depth, .mode = mode, .threads = threads,
                                .keep_leaf_keys = true};
    mr_svo *s = NULL;
    mr_error err = {0};
    int rc = mr_svo_voxelize(a, &p, &s, &err);
    if (rc != MR_OK)
        fail_msg("voxelize: %s", err.msg);
    return s;
}

/* ---------------------------------------------------------------------- */
/* Voxelisation                                                           */

/* Axis-aligned unit cube: the cube grid is padded by 1/1024 of the edge on
 * each side, so every face lies strictly inside the outermost cell layer
 * (0.03 cells from its boundary at depth 5, far beyond the 1e-4 growth) and
 * the voxels are exactly the n^3 - (n-2)^3 boundary cells. */
static void test_cube_surface(void **state)
{
    (void)state;
    mr_asset *a = make_cube();
    for (unsigned d = 1; d <= 6; d++) {
        mr_svo *s = voxelize(a, d, MR_SVO_VOXELIZE_SURFACE, 2);
        uint64_t n = 1u << d;
        uint64_t want = n <= 2 ? n * n * n : n * n * n - (n - 2) * (n - 2) * (n - 2);
        assert_int_equal(s->leaf_count, want);
        assert_int_equal(s->depth, d);
        assert_true(s->origin.x < 0 && s->origin.x + s->size > 1);
        check_leaves_overlap(s, &a->meshes[0]);
        check_surface_covered(s, &a->meshes[0], 4 << d);
        check_palette(s, a);
        /* Default albedo 0.8 -> 204; one rigid mesh -> one palette entry. */
        assert_int_equal(s->palette_count, 1);
        assert_int_equal(s->palette[0].albedo[0], 204);
        mr_svo_voxelize_free(s);
    }
    mr_asset_free(a);
}

/* UV sphere. Expected count: a plane with unit normal m cuts |mx|+|my|+|mz|
 * unit cells per unit area on average over placements, so the mesh's
 * expected count is sum over triangles of area * (|nx|+|ny|+|nz|) (cell
 * units), ~6 pi r^2 for a sphere. Tolerance 6 %: curvature and the
 * correlation between neighbouring triangles' cells move the count by a few
 * percent at r = 30 cells. Normals: within 5 degrees of the radial
 * direction (cell centre offset <= 0.87 cell at r ~ 30 cells gives ~1.7
 * degrees, octahedral encoding ~1, facets ~3 at 64 x 32). */
static void test_sphere_surface(void **state)
{
    (void)state;
    mr_asset *a = make_sphere(1.0, 64, 32);
    const mr_mesh *m = &a->meshes[0];
    mr_svo *s = voxelize(a, 6, MR_SVO_VOXELIZE_SURFACE, 2);
    grid_map g = grid_of(s);
    double expect = 0;
    for (uint32_t t = 0; t < m->triangle_count; t++) {
        double v[3][3];
        for (int q = 0; q < 3; q++)
            to_grid(&g, &m->positions[m->indices[t * 3 + q] * 3], v[q]);
        double e1[3], e2[3];
        for (int k = 0; k < 3; k++)
            e1[k] = v[1][k] - v[0][k], e2[k] = v[2][k] - v[0][k];
        double cr[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                        e1[0] * e2[1] - e1[1] * e2[0]};
        expect += 0.5 * (fabs(cr[0]) + fabs(cr[1]) + fabs(cr[2]));
    }
    double r_cells = g.scale;
    assert_true(fabs(expect / (6 * PI * r_cells * r_cells) - 1) < 0.02);
    print_message("sphere surface: %u voxels, expected %.0f\n", s->leaf_count, expect);
    assert_true(fabs(s->leaf_count / expect - 1) < 0.06);
    check_leaves_overlap(s, m);
    check_surface_covered(s, m, 64); /* edges ~3 cells: 0.05-cell spacing */
    check_palette(s, a);
    for (uint32_t i = 0; i < s->leaf_count; i++) {
        uint32_t x, y, z;
        mr_morton_decode(s->leaf_keys[i].code, &x, &y, &z);
        double c[3] = {x + 0.5, y + 0.5, z + 0.5};
        double dir[3], len = 0;
        for (int k = 0; k < 3; k++) {
            dir[k] = c[k] / g.scale + g.o[k];
            len += dir[k] * dir[k];
        }
        len = sqrt(len);
        mr_vec3 nn = mr_svo_normal_decode(s->leaves[i].normal);
        double cosang = (nn.x * dir[0] + nn.y * dir[1] + nn.z * dir[2]) / len;
        assert_true(cosang > cos(5 * PI / 180));
    }
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* Solid UV sphere at depth 6 (r ~ 32 cells). Exact checks: every cell
 * whose centre is more than 0.87 cell (half a cell diagonal) inside the
 * inscribed radius is present (interior by parity or surface), no cell
 * farther than that outside the sphere is. Volume: voxel volume vs
 * 4/3 pi r^3 within 10 % (the conservative surface shell adds about
 * 0.75 * area cells = 7 % at this radius). */
static void test_sphere_solid(void **state)
{
    (void)state;
    mr_asset *a = make_sphere(1.0, 64, 32);
    mr_svo *s = voxelize(a, 6, MR_SVO_VOXELIZE_SOLID, 2);
    mr_svo *surf = voxelize(a, 6, MR_SVO_VOXELIZE_SURFACE, 2);
    grid_map g = grid_of(s);
    double r = g.scale; /* sphere radius 1 in cells */
    double h = 1.0 / g.scale;
    double vol = s->leaf_count * h * h * h, want = 4.0 / 3.0 * PI;
    print_message("solid sphere: %u voxels, volume %.4f vs %.4f\n", s->leaf_count, vol, want);
    assert_true(fabs(vol / want - 1) < 0.10);
    assert_true(s->leaf_count > 4 * surf->leaf_count);
    /* Inscribed radius of a 64 x 32 UV sphere > cos(pi/32) r. */
    double r_in = cos(PI / 32) * r;
    uint32_t n = 1u << s->depth;
    for (uint32_t z = 0; z < n; z++)
        for (uint32_t y = 0; y < n; y++)
            for (uint32_t x = 0; x < n; x++) {
                double d = 0;
                double c[3] = {x + 0.5, y + 0.5, z + 0.5};
                for (int k = 0; k < 3; k++) {
                    double q = c[k] / g.scale + g.o[k];
                    d += q * q;
                }
                d = sqrt(d) * g.scale;
                long li = find_leaf(s, x, y, z);
                if (d < r_in - 0.87)
                    assert_true(li >= 0);
                if (d > r + 0.87)
                    assert_true(li < 0);
            }
    /* Surface voxels keep their leaf; interior ones copy a palette entry. */
    for (uint32_t i = 0; i < s->leaf_count; i++)
        assert_true(s->leaves[i].attr < s->palette_count);
    assert_int_equal(s->palette_count, surf->palette_count);
    mr_svo_voxelize_free(surf);
    mr_svo_voxelize_free(s);

    /* Open mesh (a cap removed): rows through the hole are dropped, the
     * call still succeeds with voxels. */
    a->meshes[0].triangle_count -= 64;
    mr_svo *open = voxelize(a, 6, MR_SVO_VOXELIZE_SOLID, 2);
    assert_true(open->leaf_count > 0);
    mr_svo_voxelize_free(open);
    a->meshes[0].triangle_count += 64;

    /* Solid is limited in depth. */
    mr_svo_voxelize_params p = {.depth = MR_SVO_SOLID_MAX_DEPTH + 1, .mode = MR_SVO_VOXELIZE_SOLID};
    mr_svo *bad = NULL;
    mr_error err = {0};
    assert_int_equal(mr_svo_voxelize(a, &p, &bad, &err), MR_ERR_INVALID);
    assert_null(bad);
    assert_non_null(strstr(err.msg, "solid"));
    mr_asset_free(a);
}

static bool svo_equal(const mr_svo *a, const mr_svo *b)
{
    if (a->depth != b->depth || a->node_count != b->node_count ||
        a->leaf_count != b->leaf_count || a->palette_count != b->palette_count ||
        memcmp(&a->origin, &b->origin, sizeof a->origin) || a->size != b->size)
        return false;
    size_t n = a->node_count, l = a->leaf_count;
    return !memcmp(a->first_node, b->first_node, n * 4) &&
           !memcmp(a->first_leaf, b->first_leaf, n * 4) && !memcmp(a->child_mask, b->child_mask, n) &&
           !memcmp(a->leaf_mask, b->leaf_mask, n) &&
           !memcmp(a->leaves, b->leaves, l * sizeof *a->leaves) &&
           !memcmp(a->palette, b->palette, a->palette_count * sizeof *a->palette);
}

/* Real skinned character: palette sane, and a voxel at a vertex bound
 * (>= 0.9) to one joint gets that joint as its strongest influence. The
 * voxel's triangle is the nearest to the cell centre, so near joint
 * boundaries it may belong to a neighbouring region: at least 90 % of such
 * vertices must match (measured: see the printout). */
static void test_skinned_model(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_load(MODEL, &a, &err), MR_OK);
    mr_svo *s = voxelize(a, 9, MR_SVO_VOXELIZE_SURFACE, 2);
    check_palette(s, a);
    grid_map g = grid_of(s);
    size_t checked = 0, matched = 0;
    for (size_t mi = 0; mi < a->mesh_count; mi++) {
        const mr_mesh *m = &a->meshes[mi];
        if (m->joint_count == 0)
            continue;
        for (uint32_t v = 0; v < m->vertex_count; v++) {
            if (!(m->weights[v * MR_MAX_INFLUENCES] >= 0.9f))
                continue;
            double q[3];
            to_grid(&g, &m->positions[v * 3], q);
            long li = find_leaf(s, (uint32_t)q[0], (uint32_t)q[1], (uint32_t)q[2]);
            assert_true(li >= 0); /* conservative: the vertex's cell exists */
            const mr_svo_attr *at = &s->palette[s->leaves[li].attr];
            checked++;
            if (at->mesh == mi && at->joints[0] == m->joints[v * MR_MAX_INFLUENCES])
                matched++;
        }
    }
    print_message("skinned: %zu of %zu vertices matched, %u voxels, %u palette entries\n",
                  matched, checked, s->leaf_count, s->palette_count);
    assert_true(checked > 100);
    assert_true(matched >= 0.9 * checked);

    /* Thread counts give bit-identical octrees. */
    mr_svo *s1 = voxelize(a, 9, MR_SVO_VOXELIZE_SURFACE, 1);
    mr_svo *s3 = voxelize(a, 9, MR_SVO_VOXELIZE_SURFACE, 3);
    assert_true(svo_equal(s, s1));
    assert_true(svo_equal(s, s3));
    mr_svo_voxelize_free(s1);
    mr_svo_voxelize_free(s3);
    mr_svo_voxelize_free(s);
    mr_svo *d1 = voxelize(a, 7, MR_SVO_VOXELIZE_SOLID, 1);
    mr_svo *d2 = voxelize(a, 7, MR_SVO_VOXELIZE_SOLID, 2);
    assert_true(svo_equal(d1, d2));
    mr_svo_voxelize_free(d1);
    mr_svo_voxelize_free(d2);
    mr_asset_free(a);
}

/* Albedo per mesh reaches the palette. */
static void test_albedo(void **state)
{
    (void)state;
    mr_asset *a = make_cube();
    float alb[3] = {1.0f, 0.5f, -3.0f};
    mr_svo_voxelize_params p = {.depth = 3, .albedo = alb, .threads = 1};
    mr_svo *s = NULL;
    mr_error err = {0};
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_OK);
    assert_int_equal(s->palette[0].albedo[0], 255);
    assert_int_equal(s->palette[0].albedo[1], 128);
    assert_int_equal(s->palette[0].albedo[2], 0);
    mr_svo_voxelize_free(s);
    alb[1] = NAN;
    s = NULL;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    assert_null(s);
    mr_asset_free(a);
}

/* Leaf keys are dropped by default (they cost 16 bytes per leaf) and kept on
 * request; kept keys are exactly what mr_svo_collect_keys recomputes from
 * the nodes, and the octree is otherwise the same either way. */
static void test_leaf_keys_optional(void **state)
{
    (void)state;
    mr_asset *a = make_sphere(1.0, 32, 16);
    mr_svo_voxelize_params p = {.depth = 5, .mode = MR_SVO_VOXELIZE_SOLID, .threads = 2};
    mr_svo *dropped = NULL;
    mr_error err = {0};
    assert_int_equal(mr_svo_voxelize(a, &p, &dropped, &err), MR_OK);
    assert_null(dropped->leaf_keys);
    mr_svo *kept = voxelize(a, 5, MR_SVO_VOXELIZE_SOLID, 2);
    assert_non_null(kept->leaf_keys);
    assert_true(svo_equal(dropped, kept));
    assert_int_equal(mr_svo_memory(kept) - mr_svo_memory(dropped),
                     (size_t)kept->leaf_count * sizeof(mr_svo_key));
    uint32_t n = dropped->leaf_count;
    assert_true(n > 0);
    mr_svo_key *keys = malloc(n * sizeof *keys);
    uint32_t *idx = malloc(n * sizeof *idx);
    assert_true(keys && idx);
    assert_int_equal(mr_svo_collect_keys(dropped, keys, idx, &err), MR_OK);
    for (uint32_t i = 0; i < n; i++) {
        assert_true(kept->leaf_keys[idx[i]].code == keys[i].code);
        assert_int_equal(kept->leaf_keys[idx[i]].level, keys[i].level);
    }
    mr_svo_drop_leaf_keys(kept);
    assert_null(kept->leaf_keys);
    mr_svo_drop_leaf_keys(kept); /* twice, and NULL, are fine */
    mr_svo_drop_leaf_keys(NULL);
    free(keys);
    free(idx);
    mr_svo_voxelize_free(kept);
    mr_svo_voxelize_free(dropped);
    mr_asset_free(a);
}

static void test_bad_input(void **state)
{
    (void)state;
    mr_asset *a = make_cube();
    mr_svo *s = NULL;
    mr_error err = {0};
    mr_svo_voxelize_params p = {.depth = 0};
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "depth 0"));
    p.depth = 22;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "depth 22"));
    p.depth = 4;
    p.mode = (mr_svo_voxelize_mode)7;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    p.mode = MR_SVO_VOXELIZE_SURFACE;
    assert_int_equal(mr_svo_voxelize(NULL, &p, &s, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_voxelize(a, NULL, &s, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_voxelize(a, &p, NULL, &err), MR_ERR_INVALID);
    assert_null(s);
    float keep = a->meshes[0].positions[3 * 5 + 1];
    a->meshes[0].positions[3 * 5 + 1] = NAN;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    assert_null(s);
    assert_non_null(strstr(err.msg, "'cube'"));
    assert_non_null(strstr(err.msg, "vertex 5"));
    a->meshes[0].positions[3 * 5 + 1] = INFINITY;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    a->meshes[0].positions[3 * 5 + 1] = keep;
    /* Huge but finite coordinates still voxelise (double-precision tests). */
    for (uint32_t i = 0; i < 8 * 3; i++)
        a->meshes[0].positions[i] = a->meshes[0].positions[i] * 1e37f - 5e36f;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_OK);
    assert_int_equal(s->leaf_count, 16 * 16 * 16 - 14 * 14 * 14);
    mr_svo_voxelize_free(s);
    s = NULL;
    /* Out-of-range index. */
    a->meshes[0].indices[4] = 99;
    assert_int_equal(mr_svo_voxelize(a, &p, &s, &err), MR_ERR_INVALID);
    assert_null(s);
    mr_asset_free(a);
}

/* Degenerate triangles in a mesh: a zero-area sliver and a point voxelise
 * to the cells they touch without crashing. */
static void test_degenerate_mesh(void **state)
{
    (void)state;
    static const float p[5 * 3] = {0, 0, 0, 1, 1, 1, 0.5f, 0.5f, 0.5f, 0.25f, 0.25f, 0.25f, 0, 0, 0};
    static const uint32_t idx[2 * 3] = {0, 1, 2, 3, 3, 3};
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_from_mesh("sliver", p, NULL, 5, idx, 2, &a, &err), MR_OK);
    mr_svo *s = voxelize(a, 4, MR_SVO_VOXELIZE_SURFACE, 2);
    /* The diagonal of the cube passes 16 diagonal cells, plus the cells it
     * touches at their shared corners (conservative: corners count). */
    assert_true(s->leaf_count >= 16);
    for (uint32_t i = 0; i < 16; i++)
        assert_true(find_leaf(s, i, i, i) >= 0);
    check_leaves_overlap(s, &a->meshes[0]);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_overlap_vs_brute_force),
        cmocka_unit_test(test_overlap_known_cases),
        cmocka_unit_test(test_overlap_degenerate),
        cmocka_unit_test(test_closest_point),
        cmocka_unit_test(test_quantize_weights),
        cmocka_unit_test(test_cube_surface),
        cmocka_unit_test(test_sphere_surface),
        cmocka_unit_test(test_sphere_solid),
        cmocka_unit_test(test_skinned_model),
        cmocka_unit_test(test_albedo),
        cmocka_unit_test(test_leaf_keys_optional),
        cmocka_unit_test(test_bad_input),
        cmocka_unit_test(test_degenerate_mesh),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
