/*
 * test_svo_trace.c - the sparse voxel octree ray caster (core/kinds/svo/svo_trace.h)
 * against a brute force over every leaf's box, on random sparse octrees of
 * depth 1..8, 12 and 21 (some far from the origin), with random rays from
 * outside and inside, axis-parallel rays (also lying exactly on cell
 * planes) and rays aimed at voxel corners, edges and faces; plus the root
 * leaf, the empty octree, mr_svo_bounds, subtrees and their boxes, casts
 * with a level of detail (mr_svo_lod: against the octree cut at one level,
 * and against a brute force of the rule where the bound varies along the
 * ray), and a one-off throughput figure.
 *
 * The harness (tests/support/svo_fixture.h: an octree builder from a
 * classification function, the brute force and the comparison of one ray)
 * is shared with tests/hard/test_svo_hard.c, so both use the same oracle.
 *
 * Brute force: each leaf's closed box, its planes at origin + k * size *
 * 2^-21 (k the integer finest-grid position), slab-tested in double with
 * divisions (the traversal multiplies by 1 / dir and adds in another order,
 * so the two round differently, by a few double ulps).
 *
 * Tolerance (check_ray): the traversal reports t as a float, so its t
 * matches the brute force's to within float rounding of t plus the double
 * differences above: tol = 4 * FLT_EPSILON * (|t| + size / |dir|), i.e. a
 * few float ulps relative to the cube size. Within tol:
 *  - the traversal's leaf is accepted when its box's entry t is within tol
 *    of the nearest entry over all boxes (ties: rays through a face, edge or
 *    corner shared by two leaves may report either);
 *  - a box whose interval is shorter than tol is a graze: the two sides may
 *    disagree on it by rounding, so a miss is accepted only when every box
 *    the brute force hits is such a graze, and a hit on a graze only when
 *    no box is entered properly before it.
 * With exact arithmetic (dyadic cube, rays with dyadic origins and
 * directions whose planes' t are exact: check_ray_exact) both compute the
 * same t exactly and grazes count as hits on both sides, so the comparison
 * is exact: same hit/miss, same t bit for bit.
 */
#include "util/clock.h"
#include "../support/svo_fixture.h"


/* ---- tests */

static void run_random(unsigned depth, uint64_t seed, fx_random params, mr_vec3 origin, float size, int rays)
{
    svo_fx fx;
    params.seed = seed;
    fx_build(&fx, depth, origin, size, fx_random_cls, &params);
    fx_rng r = {seed * 7919u + depth};
    fx_stats st = {0};
    for (int i = 0; i < rays; i++) {
        mr_vec3 o, d;
        float tmin, tmax;
        fx_random_ray(&fx, &r, i, &o, &d, &tmin, &tmax);
        check_ray(&fx, o, d, tmin, tmax, &st);
    }
    /* the ray mix must actually exercise hits (except for empty trees) */
    if (fx.svo.leaf_count > 0)
        assert_true(st.hits > 0);
    fx_free(&fx);
}

static void test_random_shallow(void **state)
{
    (void)state;
    for (unsigned depth = 1; depth <= 8; depth++) {
        for (uint64_t seed = 1; seed <= 6; seed++) {
            /* dense near the root for small depths, sparse further down */
            fx_random p = {0, 0.25, depth <= 4 ? 0.4 : 0.2, seed % 3 == 0 ? 2u : 0u};
            const mr_vec3 origin = seed % 2 ? mr_v3(0, 0, 0) : mr_v3(-0.75f, 0.3f, 2.5f);
            const float size = seed % 2 ? 1.0f : 3.0f;
            run_random(depth, seed * 131u + depth, p, origin, size, 1500);
        }
    }
}

static void test_random_deep(void **state)
{
    (void)state;
    /* sparse: ~1.4 split children per interior node, so depth 21 stays small */
    const fx_random p = {0, 0.15, 0.17, 2};
    run_random(12, 5, p, mr_v3(0, 0, 0), 1.0f, 3000);
    run_random(12, 6, p, mr_v3(-3, 7, 1), 10.0f, 3000);
    run_random(21, 7, p, mr_v3(0, 0, 0), 1.0f, 3000);
    run_random(21, 8, p, mr_v3(1e5f, -1e5f, 1e5f), 1.0f, 3000);
    run_random(21, 9, p, mr_v3(1e5f, 1e5f, 1e5f), 1000.0f, 3000);
}

/* A ray through the cube at (-2, 0, 4) of edge 4 of a depth-`depth`
 * octree, with a dyadic origin and a direction in {0, +-1, +-2, +-0.5}:
 * every plane t is exact. Origins on grid points (also outside the cube)
 * or half-cell points make rays run along faces and edges and through
 * corners. */
static void grid_ray(fx_rng *r, unsigned depth, mr_vec3 *org, mr_vec3 *dir)
{
    static const float comps[] = {0.0f, -0.0f, 1.0f, -1.0f, 2.0f, -2.0f, 0.5f, -0.5f};
    const float n = (float)(1u << depth), base[3] = {-2.0f, 0.0f, 4.0f};
    float ov[3], dv[3];
    for (int a = 0; a < 3; a++) {
        ov[a] = base[a] + 4.0f * (float)((int)fx_below(r, (uint32_t)(3 * n)) - (int)n) / n;
        if (fx_below(r, 4) == 0)
            ov[a] += 2.0f / n;
        dv[a] = comps[fx_below(r, 8)];
    }
    *org = mr_v3(ov[0], ov[1], ov[2]);
    *dir = mr_v3(dv[0], dv[1], dv[2]);
}

/* Dyadic cube, grid rays (grid_ray): every plane t is exact, so the
 * comparison is exact. */
static void test_exact_grid_rays(void **state)
{
    (void)state;
    for (unsigned depth = 2; depth <= 5; depth++) {
        svo_fx fx;
        fx_random p = {depth * 1000u + 3u, 0.3, 0.35, 1};
        fx_build(&fx, depth, mr_v3(-2, 0, 4), 4.0f, fx_random_cls, &p);
        fx_rng r = {depth};
        for (int i = 0; i < 4000; i++) {
            mr_vec3 org, dir;
            grid_ray(&r, depth, &org, &dir);
            float tmin = 0.0f, tmax = INFINITY;
            if (fx_below(&r, 3) == 0) {
                tmin = (float)fx_below(&r, 8) / 4.0f;
                tmax = tmin + (float)fx_below(&r, 16) / 4.0f;
            }
            check_ray_exact(&fx, org, dir, tmin, tmax, NULL);
        }
        fx_free(&fx);
    }
}

static int cls_root_leaf(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx, (void)level, (void)x, (void)y, (void)z;
    return FX_LEAF;
}

static int cls_empty(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx, (void)level, (void)x, (void)y, (void)z;
    return FX_EMPTY;
}

static void test_root_leaf_and_empty(void **state)
{
    (void)state;
    svo_fx fx;
    fx_build(&fx, 3, mr_v3(1, 2, 3), 2.0f, cls_root_leaf, NULL);
    assert_int_equal(fx.svo.node_count, 0);
    assert_int_equal(fx.svo.leaf_count, 1);
    mr_svo_hit h;
    /* from -x: enters the cube's face x = 1 at t = 1 */
    assert_true(mr_svo_intersect(&fx.svo, mr_v3(0, 3, 4), mr_v3(1, 0, 0), 0.0f, INFINITY, &h));
    assert_true(h.t == 1.0f);
    assert_int_equal(h.leaf, 0);
    assert_int_equal(h.level, 0);
    assert_int_equal(h.axis, 0);
    assert_true(h.ng.x == -1.0f);
    /* from inside */
    assert_true(mr_svo_intersect(&fx.svo, mr_v3(2, 3, 4), mr_v3(0, 0, -1), 0.5f, INFINITY, &h));
    assert_true(h.t == 0.5f);
    assert_int_equal(h.axis, -1);
    /* segment that ends before the cube */
    assert_false(mr_svo_intersect(&fx.svo, mr_v3(0, 3, 4), mr_v3(1, 0, 0), 0.0f, 0.99f, &h));
    assert_false(mr_svo_occluded(&fx.svo, mr_v3(0, 3, 4), mr_v3(1, 0, 0), 0.0f, 0.99f));
    fx_rng r = {3};
    fx_stats st = {0};
    for (int i = 0; i < 500; i++) {
        mr_vec3 o, d;
        float tmin, tmax;
        fx_random_ray(&fx, &r, i, &o, &d, &tmin, &tmax);
        check_ray(&fx, o, d, tmin, tmax, &st);
    }
    float lo[3], hi[3];
    assert_true(mr_svo_bounds(&fx.svo, lo, hi));
    assert_true(lo[0] == 1.0f && lo[1] == 2.0f && lo[2] == 3.0f);
    assert_true(hi[0] == 3.0f && hi[1] == 4.0f && hi[2] == 5.0f);
    fx_free(&fx);

    fx_build(&fx, 5, mr_v3(0, 0, 0), 1.0f, cls_empty, NULL);
    assert_int_equal(fx.svo.leaf_count, 0);
    assert_false(mr_svo_intersect(&fx.svo, mr_v3(0.5f, 0.5f, -1), mr_v3(0, 0, 1), 0.0f, INFINITY, &h));
    assert_false(mr_svo_occluded(&fx.svo, mr_v3(0.5f, 0.5f, 0.5f), mr_v3(0, 0, 1), 0.0f, INFINITY));
    assert_false(mr_svo_bounds(&fx.svo, lo, hi));
    assert_false(mr_svo_intersect(NULL, mr_v3(0, 0, 0), mr_v3(0, 0, 1), 0.0f, INFINITY, &h));
    fx_free(&fx);
}

/* One child of the root occupied: bounds shrink to that octant (rounded
 * outwards), and always contain every leaf box. */
static int cls_one_octant(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx;
    if (level == 0)
        return FX_SPLIT;
    if (level == 1)
        return (x == 1 && y == 0 && z == 1) ? FX_SPLIT : FX_EMPTY;
    return ((x + y + z) % 3 == 0) ? FX_LEAF : FX_EMPTY;
}

static void test_bounds(void **state)
{
    (void)state;
    svo_fx fx;
    fx_build(&fx, 4, mr_v3(0.1f, -0.3f, 7.0f), 0.7f, cls_one_octant, NULL);
    float lo[3], hi[3];
    assert_true(mr_svo_bounds(&fx.svo, lo, hi));
    const double o[3] = {0.1f, -0.3f, 7.0f}, s = 0.7f;
    const double elo[3] = {o[0] + 0.5 * s, o[1], o[2] + 0.5 * s};
    const double ehi[3] = {o[0] + s, o[1] + 0.5 * s, o[2] + s};
    for (int a = 0; a < 3; a++) {
        /* outward rounding: at most one float ulp outside the exact plane */
        assert_true((double)lo[a] <= elo[a] && (double)nextafterf(lo[a], INFINITY) > elo[a]);
        assert_true((double)hi[a] >= ehi[a] && (double)nextafterf(hi[a], -INFINITY) < ehi[a]);
    }
    for (uint32_t i = 0; i < fx.svo.leaf_count; i++) {
        for (int a = 0; a < 3; a++) {
            double bl, bh;
            fx_box_planes(&fx.svo, &fx.boxes[i], a, &bl, &bh);
            assert_true((double)lo[a] <= bl && bh <= (double)hi[a]);
        }
    }
    fx_free(&fx);
}

/* Two level-4 leaves, at cells (3, 5, 2) and (6, 4, 9) of the 16^3 grid:
 * their box is a sliver of the root's halves. */
static const uint32_t TWO_CELLS[2][3] = {{3, 5, 2}, {6, 4, 9}};

static int cls_two_cells(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx;
    for (int k = 0; k < 2; k++) {
        const unsigned shift = 4 - level;
        if (TWO_CELLS[k][0] >> shift == x && TWO_CELLS[k][1] >> shift == y && TWO_CELLS[k][2] >> shift == z)
            return level == 4 ? FX_LEAF : FX_SPLIT;
    }
    return FX_EMPTY;
}

/* The leaves' box (mr_svo_fit_occupied on an octree put together by hand,
 * mr_svo_build on its keys): bounds are that box rounded outwards by at
 * most an ulp, where the halves of the root were 4x-8x its volume. */
static void test_occupied_bounds(void **state)
{
    (void)state;
    svo_fx fx;
    const mr_vec3 origin = mr_v3(0.1f, -0.3f, 7.0f);
    fx_build(&fx, 4, origin, 0.7f, cls_two_cells, NULL);
    assert_int_equal(fx.svo.leaf_count, 2);
    assert_false(fx.svo.has_occupied);
    float halves_lo[3], halves_hi[3], lo[3], hi[3];
    assert_true(mr_svo_bounds(&fx.svo, halves_lo, halves_hi));
    mr_error err = {0};
    assert_int_equal(mr_svo_fit_occupied(&fx.svo, &err), MR_OK);
    assert_true(fx.svo.has_occupied);
    assert_true(mr_svo_bounds(&fx.svo, lo, hi));
    const double o[3] = {origin.x, origin.y, origin.z}, cell = 0.7f / 16.0;
    const uint32_t elo[3] = {3, 4, 2}, ehi[3] = {7, 6, 10};
    double shrunk = 1;
    for (int a = 0; a < 3; a++) {
        const double l = o[a] + elo[a] * cell, h = o[a] + ehi[a] * cell;
        assert_int_equal(fx.svo.occupied_lo[a], elo[a]);
        assert_int_equal(fx.svo.occupied_hi[a], ehi[a]);
        assert_true((double)lo[a] <= l && (double)nextafterf(lo[a], INFINITY) > l);
        assert_true((double)hi[a] >= h && (double)nextafterf(hi[a], -INFINITY) < h);
        shrunk *= ((double)hi[a] - lo[a]) / ((double)halves_hi[a] - halves_lo[a]);
    }
    assert_true(shrunk < 0.25);

    /* the builder fills the same box from the keys */
    mr_svo_key keys[2];
    mr_svo built;
    assert_int_equal(mr_svo_collect_keys(&fx.svo, keys, NULL, &err), MR_OK);
    mr_svo_attr attr = {0};
    assert_int_equal(mr_svo_build(keys, NULL, 2, 4, origin, 0.7f, &attr, 1, 1, &built, &err), MR_OK);
    assert_true(built.has_occupied);
    for (int a = 0; a < 3; a++) {
        assert_int_equal(built.occupied_lo[a], elo[a]);
        assert_int_equal(built.occupied_hi[a], ehi[a]);
    }
    mr_svo_free(&built);
    fx_free(&fx);
}

/* Whether the face of `axis` that the ray enters leaf h through lies at
 * h.t (in double: the grid rays' planes are exact). */
static bool enters_through(const mr_svo *o, const mr_svo_hit *h, mr_vec3 org, mr_vec3 dir, int axis)
{
    if (axis < 0)
        return false;
    const double oo[3] = {org.x, org.y, org.z}, d[3] = {dir.x, dir.y, dir.z};
    const double c[3] = {o->origin.x, o->origin.y, o->origin.z}, xyz[3] = {h->x, h->y, h->z};
    const double cell = ldexp((double)o->size, -(int)h->level);
    const double plane = c[axis] + (xyz[axis] + (d[axis] < 0 ? 1 : 0)) * cell;
    return d[axis] != 0 && (float)((plane - oo[axis]) / d[axis]) == h->t;
}

/* A ray through the subtrees, one after the other in the given order (as
 * Embree might visit them), keeping a hit at the held t only when its
 * subtree comes first in mr_svo_subtree_order, as the svo kind does. */
static size_t equal_t; /* hits at the held t in another subtree: the order rule decided */

static bool trace_subtrees(const mr_svo *o, const mr_svo_subtree *st, size_t n, bool reverse, mr_vec3 org,
                           mr_vec3 dir, float tmin, float tmax, mr_svo_hit *best)
{
    bool found = false;
    size_t held = 0;
    for (size_t k = 0; k < n; k++) {
        const size_t i = reverse ? n - 1 - k : k;
        mr_svo_hit h;
        if (!mr_svo_intersect_subtree(o, &st[i], org, dir, tmin, tmax, &h))
            continue;
        equal_t += found && h.t == tmax;
        if (found && h.t == tmax && mr_svo_subtree_order(&st[held], dir) < mr_svo_subtree_order(&st[i], dir))
            continue;
        *best = h;
        found = true;
        held = i;
        tmax = h.t;
    }
    return found;
}

/* Tracing from subtrees (mr_svo_subtrees) finds what one walk from the
 * root finds: the same t bit for bit and the same leaf, in whatever order
 * the subtrees are visited; the entry axis may differ only at an edge or
 * corner (both faces there lie at t). Grid rays run along faces and
 * through edges and corners, where subtrees meet at one t. */
static void test_subtrees(void **state)
{
    (void)state;
    size_t rays = 0, hits = 0, ties = 0;
    for (unsigned depth = 3; depth <= 6; depth++) {
        svo_fx fx;
        fx_random p = {depth * 977u + 5u, 0.35, 0.5, 2};
        fx_build(&fx, depth, mr_v3(-2, 0, 4), 4.0f, fx_random_cls, &p);
        const mr_svo *o = &fx.svo;
        if (o->node_count == 0) {
            fx_free(&fx);
            continue;
        }
        uint32_t counts[8];
        mr_error cerr = {0};
        assert_int_equal(mr_svo_subtree_counts(o, depth, counts, &cerr), MR_OK);
        for (unsigned level = 0; level <= depth; level++) { /* one walk counts what each level gives */
            mr_svo_subtree *all;
            uint32_t count;
            assert_int_equal(mr_svo_subtrees(o, level, &all, &count, &cerr), MR_OK);
            assert_int_equal(counts[level], count);
            free(all);
        }
        for (unsigned level = 1; level + 1 < depth; level++) {
            mr_svo_subtree *st;
            uint32_t n;
            mr_error err = {0};
            assert_int_equal(mr_svo_subtrees(o, level, &st, &n, &err), MR_OK);
            fx_rng r = {depth * 31u + level};
            for (int i = 0; i < 3000; i++) {
                mr_vec3 org, dir;
                grid_ray(&r, depth, &org, &dir);
                mr_svo_hit whole, sub[2];
                const bool w = mr_svo_intersect(o, org, dir, 0.0f, INFINITY, &whole);
                bool any = false;
                for (size_t k = 0; k < n; k++)
                    any = any || mr_svo_occluded_subtree(o, &st[k], org, dir, 0.0f, INFINITY);
                assert_int_equal(any, mr_svo_occluded(o, org, dir, 0.0f, INFINITY));
                for (int rev = 0; rev < 2; rev++) {
                    const bool f = trace_subtrees(o, st, n, rev, org, dir, 0.0f, INFINITY, &sub[rev]);
                    assert_int_equal(f, w);
                    if (!w)
                        continue;
                    const mr_svo_hit *h = &sub[rev];
                    if (memcmp(&h->t, &whole.t, sizeof h->t) || h->leaf != whole.leaf || h->level != whole.level ||
                        h->x != whole.x || h->y != whole.y || h->z != whole.z)
                        fail_msg("depth %u, subtrees at %u, ray %d: subtree hit (t %a, leaf %u) is not the walk's "
                                 "(t %a, leaf %u)", depth, level, i, (double)h->t, h->leaf, (double)whole.t,
                                 whole.leaf);
                    if (h->axis != whole.axis) {
                        ties++;
                        assert_true(enters_through(o, h, org, dir, h->axis));
                        assert_true(enters_through(o, &whole, org, dir, whole.axis));
                    }
                }
                rays++;
                hits += w;
            }
            free(st);
        }
        fx_free(&fx);
    }
    print_message("[ subtrees ] %zu rays, %zu hits, %zu decided by the order at one t, %zu entry axes told apart "
                  "at an edge or corner\n", rays, hits, equal_t, ties);
    /* the mix has to reach leaves often, and subtrees meeting at one t */
    assert_true(hits > rays / 10);
    assert_true(equal_t > 0);
}

/* mr_svo_intersect_rays gives each ray what its own query gives, bit for
 * bit: hit or miss, t, leaf, voxel, entry axis and normal, and leaves a
 * missed ray's hit untouched; with hit NULL, mr_svo_occluded's answer.
 * Batches of 1 to 32 rays (more than MR_SVO_RAYS take turns in groups),
 * over the whole octree and over each of its subtrees, with random rays
 * (inside and outside, axis-parallel, on cell planes) and grid rays on a
 * dyadic cube (in midplanes they are parallel to: the walk's tie case). */
static bool same_hit(const mr_svo_hit *a, const mr_svo_hit *b)
{
    return !memcmp(&a->t, &b->t, sizeof a->t) && a->leaf == b->leaf && a->level == b->level && a->x == b->x &&
           a->y == b->y && a->z == b->z && a->axis == b->axis && !memcmp(&a->ng, &b->ng, sizeof a->ng);
}

static size_t negative_zero_t; /* hits at t = -0: which of two equal zeros a max keeps shows */

static void check_batch(const mr_svo *o, const mr_svo_subtree *st, unsigned n, const mr_vec3 *org,
                        const mr_vec3 *dir, const float *tmin, const float *tmax, size_t *hits)
{
    mr_svo_hit together[32], alone;
    memset(together, 0xa5, sizeof together);
    const uint32_t mask = mr_svo_intersect_rays(o, st, n, org, dir, tmin, tmax, NULL, together);
    const uint32_t any = mr_svo_intersect_rays(o, st, n, org, dir, tmin, tmax, NULL, NULL);
    for (unsigned i = 0; i < n; i++) {
        const bool h = st ? mr_svo_intersect_subtree(o, st, org[i], dir[i], tmin[i], tmax[i], &alone)
                          : mr_svo_intersect(o, org[i], dir[i], tmin[i], tmax[i], &alone);
        const bool occ = st ? mr_svo_occluded_subtree(o, st, org[i], dir[i], tmin[i], tmax[i])
                            : mr_svo_occluded(o, org[i], dir[i], tmin[i], tmax[i]);
        assert_int_equal(mask >> i & 1u, h);
        assert_int_equal(any >> i & 1u, occ);
        if (h) {
            if (!same_hit(&together[i], &alone))
                fail_msg("ray %u of %u: together t %a leaf %u, alone t %a leaf %u", i, n, (double)together[i].t,
                         together[i].leaf, (double)alone.t, alone.leaf);
            ++*hits;
            negative_zero_t += alone.t == 0.0f && signbit(alone.t);
        } else {
            const unsigned char *b = (const unsigned char *)&together[i];
            for (size_t k = 0; k < sizeof together[i]; k++)
                assert_int_equal(b[k], 0xa5);
        }
    }
    if (n < 32)
        assert_int_equal(mask >> n, 0); /* no bit for a ray not asked about */
}

static void test_rays_together(void **state)
{
    (void)state;
    size_t batches = 0, hits = 0;
    for (unsigned depth = 3; depth <= 12; depth += 3) {
        svo_fx fx;
        fx_random p = {depth * 613u + 1u, 0.25, depth < 9 ? 0.35 : 0.17, 2};
        const bool grid = depth <= 6; /* the dyadic cube grid_ray aims at */
        fx_build(&fx, depth, grid ? mr_v3(-2, 0, 4) : mr_v3(-0.75f, 0.3f, 2.5f), grid ? 4.0f : 3.0f,
                 fx_random_cls, &p);
        const mr_svo *o = &fx.svo;
        mr_svo_subtree *st = NULL;
        uint32_t nst = 0;
        mr_error err = {0};
        assert_int_equal(mr_svo_subtrees(o, depth / 2, &st, &nst, &err), MR_OK);
        fx_rng r = {depth * 97u + 3u};
        for (unsigned n = 1; n <= 32; n++) {
            mr_vec3 org[32], dir[32];
            float tmin[32], tmax[32];
            for (unsigned i = 0; i < n; i++) {
                if (grid && fx_below(&r, 2)) {
                    grid_ray(&r, depth, &org[i], &dir[i]);
                    tmin[i] = 0.0f;
                    tmax[i] = INFINITY;
                } else {
                    fx_random_ray(&fx, &r, (int)(n * 32 + i), &org[i], &dir[i], &tmin[i], &tmax[i]);
                }
            }
            check_batch(o, NULL, n, org, dir, tmin, tmax, &hits);
            for (uint32_t k = 0; k < nst; k++)
                check_batch(o, &st[k], n, org, dir, tmin, tmax, &hits);
            batches += 1 + nst;
        }
        /* Packets from grid points inside the cube, every direction
         * component nonzero and of one sign per batch: rays starting on a
         * midplane, where a child's entry t is +0 or -0. */
        for (int b = 0; grid && b < 64; b++) {
            static const float comps[] = {1.0f, 2.0f, 0.5f}, corner[3] = {-2.0f, 0.0f, 4.0f}; /* the cube's */
            const unsigned m = fx_below(&r, 8), cells = 1u << depth;
            mr_vec3 org[16], dir[16];
            float tmin[16], tmax[16];
            for (unsigned i = 0; i < 16; i++) {
                float ov[3], dv[3];
                for (int a = 0; a < 3; a++) {
                    ov[a] = corner[a] + 4.0f * (float)fx_below(&r, cells + 1) / (float)cells;
                    dv[a] = comps[fx_below(&r, 3)] * (m >> a & 1u ? -1.0f : 1.0f);
                }
                org[i] = mr_v3(ov[0], ov[1], ov[2]);
                dir[i] = mr_v3(dv[0], dv[1], dv[2]);
                tmin[i] = 0.0f;
                tmax[i] = INFINITY;
            }
            check_batch(o, NULL, 16, org, dir, tmin, tmax, &hits);
            batches++;
        }
        free(st);
        fx_free(&fx);
    }
    print_message("[ rays together ] %zu batches, %zu hits, %zu at t = -0\n", batches, hits, negative_zero_t);
    assert_true(hits > 1000);
    assert_true(negative_zero_t > 0);
}

/* The same leaves through the real builder (mr_svo_build: breadth-first
 * nodes, leaves by level and code) must trace identically to the fixture's
 * depth-first layout: the walk order depends on geometry only, so hit/miss,
 * t (bit for bit) and the voxel agree, and leaf_keys names the voxel. */
static int cmp_key(const void *pa, const void *pb)
{
    const mr_svo_key *a = pa, *b = pb;
    if (a->code != b->code)
        return a->code < b->code ? -1 : 1;
    return a->level < b->level ? -1 : a->level > b->level;
}

/* The fixture's leaves through the real builder into *built (free it with
 * mr_svo_free): no interior node without leaves below, which the fixture
 * can have. */
static void build_fixture(const svo_fx *fx, mr_svo *built)
{
    const unsigned depth = fx->svo.depth;
    const uint32_t n = fx->svo.leaf_count;
    mr_svo_key *keys = calloc(n ? n : 1, sizeof *keys);
    assert_non_null(keys);
    for (uint32_t i = 0; i < n; i++) {
        const fx_box *b = &fx->boxes[i];
        const unsigned sh = depth - b->level;
        keys[i].code = mr_morton_encode(b->xyz[0] << sh, b->xyz[1] << sh, b->xyz[2] << sh);
        keys[i].level = b->level;
    }
    qsort(keys, n, sizeof *keys, cmp_key);
    const mr_svo_attr pal = {{128, 128, 128}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}};
    mr_error err;
    assert_int_equal(mr_svo_build(keys, NULL, n, depth, fx->svo.origin, fx->svo.size, &pal, 1, 1, built, &err),
                     MR_OK);
    assert_int_equal(built->leaf_count, n);
    free(keys);
}

static void crosscheck_build(unsigned depth, fx_random p, mr_vec3 origin, float size, int rays)
{
    svo_fx fx;
    fx_build(&fx, depth, origin, size, fx_random_cls, &p);
    const uint32_t n = fx.svo.leaf_count;
    mr_svo built;
    build_fixture(&fx, &built);
    assert_non_null(built.leaf_keys);
    fx_rng r = {depth * 31u + 7u};
    long hits = 0;
    for (int i = 0; i < rays; i++) {
        mr_vec3 o, d;
        float tmin, tmax;
        fx_random_ray(&fx, &r, i, &o, &d, &tmin, &tmax);
        mr_svo_hit a, b;
        const bool ha = mr_svo_intersect(&fx.svo, o, d, tmin, tmax, &a);
        const bool hb = mr_svo_intersect(&built, o, d, tmin, tmax, &b);
        assert_int_equal(ha, hb);
        assert_int_equal(hb, mr_svo_occluded(&built, o, d, tmin, tmax));
        if (!ha)
            continue;
        hits++;
        assert_true(a.t == b.t);
        assert_int_equal(a.level, b.level);
        assert_int_equal(a.x, b.x);
        assert_int_equal(a.y, b.y);
        assert_int_equal(a.z, b.z);
        assert_int_equal(a.axis, b.axis);
        const unsigned sh = depth - b.level;
        assert_true(built.leaf_keys[b.leaf].code == mr_morton_encode(b.x << sh, b.y << sh, b.z << sh));
        assert_int_equal(built.leaf_keys[b.leaf].level, b.level);
    }
    assert_true(n == 0 || hits > 0);
    mr_svo_free(&built);
    fx_free(&fx);
}

static void test_build_crosscheck(void **state)
{
    (void)state;
    const fx_random dense = {11, 0.3, 0.4, 1}, sparse = {12, 0.15, 0.17, 2};
    crosscheck_build(1, dense, mr_v3(0, 0, 0), 1.0f, 500);
    crosscheck_build(4, dense, mr_v3(-1, 2, 0.5f), 2.0f, 2000);
    crosscheck_build(8, sparse, mr_v3(0, 0, 0), 1.0f, 2000);
    crosscheck_build(21, sparse, mr_v3(1e5f, 0, -3), 4.0f, 2000);
}

/* Shell of a sphere at depth 10: leaves are the finest cells the sphere's
 * surface passes through (about a million). */
typedef struct fx_shell {
    double c, r; /* centre (all axes) and radius, in finest cells of this depth */
    unsigned depth;
} fx_shell;

static int cls_shell(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const fx_shell *s = ctx;
    const double w = ldexp(1.0, (int)(s->depth - level));
    const double p[3] = {x * w, y * w, z * w};
    double dmin = 0.0, dmax = 0.0;
    for (int a = 0; a < 3; a++) {
        const double lo = p[a] - s->c, hi = p[a] + w - s->c;
        const double n = lo > 0 ? lo : hi < 0 ? -hi : 0.0;
        const double f = fmax(fabs(lo), fabs(hi));
        dmin += n * n;
        dmax += f * f;
    }
    if (dmin > s->r * s->r || dmax < s->r * s->r)
        return FX_EMPTY;
    return FX_SPLIT;
}

/* Whether the fixture's leaf b lies below subtree s. */
static bool leaf_below(const fx_box *b, const mr_svo_subtree *s)
{
    if (b->level <= s->level)
        return false;
    for (int a = 0; a < 3; a++)
        if (b->xyz[a] >> (b->level - s->level) != s->xyz[a])
            return false;
    return true;
}

/* A subtree's cells (mr_svo_subtree_cells) `below` levels down, on random
 * octrees put together by the builder (build_fixture): the union of its
 * leaves' cells, each coarsened to the level `below` under the subtree
 * where it lies deeper, in finest-level cells, by brute force over the
 * fixture's leaves. Exact equality: the walk must find those cells, not
 * merely a box holding them (a walk that skipped a child, or counted the
 * children of another node, finds another box). Every leaf lies inside
 * whatever `below`. A subtree that names no node of the octree keeps its
 * cell, one that names no cell has none. */
static void test_subtree_cells(void **state)
{
    (void)state;
    size_t boxes = 0, shrunk = 0;
    for (unsigned depth = 3; depth <= 7; depth++) {
        svo_fx fx;
        fx_random p = {depth * 131u + 7u, 0.1, 0.25, 2};
        const mr_vec3 origin = mr_v3(-1.3f, 0.25f, 3.0f);
        fx_build(&fx, depth, origin, 2.5f, fx_random_cls, &p);
        mr_svo built;
        build_fixture(&fx, &built);
        const mr_svo *o = &built;
        float olo[3], ohi[3];
        if (o->node_count == 0 || !mr_svo_bounds(o, olo, ohi)) {
            mr_svo_free(&built);
            fx_free(&fx);
            continue;
        }
        for (unsigned level = 1; level + 1 < depth; level++) {
            mr_svo_subtree *st;
            uint32_t n;
            mr_error err = {0};
            assert_int_equal(mr_svo_subtrees(o, level, &st, &n, &err), MR_OK);
            for (uint32_t k = 0; k < n; k++) {
                const mr_svo_subtree *s = &st[k];
                for (unsigned below = 0; below <= depth - s->level + 1; below++) {
                    const unsigned stop = s->level + below < depth ? s->level + below : depth;
                    uint32_t elo[3], ehi[3];
                    for (int a = 0; a < 3; a++) {
                        elo[a] = below ? UINT32_MAX : s->xyz[a] << (depth - s->level);
                        ehi[a] = below ? 0 : (s->xyz[a] + 1) << (depth - s->level);
                    }
                    for (uint32_t l = 0; l < o->leaf_count && below; l++) {
                        const fx_box *b = &fx.boxes[l];
                        if (!leaf_below(b, s))
                            continue; /* not below s */
                        const unsigned lv = b->level < stop ? b->level : stop;
                        for (int a = 0; a < 3; a++) {
                            const uint32_t x = b->xyz[a] >> (b->level - lv);
                            elo[a] = (x << (depth - lv)) < elo[a] ? x << (depth - lv) : elo[a];
                            ehi[a] = ((x + 1) << (depth - lv)) > ehi[a] ? (x + 1) << (depth - lv) : ehi[a];
                        }
                    }
                    assert_true(elo[0] < ehi[0]); /* a subtree holds a leaf */
                    uint32_t lo[3], hi[3];
                    assert_true(mr_svo_subtree_cells(o, s, below, lo, hi));
                    bool smaller = false;
                    for (int a = 0; a < 3; a++) {
                        if (lo[a] != elo[a] || hi[a] != ehi[a])
                            fail_msg("depth %u, subtree %u at level %u, %u below: axis %d cells [%u, %u), expected "
                                     "[%u, %u)", depth, k, s->level, below, a, lo[a], hi[a], elo[a], ehi[a]);
                        smaller |= ehi[a] - elo[a] < 1u << (depth - s->level);
                    }
                    for (uint32_t l = 0; l < o->leaf_count; l++) { /* every leaf below s inside */
                        const fx_box *b = &fx.boxes[l];
                        if (!leaf_below(b, s))
                            continue;
                        for (int a = 0; a < 3; a++) {
                            const uint32_t first = b->xyz[a] << (depth - b->level);
                            assert_true(lo[a] <= first && first + (1u << (depth - b->level)) <= hi[a]);
                        }
                    }
                    boxes++;
                    shrunk += smaller;
                }
            }
            free(st);
        }
        /* no walk past the arrays: a subtree naming no node keeps its
         * cell, one deeper than the octree or outside it has none */
        uint32_t lo[3], hi[3];
        const mr_svo_subtree nowhere = {o->node_count + 5u, 1, {1, 0, 1}}, deep = {0, depth + 1, {0, 0, 0}},
                             outside = {0, 1, {2, 0, 0}};
        assert_true(mr_svo_subtree_cells(o, &nowhere, 3, lo, hi));
        const uint32_t half = 1u << (depth - 1);
        const uint32_t cell_lo[3] = {half, 0, half}, cell_hi[3] = {2 * half, half, 2 * half};
        assert_memory_equal(lo, cell_lo, sizeof lo);
        assert_memory_equal(hi, cell_hi, sizeof hi);
        assert_false(mr_svo_subtree_cells(o, &deep, 3, lo, hi));
        assert_false(mr_svo_subtree_cells(o, &outside, 0, lo, hi));
        mr_svo_free(&built);
        fx_free(&fx);
    }
    print_message("[ subtree cells ] %zu boxes, %zu smaller than the subtree's cell\n", boxes, shrunk);
    assert_true(shrunk > boxes / 4); /* the octrees are sparse enough to tell the walk from the cell */
}

/* Throughput on ~1M leaves, printed once, never asserted. Also spot-checks
 * a few hundred of the rays against the brute force. */
static void test_throughput(void **state)
{
    (void)state;
    fx_shell sh = {512.0, 290.0, 10};
    svo_fx fx;
    fx_build(&fx, 10, mr_v3(-1, -1, -1), 2.0f, cls_shell, &sh);
    assert_true(fx.svo.leaf_count > 500000);
    fx_rng r = {42};
    enum { N = 1 << 19 };
    mr_vec3 *o = malloc(N * sizeof *o), *d = malloc(N * sizeof *d);
    assert_non_null(o);
    assert_non_null(d);
    for (int i = 0; i < N; i++) {
        /* camera-like: from a sphere around the object towards points near it */
        const mr_vec3 u = fx_random_dir(&r);
        const float l = mr_v3_len(u);
        o[i] = mr_v3(3.0f * u.x / l, 3.0f * u.y / l, 3.0f * u.z / l);
        const mr_vec3 tgt = mr_v3((float)fx_range(&r, -0.7, 0.7), (float)fx_range(&r, -0.7, 0.7),
                                  (float)fx_range(&r, -0.7, 0.7));
        d[i] = mr_v3_sub(tgt, o[i]);
    }
    long hits = 0;
    const double t0 = mr_now();
    for (int i = 0; i < N; i++) {
        mr_svo_hit h;
        hits += mr_svo_intersect(&fx.svo, o[i], d[i], 0.0f, INFINITY, &h);
    }
    const double t1 = mr_now();
    long occ = 0;
    for (int i = 0; i < N; i++)
        occ += mr_svo_occluded(&fx.svo, o[i], d[i], 0.0f, INFINITY);
    const double t2 = mr_now();
    assert_int_equal(hits, occ);
    assert_true(hits > N / 4);
    printf("svo_trace: %u leaves, %u nodes (depth 10 sphere shell), %d rays (%.0f%% hit): intersect %.2f Mrays/s, "
           "occluded %.2f Mrays/s (one thread)\n",
           fx.svo.leaf_count, fx.svo.node_count, N, 100.0 * (double)hits / N, N / (t1 - t0) * 1e-6,
           N / (t2 - t1) * 1e-6);
    fx_stats st = {0};
    for (int i = 0; i < 64; i++)
        check_ray(&fx, o[i], d[i], 0.0f, INFINITY, &st);
    free(o);
    free(d);
    fx_free(&fx);
}

/* ---- level of detail (mr_svo_lod) */

/* The octree a level of detail at level L gives: the random one with every
 * cell of level L that would be split taken as a leaf. */
typedef struct lod_cut {
    fx_random *p;
    unsigned level;
} lod_cut;

static int cls_cut(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const lod_cut *c = ctx;
    const int k = fx_random_cls(c->p, level, x, y, z);
    return level == c->level && k == FX_SPLIT ? FX_LEAF : k;
}

/* Each interior node's cell (level in [3], coordinates in [0..2]). */
static void node_cells(const mr_svo *o, uint32_t n, unsigned level, const uint32_t xyz[3], uint32_t (*cell)[4])
{
    cell[n][0] = xyz[0], cell[n][1] = xyz[1], cell[n][2] = xyz[2], cell[n][3] = level;
    const unsigned inner = o->child_mask[n] & ~o->leaf_mask[n];
    for (unsigned c = 0; c < 8; c++)
        if (inner >> c & 1u) {
            const uint32_t cxyz[3] = {xyz[0] * 2 + (c & 1), xyz[1] * 2 + ((c >> 1) & 1), xyz[2] * 2 + (c >> 2)};
            node_cells(o, o->first_node[n] + mr_svo_popcount8(inner & ((1u << c) - 1u)), level + 1, cxyz, cell);
        }
}

static mr_svo_hit lod_hit_of(const mr_svo *o, const mr_svo_lod *lod, mr_vec3 org, mr_vec3 dir, float tmin,
                             float tmax, bool *hit)
{
    mr_svo_hit h;
    memset(&h, 0, sizeof h);
    *hit = mr_svo_intersect_rays(o, NULL, 1, &org, &dir, &tmin, &tmax, lod, &h) & 1u;
    return h;
}

/* A level of detail whose bound is one cell edge everywhere (a = 0, b the
 * edge of level L) makes every interior node of level L a leaf: the walk
 * must then give, ray by ray, what the plain walk gives over the octree cut
 * at L, bit for bit (t, level, cell, entry axis, normal), and name a node
 * (leaf_count + n) exactly where the cut octree's leaf is a cut node; any
 * hit alike (occlusion). b just above or below the edge moves the cut by
 * no level or one (a node is cut when its edge is at most b). */
static void test_lod_cut(void **state)
{
    (void)state;
    size_t rays = 0, node_hits = 0;
    for (unsigned depth = 4; depth <= 12; depth += 4) {
        fx_random p = {depth * 31u + 7u, 0.2, depth < 9 ? 0.4 : 0.2, 2};
        svo_fx fx;
        fx_build(&fx, depth, mr_v3(-0.75f, 0.3f, 2.5f), 3.0f, fx_random_cls, &p);
        const mr_svo *o = &fx.svo;
        uint32_t(*cell)[4] = malloc((o->node_count + 1) * sizeof *cell);
        assert_non_null(cell);
        const uint32_t root[3] = {0, 0, 0};
        if (o->node_count)
            node_cells(o, 0, 0, root, cell);
        for (unsigned level = 1; level < depth; level += depth / 4) {
            lod_cut cut = {&p, level};
            svo_fx cf;
            fx_build(&cf, depth, o->origin, o->size, cls_cut, &cut);
            const double edge = ldexp((double)o->size, -(int)level);
            const mr_svo_lod at = {.b = edge}, below = {.b = nextafter(edge, 0.0)};
            fx_rng r = {depth * 7u + level};
            for (int i = 0; i < 600; i++) {
                mr_vec3 org, dir;
                float tmin, tmax;
                fx_random_ray(&fx, &r, i, &org, &dir, &tmin, &tmax);
                mr_svo_hit want;
                const bool wh = mr_svo_intersect(&cf.svo, org, dir, tmin, tmax, &want);
                bool h;
                const mr_svo_hit got = lod_hit_of(o, &at, org, dir, tmin, tmax, &h);
                assert_int_equal(h, wh);
                const mr_svo_lod none = {.b = -INFINITY};
                assert_int_equal(mr_svo_intersect_rays(o, NULL, 1, &org, &dir, &tmin, &tmax, &at, NULL) & 1u,
                                 mr_svo_occluded(&cf.svo, org, dir, tmin, tmax));
                rays++;
                /* below the edge: the cut one level further down, or none */
                bool hb;
                const mr_svo_hit gb = lod_hit_of(o, &below, org, dir, tmin, tmax, &hb);
                if (hb)
                    assert_true(gb.level != level || gb.leaf < o->leaf_count);
                /* b = -inf: the plain walk */
                bool hn;
                mr_svo_hit plain;
                const mr_svo_hit gn = lod_hit_of(o, &none, org, dir, tmin, tmax, &hn);
                assert_int_equal(hn, mr_svo_intersect(o, org, dir, tmin, tmax, &plain));
                if (hn)
                    assert_true(same_hit(&gn, &plain));
                if (!h)
                    continue;
                if (memcmp(&got.t, &want.t, sizeof got.t) || got.level != want.level || got.x != want.x ||
                    got.y != want.y || got.z != want.z || got.axis != want.axis ||
                    memcmp(&got.ng, &want.ng, sizeof got.ng))
                    fail_msg("depth %u cut at %u, ray %d: t %a level %u, the cut octree's t %a level %u", depth,
                             level, i, (double)got.t, got.level, (double)want.t, want.level);
                /* a node exactly where the cut octree's leaf was a split cell */
                const fx_box *wb = &cf.boxes[want.leaf];
                const bool cut_cell = wb->level == level &&
                                      fx_random_cls(&p, level, wb->xyz[0], wb->xyz[1], wb->xyz[2]) == FX_SPLIT;
                assert_int_equal(got.leaf >= o->leaf_count, cut_cell);
                /* the leaf or node named is the cell hit */
                const uint32_t *named = NULL;
                if (cut_cell) {
                    assert_true(got.leaf - o->leaf_count < o->node_count);
                    named = cell[got.leaf - o->leaf_count];
                    assert_int_equal(named[3], got.level);
                    node_hits++;
                } else {
                    assert_true(got.leaf < o->leaf_count);
                    named = fx.boxes[got.leaf].xyz;
                    assert_int_equal(fx.boxes[got.leaf].level, got.level);
                }
                assert_true(named[0] == got.x && named[1] == got.y && named[2] == got.z);
            }
            fx_free(&cf);
        }
        free(cell);
        fx_free(&fx);
    }
    print_message("[ lod cut ] %zu rays, %zu node hits\n", rays, node_hits);
    assert_true(node_hits > 500);
}

/* The brute force of a cast with a level of detail: the nearest of the
 * cells the rule selects (a leaf, or a node whose edge is at most the
 * bound where the ray enters it, below no selected node), every cell by
 * the fixture's slab test. Its entry t rounds differently from the walk's
 * (fx_slab divides), so a ray with a decision within rounding of the
 * bound (near) or two candidates within tol of the nearest (tie) is
 * compared by t only. */
typedef struct lod_ref {
    bool hit, near, tie;
    double t;
    unsigned level;
    uint32_t xyz[3];
} lod_ref;

/* Cell b of node n (leaf: a leaf cell, n unused); interior nodes below
 * the root are cut where the rule says, the part within lod's clip box
 * when it has one. */
static void lod_brute(const mr_svo *o, const mr_svo_lod *lod, bool leaf, uint32_t n, const fx_box *b,
                      const double org[3], const double dir[3], double tmin, double tmax, double tol,
                      lod_ref *best)
{
    double t0, t1;
    if (!fx_slab(o, b, org, dir, tmin, tmax, &t0, &t1))
        return;
    if (!leaf) {
        const double z0 = lod->a[0] * org[0] + lod->a[1] * org[1] + lod->a[2] * org[2] + lod->b;
        const double zd = lod->a[0] * dir[0] + lod->a[1] * dir[1] + lod->a[2] * dir[2];
        const double edge = ldexp((double)o->size, -(int)b->level), bound = z0 + t0 * zd;
        if (b->level > 0)
            best->near |= fabs(bound - edge) <= 1e-9 * (fabs(bound) + edge) + fabs(zd) * tol;
        if (b->level == 0 || !(edge <= bound)) {
            const unsigned cm = o->child_mask[n], lm = o->leaf_mask[n], inner = cm & ~lm;
            for (unsigned c = 0; c < 8; c++) {
                if (!(cm >> c & 1u))
                    continue;
                const fx_box cb = {b->level + 1, {b->xyz[0] * 2 + (c & 1), b->xyz[1] * 2 + ((c >> 1) & 1),
                                                  b->xyz[2] * 2 + (c >> 2)}};
                const bool cl = lm >> c & 1u;
                lod_brute(o, lod, cl, cl ? 0 : o->first_node[n] + mr_svo_popcount8(inner & ((1u << c) - 1u)), &cb,
                          org, dir, tmin, tmax, tol, best);
            }
            return;
        }
        /* cut: the cell's part within the clip box */
        const fx_clip clip = {lod->clip_level,
                              {lod->clip_lo[0], lod->clip_lo[1], lod->clip_lo[2]},
                              {lod->clip_hi[0], lod->clip_hi[1], lod->clip_hi[2]}};
        if (lod->clip && !fx_slab_within(o, b, &clip, org, dir, tmin, tmax, &t0, &t1))
            return;
    }
    if (best->hit && fabs(t0 - best->t) <= tol)
        best->tie = true;
    if (!best->hit || t0 < best->t) {
        best->tie = best->hit && best->t - t0 <= tol;
        *best = (lod_ref){true, best->near, best->tie, t0, b->level, {b->xyz[0], b->xyz[1], b->xyz[2]}};
    }
}

/* A level of detail that grows with distance (a . p + b, as the camera's
 * depth makes it): no ray loses its hit or meets it later than the plain
 * walk does (the cut cell holds the leaves), a node hit's cell is at most
 * the bound at its entry point, and rays traced together get what each
 * gets alone. */
static void test_lod_depth(void **state)
{
    (void)state;
    size_t hits = 0, nodes = 0, batches = 0;
    unsigned node_levels = 0; /* bit l: a node of level l was hit */
    size_t far_cuts = 0, checked = 0; /* hits whose cell the brute force decided alone */
    for (unsigned depth = 9; depth <= 12; depth += 3) {
        fx_random p = {depth * 53u + 1u, 0.25, 0.17, 2};
        svo_fx fx;
        fx_build(&fx, depth, mr_v3(-0.75f, 0.3f, 2.5f), 3.0f, fx_random_cls, &p);
        const mr_svo *o = &fx.svo;
        /* a camera at z = 2.4 looking down +z, near the cube's face at z
         * = 2.5: the bound runs from a cell of level depth - 1 there to
         * one about five levels coarser at the far face (z = 5.5), and is
         * negative (no cut) behind the camera; depths of 9 and more, so
         * the coarsest cut stays below level 1 (the walk never cuts the
         * root's children's parent) */
        const double scale = 10.0 * ldexp((double)o->size, 1 - (int)depth);
        const mr_svo_lod lod = {.a = {0, 0, scale}, .b = -2.4 * scale};
        fx_rng r = {depth * 11u + 5u};
        for (unsigned round = 0; round < 128; round++) {
            const unsigned n = round % 32 + 1;
            mr_vec3 org[32], dir[32];
            float tmin[32], tmax[32];
            for (unsigned i = 0; i < n; i++)
                fx_random_ray(&fx, &r, (int)(round * 32 + i), &org[i], &dir[i], &tmin[i], &tmax[i]);
            mr_svo_hit together[32];
            const uint32_t mask = mr_svo_intersect_rays(o, NULL, n, org, dir, tmin, tmax, &lod, together);
            const uint32_t any = mr_svo_intersect_rays(o, NULL, n, org, dir, tmin, tmax, &lod, NULL);
            assert_int_equal(mask, any);
            for (unsigned i = 0; i < n; i++) {
                bool h;
                const mr_svo_hit alone = lod_hit_of(o, &lod, org[i], dir[i], tmin[i], tmax[i], &h);
                assert_int_equal(mask >> i & 1u, h);
                mr_svo_hit plain;
                const bool ph = mr_svo_intersect(o, org[i], dir[i], tmin[i], tmax[i], &plain);
                if (ph)
                    assert_true(h); /* no holes */
                const double od[3] = {org[i].x, org[i].y, org[i].z}, dd[3] = {dir[i].x, dir[i].y, dir[i].z};
                const double tol = fx_tol(o, dd, h ? (double)alone.t : 0.0);
                lod_ref ref = {0};
                const fx_box root = {0, {0, 0, 0}};
                if (o->node_count)
                    lod_brute(o, &lod, false, 0, &root, od, dd, tmin[i], tmax[i], tol, &ref);
                assert_true(h == ref.hit || ref.near);
                if (!h)
                    continue;
                assert_true(same_hit(&together[i], &alone));
                if (ph)
                    assert_true(alone.t <= plain.t);
                /* the brute force's cell, where rounding cannot decide */
                if (ref.hit && !ref.near) {
                    if (fabs((double)alone.t - ref.t) > tol)
                        fail_msg("depth %u: t %.9g, the brute force's %.9g", depth, (double)alone.t, ref.t);
                    if (!ref.tie) {
                        assert_int_equal(alone.level, ref.level);
                        assert_true(alone.x == ref.xyz[0] && alone.y == ref.xyz[1] && alone.z == ref.xyz[2]);
                        checked++;
                    }
                }
                hits++;
                if (alone.leaf >= o->leaf_count) {
                    nodes++;
                    node_levels |= 1u << alone.level;
                    /* cut coarser than where the ray entered the cube
                     * allows: the walk tests the bound along the ray */
                    far_cuts += dir[i].z > 0 && alone.level + 2 < depth;
                    const double z = (double)org[i].z + (double)alone.t * (double)dir[i].z;
                    const double bound = scale * z - 2.4 * scale, e = ldexp((double)o->size, -(int)alone.level);
                    /* the walk's own entry t is a double; the hit's t is
                     * it rounded to float: a float ulp of t along dir */
                    const double slack = 4.0 * FLT_EPSILON * (fabs((double)alone.t) + 1.0) * fabs((double)dir[i].z) * scale;
                    assert_true(e <= bound + slack);
                    assert_true(alone.level < depth);
                }
            }
            batches++;
        }
        fx_free(&fx);
    }
    print_message("[ lod depth ] %zu batches, %zu hits (%zu cells checked against the brute force), %zu on "
                  "nodes of %u levels, %zu cut coarser going away\n", batches, hits, checked, nodes,
                  (unsigned)__builtin_popcount(node_levels), far_cuts);
    assert_true(far_cuts > 10 && checked > hits / 2);
    assert_true(nodes > 100 && nodes < hits);
    assert_true(__builtin_popcount(node_levels) >= 4); /* the bound varies along the rays */
}

/* The level of detail walked from pieces (mr_svo_intersect_rays from the
 * subtrees at level L, as the svo kind traces an octree) cuts where the
 * whole walk does: a piece tests its own node as the whole walk tests it
 * when it enters that cell. A sphere's shell (leaves at the finest level
 * only, so the subtrees lie at L), z from 3.15 to 4.85; the bound is the
 * edge of level L + 1 at z = 3.2 and grows along z to that of L at 3.7
 * and L - 1 at 4.7, so the whole walk cuts below L, at L (the pieces' own
 * nodes) and above: a cut above the pieces has no piece to match, those
 * rays are counted, not compared. Every other ray gets from the nearest
 * piece hit the whole walk's t, and its cell when that t is one piece's
 * alone (at one t two pieces can hold hits: the kind keeps the one the
 * whole walk meets first). */
static void test_lod_pieces(void **state)
{
    (void)state;
    const unsigned depth = 9, L = 4;
    fx_shell sh = {256.0, 145.0, depth}; /* leaves at the finest level only: pieces at L */
    svo_fx fx;
    fx_build(&fx, depth, mr_v3(-0.75f, 0.3f, 2.5f), 3.0f, cls_shell, &sh);
    const mr_svo *o = &fx.svo;
    const double edge = ldexp((double)o->size, -(int)L), slope = edge;
    const mr_svo_lod lod = {.a = {0, 0, slope}, .b = edge / 2.0 - 3.2 * slope};
    mr_svo_subtree *st;
    uint32_t n;
    mr_error err = {0};
    assert_int_equal(mr_svo_subtrees(o, L, &st, &n, &err), MR_OK);
    assert_true(n > 8);
    size_t compared = 0, root_cuts = 0, above = 0, hits = 0;
    fx_rng r = {77};
    for (int k = 0; k < 4000; k++) {
        mr_vec3 org, dir;
        float tmin, tmax;
        fx_random_ray(&fx, &r, k, &org, &dir, &tmin, &tmax);
        bool h;
        const mr_svo_hit whole = lod_hit_of(o, &lod, org, dir, tmin, tmax, &h);
        if (h && whole.leaf >= o->leaf_count && whole.level < L) {
            above++;
            continue;
        }
        bool any = false, near_root = false;
        unsigned holders = 0;
        mr_svo_hit near;
        memset(&near, 0, sizeof near);
        for (uint32_t i = 0; i < n; i++) {
            mr_svo_hit ph;
            if (!(mr_svo_intersect_rays(o, &st[i], 1, &org, &dir, &tmin, &tmax, &lod, &ph) & 1u))
                continue;
            if (any && ph.t == near.t)
                holders++;
            if (!any || ph.t < near.t) {
                near = ph;
                holders = 1;
                near_root = ph.level == st[i].level && ph.leaf == o->leaf_count + st[i].node;
            }
            any = true;
        }
        assert_int_equal(any, h);
        compared++;
        if (!h)
            continue;
        hits++;
        root_cuts += near_root;
        if (memcmp(&near.t, &whole.t, sizeof near.t) != 0)
            fail_msg("ray %d: pieces' nearest t %a, the whole walk's %a", k, (double)near.t, (double)whole.t);
        if (holders == 1)
            assert_true(near.leaf == whole.leaf && near.level == whole.level && near.x == whole.x &&
                        near.y == whole.y && near.z == whole.z);
    }
    print_message("[ lod pieces ] %zu rays compared (%zu hits), %zu cut above the pieces' level %u, %zu piece "
                  "nodes cut there\n", compared, hits, above, L, root_cuts);
    assert_true(hits > 500 && root_cuts > 100 && hits - root_cuts > 100 && above > 100);
    free(st);
    fx_free(&fx);
}

/* The level of detail clipped to a box (mr_svo_lod.clip), as the svo kind
 * casts a piece: the box its occupied cells fill one and two levels below
 * it (mr_svo_subtree_cells), the pieces and bound of test_lod_pieces, so
 * nodes are cut at the pieces' level and the next, above the box's
 * level. A cut node is hit where the ray enters the part of its cell
 * within the box: against the brute force (t within tol, the cell where
 * rounding cannot decide); the hit point lies in the box (within tol); no
 * ray loses its hit or meets it later than the piece's leaves. */
static void test_lod_clip(void **state)
{
    (void)state;
    const unsigned depth = 9, L = 4;
    fx_shell sh = {256.0, 145.0, depth};
    svo_fx fx;
    fx_build(&fx, depth, mr_v3(-0.75f, 0.3f, 2.5f), 3.0f, cls_shell, &sh);
    const mr_svo *o = &fx.svo;
    const double edge = ldexp((double)o->size, -(int)L);
    mr_svo_subtree *st;
    uint32_t n;
    mr_error err = {0};
    assert_int_equal(mr_svo_subtrees(o, L, &st, &n, &err), MR_OK);
    size_t hits = 0, outside = 0, checked = 0;
    fx_rng r = {91};
    for (int k = 0; k < 3000; k++) {
        mr_vec3 org, dir;
        float tmin, tmax;
        fx_random_ray(&fx, &r, k, &org, &dir, &tmin, &tmax);
        const double od[3] = {org.x, org.y, org.z}, dd[3] = {dir.x, dir.y, dir.z};
        for (uint32_t i = 0; i < n; i++) {
            mr_svo_lod lod = {.a = {0, 0, edge}, .b = edge / 2.0 - 3.2 * edge, .clip = true,
                              .clip_level = L + 1u + (unsigned)(k & 1)};
            const unsigned below = lod.clip_level - L, shift = depth - lod.clip_level;
            uint32_t lo[3], hi[3];
            assert_true(mr_svo_subtree_cells(o, &st[i], below, lo, hi));
            for (int a = 0; a < 3; a++) {
                lod.clip_lo[a] = lo[a] >> shift;
                lod.clip_hi[a] = ((hi[a] - 1u) >> shift) + 1u;
            }
            mr_svo_hit h, plain;
            const bool got = mr_svo_intersect_rays(o, &st[i], 1, &org, &dir, &tmin, &tmax, &lod, &h) & 1u;
            if (mr_svo_intersect_subtree(o, &st[i], org, dir, tmin, tmax, &plain))
                assert_true(got && h.t <= plain.t); /* no holes */
            const double tol = fx_tol(o, dd, got ? (double)h.t : 0.0);
            lod_ref ref = {0};
            const fx_box piece = {L, {st[i].xyz[0], st[i].xyz[1], st[i].xyz[2]}};
            lod_brute(o, &lod, false, st[i].node, &piece, od, dd, tmin, tmax, tol, &ref);
            assert_true(got == ref.hit || ref.near);
            if (!got)
                continue;
            hits++;
            if (ref.hit && !ref.near) {
                if (fabs((double)h.t - ref.t) > tol)
                    fail_msg("ray %d, piece %u: t %.9g, the brute force's %.9g", k, i, (double)h.t, ref.t);
                if (!ref.tie) {
                    assert_true(h.level == ref.level && h.x == ref.xyz[0] && h.y == ref.xyz[1] &&
                                h.z == ref.xyz[2]);
                    checked++;
                }
            }
            /* in the box, and where a cut cell reaches out of it */
            const double cell = ldexp((double)o->size, -(int)lod.clip_level);
            const double c[3] = {o->origin.x, o->origin.y, o->origin.z};
            const double span = ldexp(1.0, -(int)h.level) / ldexp(1.0, -(int)lod.clip_level);
            const uint32_t hxyz[3] = {h.x, h.y, h.z};
            bool reaches = false;
            for (int a = 0; a < 3; a++) {
                const double p = od[a] + (double)h.t * dd[a];
                const double slack = tol * fabs(dd[a]); /* t within tol */
                if (!(p >= c[a] + lod.clip_lo[a] * cell - slack && p <= c[a] + lod.clip_hi[a] * cell + slack))
                    fail_msg("ray %d, piece %u: hit at %.9g on axis %d, outside [%.9g, %.9g]; t %.9g level %u leaf %d "
                             "axis %d tmin %.9g", k, i, p, a, c[a] + lod.clip_lo[a] * cell,
                             c[a] + lod.clip_hi[a] * cell, (double)h.t, h.level, h.leaf < o->leaf_count, h.axis,
                             (double)tmin);
                reaches |= hxyz[a] * span < lod.clip_lo[a] || (hxyz[a] + 1) * span > lod.clip_hi[a];
            }
            outside += reaches;
        }
    }
    print_message("[ lod clip ] %zu piece hits (%zu cells checked against the brute force), %zu on cut cells "
                  "reaching out of the box\n", hits, checked, outside);
    assert_true(hits > 500 && checked > hits / 2 && outside > 100);
    free(st);
    fx_free(&fx);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_random_shallow),  cmocka_unit_test(test_random_deep),
        cmocka_unit_test(test_exact_grid_rays), cmocka_unit_test(test_root_leaf_and_empty),
        cmocka_unit_test(test_bounds),          cmocka_unit_test(test_occupied_bounds),
        cmocka_unit_test(test_build_crosscheck), cmocka_unit_test(test_subtrees),
        cmocka_unit_test(test_subtree_cells),        cmocka_unit_test(test_rays_together),
        cmocka_unit_test(test_lod_cut),          cmocka_unit_test(test_lod_depth),
        cmocka_unit_test(test_lod_pieces),      cmocka_unit_test(test_lod_clip),
        cmocka_unit_test(test_throughput),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
