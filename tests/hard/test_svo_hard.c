/*
 * test_svo_hard.c - hard cases for the sparse voxel octree ray caster
 * (core/kinds/svo/svo_trace.h): rays along shared faces, edges and corners of a
 * solid block and of voxels that touch only at an edge or a corner (no
 * leaks), a 3D checkerboard, rays starting inside a voxel, the deepest
 * level (21) far from the origin, tiny and huge cubes, the empty octree and
 * single voxels, extreme tmin / tmax, zero, negative-zero and denormal
 * direction components, non-finite input and a corrupted octree.
 *
 * The fixture (builder, brute force, check_ray / check_ray_exact and their
 * tolerances) is tests/support/svo_fixture.h, shared with
 * tests/unit/test_svo_trace.c. Cubes here
 * are dyadic and most rays have dyadic origins and directions in {0, +-1,
 * +-2, +-0.5}, so every plane's t is exact in both the traversal and the
 * brute force and check_ray_exact demands the same hit/miss and t bit for
 * bit, grazes (a ray touching a box only along an edge or at a corner)
 * included. Where a hit is guaranteed by construction the test demands it
 * outright as well.
 *
 * Each case reports for `make hard` (hard_report.h, report_rays below) the
 * rays its checks against the brute force failed on (0: they stop at the
 * first), the non-finite hits, the largest t error in tolerances, and its
 * own counts of rays that missed what they must hit or got a wrong answer.
 */
#include "../support/svo_fixture.h"

#include <limits.h>

#define HARD_KIND "svo"
#include "../support/hard_report.h"

/* The figures of the rays a case checked against the brute force. */
static void report_rays(const char *test, const fx_stats *st)
{
    hard_check(test, "error", (double)st->mismatches, "==", 0,
               "rays disagreeing with the brute force (of %ld: %ld exact, %ld hit)", st->rays, st->exact,
               st->hits);
    hard_check(test, "nan", (double)st->nonfinite, "==", 0, "non-finite hits (t, ng)");
    if (st->rays > st->exact)
        hard_check(test, "error", st->worst_t, "<=", 1,
                   "largest |t - its leaf's entry|, in tolerances (4 ulps of |t| + cube / |d|)");
}

/* ---- solid block: cells [3, 12) x [4, 13) x [2, 14) of a depth-4 grid
 * over [0, 16)^3 (one unit per finest cell), so coarse leaves (level 2:
 * [4, 8)^3 ...) meet finer ones along faces. */

typedef struct box_cls {
    unsigned depth;
    uint32_t lo[3], hi[3]; /* finest cells [lo, hi) */
} box_cls;

static int cls_box(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const box_cls *b = ctx;
    const uint32_t w = 1u << (b->depth - level), p[3] = {x * w, y * w, z * w};
    bool inside = true;
    for (int a = 0; a < 3; a++) {
        if (p[a] + w <= b->lo[a] || p[a] >= b->hi[a])
            return FX_EMPTY;
        if (p[a] < b->lo[a] || p[a] + w > b->hi[a])
            inside = false;
    }
    return inside ? FX_LEAF : FX_SPLIT;
}

static void test_block_axis_parallel(void **state)
{
    (void)state;
    box_cls bc = {4, {3, 4, 2}, {12, 13, 14}};
    svo_fx fx;
    fx_build(&fx, 4, mr_v3(0, 0, 0), 16.0f, cls_box, &bc);
    unsigned levels = 0;
    for (uint32_t i = 0; i < fx.svo.leaf_count; i++)
        levels |= 1u << fx.boxes[i].level;
    assert_true((levels & (1u << 2)) && (levels & (1u << 4)));
    fx_stats st = {0};
    long wrong = 0;
    /* Along every axis, both ways, through every grid line and half line
     * of a face: hits exactly when the line meets the closed block. */
    for (int a = 0; a < 3; a++) {
        for (int sgn = -1; sgn <= 1; sgn += 2) {
            for (int i = 4; i <= 28; i++) {
                for (int j = 4; j <= 28; j++) {
                    const float u = (float)i * 0.5f, v = (float)j * 0.5f;
                    float o[3], d[3] = {0.0f, 0.0f, 0.0f};
                    o[a] = sgn > 0 ? -5.0f : 21.0f;
                    o[(a + 1) % 3] = u;
                    o[(a + 2) % 3] = v;
                    d[a] = (float)sgn;
                    mr_svo_hit h;
                    const bool hit = mr_svo_intersect(&fx.svo, mr_v3(o[0], o[1], o[2]),
                                                      mr_v3(d[0], d[1], d[2]), 0.0f, INFINITY, &h);
                    const int b = (a + 1) % 3, c = (a + 2) % 3;
                    const bool expect = u >= (float)bc.lo[b] && u <= (float)bc.hi[b] && v >= (float)bc.lo[c] &&
                                        v <= (float)bc.hi[c];
                    HARD_EXPECT(wrong, hit == expect);
                    if (hit && expect) {
                        HARD_EXPECT(wrong, h.t == (sgn > 0 ? 5.0f + (float)bc.lo[a] : 21.0f - (float)bc.hi[a]));
                        HARD_EXPECT(wrong, h.axis == a);
                    }
                    check_ray_exact(&fx, mr_v3(o[0], o[1], o[2]), mr_v3(d[0], d[1], d[2]), 0.0f, INFINITY, &st);
                }
            }
        }
    }
    HARD_CHECK("error", wrong, "==", 0,
               "axis-parallel rays on face grid lines: hit, t or face other than the closed block's (of %ld)",
               st.rays);
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* Exactly diagonal rays (components in {0, +-1}) through grid corners and
 * edge midpoints on and inside the block: every such ray reaches a point of
 * the closed block, so it must hit, at the brute force's t exactly. */
static void test_block_diagonal(void **state)
{
    (void)state;
    box_cls bc = {4, {4, 4, 4}, {12, 12, 12}};
    svo_fx fx;
    fx_build(&fx, 4, mr_v3(0, 0, 0), 16.0f, cls_box, &bc);
    long rays = 0, missed = 0, late = 0;
    fx_stats st = {0};
    for (int dx = -1; dx <= 1; dx++)
        for (int dy = -1; dy <= 1; dy++)
            for (int dz = -1; dz <= 1; dz++) {
                if (!dx && !dy && !dz)
                    continue;
                for (int x = 8; x <= 24; x++)
                    for (int y = 8; y <= 24; y++)
                        for (int z = 8; z <= 24; z += 2) {
                            /* target (x, y, z) / 2 in [4, 12]^3 */
                            const float tx = 0.5f * x, ty = 0.5f * y, tz = 0.5f * z;
                            const mr_vec3 d = mr_v3((float)dx, (float)dy, (float)dz);
                            const mr_vec3 o = mr_v3(tx - 20.0f * dx, ty - 20.0f * dy, tz - 20.0f * dz);
                            mr_svo_hit h;
                            const bool hit = mr_svo_intersect(&fx.svo, o, d, 0.0f, INFINITY, &h);
                            HARD_EXPECT(missed, hit);
                            if (hit)
                                HARD_EXPECT(late, h.t <= 20.0f);
                            check_ray_exact(&fx, o, d, 0.0f, INFINITY, &st);
                            rays++;
                        }
            }
    HARD_CHECK("leaks", missed, "==", 0, "diagonal rays through corners and edges of the block that missed (of %ld)",
               rays);
    HARD_CHECK("error", late, "==", 0, "hits beyond the target point (t > 20)");
    HARD_CHECK("other", rays, ">", 10000, "diagonal rays");
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* ---- voxels that touch only along an edge or at a corner */

typedef struct list_cls {
    unsigned depth;
    const uint32_t (*cells)[3];
    int count;
} list_cls;

static int cls_list(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const list_cls *l = ctx;
    const unsigned sh = l->depth - level;
    for (int i = 0; i < l->count; i++)
        if ((l->cells[i][0] >> sh) == x && (l->cells[i][1] >> sh) == y && (l->cells[i][2] >> sh) == z)
            return level == l->depth ? FX_LEAF : FX_SPLIT;
    return FX_EMPTY;
}

static void test_edge_and_corner_contacts(void **state)
{
    (void)state;
    /* A diagonal wall of columns (2, 3, z) and (3, 2, z): neighbours share
     * only the edge x = y = 3. */
    static const uint32_t wall[][3] = {{2, 3, 0}, {2, 3, 1}, {2, 3, 2}, {2, 3, 3}, {2, 3, 4}, {2, 3, 5},
                                       {2, 3, 6}, {2, 3, 7}, {3, 2, 0}, {3, 2, 1}, {3, 2, 2}, {3, 2, 3},
                                       {3, 2, 4}, {3, 2, 5}, {3, 2, 6}, {3, 2, 7}};
    list_cls lw = {3, wall, 16};
    svo_fx fx;
    fx_build(&fx, 3, mr_v3(0, 0, 0), 8.0f, cls_list, &lw);
    fx_stats st = {0};
    long aimed = 0, missed = 0, wrong = 0;
    for (int k = 0; k <= 16; k++) {
        const float z = 0.5f * k;
        /* along x = y: crosses the wall exactly at its shared edge */
        mr_svo_hit h;
        aimed += 3;
        bool hit = mr_svo_intersect(&fx.svo, mr_v3(0, 0, z), mr_v3(1, 1, 0), 0.0f, INFINITY, &h);
        HARD_EXPECT(missed, hit);
        if (hit)
            HARD_EXPECT(wrong, h.t == 2.0f || h.t == 3.0f);
        check_ray_exact(&fx, mr_v3(0, 0, z), mr_v3(1, 1, 0), 0.0f, INFINITY, &st);
        /* the same, tilted in z */
        check_ray_exact(&fx, mr_v3(0, 0, z), mr_v3(1, 1, 0.5f), 0.0f, INFINITY, &st);
        check_ray_exact(&fx, mr_v3(6, 6, z), mr_v3(-1, -1, 0), 0.0f, INFINITY, &st);
        /* along the shared edge itself (z-parallel through x = y = 3) */
        hit = mr_svo_intersect(&fx.svo, mr_v3(3, 3, -1), mr_v3(0, 0, 1), 0.0f, INFINITY, &h);
        HARD_EXPECT(missed, hit);
        if (hit)
            HARD_EXPECT(wrong, h.t == 1.0f);
        /* across the wall's gap direction x = -y through the edge: grazes */
        HARD_EXPECT(missed, mr_svo_intersect(&fx.svo, mr_v3(0, 6, z), mr_v3(1, -1, 0), 0.0f, INFINITY, &h));
        check_ray_exact(&fx, mr_v3(0, 6, z), mr_v3(1, -1, 0), 0.0f, INFINITY, &st);
    }
    fx_free(&fx);

    /* Two voxels sharing only the corner (3, 3, 3); rays through that
     * corner in directions that pass between them must still hit it. */
    static const uint32_t pair[][3] = {{2, 2, 2}, {3, 3, 3}};
    list_cls lp = {3, pair, 2};
    fx_build(&fx, 3, mr_v3(0, 0, 0), 8.0f, cls_list, &lp);
    const float dirs[][3] = {{1, -1, 0.5f}, {-1, 1, 0.5f}, {1, -1, -1}, {0.5f, 1, -1}, {1, 1, 1}, {-1, -1, -1},
                             {1, 0, -1},    {0, 1, -1},    {2, -1, 0.5f}};
    for (size_t i = 0; i < sizeof dirs / sizeof dirs[0]; i++) {
        const mr_vec3 d = mr_v3(dirs[i][0], dirs[i][1], dirs[i][2]);
        const mr_vec3 o = mr_v3(3.0f - 4.0f * d.x, 3.0f - 4.0f * d.y, 3.0f - 4.0f * d.z);
        mr_svo_hit h;
        aimed += 2;
        const bool hit = mr_svo_intersect(&fx.svo, o, d, 0.0f, INFINITY, &h);
        HARD_EXPECT(missed, hit);
        if (hit)
            HARD_EXPECT(wrong, h.t <= 4.0f);
        HARD_EXPECT(missed, mr_svo_occluded(&fx.svo, o, d, 0.0f, INFINITY));
        check_ray_exact(&fx, o, d, 0.0f, INFINITY, &st);
    }
    HARD_CHECK("leaks", missed, "==", 0,
               "rays through edges and corners where voxels touch that missed (of %ld)", aimed);
    HARD_CHECK("error", wrong, "==", 0, "of those, hits at another t than the contact's");
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* A 3D checkerboard: full cells share only edges and corners. Any segment
 * longer than a cell diagonal inside the cube leaves its first cell through
 * a face (into a full cell), an edge or a corner (both touch full cells),
 * so it must hit. */
static int cls_checker(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const unsigned depth = *(const unsigned *)ctx;
    if (level < depth)
        return FX_SPLIT;
    return ((x + y + z) & 1u) ? FX_LEAF : FX_EMPTY;
}

static void test_checkerboard(void **state)
{
    (void)state;
    unsigned depth = 4;
    svo_fx fx;
    fx_build(&fx, depth, mr_v3(0, 0, 0), 16.0f, cls_checker, &depth);
    fx_rng r = {77};
    fx_stats st = {0};
    long long_segments = 0, passed = 0;
    const float comps[] = {0.0f, 1.0f, -1.0f, 0.5f, -0.5f, 2.0f, -2.0f};
    for (int i = 0; i < 20000; i++) {
        mr_vec3 o, d;
        float tmin = 0.0f, tmax = INFINITY;
        if (i & 1) {
            /* exact: dyadic origin on the grid or half grid, dyadic dir */
            o = mr_v3(0.5f * (float)fx_below(&r, 33), 0.5f * (float)fx_below(&r, 33), 0.5f * (float)fx_below(&r, 33));
            d = mr_v3(comps[fx_below(&r, 7)], comps[fx_below(&r, 7)], comps[fx_below(&r, 7)]);
            check_ray_exact(&fx, o, d, tmin, tmax, &st);
        } else {
            fx_random_ray(&fx, &r, i / 2, &o, &d, &tmin, &tmax);
            check_ray(&fx, o, d, tmin, tmax, &st);
        }
        /* the segment inside the cube, by the brute force of the cube */
        const fx_box cube = {0, {0, 0, 0}};
        const double org[3] = {o.x, o.y, o.z}, dir[3] = {d.x, d.y, d.z};
        double t0, t1;
        const double len = sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
        if (fx_slab(&fx.svo, &cube, org, dir, tmin, tmax, &t0, &t1) && (t1 - t0) * len > 1.8) {
            long_segments++;
            HARD_EXPECT(passed, mr_svo_occluded(&fx.svo, o, d, tmin, tmax));
        }
    }
    HARD_CHECK("leaks", passed, "==", 0,
               "segments longer than a cell diagonal that passed through the checkerboard (of %ld)",
               long_segments);
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* ---- rays that start inside a voxel */

static void test_inside_voxel(void **state)
{
    (void)state;
    box_cls bc = {5, {3, 3, 3}, {20, 9, 30}};
    svo_fx fx;
    fx_build(&fx, 5, mr_v3(-1, -1, -1), 2.0f, cls_box, &bc);
    fx_rng r = {5};
    fx_stats st = {0};
    long inside = 0, wrong = 0;
    for (int i = 0; i < 3000; i++) {
        /* a point strictly inside the block */
        const double u = fx_range(&r, 3.01, 19.99), v = fx_range(&r, 3.01, 8.99), w = fx_range(&r, 3.01, 29.99);
        const mr_vec3 o = fx_v3d(-1.0 + u / 16.0, -1.0 + v / 16.0, -1.0 + w / 16.0);
        const mr_vec3 d = (i % 10 == 0) ? mr_v3(0, 0, 0) : fx_random_dir(&r);
        const float tmin = (i & 1) ? 0.0f : 1e-3f / (mr_v3_len(d) > 0 ? mr_v3_len(d) : 1.0f);
        mr_svo_hit h;
        if (i % 10 == 0 || tmin == 0.0f) {
            inside++;
            const bool hit = mr_svo_intersect(&fx.svo, o, d, tmin, INFINITY, &h);
            HARD_EXPECT(wrong, hit && h.t == tmin && h.axis == -1);
        }
        if (i % 10 != 0)
            check_ray(&fx, o, d, tmin, INFINITY, &st);
    }
    /* exactly on a voxel's face, leaving it: the face counts (closed box) */
    mr_svo_hit h;
    const float face = -1.0f + 3.0f / 16.0f;
    const bool hit = mr_svo_intersect(&fx.svo, mr_v3(face, -0.6f, -0.6f), mr_v3(-1, 0, 0), 0.0f, INFINITY, &h);
    HARD_EXPECT(wrong, hit && h.t == 0.0f && h.axis == -1);
    /* zero direction outside every voxel: nothing */
    HARD_EXPECT(wrong, !mr_svo_intersect(&fx.svo, mr_v3(0.9f, 0.9f, -0.99f), mr_v3(0, 0, 0), 0.0f, INFINITY, &h));
    HARD_CHECK("error", wrong, "==", 0,
               "rays from inside a voxel or on its face not hit at tmin (of %ld), zero direction outside hit",
               inside + 1);
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* ---- the deepest level */

static void test_level21_far(void **state)
{
    (void)state;
    const uint32_t m = 1u << 20;
    static uint32_t cells[10][3];
    /* one lone voxel, and a 2x2x2 cluster straddling all three root
     * midplanes, and one at the far corner */
    cells[0][0] = 123457;
    cells[0][1] = 654321;
    cells[0][2] = 1048575;
    int n = 1;
    for (unsigned c = 0; c < 8; c++, n++) {
        cells[n][0] = m - 1 + (c & 1);
        cells[n][1] = m - 1 + ((c >> 1) & 1);
        cells[n][2] = m - 1 + (c >> 2);
    }
    cells[n][0] = cells[n][1] = cells[n][2] = 2 * m - 1;
    n++;
    list_cls lc = {21, (const uint32_t(*)[3])cells, n};
    const mr_vec3 origins[2] = {mr_v3(1e5f, 1e5f, 1e5f), mr_v3(0, 0, 0)};
    fx_stats st = {0};
    long aimed = 0, missed = 0, wrong = 0;
    for (int oi = 0; oi < 2; oi++) {
        svo_fx fx;
        fx_build(&fx, 21, origins[oi], 1.0f, cls_list, &lc);
        assert_int_equal(fx.svo.leaf_count, (uint32_t)n);
        fx_rng r = {19u + (uint64_t)oi};
        const double cell = ldexp(1.0, -21);
        for (int i = 0; i < 3000; i++) {
            const int k = (int)fx_below(&r, (uint32_t)n);
            double c[3];
            c[0] = origins[oi].x + (cells[k][0] + 0.5) * cell;
            c[1] = origins[oi].y + (cells[k][1] + 0.5) * cell;
            c[2] = origins[oi].z + (cells[k][2] + 0.5) * cell;
            /* from up to a cube away, towards the voxel's centre */
            const mr_vec3 u = fx_random_dir(&r);
            const double ul = mr_v3_len(u), dist = fx_range(&r, 0.01, 1.0);
            const mr_vec3 o = fx_v3d(c[0] + dist * u.x / ul, c[1] + dist * u.y / ul, c[2] + dist * u.z / ul);
            const mr_vec3 d = fx_v3d(c[0] - o.x, c[1] - o.y, c[2] - o.z);
            mr_svo_hit h;
            /* float direction: off the centre by ~2^-24 of the distance,
             * well inside the half-voxel 2^-22 */
            aimed++;
            if (!mr_svo_intersect(&fx.svo, o, d, 0.0f, INFINITY, &h)) {
                print_error("miss: voxel %d, origin %d, org %a %a %a dir %a %a %a\n", k, oi, (double)o.x,
                            (double)o.y, (double)o.z, (double)d.x, (double)d.y, (double)d.z);
                missed++;
                continue;
            }
            HARD_EXPECT(wrong, h.level == 21);
            if (k == 0 || k == n - 1)
                HARD_EXPECT(wrong, h.x == cells[k][0] && h.y == cells[k][1] && h.z == cells[k][2]);
            else
                HARD_EXPECT(wrong, h.x >= m - 1 && h.x <= m && h.y >= m - 1 && h.y <= m && h.z >= m - 1 && h.z <= m);
            check_ray(&fx, o, d, 0.0f, INFINITY, &st);
        }
        if (oi == 1) {
            /* exact rays along the cluster's shared faces and edges and
             * through its centre corner (planes at multiples of 2^-21) */
            const float g = (float)ldexp(1.0, -21), mid = (float)m * g;
            const float offs[] = {-1, -0.5f, 0, 0.5f, 1, 1.5f, 2};
            for (size_t a = 0; a < 7; a++)
                for (size_t b = 0; b < 7; b++) {
                    const float p = mid + offs[a] * g, q = mid + offs[b] * g;
                    check_ray_exact(&fx, mr_v3(p, q, -1), mr_v3(0, 0, 1), 0.0f, INFINITY, &st);
                    check_ray_exact(&fx, mr_v3(p, -1, q), mr_v3(0, 1, 0), 0.0f, INFINITY, &st);
                    check_ray_exact(&fx, mr_v3(2, p, q), mr_v3(-1, 0, 0), 0.0f, INFINITY, &st);
                    check_ray_exact(&fx, mr_v3(p - 0.25f, q - 0.25f, mid - 0.25f), mr_v3(1, 1, 1), 0.0f,
                                    INFINITY, &st);
                }
            mr_svo_hit h;
            aimed++;
            const bool hit = mr_svo_intersect(&fx.svo, mr_v3(mid - 0.5f, mid - 0.5f, mid - 0.5f), mr_v3(1, 1, 1),
                                              0.0f, INFINITY, &h);
            HARD_EXPECT(missed, hit);
            if (hit)
                HARD_EXPECT(wrong, h.t == 0.5f - g);
        }
        fx_free(&fx);
    }
    HARD_CHECK("leaks", missed, "==", 0, "rays at level-21 voxels (1e5 from the origin and at it) that missed (of %ld)",
               aimed);
    HARD_CHECK("error", wrong, "==", 0, "hits at another voxel or level than aimed at");
    report_rays(__func__, &st);
}

/* ---- tiny and huge cubes, far away */

static void test_sizes(void **state)
{
    (void)state;
    const struct {
        mr_vec3 origin;
        float size;
        unsigned depth;
    } cases[] = {
        {{0, 0, 0}, 1e-6f, 8},   {{1e-3f, -2e-3f, 0}, 3e-7f, 12}, {{-5e29f, -5e29f, -5e29f}, 1e30f, 6},
        {{1e5f, 1e5f, -1e5f}, 64.0f, 10}, {{3e37f, 0, 0}, 1e37f, 5},
    };
    fx_stats all = {0};
    long fewest_hits = LONG_MAX, nonfinite = 0, bad_bounds = 0;
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        fx_random p = {100 + i, 0.25, 0.2, 2}; /* sparse: ~1.6 split children per node */
        svo_fx fx;
        fx_build(&fx, cases[i].depth, cases[i].origin, cases[i].size, fx_random_cls, &p);
        fx_rng r = {i + 1};
        fx_stats st = {0};
        for (int k = 0; k < 1500; k++) {
            mr_vec3 o, d;
            float tmin, tmax;
            fx_random_ray(&fx, &r, k, &o, &d, &tmin, &tmax);
            check_ray(&fx, o, d, tmin, tmax, &st);
        }
        fewest_hits = st.hits < fewest_hits ? st.hits : fewest_hits;
        float lo[3], hi[3];
        HARD_EXPECT(bad_bounds, mr_svo_bounds(&fx.svo, lo, hi));
        for (int a = 0; a < 3; a++) {
            HARD_EXPECT(nonfinite, isfinite(lo[a]) && isfinite(hi[a]));
            HARD_EXPECT(bad_bounds, lo[a] < hi[a]);
        }
        fx_stats_add(&all, &st);
        fx_free(&fx);
    }
    HARD_CHECK("other", fewest_hits, ">", 0, "hits of 1500 random rays, fewest over 5 cubes (1e-6 .. 1e37)");
    HARD_NONFINITE(nonfinite, "non-finite bounds of the cubes");
    HARD_CHECK("other", bad_bounds, "==", 0, "cubes without bounds or with empty ones");
    report_rays(__func__, &all);
}

/* ---- empty octree, single voxels at every depth */

static void test_empty_and_single(void **state)
{
    (void)state;
    svo_fx fx;
    box_cls none = {3, {0, 0, 0}, {0, 0, 0}};
    fx_build(&fx, 3, mr_v3(0, 0, 0), 1.0f, cls_box, &none);
    assert_int_equal(fx.svo.leaf_count, 0);
    fx_rng r = {1};
    long phantom = 0;
    for (int i = 0; i < 500; i++) {
        mr_vec3 o, d;
        float tmin, tmax;
        fx_random_ray(&fx, &r, i, &o, &d, &tmin, &tmax);
        HARD_EXPECT(phantom, !mr_svo_intersect(&fx.svo, o, d, tmin, tmax, NULL));
        HARD_EXPECT(phantom, !mr_svo_occluded(&fx.svo, o, d, tmin, tmax));
    }
    HARD_CHECK("other", phantom, "==", 0, "hits in the empty octree (500 rays, intersect and occluded)");
    fx_free(&fx);
    fx_stats st = {0};
    long aimed = 0, missed = 0, wrong = 0;
    for (unsigned depth = 1; depth <= MR_SVO_MAX_DEPTH; depth++) {
        uint32_t cell[1][3];
        for (int a = 0; a < 3; a++)
            cell[0][a] = fx_below(&r, 1u << depth);
        list_cls lc = {depth, (const uint32_t(*)[3])cell, 1};
        fx_build(&fx, depth, mr_v3(-0.5f, 0.25f, 8), 2.0f, cls_list, &lc);
        assert_int_equal(fx.svo.leaf_count, 1);
        assert_int_equal(fx.svo.node_count, depth);
        const double w = ldexp(2.0, -(int)depth);
        const mr_vec3 c = fx_v3d(-0.5 + (cell[0][0] + 0.5) * w, 0.25 + (cell[0][1] + 0.5) * w,
                                 8.0 + (cell[0][2] + 0.5) * w);
        for (int i = 0; i < 200; i++) {
            const mr_vec3 u = fx_random_dir(&r);
            const mr_vec3 o = mr_v3_add(c, mr_v3_scale(u, 3.0f / mr_v3_len(u)));
            const mr_vec3 d = fx_sub(c, o);
            mr_svo_hit h;
            aimed++;
            if (mr_svo_intersect(&fx.svo, o, d, 0.0f, INFINITY, &h))
                HARD_EXPECT(wrong, h.level == depth && h.x == cell[0][0] && h.y == cell[0][1] && h.z == cell[0][2]);
            else
                HARD_EXPECT(missed, false);
            check_ray(&fx, o, d, 0.0f, INFINITY, &st);
            mr_vec3 o2, d2;
            float tmin, tmax;
            fx_random_ray(&fx, &r, i, &o2, &d2, &tmin, &tmax);
            check_ray(&fx, o2, d2, tmin, tmax, &st);
        }
        fx_free(&fx);
    }
    HARD_CHECK("leaks", missed, "==", 0, "rays at a single voxel (depths 1-21) that missed it (of %ld)", aimed);
    HARD_CHECK("error", wrong, "==", 0, "hits naming another voxel or level");
    report_rays(__func__, &st);
}

/* ---- tmin / tmax */

static void test_t_range(void **state)
{
    (void)state;
    box_cls bc = {3, {2, 2, 2}, {6, 6, 6}};
    svo_fx fx;
    fx_build(&fx, 3, mr_v3(0, 0, 0), 8.0f, cls_box, &bc);
    const mr_vec3 o = mr_v3(3, 3, -2), d = mr_v3(0, 0, 1);
    mr_svo_hit h;
    int bad = 0;
    /* the block spans t in [4, 8] */
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, 0.0f, INFINITY, &h) && h.t == 4.0f);
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, 0.0f, FLT_MAX, &h) && h.t == 4.0f);
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, -1e30f, INFINITY, &h) && h.t == 4.0f);
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, 0.0f, 4.0f, &h) && h.t == 4.0f); /* closed at tmax */
    HARD_EXPECT(bad, !mr_svo_intersect(&fx.svo, o, d, 0.0f, nextafterf(4.0f, 0.0f), &h));
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, 6.0f, 6.0f, &h) && h.t == 6.0f && h.axis == -1);
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, d, 8.0f, 100.0f, &h) && h.t == 8.0f);
    HARD_EXPECT(bad, !mr_svo_intersect(&fx.svo, o, d, nextafterf(8.0f, 9.0f), 100.0f, &h));
    HARD_EXPECT(bad, !mr_svo_intersect(&fx.svo, o, d, 5.0f, 4.0f, &h)); /* tmax < tmin */
    HARD_EXPECT(bad, !mr_svo_occluded(&fx.svo, o, d, 5.0f, 4.0f));
    /* reversed direction: the block lies behind the origin */
    HARD_EXPECT(bad, !mr_svo_intersect(&fx.svo, o, mr_v3(0, 0, -1), 0.0f, INFINITY, &h));
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, mr_v3(0, 0, -1), -8.0f, INFINITY, &h) && h.t == -8.0f);
    /* huge and tiny direction scales */
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, mr_v3(0, 0, 1e30f), 0.0f, INFINITY, &h) &&
                         h.t == (float)(4.0 / (double)1e30f));
    HARD_EXPECT(bad, mr_svo_intersect(&fx.svo, o, mr_v3(0, 0, 1e-30f), 0.0f, INFINITY, &h) &&
                         h.t == (float)(4.0 / (double)1e-30f));
    /* t past FLT_MAX cannot be reported */
    HARD_EXPECT(bad, !mr_svo_intersect(&fx.svo, o, mr_v3(0, 0, 1e-38f), 0.0f, INFINITY, &h));
    HARD_CHECK("error", bad, "==", 0,
               "rays at the t interval's ends, empty intervals, huge and tiny directions: wrong hit or t (of 15)");
    fx_free(&fx);
}

/* ---- direction components 0, -0, denormal */

static void test_degenerate_dirs(void **state)
{
    (void)state;
    fx_random p = {4242, 0.3, 0.35, 1};
    svo_fx fx;
    fx_build(&fx, 5, mr_v3(0, 0, 0), 1.0f, fx_random_cls, &p);
    fx_rng r = {8};
    fx_stats st = {0};
    const float specials[] = {0.0f, -0.0f, 1e-40f, -1e-40f, FLT_MIN, -FLT_MIN, 1e-45f, 1.0f, -1.0f, 0.3f};
    long nan_hits = 0;
    for (int i = 0; i < 6000; i++) {
        mr_vec3 o = fx_cube_point(&fx.svo, fx_range(&r, -0.2, 1.2), fx_range(&r, -0.2, 1.2), fx_range(&r, -0.2, 1.2));
        if (i & 1)
            o = fx_leaf_point(&fx, &r); /* on faces, edges, corners */
        const mr_vec3 d = mr_v3(specials[fx_below(&r, 10)], specials[fx_below(&r, 10)], specials[fx_below(&r, 10)]);
        float tmin = 0.0f;
        check_ray(&fx, o, d, tmin, INFINITY, &st);
        mr_svo_hit h;
        if (mr_svo_intersect(&fx.svo, o, d, tmin, INFINITY, &h))
            HARD_EXPECT(nan_hits, !(isnan(h.t) || isnan(h.ng.x) || isnan(h.ng.y) || isnan(h.ng.z)));
    }
    HARD_NONFINITE(nan_hits, "NaN hits of rays with 0, -0 and denormal direction components (of %ld)", st.rays);
    report_rays(__func__, &st);
    fx_free(&fx);
}

/* ---- non-finite input: no hit, no crash, hit untouched */

static void test_nonfinite(void **state)
{
    (void)state;
    box_cls bc = {3, {0, 0, 0}, {8, 8, 8}};
    svo_fx fx;
    fx_build(&fx, 3, mr_v3(0, 0, 0), 1.0f, cls_box, &bc); /* root leaf: everything inside hits */
    const float bad[] = {NAN, INFINITY, -INFINITY};
    mr_svo_hit h;
    int taken = 0, queries = 0; /* non-finite inputs answered with a hit or a changed record */
    for (size_t b = 0; b < 3; b++) {
        for (int a = 0; a < 3; a++) {
            float o[3] = {0.5f, 0.5f, 0.5f}, d[3] = {0.0f, 0.0f, 1.0f};
            o[a] = bad[b];
            memset(&h, 0x5a, sizeof h);
            const mr_svo_hit before = h;
            HARD_EXPECT(taken, !mr_svo_intersect(&fx.svo, mr_v3(o[0], o[1], o[2]), mr_v3(d[0], d[1], d[2]), 0.0f,
                                                 INFINITY, &h));
            HARD_EXPECT(taken, memcmp(&h, &before, sizeof h) == 0);
            o[a] = 0.5f;
            d[a] = bad[b];
            HARD_EXPECT(taken, !mr_svo_intersect(&fx.svo, mr_v3(o[0], o[1], o[2]), mr_v3(d[0], d[1], d[2]), 0.0f,
                                                 INFINITY, &h));
            HARD_EXPECT(taken, !mr_svo_occluded(&fx.svo, mr_v3(o[0], o[1], o[2]), mr_v3(d[0], d[1], d[2]), 0.0f,
                                                INFINITY));
            queries += 3;
        }
        HARD_EXPECT(taken, !mr_svo_intersect(&fx.svo, mr_v3(0.5f, 0.5f, -1), mr_v3(0, 0, 1), bad[b], 10.0f, &h));
        queries++;
    }
    HARD_EXPECT(taken, !mr_svo_intersect(&fx.svo, mr_v3(0.5f, 0.5f, -1), mr_v3(0, 0, 1), 0.0f, NAN, &h));
    /* a cube with a broken size */
    fx.svo.size = NAN;
    HARD_EXPECT(taken, !mr_svo_intersect(&fx.svo, mr_v3(0.5f, 0.5f, -1), mr_v3(0, 0, 1), 0.0f, INFINITY, &h));
    fx.svo.size = 0.0f;
    HARD_EXPECT(taken, !mr_svo_occluded(&fx.svo, mr_v3(0.5f, 0.5f, -1), mr_v3(0, 0, 1), 0.0f, INFINITY));
    queries += 3;
    HARD_CHECK("nan", taken, "==", 0,
               "queries with a NaN or Inf origin, direction, t or cube size that hit or touched the hit (of %d)",
               queries);
    fx_free(&fx);
}

/* ---- corrupted child indices: skipped, never read out of bounds (the
 * ASan build checks the "never") */

static void test_corrupt_indices(void **state)
{
    (void)state;
    fx_random p = {99, 0.3, 0.35, 1};
    svo_fx fx;
    fx_build(&fx, 6, mr_v3(0, 0, 0), 1.0f, fx_random_cls, &p);
    for (uint32_t n = 0; n < fx.svo.node_count; n += 3) {
        fx.svo.first_leaf[n] = fx.svo.leaf_count - 1u + n % 5u;
        fx.svo.first_node[n] = fx.svo.node_count - 1u + n % 7u;
    }
    fx_rng r = {3};
    long beyond = 0;
    for (int i = 0; i < 3000; i++) {
        mr_vec3 o, d;
        float tmin, tmax;
        fx_random_ray(&fx, &r, i, &o, &d, &tmin, &tmax);
        mr_svo_hit h;
        if (mr_svo_intersect(&fx.svo, o, d, tmin, tmax, &h))
            HARD_EXPECT(beyond, h.leaf < fx.svo.leaf_count);
        (void)mr_svo_occluded(&fx.svo, o, d, tmin, tmax);
    }
    /* reading out of bounds stops the program under ASan (make hard) */
    HARD_CHECK("other", beyond, "==", 0, "hits naming a leaf beyond the octree (3000 rays, corrupt child indices)");
    fx_free(&fx);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_block_axis_parallel),
        cmocka_unit_test(test_block_diagonal),
        cmocka_unit_test(test_edge_and_corner_contacts),
        cmocka_unit_test(test_checkerboard),
        cmocka_unit_test(test_inside_voxel),
        cmocka_unit_test(test_level21_far),
        cmocka_unit_test(test_sizes),
        cmocka_unit_test(test_empty_and_single),
        cmocka_unit_test(test_t_range),
        cmocka_unit_test(test_degenerate_dirs),
        cmocka_unit_test(test_nonfinite),
        cmocka_unit_test(test_corrupt_indices),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
