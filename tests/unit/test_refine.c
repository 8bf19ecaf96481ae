/*
 * test_refine.c - Loop refinement of meshes (core/asset/refine.h): counts,
 * closedness across UV seams, convergence, exact identity, skin weight
 * rules, skinning the refined real character BCN_Epileptic.X, thread-count
 * determinism, the noise, and bad input.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "anim/pose.h"
#include "asset/asset.h"
#include "asset/refine.h"
#include "util/clock.h"

#define BCN_MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"

static mr_asset *make_asset(const float *pos, uint32_t nv, const uint32_t *idx, uint32_t nt)
{
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_from_mesh("m", pos, NULL, nv, idx, nt, &a, &err) != MR_OK)
        fail_msg("mr_asset_from_mesh: %s", err.msg);
    return a;
}

static mr_asset *make_octahedron(void)
{
    static const float pos[] = {1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1};
    /* outward winding: +x+y+z is (0, 2, 4) */
    static const uint32_t idx[] = {0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4,
                                   2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5};
    return make_asset(pos, 6, idx, 8);
}

/* A unit cube with 4 vertices per face (24 wedges), like an importer splits
 * it at hard normals and UV seams, with per-face UVs. */
static mr_asset *make_split_cube(void)
{
    float pos[24 * 3];
    uint32_t idx[12 * 3];
    float uv[24 * 2];
    static const int axes[6][3] = {{0, 1, 2}, {0, 1, 2}, {1, 2, 0}, {1, 2, 0}, {2, 0, 1}, {2, 0, 1}};
    for (int f = 0; f < 6; f++) {
        int u = axes[f][0], v = axes[f][1], w = axes[f][2];
        float side = (f & 1) ? 1.0f : -1.0f;
        static const float cu[4] = {-1, 1, 1, -1}, cv[4] = {-1, -1, 1, 1};
        for (int c = 0; c < 4; c++) {
            float *p = &pos[(f * 4 + c) * 3];
            p[u] = cu[c];
            p[v] = cv[c];
            p[w] = side;
            uv[(f * 4 + c) * 2] = (cu[c] + 1) * 0.5f;
            uv[(f * 4 + c) * 2 + 1] = (cv[c] + 1) * 0.5f;
        }
        /* (u, v, w) is right-handed, so counter-clockwise in (u, v) faces +w. */
        uint32_t b = (uint32_t)f * 4;
        uint32_t q[6] = {b, b + 1, b + 2, b, b + 2, b + 3};
        if (side < 0) {
            q[1] = b + 2, q[2] = b + 1, q[4] = b + 3, q[5] = b + 2;
        }
        memcpy(&idx[f * 6], q, sizeof q);
    }
    mr_asset *a = make_asset(pos, 24, idx, 12);
    a->meshes[0].uvs = malloc(sizeof uv);
    assert_non_null(a->meshes[0].uvs);
    memcpy(a->meshes[0].uvs, uv, sizeof uv);
    return a;
}

static mr_mesh refine(const mr_mesh *in, unsigned rounds, float amp, float freq, unsigned threads)
{
    mr_refine_params p = {.rounds = rounds, .amplitude = amp, .frequency = freq, .octaves = 3,
                          .seed = 7, .threads = threads};
    mr_mesh out;
    mr_error err = {0};
    if (mr_refine_mesh(in, &p, &out, &err) != MR_OK)
        fail_msg("mr_refine_mesh: %s", err.msg);
    return out;
}

/* ---- closedness by position --------------------------------------------- */

typedef struct pkey { float x, y, z; uint32_t i; } pkey;

static int pkey_cmp(const void *pa, const void *pb)
{
    const pkey *a = pa, *b = pb;
    if (a->x != b->x)
        return a->x < b->x ? -1 : 1;
    if (a->y != b->y)
        return a->y < b->y ? -1 : 1;
    if (a->z != b->z)
        return a->z < b->z ? -1 : 1;
    return a->i < b->i ? -1 : (a->i > b->i);
}

typedef struct dedge { uint32_t a, b; } dedge;

static int dedge_cmp(const void *pa, const void *pb)
{
    const dedge *x = pa, *y = pb;
    if (x->a != y->a)
        return x->a < y->a ? -1 : 1;
    return x->b < y->b ? -1 : (x->b > y->b);
}

/* Welds m's vertices by exact position and checks the result is a closed,
 * consistently oriented 2-manifold: every directed edge appears exactly once
 * and its reverse exactly once (so every edge has exactly two triangles and
 * no crack exists between seam duplicates). Returns the welded vertex count. */
static size_t check_closed(const mr_mesh *m)
{
    size_t nv = m->vertex_count, nt = m->triangle_count;
    pkey *k = malloc(nv * sizeof *k);
    uint32_t *id = malloc(nv * sizeof *id);
    dedge *e = malloc(nt * 3 * sizeof *e);
    assert_true(k && id && e);
    for (size_t i = 0; i < nv; i++)
        k[i] = (pkey){m->positions[i * 3], m->positions[i * 3 + 1], m->positions[i * 3 + 2],
                      (uint32_t)i};
    qsort(k, nv, sizeof *k, pkey_cmp);
    size_t nw = 0;
    for (size_t i = 0; i < nv; i++) {
        if (i > 0 && (k[i].x != k[i - 1].x || k[i].y != k[i - 1].y || k[i].z != k[i - 1].z))
            nw++;
        id[k[i].i] = (uint32_t)nw;
    }
    nw++;
    for (size_t t = 0; t < nt; t++)
        for (int c = 0; c < 3; c++)
            e[t * 3 + c] = (dedge){id[m->indices[t * 3 + c]], id[m->indices[t * 3 + (c + 1) % 3]]};
    qsort(e, nt * 3, sizeof *e, dedge_cmp);
    for (size_t i = 0; i < nt * 3; i++) {
        if (e[i].a == e[i].b)
            fail_msg("degenerate edge at welded vertex %u", e[i].a);
        if (i > 0 && e[i].a == e[i - 1].a && e[i].b == e[i - 1].b)
            fail_msg("directed edge %u-%u used twice", e[i].a, e[i].b);
        dedge rev = {e[i].b, e[i].a};
        if (!bsearch(&rev, e, nt * 3, sizeof *e, dedge_cmp))
            fail_msg("edge %u-%u has one triangle (open)", e[i].a, e[i].b);
    }
    free(k);
    free(id);
    free(e);
    return nw;
}

static void test_counts_and_closed(void **state)
{
    (void)state;
    mr_asset *oct = make_octahedron(), *cube = make_split_cube();
    for (unsigned r = 0; r <= 4; r++) {
        mr_mesh m = refine(&oct->meshes[0], r, 0, 0, 1);
        assert_int_equal(m.triangle_count, 8u << (2 * r));
        /* Euler, closed genus 0: V = 2 + F / 2. */
        assert_int_equal(check_closed(&m), 2 + m.triangle_count / 2);
        mr_refine_mesh_free(&m);

        /* The split cube: seams must not open, and duplicates across a seam
         * must sit at bit-identical positions (else the welded count grows). */
        m = refine(&cube->meshes[0], r, r ? 0.05f : 0.0f, 3.0f, 2);
        assert_int_equal(m.triangle_count, 12u << (2 * r));
        assert_int_equal(check_closed(&m), 2 + m.triangle_count / 2);
        assert_non_null(m.uvs);
        for (size_t i = 0; i < (size_t)m.vertex_count * 2; i++)
            assert_true(m.uvs[i] >= 0.0f && m.uvs[i] <= 1.0f);
        mr_refine_mesh_free(&m);
    }
    mr_asset_free(oct);
    mr_asset_free(cube);
}

/* Loop subdivision of the octahedron converges to its smooth limit
 * surface:
 *  - an original vertex converges to Loop's limit position (for valence n:
 *    (1 - n chi) v + chi sum(ring), chi = 1 / (n + 3 / (8 beta))), here
 *    x = 1 - 4 chi = 0.436364 for vertex (1, 0, 0), with the error shrinking
 *    by the subdominant eigenvalue (about 1/7) each round;
 *  - the change of the largest and smallest distance from the centre
 *    between rounds shrinks every round (the radii settle);
 *  - the largest angle between neighbouring triangles' normals shrinks
 *    every round (the surface gets smoother);
 *  - every vertex stays in the convex hull (stencils are convex
 *    combinations), allowing 1e-6 for float storage.
 * Tolerances: the limit position after 7 rounds is within 1e-5 (the error
 * is about 0.48 / 7^7 ~ 6e-7 plus float rounding). */
static double max_dihedral(const mr_mesh *m)
{
    /* The refined octahedron has no seams, so shared edges share indices. */
    size_t nt = m->triangle_count;
    double *fn = malloc(nt * 3 * sizeof *fn);
    assert_non_null(fn);
    for (size_t t = 0; t < nt; t++) {
        const float *a = &m->positions[m->indices[t * 3] * 3];
        const float *b = &m->positions[m->indices[t * 3 + 1] * 3];
        const float *c = &m->positions[m->indices[t * 3 + 2] * 3];
        double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
        double v[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        double n[3] = {u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                       u[0] * v[1] - u[1] * v[0]};
        double l = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        for (int k = 0; k < 3; k++)
            fn[t * 3 + k] = n[k] / l;
    }
    double worst = 0;
    for (size_t t = 0; t < nt; t++)
        for (size_t s2 = t + 1; s2 < nt; s2++) {
            int shared = 0;
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    shared += m->indices[t * 3 + i] == m->indices[s2 * 3 + j];
            if (shared == 2) {
                double d = fn[t * 3] * fn[s2 * 3] + fn[t * 3 + 1] * fn[s2 * 3 + 1] +
                           fn[t * 3 + 2] * fn[s2 * 3 + 2];
                worst = fmax(worst, acos(fmin(1.0, d)));
            }
        }
    free(fn);
    return worst;
}

static void test_loop_convergence(void **state)
{
    (void)state;
    mr_asset *oct = make_octahedron();
    double beta = (0.625 - 0.375 * 0.375) / 4.0; /* cos(2 pi / 4) = 0 */
    double limit = 1.0 - 4.0 / (4.0 + 3.0 / (8.0 * beta));
    double prev_lo = 1, prev_hi = 1, prev_dlo = INFINITY, prev_dhi = INFINITY;
    double prev_err = INFINITY, prev_angle = INFINITY;
    for (unsigned r = 1; r <= 7; r++) {
        mr_mesh m = refine(&oct->meshes[0], r, 0, 0, 0);
        double lo = INFINITY, hi = 0;
        for (size_t i = 0; i < m.vertex_count; i++) {
            const float *p = &m.positions[i * 3];
            double d = sqrt((double)p[0] * p[0] + (double)p[1] * p[1] + (double)p[2] * p[2]);
            lo = fmin(lo, d);
            hi = fmax(hi, d);
            assert_true(fabs(p[0]) + fabs(p[1]) + fabs(p[2]) <= 1.0 + 1e-6);
            /* Normals point outwards on this convex surface. */
            const float *n = &m.normals[i * 3];
            assert_true(n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0f);
        }
        double dlo = fabs(lo - prev_lo), dhi = fabs(hi - prev_hi);
        if (!(dlo < prev_dlo && dhi < prev_dhi))
            fail_msg("round %u: radius changes %g / %g did not shrink (were %g / %g)", r, dlo,
                     dhi, prev_dlo, prev_dhi);
        double e = fabs(m.positions[0] - limit);
        if (r >= 2 && !(e < prev_err * 0.25))
            fail_msg("round %u: limit error %g did not shrink fast (was %g)", r, e, prev_err);
        if (r <= 4) { /* the all-pairs angle scan is quadratic */
            double angle = max_dihedral(&m);
            if (!(angle < prev_angle))
                fail_msg("round %u: largest normal angle %g did not shrink (was %g)", r, angle,
                         prev_angle);
            prev_angle = angle;
        }
        prev_lo = lo, prev_hi = hi, prev_dlo = dlo, prev_dhi = dhi, prev_err = e;
        if (r == 7)
            assert_true(e < 1e-5);
        mr_refine_mesh_free(&m);
    }
    mr_asset_free(oct);
}

static void same_mesh(const mr_mesh *a, const mr_mesh *b)
{
    assert_int_equal(a->vertex_count, b->vertex_count);
    assert_int_equal(a->triangle_count, b->triangle_count);
    assert_int_equal(a->node, b->node);
    assert_int_equal(a->joint_count, b->joint_count);
    size_t nv = a->vertex_count;
    assert_memory_equal(a->positions, b->positions, nv * 3 * sizeof(float));
    assert_memory_equal(a->normals, b->normals, nv * 3 * sizeof(float));
    assert_memory_equal(a->indices, b->indices, (size_t)a->triangle_count * 3 * sizeof(uint32_t));
    assert_int_equal(a->uvs == NULL, b->uvs == NULL);
    if (a->uvs)
        assert_memory_equal(a->uvs, b->uvs, nv * 2 * sizeof(float));
    if (a->joint_count) {
        assert_memory_equal(a->joint_nodes, b->joint_nodes, a->joint_count * sizeof(int));
        assert_memory_equal(a->inverse_bind, b->inverse_bind, a->joint_count * sizeof(mr_mat4));
        assert_memory_equal(a->joints, b->joints, nv * MR_MAX_INFLUENCES * sizeof(uint16_t));
        assert_memory_equal(a->weights, b->weights, nv * MR_MAX_INFLUENCES * sizeof(float));
    }
}

static mr_asset *load_bcn(void)
{
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_load(BCN_MODEL, &a, &err) != MR_OK)
        fail_msg("load %s: %s", BCN_MODEL, err.msg);
    return a;
}

/* Zero rounds and zero amplitude give the input back bit for bit, through
 * the asset-level call too (deep copy of nodes, clips and cameras). */
static void test_identity(void **state)
{
    (void)state;
    mr_asset *a = load_bcn(), *b = NULL;
    mr_error err = {0};
    mr_refine_params p = {0};
    assert_int_equal(mr_refine_asset(a, &p, &b, &err), MR_OK);
    assert_int_equal(b->mesh_count, a->mesh_count);
    assert_int_equal(b->node_count, a->node_count);
    assert_int_equal(b->clip_count, a->clip_count);
    assert_int_equal(b->camera_count, a->camera_count);
    assert_int_equal(b->triangle_count, a->triangle_count);
    for (size_t i = 0; i < a->mesh_count; i++)
        same_mesh(&a->meshes[i], &b->meshes[i]);
    for (size_t i = 0; i < a->node_count; i++) {
        assert_string_equal(a->nodes[i].name, b->nodes[i].name);
        assert_ptr_not_equal(a->nodes[i].name, b->nodes[i].name);
        assert_int_equal(a->nodes[i].parent, b->nodes[i].parent);
    }
    for (size_t i = 0; i < a->clip_count; i++) {
        assert_int_equal(a->clips[i].channel_count, b->clips[i].channel_count);
        for (size_t c = 0; c < a->clips[i].channel_count; c++)
            assert_int_equal(a->clips[i].channels[c].rotation_count,
                             b->clips[i].channels[c].rotation_count);
    }
    mr_asset_free(b);

    mr_asset *cube = make_split_cube();
    mr_mesh m = refine(&cube->meshes[0], 0, 0, 0, 1);
    same_mesh(&cube->meshes[0], &m);
    mr_refine_mesh_free(&m);
    mr_asset_free(cube);
    mr_asset_free(a);
}

/* Every vertex: weights sorted, positive ones sum to 1 (float rounding of a
 * renormalised sum of at most 8 terms: 1e-5), at most 8, joints in range. */
static void check_weights(const mr_mesh *m)
{
    for (size_t v = 0; v < m->vertex_count; v++) {
        const float *w = &m->weights[v * MR_MAX_INFLUENCES];
        const uint16_t *j = &m->joints[v * MR_MAX_INFLUENCES];
        double sum = 0;
        for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
            assert_true(w[k] >= 0.0f);
            if (k > 0)
                assert_true(w[k] <= w[k - 1]);
            if (w[k] > 0.0f)
                assert_true(j[k] < m->joint_count);
            sum += w[k];
        }
        if (fabs(sum - 1.0) > 1e-5)
            fail_msg("vertex %zu: weights sum to %.9f", v, sum);
    }
}

/* A flat 6x4 grid with joint 0 on columns x <= 2 and joint 1 on x >= 3,
 * plus a fan of 10 ring vertices on 10 different joints around a centre
 * on joint 10 (so the centre's stencil names 11 joints). */
static void test_weight_rules(void **state)
{
    (void)state;
    enum { GX = 6, GY = 4, NG = GX * GY, RING = 10 };
    float pos[(NG + RING + 1) * 3];
    uint32_t idx[((GX - 1) * (GY - 1) * 2 + RING) * 3];
    size_t nt = 0;
    for (int y = 0; y < GY; y++)
        for (int x = 0; x < GX; x++) {
            float *p = &pos[(y * GX + x) * 3];
            p[0] = (float)x, p[1] = (float)y, p[2] = 0;
        }
    for (int y = 0; y + 1 < GY; y++)
        for (int x = 0; x + 1 < GX; x++) {
            uint32_t a = (uint32_t)(y * GX + x), b = a + 1, c = a + GX + 1, d = a + GX;
            uint32_t q[6] = {a, b, c, a, c, d};
            memcpy(&idx[nt * 3], q, sizeof q);
            nt += 2;
        }
    uint32_t centre = NG + RING;
    for (int i = 0; i < RING; i++) {
        double ang = 2.0 * 3.14159265358979 * i / RING;
        float *p = &pos[(NG + i) * 3];
        p[0] = 20 + (float)cos(ang), p[1] = (float)sin(ang), p[2] = 0;
        uint32_t t[3] = {centre, (uint32_t)(NG + i), (uint32_t)(NG + (i + 1) % RING)};
        memcpy(&idx[nt * 3], t, sizeof t);
        nt++;
    }
    pos[centre * 3] = 20, pos[centre * 3 + 1] = 0, pos[centre * 3 + 2] = 0;
    mr_asset *a = make_asset(pos, NG + RING + 1, idx, (uint32_t)nt);
    mr_mesh *m = &a->meshes[0];
    m->joint_count = RING + 1;
    m->joint_nodes = calloc(RING + 1, sizeof(int));
    m->inverse_bind = malloc((RING + 1) * sizeof(mr_mat4));
    m->joints = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(uint16_t));
    m->weights = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(float));
    assert_true(m->joint_nodes && m->inverse_bind && m->joints && m->weights);
    for (int j = 0; j <= RING; j++)
        m->inverse_bind[j] = mr_mat4_identity();
    for (uint32_t v = 0; v < m->vertex_count; v++) {
        uint16_t j = v < NG ? (uint16_t)(pos[v * 3] <= 2 ? 0 : 1)
                            : (uint16_t)(v == centre ? RING : v - NG);
        m->joints[v * MR_MAX_INFLUENCES] = j;
        m->weights[v * MR_MAX_INFLUENCES] = 1.0f;
    }

    mr_mesh r = refine(m, 1, 0, 0, 1);
    check_weights(&r);
    int whole = 0, mixed = 0;
    for (size_t v = 0; v < r.vertex_count; v++) {
        const float *p = &r.positions[v * 3];
        const float *w = &r.weights[v * MR_MAX_INFLUENCES];
        const uint16_t *j = &r.joints[v * MR_MAX_INFLUENCES];
        if (p[0] <= 1.0f) {
            /* Every parent in the stencil (one ring of the coarse grid) is
             * rigidly on joint 0, so the child is exactly on it. */
            assert_int_equal(j[0], 0);
            assert_true(w[0] == 1.0f);
            whole++;
        } else if (p[0] > 2.0f && p[0] < 3.0f) {
            /* Between the two bound regions: both joints, nothing else. */
            assert_true(w[0] > 0.0f && w[1] > 0.0f && w[2] == 0.0f);
            mixed++;
        }
        if (p[0] == 20.0f && p[1] == 0.0f) {
            /* The fan centre mixes 11 joints; the 8 largest are kept. */
            assert_true(w[7] > 0.0f);
            assert_int_equal(j[0], RING);
        }
    }
    assert_true(whole > 10 && mixed > 3);
    mr_refine_mesh_free(&r);
    mr_asset_free(a);
}

static void bbox_diag(const mr_mesh *m, double *diag)
{
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t i = 0; i < m->vertex_count; i++)
        for (int d = 0; d < 3; d++) {
            lo[d] = fmin(lo[d], m->positions[i * 3 + d]);
            hi[d] = fmax(hi[d], m->positions[i * 3 + d]);
        }
    *diag = sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
                 (hi[2] - lo[2]) * (hi[2] - lo[2]));
}

/*
 * Skin the refined character with its own clip and compare with the skinned
 * coarse mesh. Input wedges keep their indices in the refined mesh, so each
 * coarse vertex is compared with its own refined (Loop-smoothed, weight-
 * smoothed, displaced) successor.
 *
 * Tolerance: in the rest pose Loop moves a vertex towards the average of its
 * ring, by up to a fraction of the local edge length; the detail adds at
 * most `amp`. Skinning maps both through nearly rigid blends, so the posed
 * gap stays about the rest gap; what grows it is the smoothed weights: each
 * round spreads a bone's influence over one more (halved) ring, and at a
 * bent joint neighbouring bones place a point differently. Measured on this
 * clip (4 frames): the posed gap exceeds the rest gap by at most 1.8%, 2.2%,
 * 2.35% of the bounding-box diagonal after 1, 2, 3 rounds (converging like
 * the surface), and the mean gap per frame is at most 0.9%. We require
 * every posed gap <= rest gap + 4% of the diagonal and each frame's mean
 * <= 1.5%: a wrong joint index, a lost inverse bind or unnormalised weights
 * move vertices by a sizeable part of the body (10% and more) instead.
 */
static void test_skin_bcn(void **state)
{
    (void)state;
    mr_asset *a = load_bcn();
    assert_true(a->clip_count > 0);
    for (unsigned rounds = 1; rounds <= 3; rounds++) {
        mr_refine_params p = {.rounds = rounds, .threads = 0};
        double diag;
        bbox_diag(&a->meshes[0], &diag);
        p.amplitude = (float)(0.002 * diag);
        p.frequency = (float)(20.0 / diag);
        p.octaves = 2;
        mr_asset *r = NULL;
        mr_error err = {0};
        double t0 = mr_now();
        assert_int_equal(mr_refine_asset(a, &p, &r, &err), MR_OK);
        double t1 = mr_now();
        print_message("BCN_Epileptic.X %u round(s): %zu -> %zu triangles, %.3f s\n", rounds,
                      a->triangle_count, r->triangle_count, t1 - t0);
        assert_int_equal(r->triangle_count, a->triangle_count << (2 * rounds));
        mr_pose *pc = NULL, *pr = NULL;
        assert_int_equal(mr_pose_new(a, &pc, &err), MR_OK);
        assert_int_equal(mr_pose_new(r, &pr, &err), MR_OK);
        double worst = 0, excess = 0, mean = 0;
        for (size_t mi = 0; mi < a->mesh_count; mi++) {
            const mr_mesh *cm = &a->meshes[mi], *rm = &r->meshes[mi];
            if (cm->joint_count)
                check_weights(rm);
            size_t nc = cm->vertex_count, nr = rm->vertex_count;
            float *cp = malloc(nc * 3 * sizeof(float)), *rp = malloc(nr * 3 * sizeof(float));
            float *rn = malloc(nr * 3 * sizeof(float));
            double *rest = malloc(nc * sizeof(double));
            assert_true(cp && rp && rn && rest);
            for (size_t v = 0; v < nc; v++) {
                double d2 = 0;
                for (int k = 0; k < 3; k++) {
                    double d = (double)rm->positions[v * 3 + k] - cm->positions[v * 3 + k];
                    d2 += d * d;
                }
                rest[v] = sqrt(d2);
            }
            for (int f = 0; f < 4; f++) {
                double t = a->clips[0].duration * f / 4.0;
                mr_pose_desc desc = {.has_clip = true, .clip_index = 0, .has_time = true,
                                     .time = t, .loop = true};
                assert_int_equal(mr_pose_eval(pc, a, &desc, 0, &err), MR_OK);
                assert_int_equal(mr_pose_eval(pr, r, &desc, 0, &err), MR_OK);
                mr_skin_mesh(a, mi, pc, NULL, cp, NULL, 1);
                mr_skin_mesh(r, mi, pr, NULL, rp, rn, 0);
                for (size_t i = 0; i < nr * 3; i++)
                    assert_true(isfinite(rp[i]) && isfinite(rn[i]));
                double sum = 0;
                for (size_t v = 0; v < nc; v++) {
                    double d2 = 0;
                    for (int k = 0; k < 3; k++) {
                        double d = (double)rp[v * 3 + k] - cp[v * 3 + k];
                        d2 += d * d;
                    }
                    double gap = sqrt(d2);
                    sum += gap;
                    worst = fmax(worst, gap / diag);
                    excess = fmax(excess, (gap - rest[v]) / diag);
                    if (!(gap <= rest[v] + 0.04 * diag))
                        fail_msg("mesh %zu vertex %zu t=%g: posed gap %g, rest gap %g, diag %g",
                                 mi, v, t, gap, rest[v], diag);
                }
                mean = fmax(mean, sum / (double)nc / diag);
                if (!(sum / (double)nc <= 0.015 * diag))
                    fail_msg("mesh %zu t=%g: mean gap %g of diag %g", mi, t, sum / nc, diag);
            }
            free(cp);
            free(rp);
            free(rn);
            free(rest);
        }
        print_message("  posed gap / diagonal: worst %.4f, worst beyond the rest gap %.4f, "
                      "worst per-frame mean %.4f\n", worst, excess, mean);
        mr_pose_free(pc);
        mr_pose_free(pr);
        mr_asset_free(r);
    }
    mr_asset_free(a);
}

/* Same bits for 1, 2 and 3 threads (the parallel stencils, weights and
 * noise are per item). */
static void test_threads(void **state)
{
    (void)state;
    mr_asset *a = load_bcn();
    mr_mesh m1 = refine(&a->meshes[0], 2, 0.5f, 0.3f, 1);
    mr_mesh m2 = refine(&a->meshes[0], 2, 0.5f, 0.3f, 2);
    mr_mesh m3 = refine(&a->meshes[0], 2, 0.5f, 0.3f, 3);
    same_mesh(&m1, &m2);
    same_mesh(&m1, &m3);
    mr_refine_mesh_free(&m1);
    mr_refine_mesh_free(&m2);
    mr_refine_mesh_free(&m3);
    mr_asset_free(a);
}

/* The noise: bounded, zero on the lattice of the first band with one
 * octave, deterministic, seed-dependent, 0 for non-finite input; and the
 * displacement never exceeds the amplitude (float rounding of O(1)
 * positions: 1e-6). */
static void test_noise_and_detail(void **state)
{
    (void)state;
    double lo = 0, hi = 0, differ = 0;
    for (int i = 0; i < 20000; i++) {
        double x = (i % 37) * 0.173 - 3, y = (i % 101) * 0.0931 - 4, z = i * 0.00071 - 7;
        double n = mr_refine_noise(x, y, z, 4, 3);
        lo = fmin(lo, n);
        hi = fmax(hi, n);
        assert_true(n == mr_refine_noise(x, y, z, 4, 3));
        differ += fabs(n - mr_refine_noise(x, y, z, 4, 4));
    }
    assert_true(lo >= -1.0 && hi <= 1.0);
    /* Not degenerate: the noise uses a good part of its range. */
    assert_true(hi - lo > 0.5);
    assert_true(differ > 100.0);
    assert_true(mr_refine_noise(3, -2, 5, 1, 9) == 0.0);
    assert_true(mr_refine_noise(NAN, 0, 0, 1, 0) == 0.0);
    assert_true(mr_refine_noise(INFINITY, 0, 0, 1, 0) == 0.0);
    assert_true(isfinite(mr_refine_noise(1e300, -1e300, 0.5, 16, 0)));

    mr_asset *oct = make_octahedron();
    mr_mesh flat = refine(&oct->meshes[0], 3, 0, 0, 1);
    mr_mesh bump = refine(&oct->meshes[0], 3, 0.05f, 4.0f, 1);
    assert_int_equal(flat.vertex_count, bump.vertex_count);
    double moved = 0;
    for (size_t v = 0; v < flat.vertex_count; v++) {
        double d2 = 0;
        for (int k = 0; k < 3; k++) {
            double d = (double)bump.positions[v * 3 + k] - flat.positions[v * 3 + k];
            d2 += d * d;
        }
        assert_true(sqrt(d2) <= 0.05 + 1e-6);
        moved = fmax(moved, sqrt(d2));
    }
    assert_true(moved > 0.01);
    check_closed(&bump);
    mr_refine_mesh_free(&flat);
    mr_refine_mesh_free(&bump);
    mr_asset_free(oct);
}

static void test_bad_input(void **state)
{
    (void)state;
    mr_asset *oct = make_octahedron();
    mr_mesh out;
    mr_error err = {0};
    mr_refine_params p = {.rounds = MR_REFINE_MAX_ROUNDS + 1};
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], &p, &out, &err), MR_ERR_INVALID);
    assert_null(out.positions);
    p = (mr_refine_params){.rounds = 1, .amplitude = NAN, .frequency = 1};
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], &p, &out, &err), MR_ERR_INVALID);
    p = (mr_refine_params){.rounds = 1, .amplitude = 1, .frequency = 0};
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], &p, &out, &err), MR_ERR_INVALID);
    p = (mr_refine_params){.rounds = 1};
    assert_int_equal(mr_refine_mesh(NULL, &p, &out, &err), MR_ERR_INVALID);
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], NULL, &out, &err), MR_ERR_INVALID);
    assert_int_equal(mr_refine_asset(oct, &p, NULL, &err), MR_ERR_INVALID);
    oct->meshes[0].indices[4] = 99;
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], &p, &out, &err), MR_ERR_INVALID);
    mr_asset *r = (mr_asset *)1;
    assert_int_equal(mr_refine_asset(oct, &p, &r, &err), MR_ERR_INVALID);
    assert_null(r);
    oct->meshes[0].indices[4] = 4;
    oct->meshes[0].positions[2] = NAN;
    assert_int_equal(mr_refine_mesh(&oct->meshes[0], &p, &out, &err), MR_ERR_INVALID);
    oct->meshes[0].positions[2] = 0;

    /* A degenerate triangle and an open, non-manifold fan still refine. */
    static const float pos[] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, -1, 1, 0, 0};
    static const uint32_t idx[] = {0, 1, 2, 0, 1, 3, 0, 1, 4, 0, 5, 1, 2, 2, 3};
    mr_asset *nm = make_asset(pos, 6, idx, 5);
    mr_mesh m = refine(&nm->meshes[0], 2, 0.01f, 1.0f, 2);
    assert_int_equal(m.triangle_count, 80);
    for (size_t i = 0; i < (size_t)m.vertex_count * 3; i++)
        assert_true(isfinite(m.positions[i]) && isfinite(m.normals[i]));
    mr_refine_mesh_free(&m);
    mr_asset_free(nm);
    mr_asset_free(oct);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_counts_and_closed),
        cmocka_unit_test(test_loop_convergence),
        cmocka_unit_test(test_identity),
        cmocka_unit_test(test_weight_rules),
        cmocka_unit_test(test_skin_bcn),
        cmocka_unit_test(test_threads),
        cmocka_unit_test(test_noise_and_detail),
        cmocka_unit_test(test_bad_input),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
