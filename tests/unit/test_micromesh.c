/*
 * test_micromesh.c - micro-mesh topology, displaced micro-vertex evaluation
 * and watertightness across shared base edges (core/kinds/dmm/micromesh.h).
 *
 * Topology is checked exactly in integer (a, b) coordinates. Positions on a
 * shared edge are compared bit for bit (memcmp): that is the property the
 * edge rule promises, no tolerance. The crack test fires rays with the
 * watertight test of core/math/watertight.h at a displaced two-triangle patch
 * whose sides have levels 3 and 2, and requires every ray to hit; a control
 * without decimation must leak, which shows the rays can see a crack.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "kinds/dmm/micromesh.h"
#include "math/watertight.h"

/* Small deterministic generator so failures reproduce. */
static uint32_t rng_next(uint32_t *s)
{
    *s ^= *s << 13;
    *s ^= *s >> 17;
    *s ^= *s << 5;
    return *s;
}
static float rng_float(uint32_t *s, float lo, float hi)
{
    return lo + (hi - lo) * (float)(rng_next(s) >> 8) / 16777216.0f;
}
static mr_vec3 rng_vec(uint32_t *s, float lo, float hi)
{
    float x = rng_float(s, lo, hi), y = rng_float(s, lo, hi);
    return mr_v3(x, y, rng_float(s, lo, hi));
}

static void test_counts(void **state)
{
    (void)state;
    for (unsigned level = 0; level <= 5; level++) {
        uint32_t n = 1u << level;
        assert_int_equal(mr_umesh_segments(level), n);
        assert_int_equal(mr_umesh_triangle_count(level), 1u << (2 * level));
        assert_int_equal(mr_umesh_vertex_count(level), (n + 1) * (n + 2) / 2);
    }
    assert_int_equal(mr_umesh_vertex_count(0), 3);
    assert_int_equal(mr_umesh_vertex_count(5), 561);
    assert_int_equal(mr_umesh_triangle_count(5), 1024);
    assert_int_equal(mr_umesh_segments(6), 0);
    assert_int_equal(mr_umesh_vertex_count(6), 0);
    assert_int_equal(mr_umesh_triangle_count(6), 0);
}

static void test_index_round_trip(void **state)
{
    (void)state;
    for (unsigned level = 0; level <= 5; level++) {
        uint32_t n = 1u << level, count = mr_umesh_vertex_count(level);
        char *seen = calloc(count, 1);
        assert_non_null(seen);
        for (uint32_t b = 0; b <= n; b++)
            for (uint32_t a = 0; a + b <= n; a++) {
                uint32_t i = mr_umesh_vertex_index(level, a, b), a2, b2;
                assert_true(i < count);
                assert_false(seen[i]);
                seen[i] = 1;
                assert_true(mr_umesh_vertex_coords(level, i, &a2, &b2));
                assert_int_equal(a2, a);
                assert_int_equal(b2, b);
                float u, v;
                assert_true(mr_umesh_vertex_bary(level, i, &u, &v));
                /* a/n with n a power of two is exact in float */
                assert_true(u == (float)a / (float)n && v == (float)b / (float)n);
            }
        for (uint32_t i = 0; i < count; i++)
            assert_true(seen[i]);
        free(seen);
        uint32_t a, b;
        assert_false(mr_umesh_vertex_coords(level, count, &a, &b));
        assert_int_equal(mr_umesh_vertex_index(level, n, 1), UINT32_MAX);
    }
    uint32_t a, b;
    assert_false(mr_umesh_vertex_coords(6, 0, &a, &b));
}

/* Twice the signed area of a micro-triangle in integer (a, b) coordinates. */
static int64_t area2(unsigned level, const uint32_t idx[3])
{
    uint32_t a[3], b[3];
    for (int i = 0; i < 3; i++)
        assert_true(mr_umesh_vertex_coords(level, idx[i], &a[i], &b[i]));
    int64_t ex = (int64_t)a[1] - a[0], ey = (int64_t)b[1] - b[0];
    int64_t fx = (int64_t)a[2] - a[0], fy = (int64_t)b[2] - b[0];
    return ex * fy - ey * fx;
}

/* Every triangle has positive area, the areas sum to the base triangle's,
 * and every directed edge occurs at most once (so no two triangles overlap
 * across an edge with the same winding): together these make an exact
 * single cover of the base triangle. Also with every edge decimated. */
static void check_cover(unsigned level, unsigned mask)
{
    uint32_t n = 1u << level, vc = mr_umesh_vertex_count(level);
    uint32_t *tris = malloc(sizeof(uint32_t) * 3 * mr_umesh_triangle_count(level));
    char *dir_edge = calloc((size_t)vc * vc, 1);
    assert_non_null(tris);
    assert_non_null(dir_edge);
    uint32_t count = mr_umesh_triangles(level, mask, tris);
    int64_t sum = 0;
    for (uint32_t t = 0; t < count; t++) {
        int64_t ar = area2(level, tris + 3 * t);
        assert_true(ar > 0);
        sum += ar;
        for (int e = 0; e < 3; e++) {
            size_t key = (size_t)tris[3 * t + e] * vc + tris[3 * t + (e + 1) % 3];
            assert_false(dir_edge[key]);
            dir_edge[key] = 1;
        }
    }
    assert_true(sum == (int64_t)n * n);
    free(dir_edge);
    free(tris);
}

static void test_triangles_cover_once(void **state)
{
    (void)state;
    for (unsigned level = 0; level <= 5; level++) {
        uint32_t count = mr_umesh_triangle_count(level), idx[3], vc = mr_umesh_vertex_count(level);
        for (uint32_t t = 0; t < count; t++) {
            assert_true(mr_umesh_triangle(level, t, idx));
            for (int i = 0; i < 3; i++)
                assert_true(idx[i] < vc);
            /* exactly one unit cell: 1/(2 n^2) of the base area */
            assert_true(area2(level, idx) == 1);
        }
        assert_false(mr_umesh_triangle(level, count, idx));
        check_cover(level, 0);
        for (unsigned mask = 1; mask < 8 && level > 0; mask++)
            check_cover(level, mask);
        if (level > 0) {
            /* each decimated odd vertex makes exactly one triangle degenerate
             * (the one holding the boundary edge it collapses along) */
            uint32_t *tris = malloc(sizeof(uint32_t) * 3 * count), n = 1u << level;
            assert_non_null(tris);
            assert_int_equal(mr_umesh_triangles(level, 7, tris), count - 3 * n / 2);
            assert_int_equal(mr_umesh_triangles(level, 0, tris), count);
            free(tris);
        }
    }
}

/* Displacement as a function of the undisplaced point only, the way a baker
 * measures it: equal bits in give equal bits out. */
static float edge_disp(mr_vec3 p)
{
    return 0.2f * sinf(7.0f * p.x + 3.0f * p.y) + 0.1f * cosf(5.0f * p.z - 2.0f * p.x);
}

/* Per-vertex displacements: edge_disp on the base edges, edge_disp plus a
 * per-triangle bump inside. */
static void make_disp(const mr_umesh_tri *tri, unsigned level, float bump, float *disp)
{
    uint32_t count = mr_umesh_vertex_count(level);
    for (uint32_t i = 0; i < count; i++) {
        uint32_t a, b;
        mr_vec3 p, d;
        assert_true(mr_umesh_vertex_coords(level, i, &a, &b));
        assert_int_equal(mr_umesh_frame(tri, level, a, b, &p, &d, NULL), MR_OK);
        disp[i] = edge_disp(p);
        if (mr_umesh_vertex_edge(level, a, b, NULL) < 0)
            disp[i] += bump * (float)(a * 7 % 5) - 0.3f * bump;
    }
}

/* Micro-vertex at step k of edge e (in the triangle's own direction). */
static uint32_t edge_vertex(unsigned level, int e, uint32_t k)
{
    uint32_t n = 1u << level;
    switch (e) {
    case 0: return mr_umesh_vertex_index(level, k, 0);
    case 1: return mr_umesh_vertex_index(level, n - k, k);
    default: return mr_umesh_vertex_index(level, 0, n - k);
    }
}

static void test_shared_edge_bit_identical(void **state)
{
    (void)state;
    uint32_t seed = 12345;
    static mr_vec3 out1[561], out2[561];
    static float d1[561], d2[561];
    for (int trial = 0; trial < 200; trial++) {
        mr_vec3 p0 = rng_vec(&seed, -100, 100), p1 = rng_vec(&seed, -100, 100);
        mr_vec3 p2 = rng_vec(&seed, -100, 100), p3 = rng_vec(&seed, -100, 100);
        mr_vec3 n0 = mr_v3_normalize_or(rng_vec(&seed, -1, 1), mr_v3(0, 0, 1));
        mr_vec3 n1 = mr_v3_normalize_or(rng_vec(&seed, -1, 1), mr_v3(0, 0, 1));
        mr_vec3 n2 = mr_v3_normalize_or(rng_vec(&seed, -1, 1), mr_v3(0, 0, 1));
        mr_vec3 n3 = mr_v3_normalize_or(rng_vec(&seed, -1, 1), mr_v3(0, 0, 1));
        /* T1 has the edge p0->p1 as its edge 0; T2 lists it p1->p0 as its
         * edge (trial % 3), with the corners rotated accordingly. */
        mr_umesh_tri t1 = {{p0, p1, p2}, {n0, n1, n2}};
        int e2 = trial % 3;
        mr_umesh_tri t2;
        t2.pos[e2] = p1, t2.dir[e2] = n1;
        t2.pos[(e2 + 1) % 3] = p0, t2.dir[(e2 + 1) % 3] = n0;
        t2.pos[(e2 + 2) % 3] = p3, t2.dir[(e2 + 2) % 3] = n3;
        unsigned l1 = (unsigned)(trial / 3) % 6;
        /* the neighbour has the same level or one less (then T1 decimates) */
        unsigned l2 = (trial % 2 && l1 > 0) ? l1 - 1 : l1;
        unsigned mask1 = l2 < l1 ? 1u : 0u;
        make_disp(&t1, l1, 0.5f, d1);
        make_disp(&t2, l2, -0.25f, d2);
        assert_int_equal(mr_umesh_eval_all(&t1, l1, mask1, d1, out1, NULL), MR_OK);
        assert_int_equal(mr_umesh_eval_all(&t2, l2, 0, d2, out2, NULL), MR_OK);
        uint32_t n2s = 1u << l2, step = l2 < l1 ? 2u : 1u;
        for (uint32_t k = 0; k <= n2s; k++) {
            uint32_t i1 = edge_vertex(l1, 0, k * step);
            uint32_t i2 = edge_vertex(l2, e2, n2s - k);
            assert_memory_equal(&out1[i1], &out2[i2], sizeof(mr_vec3));
            uint32_t a1, b1, a2, b2;
            mr_vec3 q1, q2, m1, m2;
            mr_umesh_vertex_coords(l1, i1, &a1, &b1);
            mr_umesh_vertex_coords(l2, i2, &a2, &b2);
            mr_umesh_frame(&t1, l1, a1, b1, &q1, &m1, NULL);
            mr_umesh_frame(&t2, l2, a2, b2, &q2, &m2, NULL);
            assert_memory_equal(&q1, &q2, sizeof q1);
            assert_memory_equal(&m1, &m2, sizeof m1);
        }
        /* the interior really differs, so the equality above is the edge rule's */
        if (l1 >= 2 && l1 == l2) {
            uint32_t mid = mr_umesh_vertex_index(l1, 1, 1);
            assert_true(d1[mid] != d2[mid]);
        }
    }
}

/* A coordinate for test_eval_many: often exactly +0 or -0 (the signs of
 * zero are where summing other corners' zero terms, as a vectorised sum
 * might, changes the bits), else of any magnitude up to scale, 2^-40 of it
 * at the least (where the order of a sum's terms decides its rounding). */
static float odd_float(uint32_t *s, float scale)
{
    switch (rng_next(s) % 4) {
    case 0: return 0.0f;
    case 1: return -0.0f;
    default: return ldexpf(rng_float(s, -scale, scale), -(int)(rng_next(s) % 41));
    }
}

/* mr_umesh_eval_many gives mr_umesh_eval_at's bits for every vertex of
 * every level: interior, edge (either endpoint order) and corner vertices,
 * in a scrambled order, with corners and displacements of both signs of
 * zero; mr_umesh_eval_interpolated_many mr_umesh_eval_interpolated_at's,
 * under corner matrices of such elements too. */
static void test_eval_many(void **state)
{
    (void)state;
    uint32_t seed = 777;
    static uint32_t a[561], b[561];
    static float disp[561];
    static mr_vec3 many[561], interpolated[561];
    for (int trial = 0; trial < 600; trial++) {
        mr_umesh_tri t;
        for (int i = 0; i < 3; i++) {
            float s = trial % 2 ? 1e4f : 2.0f;
            t.pos[i] = mr_v3(odd_float(&seed, s), odd_float(&seed, s), odd_float(&seed, s));
            t.dir[i] = mr_v3(odd_float(&seed, 1), odd_float(&seed, 1), odd_float(&seed, 1));
        }
        if (trial % 5 == 0) /* two corners alike: the edge rule's tie */
            t.pos[1] = t.pos[0], t.dir[1] = t.dir[0];
        unsigned level = (unsigned)trial % 6;
        uint32_t count = mr_umesh_vertex_count(level);
        for (uint32_t i = 0; i < count; i++) {
            uint32_t j = (i * 7 + (uint32_t)trial) % count; /* 7 is prime to every count */
            assert_true(mr_umesh_vertex_coords(level, j, &a[i], &b[i]));
            disp[i] = odd_float(&seed, 0.3f);
        }
        mr_affine m[3];
        for (int i = 0; i < 3; i++)
            for (int e = 0; e < 12; e++)
                m[i].m[e] = odd_float(&seed, 4.0f);
        if (trial % 7 == 0) /* two corners' matrices alike */
            m[2] = m[0];
        const mr_affine *const mats[3] = {&m[0], &m[1], &m[2]};
        mr_umesh_eval_many(&t, level, (int)count, a, b, disp, many);
        mr_umesh_eval_interpolated_many(&t, mats, level, (int)count, a, b, disp, interpolated);
        for (uint32_t i = 0; i < count; i++) {
            mr_vec3 one = mr_umesh_eval_at(&t, level, a[i], b[i], disp[i]);
            assert_memory_equal(&many[i], &one, sizeof one);
            one = mr_umesh_eval_interpolated_at(&t, mats, level, a[i], b[i], disp[i]);
            assert_memory_equal(&interpolated[i], &one, sizeof one);
        }
    }
}

/* Rays at points near the shared edge from above and below, tilted across
 * the edge both ways; returns how many of them hit no micro-triangle. */
static int count_leaks(unsigned mask_a)
{
    /* a gently curved quad p0 p1 p3 p2 split along p1-p2 */
    mr_vec3 p0 = mr_v3(0, 0, 0), p1 = mr_v3(1.1f, 0.05f, 0.1f), p2 = mr_v3(-0.05f, 0.97f, 0.07f),
            p3 = mr_v3(1.03f, 1.08f, -0.12f);
    mr_vec3 n0 = mr_v3_normalize_or(mr_v3(-0.2f, -0.1f, 1), mr_v3(0, 0, 1));
    mr_vec3 n1 = mr_v3_normalize_or(mr_v3(0.15f, -0.2f, 1), mr_v3(0, 0, 1));
    mr_vec3 n2 = mr_v3_normalize_or(mr_v3(-0.1f, 0.25f, 1), mr_v3(0, 0, 1));
    mr_vec3 n3 = mr_v3_normalize_or(mr_v3(0.2f, 0.1f, 1), mr_v3(0, 0, 1));
    mr_umesh_tri ta = {{p0, p1, p2}, {n0, n1, n2}}; /* level 3, edge 1 = p1->p2 */
    mr_umesh_tri tb = {{p2, p1, p3}, {n2, n1, n3}}; /* level 2, edge 0 = p2->p1 */
    const unsigned la = 3, lb = 2;
    static float da[45], db[15];
    static mr_vec3 va[45], vb[15];
    static uint32_t ia[3 * 64], ib[3 * 16];
    make_disp(&ta, la, 0.3f, da);
    make_disp(&tb, lb, -0.2f, db);
    assert_int_equal(mr_umesh_eval_all(&ta, la, mask_a, da, va, NULL), MR_OK);
    assert_int_equal(mr_umesh_eval_all(&tb, lb, 0, db, vb, NULL), MR_OK);
    uint32_t ca = mr_umesh_triangles(la, mask_a, ia), cb = mr_umesh_triangles(lb, 0, ib);

    mr_vec3 edge = mr_v3_sub(p2, p1);
    mr_vec3 up = mr_v3_normalize_or(mr_v3_add(n1, n2), mr_v3(0, 0, 1));
    /* in-surface direction across the edge, pointing into ta */
    mr_vec3 side = mr_v3_normalize_or(mr_v3_cross(up, edge), mr_v3(1, 0, 0));
    if (mr_v3_dot(side, mr_v3_sub(p0, p1)) < 0)
        side = mr_v3_scale(side, -1);
    int leaks = 0;
    for (uint32_t seg = 0; seg < 4; seg++) {
        /* displaced coarse edge vertices of tb (edge 0 runs p2->p1) */
        mr_vec3 a = vb[edge_vertex(lb, 0, seg)], b = vb[edge_vertex(lb, 0, seg + 1)];
        for (int s = 0; s <= 16; s++) {
            /* the ends of the shared edge are corners of the whole patch,
             * where rays may legitimately pass outside it */
            if ((seg == 0 && s < 2) || (seg == 3 && s > 14))
                continue;
            mr_vec3 x = mr_v3_lerp(a, b, (float)s / 16.0f);
            for (int off = -1; off <= 1; off++) {
                mr_vec3 target = mr_v3_add(x, mr_v3_scale(side, 1e-4f * (float)off));
                for (int vert = -1; vert <= 1; vert += 2)
                    for (int tilt = -2; tilt <= 2; tilt++) {
                        mr_vec3 dir = mr_v3_add(mr_v3_scale(up, (float)-vert),
                                                mr_v3_scale(side, 0.3f * (float)tilt));
                        mr_vec3 org = mr_v3_sub(target, mr_v3_scale(dir, 2.0f));
                        mr_wt_ray ray = mr_wt_ray_setup(org, dir);
                        mr_wt_hit hit;
                        bool any = false;
                        for (uint32_t t = 0; t < ca && !any; t++)
                            any = mr_wt_intersect(&ray, va[ia[3 * t]], va[ia[3 * t + 1]],
                                                  va[ia[3 * t + 2]], 0, INFINITY, &hit);
                        for (uint32_t t = 0; t < cb && !any; t++)
                            any = mr_wt_intersect(&ray, vb[ib[3 * t]], vb[ib[3 * t + 1]],
                                                  vb[ib[3 * t + 2]], 0, INFINITY, &hit);
                        if (!any && getenv("DMM_DEBUG"))
                            print_message("leak seg %u s %d off %d vert %d tilt %d\n", seg, s,
                                          off, vert, tilt);
                        leaks += !any;
                    }
            }
        }
    }
    return leaks;
}

/* Edge decimation's rule, written out here from its definition: an odd
 * step k of a decimated edge (edge 0 from (0, 0) to (n, 0), edge 1 from
 * (n, 0) to (0, n), edge 2 from (0, n) to (0, 0); corners belong to none)
 * collapses onto step k - 1 of the same edge. mr_umesh_remap_coords (on
 * coordinates) and mr_umesh_vertex_remap (on indices) must both move
 * every vertex of every level and mask so, and leave coordinates off the
 * lattice as they are. */
static void test_remap_follows_the_edge_rule(void **state)
{
    (void)state;
    unsigned moved = 0;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        const uint32_t n = mr_umesh_segments(level);
        for (unsigned mask = 0; mask < 8; mask++)
            for (uint32_t b = 0; b <= n; b++)
                for (uint32_t a = 0; a + b <= n; a++) {
                    uint32_t wa = a, wb = b;
                    const bool corner = (a == 0 || a == n) && (b == 0 || b == n);
                    if (!corner && b == 0 && (mask & 1u) && a % 2 == 1)
                        wa = a - 1;
                    else if (!corner && a + b == n && a > 0 && (mask & 2u) && b % 2 == 1)
                        wa = n - (b - 1), wb = b - 1;
                    else if (!corner && a == 0 && (mask & 4u) && (n - b) % 2 == 1)
                        wb = n - (n - b - 1);
                    uint32_t ca = a, cb = b;
                    mr_umesh_remap_coords(level, mask, &ca, &cb);
                    assert_true(ca == wa && cb == wb);
                    const uint32_t r = mr_umesh_vertex_remap(level, mask, mr_umesh_vertex_index(level, a, b));
                    assert_int_equal(r, mr_umesh_vertex_index(level, wa, wb));
                    moved += wa != a || wb != b;
                }
    }
    assert_true(moved > 0);
    uint32_t a = 3, b = 2; /* a + b > 4 at level 2 */
    mr_umesh_remap_coords(2, 7, &a, &b);
    assert_true(a == 3 && b == 2);
}

static void test_level_difference_no_crack(void **state)
{
    (void)state;
    /* ta's edge 1 borders the coarser tb: decimated, nothing leaks */
    assert_int_equal(count_leaks(2u), 0);
    /* control: without decimation the odd edge vertices of ta leave a crack */
    assert_true(count_leaks(0u) > 0);
}

/* Zero displacement reproduces the flat base triangle. Tolerance: weights are
 * k/32 at most, so each weight * coordinate is exact in double; the sum is
 * rounded once in double (relative 2^-53) and once to float (half an ulp of
 * the result), hence within one float ulp of max |v_i| of the exact point,
 * which long double (64-bit mantissa) gives here to far better than that. */
static void test_zero_displacement_is_flat(void **state)
{
    (void)state;
    uint32_t seed = 777;
    static mr_vec3 out[561];
    for (int trial = 0; trial < 50; trial++) {
        mr_umesh_tri t;
        for (int i = 0; i < 3; i++) {
            t.pos[i] = rng_vec(&seed, -1000, 1000);
            t.dir[i] = rng_vec(&seed, -1, 1);
        }
        unsigned level = (unsigned)trial % 6;
        uint32_t n = 1u << level, count = mr_umesh_vertex_count(level);
        assert_int_equal(mr_umesh_eval_all(&t, level, 0, NULL, out, NULL), MR_OK);
        for (uint32_t i = 0; i < count; i++) {
            uint32_t a, b;
            mr_umesh_vertex_coords(level, i, &a, &b);
            long double w0 = (long double)(n - a - b) / n, w1 = (long double)a / n,
                        w2 = (long double)b / n;
            const float c0[3] = {t.pos[0].x, t.pos[0].y, t.pos[0].z};
            const float c1[3] = {t.pos[1].x, t.pos[1].y, t.pos[1].z};
            const float c2[3] = {t.pos[2].x, t.pos[2].y, t.pos[2].z};
            const float got[3] = {out[i].x, out[i].y, out[i].z};
            for (int c = 0; c < 3; c++) {
                long double exact = w0 * c0[c] + w1 * c1[c] + w2 * c2[c];
                float m = fmaxf(fabsf(c0[c]), fmaxf(fabsf(c1[c]), fabsf(c2[c])));
                float ulp = nextafterf(m, INFINITY) - m;
                assert_true(fabsl((long double)got[c] - exact) <= ulp);
            }
        }
        /* corners are the base vertices, bit for bit */
        for (int c = 0; c < 3; c++) {
            uint32_t k = c == 0 ? 0 : c == 1 ? mr_umesh_vertex_index(level, n, 0)
                                             : mr_umesh_vertex_index(level, 0, n);
            assert_memory_equal(&out[k], &t.pos[c], sizeof(mr_vec3));
        }
    }
    /* a triangle in the plane z = 3 stays exactly in it */
    mr_umesh_tri flat = {{mr_v3(0.1f, 0.2f, 3), mr_v3(7.3f, -1.1f, 3), mr_v3(-2.9f, 5.7f, 3)},
                         {mr_v3(0, 0, 1), mr_v3(0.6f, 0, 0.8f), mr_v3(0, -0.6f, 0.8f)}};
    assert_int_equal(mr_umesh_eval_all(&flat, 5, 0, NULL, out, NULL), MR_OK);
    for (uint32_t i = 0; i < 561; i++)
        assert_true(out[i].z == 3.0f);
}

/* The direction is interpolated and not normalised (eq. 5). */
static void test_direction_not_normalised(void **state)
{
    (void)state;
    mr_umesh_tri t = {{mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0)},
                      {mr_v3(1, 0, 0), mr_v3(0, 1, 0), mr_v3(0, 0, 1)}};
    mr_vec3 p, d;
    /* centre of edge 0 at level 1: (n0 + n1) / 2 has length sqrt(0.5) */
    assert_int_equal(mr_umesh_frame(&t, 1, 1, 0, &p, &d, NULL), MR_OK);
    assert_true(d.x == 0.5f && d.y == 0.5f && d.z == 0.0f);
    assert_int_equal(mr_umesh_eval(&t, 1, 1, 0, 2.0f, &p, NULL), MR_OK);
    assert_true(p.x == 1.5f && p.y == 1.0f && p.z == 0.0f);
}

static void test_bad_input(void **state)
{
    (void)state;
    mr_umesh_tri t = {{mr_v3(0, 0, 0), mr_v3(1, 0, 0), mr_v3(0, 1, 0)},
                      {mr_v3(0, 0, 1), mr_v3(0, 0, 1), mr_v3(0, 0, 1)}};
    mr_error err = {0};
    mr_vec3 out[15];
    float disp[15] = {0};
    assert_int_equal(mr_umesh_eval_all(&t, 6, 0, NULL, out, &err), MR_ERR_INVALID);
    assert_true(err.msg[0] != 0);
    assert_int_equal(mr_umesh_eval_all(&t, 2, 8, NULL, out, &err), MR_ERR_INVALID);
    disp[4] = NAN;
    assert_int_equal(mr_umesh_eval_all(&t, 2, 0, disp, out, &err), MR_ERR_INVALID);
    disp[4] = 0;
    t.dir[2].y = INFINITY;
    assert_int_equal(mr_umesh_eval_all(&t, 2, 0, disp, out, &err), MR_ERR_INVALID);
    t.dir[2].y = 0;
    assert_int_equal(mr_umesh_eval(&t, 2, 3, 2, 0, out, &err), MR_ERR_INVALID);
    assert_int_equal(mr_umesh_frame(&t, 9, 0, 0, out, NULL, &err), MR_ERR_INVALID);
    assert_int_equal(mr_umesh_vertex_remap(2, 7, 99), UINT32_MAX);
    /* level 0 has no odd edge vertices: decimation changes nothing */
    uint32_t tris[3];
    assert_int_equal(mr_umesh_triangles(0, 7, tris), 1);
}

/* mr_umesh_balance on a 12 x 12 grid of quads split in two (288
 * triangles) with random levels, 50 times: the levels it ends at are the
 * least that keep neighbours (sharing an edge) at most one apart, as a
 * brute force that raises the coarse side of any pair until nothing moves
 * finds them, and exactly the finer side of every edge between two levels
 * is decimated. */
static void test_balance_is_least(void **state)
{
    (void)state;
    enum { N = 12, NT = 2 * N * N };
    uint32_t idx[3 * NT];
    for (uint32_t y = 0, t = 0; y < N; y++)
        for (uint32_t x = 0; x < N; x++, t += 2) {
            uint32_t a = y * (N + 1) + x, b = a + 1, c = a + N + 1, d = c + 1;
            uint32_t q[6] = {a, b, c, b, d, c};
            memcpy(idx + 3 * t, q, sizeof q);
        }
    mr_umesh_edges e;
    mr_error err;
    assert_int_equal(mr_umesh_edges_init(&e, idx, NT, &err), MR_OK);
    uint32_t seed = 7;
    for (int run = 0; run < 50; run++) {
        uint8_t level[NT], want[NT], decimate[NT];
        for (uint32_t t = 0; t < NT; t++) {
            seed = seed * 1664525u + 1013904223u;
            /* mostly coarse, a few fine: long raises */
            level[t] = (seed >> 24) < 8 ? (uint8_t)(3 + (seed >> 8) % 3) : (uint8_t)((seed >> 8) % 2);
        }
        memcpy(want, level, sizeof want);
        for (bool moved = true; moved;) {
            moved = false;
            for (uint32_t a = 0; a < NT; a++)
                for (uint32_t b = 0; b < NT; b++) {
                    int shared = 0;
                    for (int i = 0; i < 3; i++)
                        for (int j = 0; j < 3; j++)
                            shared += idx[3 * a + i] == idx[3 * b + j];
                    if (a != b && shared == 2 && want[a] + 1 < want[b]) {
                        want[a] = (uint8_t)(want[b] - 1);
                        moved = true;
                    }
                }
        }
        mr_umesh_balance(&e, level, decimate);
        assert_memory_equal(level, want, sizeof want);
        for (size_t i = 0; i < e.count; i++) {
            const mr_umesh_edge *x = &e.e[i];
            unsigned low = level[x->tri];
            for (size_t m = e.group[i]; m < e.count && e.group[m] == e.group[i]; m++)
                low = level[e.e[m].tri] < low ? level[e.e[m].tri] : low;
            assert_int_equal(decimate[x->tri] >> x->k & 1u, level[x->tri] > low);
        }
    }
    mr_umesh_edges_free(&e);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_counts),
        cmocka_unit_test(test_index_round_trip),
        cmocka_unit_test(test_triangles_cover_once),
        cmocka_unit_test(test_shared_edge_bit_identical),
        cmocka_unit_test(test_eval_many),
        cmocka_unit_test(test_remap_follows_the_edge_rule),
        cmocka_unit_test(test_level_difference_no_crack),
        cmocka_unit_test(test_zero_displacement_is_flat),
        cmocka_unit_test(test_direction_not_normalised),
        cmocka_unit_test(test_bad_input),
        cmocka_unit_test(test_balance_is_least),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
