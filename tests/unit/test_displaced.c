/*
 * test_displaced.c - the displaced kind's parts (issue 14):
 *  - affine arithmetic (math/affine_arith.h): every operation's interval
 *    holds the exact value at sampled corners and interior points of its
 *    parameter square (exact: computed in long double, whose 64-bit
 *    mantissa holds the products of doubles' sums here far better than the
 *    bounds' margin);
 *  - the min/max pyramid of textures of any size and sample type: every
 *    node's bounds hold every sample of its cells (brute force), and the
 *    quantisation never cuts into them;
 *  - the surface: a cell clearly inside a base triangle is made directly
 *    with exactly the triangles (vertex records and order) that cutting it
 *    makes;
 *  - bounds: every micro-vertex lies in its triangle's Embree box and in the
 *    box (3D and local frame) of the cell it belongs to;
 *  - the traversal: rays through Embree and the kind's callbacks against the
 *    brute force over the tessellation (displaced_fixture.h): identical hits,
 *    t bit for bit, on a plane, a bumpy mesh with varying normals, and a
 *    UV sphere (examples/models/sphere960.obj);
 *  - a constant texture is the base mesh offset along its unit normals;
 *  - bilinear leaves: hits on the patches against their fine tessellation.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <float.h>
#include <math.h>

#include "../support/displaced_fixture.h"
#include "../support/grid_fixture.h"
#include "../support/kind_stat_fixture.h"
#include "kinds/displaced/dgrid.h"
#include "kinds/displaced/dsurf.h"
#include "kinds/displaced/dtrace.h"
#include "kinds/displaced/tiling.h"
#include "math/affine_arith.h"

/* ---- affine arithmetic ---------------------------------------------------------- */

typedef struct af_exact {
    long double c, u, v; /* the form without its K term, evaluated exactly enough */
} af_exact;

static mr_af rnd_form(uint64_t *s)
{
    double scale = ldexp(1.0, (int)(rnd(s) % 40) - 20);
    return (mr_af){(rnd01(s) - 0.5) * scale, (rnd01(s) - 0.5) * scale, (rnd01(s) - 0.5) * scale, 0};
}

static long double at(mr_af a, long double eu, long double ev)
{
    return (long double)a.c + (long double)a.u * eu + (long double)a.v * ev;
}

static void test_affine_arith(void **state)
{
    (void)state;
    uint64_t s = 12345;
    int fails = 0;
    for (int k = 0; k < 20000; k++) {
        mr_af a = rnd_form(&s), b = rnd_form(&s);
        double sc = (rnd01(&s) - 0.5) * 1e3;
        mr_af sum = mr_af_add(a, b), dif = mr_af_sub(a, b), pro = mr_af_mul(a, b),
              sq = mr_af_sqr(a), scl = mr_af_scale(a, sc);
        mr_interval is = mr_af_interval(sum), id = mr_af_interval(dif), ip = mr_af_interval(pro),
                    iq = mr_af_interval(sq), ic = mr_af_interval(scl);
        for (int e = 0; e < 9; e++) {
            long double eu = e < 4 ? (e & 1 ? 1 : -1) : (long double)(rnd01(&s) * 2 - 1);
            long double ev = e < 4 ? (e & 2 ? 1 : -1) : (long double)(rnd01(&s) * 2 - 1);
            long double x = at(a, eu, ev), y = at(b, eu, ev);
            long double vs = x + y, vd = x - y, vp = x * y, vq = x * x, vc = x * sc;
            fails += vs < is.lo || vs > is.hi;
            fails += vd < id.lo || vd > id.hi;
            fails += vp < ip.lo || vp > ip.hi;
            fails += vq < iq.lo || vq > iq.hi;
            fails += vc < ic.lo || vc > ic.hi;
        }
        assert_true(sum.k >= 0 && pro.k >= 0 && sq.k >= 0);
        assert_true(iq.lo >= -mr_af_radius(sq) - fabs(sq.c)); /* sanity */
    }
    assert_int_equal(fails, 0);
    /* the hazards: sqrt of an interval reaching below 0, 1/x of one reaching 0 */
    mr_interval r = mr_interval_sqrt((mr_interval){-1e-9, 4});
    assert_true(r.lo == 0 && r.hi >= 2);
    mr_interval inv;
    assert_false(mr_interval_recip((mr_interval){0, 1}, &inv));
    assert_false(mr_interval_recip((mr_interval){-1, 1}, &inv));
    assert_true(mr_interval_recip((mr_interval){2, 4}, &inv));
    assert_true(inv.lo <= 0.25 && inv.hi >= 0.5);
}

/* ---- the pyramid ----------------------------------------------------------------- */

/* The traversal's four children's heights at once (AVX2) against
 * mr_dgrid_node_heights one by one, bit for bit, for node (I, J) of level
 * l: every subset of the children that exist. */
static void check_child_heights(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J)
{
#if defined(__x86_64__) && defined(__GNUC__)
    if (!__builtin_cpu_supports("avx2"))
        return;
    const unsigned c = l - 1;
    unsigned have = 0;
    for (unsigned k = 0; k < 4; k++)
        have |= (unsigned)(2 * I + (k & 1u) < g->lw[c] && 2 * J + (k >> 1) < g->lh[c]) << k;
    for (unsigned mask = have; mask; mask = (mask - 1) & have) {
        double hl[4], hh[4];
        mr_dgrid_child_heights_avx2(g, c, 2 * I, 2 * J, mask, hl, hh);
        for (unsigned m = mask; m; m &= m - 1) {
            const unsigned k = (unsigned)__builtin_ctz(m);
            double el, eh;
            mr_dgrid_node_heights(g, c, 2 * I + (k & 1u), 2 * J + (k >> 1), &el, &eh);
            if (memcmp(&el, &hl[k], sizeof el) || memcmp(&eh, &hh[k], sizeof eh))
                fail_msg("%ux%u level %u node (%u, %u) child %u: [%.17g, %.17g], one by one "
                         "[%.17g, %.17g]",
                         g->w, g->h, l, I, J, k, hl[k], hh[k], el, eh);
        }
    }
#else
    (void)g, (void)l, (void)I, (void)J;
#endif
}

static void test_pyramid_any_size(void **state)
{
    (void)state;
    /* widths around the builders' 16-wide steps (dgrid.c: a level-1 row of
     * 8-bit samples 16 nodes at a time from 34 columns on, upper levels 8
     * nodes at a time from 16 children on) and their scalar tails */
    static const uint32_t SIZES[][2] = {{1, 1},    {1, 7},   {7, 1},   {5, 3},    {64, 64},
                                        {257, 129}, {400, 400}, {33, 5}, {34, 6}, {35, 7},
                                        {67, 9},    {1031, 3}};
    static const mr_sample_type TYPES[] = {MR_SAMPLE_U8, MR_SAMPLE_U16, MR_SAMPLE_F32};
    uint64_t seed = 99;
    for (size_t si = 0; si < sizeof SIZES / sizeof SIZES[0]; si++)
        for (size_t ti = 0; ti < 3; ti++) {
            mr_asset *tex = dfx_texture(SIZES[si][0], SIZES[si][1], TYPES[ti], dfx_noise, &seed);
            if (TYPES[ti] == MR_SAMPLE_F32) /* signed, non-integer values */
                for (size_t k = 0; k < (size_t)SIZES[si][0] * SIZES[si][1]; k++)
                    ((float *)tex->image->samples)[k] = ((float *)tex->image->samples)[k] * 0.37f - 40;
            mr_dgrid g;
            mr_error err;
            assert_int_equal(mr_dgrid_init(&g, tex->image, 0, -2.0, 0.5, 2, &err), MR_OK);
            assert_true(g.lw[g.levels] == 1 && g.lh[g.levels] == 1);
            for (unsigned l = 0; l <= g.levels; l++)
                for (uint32_t J = 0; J < g.lh[l]; J++)
                    for (uint32_t I = 0; I < g.lw[l]; I++) {
                        double lo, hi;
                        mr_dgrid_node_samples(&g, l, I, J, &lo, &hi);
                        /* the node's cells' corners, by brute force */
                        uint64_t x0 = (uint64_t)I << l, y0 = (uint64_t)J << l;
                        uint64_t x1 = ((uint64_t)(I + 1) << l) < g.w ? (uint64_t)(I + 1) << l : g.w;
                        uint64_t y1 = ((uint64_t)(J + 1) << l) < g.h ? (uint64_t)(J + 1) << l : g.h;
                        double mn = INFINITY, mx = -INFINITY;
                        for (uint64_t y = y0; y <= y1; y++)
                            for (uint64_t x = x0; x <= x1; x++) {
                                double v = mr_dgrid_sample(&g, (uint32_t)(x % g.w), (uint32_t)(y % g.h));
                                mn = fmin(mn, v), mx = fmax(mx, v);
                            }
                        if (!(lo <= mn && hi >= mx))
                            fail_msg("%ux%u type %d level %u node (%u, %u): [%g, %g] misses [%g, %g]",
                                     g.w, g.h, (int)TYPES[ti], l, I, J, lo, hi, mn, mx);
                        /* quantised, but never looser than one step and a bit */
                        if (l > 0)
                            assert_true(lo >= mn - 3 * g.qstep - 1e-12 && hi <= mx + 3 * g.qstep + 1e-12);
                        /* and exactly the quantised extremes (dgrid.h: a step below the
                         * rounded-down minimum, a step above the rounded-up maximum) */
                        if (l > 0 && g.qstep > 0) {
                            double ql = fmin(fmax(floor((mn - g.gmin) / g.qstep) - 1, 0), 65535);
                            double qh = fmin(fmax(ceil((mx - g.gmin) / g.qstep) + 1, 0), 65535);
                            double el = ql == 0 ? g.gmin : ql == 65535 ? g.gmax : g.gmin + ql * g.qstep;
                            double eh = qh == 0 ? g.gmin : qh == 65535 ? g.gmax : g.gmin + qh * g.qstep;
                            if (lo != el || hi != eh)
                                fail_msg("%ux%u type %d level %u node (%u, %u): [%.17g, %.17g], "
                                         "expected [%.17g, %.17g]",
                                         g.w, g.h, (int)TYPES[ti], l, I, J, lo, hi, el, eh);
                        }
                        double hl, hh, sl, sh;
                        mr_dgrid_node_heights(&g, l, I, J, &hl, &hh);
                        assert_true(hl <= mr_dgrid_height_of(&g, mx) && hh >= mr_dgrid_height_of(&g, mn));
                        /* the traversal's inline path (8-bit heights looked up)
                         * gives the reference's bits */
                        mr_dgrid_node_heights_slow(&g, l, I, J, &sl, &sh);
                        if (hl != sl || hh != sh)
                            fail_msg("%ux%u type %d level %u node (%u, %u): heights [%.17g, %.17g], "
                                     "reference [%.17g, %.17g]",
                                     g.w, g.h, (int)TYPES[ti], l, I, J, hl, hh, sl, sh);
                        if (l > 0)
                            check_child_heights(&g, l, I, J);
                    }
            mr_dgrid_free(&g);
            mr_asset_free(tex);
        }
}

/* ---- the surface ------------------------------------------------------------------- */

static double tex_height(const void *src, int64_t i, int64_t j)
{
    (void)src;
    int64_t m = (i * 7 + j * 13) % 11;
    return 0.01 * (double)(m < 0 ? m + 11 : m) - 0.03; /* in [-0.03, 0.07] */
}

static void rnd_base(uint64_t *s, mr_dbase *b, float P[3][3], float N[3][3], double scale)
{
    double g[3][2];
    for (int k = 0; k < 3; k++) {
        g[k][0] = (rnd01(s) - 0.5) * scale;
        g[k][1] = (rnd01(s) - 0.5) * scale;
        mr_vec3 p = rnd_vec(s, -1, 1), n = rnd_unit(s);
        P[k][0] = p.x, P[k][1] = p.y, P[k][2] = p.z;
        N[k][0] = n.x, N[k][1] = n.y, N[k][2] = n.z;
        if (k) /* keep normals roughly agreeing */
            for (int c = 0; c < 3; c++)
                N[k][c] = 0.5f * N[k][c] + N[0][c];
    }
    const float *p[3] = {P[0], P[1], P[2]}, *n[3] = {N[0], N[1], N[2]};
    mr_dheights hs = {tex_height, NULL};
    mr_dbase_init(b, g, p, n, &hs);
}

static void test_whole_cells_are_cut_cells(void **state)
{
    (void)state;
    uint64_t s = 7;
    int whole = 0;
    for (int k = 0; k < 300; k++) {
        mr_dbase b;
        float P[3][3], N[3][3];
        rnd_base(&s, &b, P, N, 2 + 40 * rnd01(&s));
        int64_t i0, i1, j0, j1;
        mr_dbase_cells(&b, &i0, &i1, &j0, &j1);
        for (int64_t j = j0; j <= j1; j++)
            for (int64_t i = i0; i <= i1; i++) {
                if (!mr_dsurf_cell_inside(&b, i, j))
                    continue;
                whole++;
                mr_dcell fast, cut;
                mr_dsurf_cell(&b, i, j, 2, &fast);
                mr_dsurf_cell_cut(&b, i, j, 2, &cut);
                assert_int_equal(fast.nt, cut.nt);
                for (int t = 0; t < fast.nt; t++)
                    for (int c = 0; c < 3; c++) {
                        const mr_dvert *a = &fast.v[fast.tri[t][c]], *d = &cut.v[cut.tri[t][c]];
                        assert_int_equal(a->kind, MR_DV_GRID);
                        assert_int_equal(d->kind, MR_DV_GRID);
                        assert_true(a->a == d->a && a->b == d->b);
                    }
            }
    }
    assert_true(whole > 1000);
}

/* The same micro-triangles, in the same order, made of the same vertex
 * records (bit for bit): what the traversal tests and evaluates. (A whole
 * cell keeps all four corners when one half is asked for.) */
static void assert_same_cell(const mr_dcell *a, const mr_dcell *c)
{
    assert_int_equal(a->nt, c->nt);
    for (int t = 0; t < a->nt; t++) {
        assert_int_equal(a->half[t], c->half[t]);
        for (int k = 0; k < 3; k++) {
            const mr_dvert *p = &a->v[a->tri[t][k]], *q = &c->v[c->tri[t][k]];
            assert_int_equal(p->kind, q->kind);
            assert_int_equal(p->idx, q->idx);
            assert_int_equal(p->fam, q->fam);
            assert_true(p->a == q->a && p->b == q->b);
            assert_true(p->x == q->x && p->y == q->y && p->t == q->t);
        }
    }
}

/* The same vertex records in the same order (a cell that is not whole:
 * a whole cell's short cut keeps all four corners for one half). */
static void assert_same_records(const mr_dcell *a, const mr_dcell *c)
{
    assert_int_equal(a->nv, c->nv);
    for (int k = 0; k < a->nv; k++) {
        const mr_dvert *p = &a->v[k], *q = &c->v[k];
        assert_true(p->kind == q->kind && p->idx == q->idx && p->fam == q->fam);
        assert_true(p->a == q->a && p->b == q->b);
        assert_true(p->x == q->x && p->y == q->y && p->t == q->t);
    }
}

/* mr_dsurf_cell takes two short cuts, a whole cell and a cell crossed by
 * one edge of T alone; both must make exactly what cutting T by the
 * cell's lines makes (the same vertices, bit for bit, in the same order,
 * the same triangles), or the micro-surface (and its seams with the
 * neighbouring triangles) would depend on the path. Random triangles, and
 * triangles whose corners sit on the grid's lines and half-lines, where
 * an edge runs through cell corners (no short cut may be taken there), in
 * both orientations, both halves and each alone. */
static void test_cells_are_their_cuts(void **state)
{
    (void)state;
    uint64_t s = 11;
    long compared = 0, crossed = 0;
    for (int k = 0; k < 600; k++) {
        mr_dbase b;
        float P[3][3], N[3][3];
        rnd_base(&s, &b, P, N, 2 + 30 * rnd01(&s));
        if (k % 2) { /* snap to halves of cells: edges through corners */
            double g[3][2];
            for (int v = 0; v < 3; v++)
                for (int c = 0; c < 2; c++)
                    g[v][c] = floor(b.g[v][c] * 2) / 2;
            const float *p[3] = {P[0], P[1], P[2]}, *n[3] = {N[0], N[1], N[2]};
            mr_dheights hs = {tex_height, NULL};
            mr_dbase_init(&b, g, p, n, &hs);
        }
        int64_t i0, i1, j0, j1;
        mr_dbase_cells(&b, &i0, &i1, &j0, &j1);
        for (int64_t j = j0; j <= j1; j++)
            for (int64_t i = i0; i <= i1; i++)
                for (int half = 0; half <= 2; half++) {
                    mr_dcell fast, cut;
                    mr_dsurf_cell(&b, i, j, half, &fast);
                    mr_dsurf_cell_cut(&b, i, j, half, &cut);
                    assert_same_cell(&fast, &cut);
                    if (!mr_dsurf_cell_inside(&b, i, j)) /* and every record, in order */
                        assert_same_records(&fast, &cut);
                    compared++;
                    crossed += half == 2 && !mr_dsurf_cell_inside(&b, i, j) && cut.nt > 0;
                }
    }
    assert_true(compared > 100000);
    assert_true(crossed > 10000);
}

/* Every micro-vertex lies in its triangle's box and its cell's boxes. */
static void test_boxes_hold_micro_vertices(void **state)
{
    (void)state;
    uint64_t s = 3;
    mr_dheights hs = {tex_height, NULL};
    long checked = 0;
    for (int k = 0; k < 200; k++) {
        mr_dbase b;
        float P[3][3], N[3][3];
        rnd_base(&s, &b, P, N, 3 + 20 * rnd01(&s));
        if (b.flat)
            continue;
        mr_dgrad gr = {0};
        mr_dgrad_init(&gr, &b, -0.03, 0.07);
        float tlo[3], thi[3];
        mr_dtrace_tri_box(&b, &hs, &gr, tlo, thi);
        int64_t i0, i1, j0, j1;
        mr_dbase_cells(&b, &i0, &i1, &j0, &j1);
        for (int64_t j = j0; j <= j1; j++)
            for (int64_t i = i0; i <= i1; i++) {
                mr_dcell c;
                mr_dsurf_cell(&b, i, j, 2, &c);
                float clo[3], chi[3];
                bool boxed = mr_dtrace_rect_box(&b, &gr, (double)i, (double)i + 1, (double)j,
                                                (double)j + 1, -0.03, 0.07, clo, chi);
                for (int v = 0; v < c.nv; v++) {
                    mr_vec3 x = mr_dsurf_vertex(&b, &hs, &c.v[v]);
                    float xv[3] = {x.x, x.y, x.z};
                    assert_true(boxed);
                    for (int a = 0; a < 3; a++) {
                        assert_true(xv[a] >= tlo[a] && xv[a] <= thi[a]);
                        assert_true(xv[a] >= clo[a] && xv[a] <= chi[a]);
                    }
                    double l[3];
                    if (gr.local) {
                        mr_dtrace_local_point(&gr, &b, x, l);
                        double lo[3], hi[3];
                        mr_dtrace_local_box(&gr, (double)i, (double)i + 1, (double)j,
                                            (double)j + 1, -0.03, 0.07, lo, hi);
                        for (int a = 0; a < 3; a++)
                            if (!(l[a] >= lo[a] && l[a] <= hi[a]))
                                fail_msg("local coordinate %d of a micro-vertex %.17g outside "
                                         "[%.17g, %.17g]", a, l[a], lo[a], hi[a]);
                    }
                    checked++;
                }
            }
    }
    assert_true(checked > 10000);
}

/* ---- the traversal ----------------------------------------------------------------- */

static const float PLANE_P[] = {-1, 0, 1, 1, 0, 1, 1, 0, -1, -1, 0, -1};
static const float PLANE_N[] = {0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0};
static const float PLANE_UV[] = {0, 0, 1, 0, 1, 1, 0, 1};
static const uint32_t PLANE_I[] = {0, 1, 2, 0, 2, 3};

static void test_plane_against_brute_force(void **state)
{
    (void)state;
    uint64_t seed = 11;
    mr_asset *mesh = dfx_mesh(PLANE_P, PLANE_N, PLANE_UV, 4, PLANE_I, 2);
    mr_asset *tex = dfx_texture(37, 23, MR_SAMPLE_U8, dfx_noise, &seed); /* not a power of two */
    dfx f = {0};
    dfx_params(&f, 0.2f, -0.05f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    assert_int_equal(dfx_random_rays(&f, &seed, 3000), 0);
    assert_true(f.hits > 1000);
    /* straight down the middle of every texel corner: edges and vertices */
    int bad = 0;
    for (int j = 0; j <= 23; j++)
        for (int i = 0; i <= 37; i++) {
            float x = -1 + 2.0f * i / 37, z = 1 - 2.0f * j / 23;
            bad += dfx_check_ray(&f, mr_v3(x, 2, z), mr_v3(0, -1, 0), 0, INFINITY);
            bad += dfx_check_ray(&f, mr_v3(x + 0.3f, 1, z - 0.2f), mr_v3(-0.3f, -1, 0.2f), 0, INFINITY);
        }
    /* directions whose largest components tie in magnitude, each sign: the
     * watertight set-up's axis choice (its ties broken one way, made one
     * ray at a time or eight at once) must be the same alone and in a
     * packet */
    static const float TIED[4][3] = {{1, -1, 0.2f}, {0.2f, -1, 1}, {1, -0.5f, 1}, {1, -1, 1}};
    for (int d = 0; d < 4; d++)
        for (int sg = 0; sg < 4; sg++) {
            const mr_vec3 dir = mr_v3(sg & 1 ? -TIED[d][0] : TIED[d][0], TIED[d][1],
                                      sg & 2 ? -TIED[d][2] : TIED[d][2]);
            for (int j = 0; j < 7; j++)
                for (int i = 0; i < 7; i++) {
                    const mr_vec3 at = mr_v3(-0.9f + 0.3f * i, 0, -0.9f + 0.3f * j);
                    bad += dfx_check_ray(&f, mr_v3_sub(at, mr_v3_scale(dir, 1.5f)), dir, 0,
                                         INFINITY);
                }
        }
    assert_int_equal(bad, 0);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* The traversal keeps the cells it made per thread, valid for one pose of
 * the bases (dtrace.c cell_get): a small object whose every cell fits in
 * that cache, traced, moved (a new transform: new bases under the same
 * Embree geometry), traced again, must meet its new surface, not the
 * cells of the old one. Fails when a new pose keeps the old pose's id. */
static void test_new_pose_new_cells(void **state)
{
    (void)state;
    uint64_t seed = 17;
    mr_asset *mesh = dfx_mesh(PLANE_P, PLANE_N, PLANE_UV, 4, PLANE_I, 2);
    mr_asset *tex = dfx_texture(3, 2, MR_SAMPLE_U8, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.3f, 0.0f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    /* The same rays twice in one pose (each alone, in packets of 8 and as
     * occlusion queries): the first time each cell is made once (a 3 x 2
     * texture: the two triangles' boxes touch at most 2 x 5 x 4 cells,
     * with the cells along their edges), the second time every one comes
     * from this thread's cache. A direct-mapped cache made 622 and 598
     * here: two cells of the two triangles shared a slot. */
    for (int pass = 0; pass < 2; pass++) {
        fx_kind_stat(&mr_kind_displaced, f.geom, "displaced_cells"); /* clears */
        uint64_t again = 99;
        assert_int_equal(dfx_random_rays(&f, &again, 200), 0);
        double cells = fx_kind_stat(&mr_kind_displaced, f.geom, "displaced_cells");
        if (pass == 0 ? !(cells >= 6 && cells <= 40) : cells != 0)
            fail_msg("pass %d: %g cells made", pass, cells);
    }
    static const float LIFT[] = {0.0f, 0.05f, 0.4f, -0.7f};
    for (int k = 0; k < 4; k++) {
        if (k > 0) {
            mr_mat4 m = mr_mat4_from_trs(mr_v3(0.1f * (float)k, LIFT[k], 0),
                                         mr_quat_from_axis_angle(mr_v3(1, 0, 0), 0.2f * (float)k),
                                         mr_v3(1, 1, 1));
            dfx_repose(&f, NULL, &m, 0);
        }
        /* straight down through every cell's middle and corners, then
         * random rays: each pose's own tessellation is the reference */
        int bad = 0;
        for (int j = 0; j <= 4; j++)
            for (int i = 0; i <= 6; i++) {
                mr_vec3 o = mr_v3(-1 + (float)i / 3, 3, 1 - (float)j / 2);
                bad += dfx_check_ray(&f, o, mr_v3(0.05f, -1, 0.02f), 0, INFINITY);
            }
        bad += dfx_random_rays(&f, &seed, 300);
        if (bad)
            fail_msg("pose %d: %d rays disagree with the brute force", k, bad);
    }
    assert_true(f.hits > 500);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* A ray tests only the micro-triangles of the cells whose boxes it enters,
 * also where the grid is so coarse that a base triangle's roots are its
 * cells (a 2 x 2 texture on the plane's two triangles). Straight down
 * through a point of each cell, alone and as a packet of 8 such rays, a
 * ray tests the micro-triangles of the cell at that point only: the plane
 * is flat, so a cell's box holds the rays through its own square (a cell
 * cut by the texture's edge is a fan of 3; one cut by the base diagonal,
 * two parts of 3 in the two triangles: at most 6). Before the roots had
 * boxes every ray tested all 18 micro-triangles of both triangles. */
static void test_coarse_roots_culled(void **state)
{
    (void)state;
    uint64_t seed = 5;
    /* UVs inside the texture's square, so each triangle's cells span two
     * per axis and the roots are level 0 */
    static const float UV[] = {0.05f, 0.05f, 0.95f, 0.05f, 0.95f, 0.95f, 0.05f, 0.95f};
    mr_asset *mesh = dfx_mesh(PLANE_P, PLANE_N, UV, 4, PLANE_I, 2);
    mr_asset *tex = dfx_texture(2, 2, MR_SAMPLE_U8, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.3f, 0.0f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    for (int j = 0; j < 2; j++)
        for (int i = 0; i < 2; i++) {
            /* (u, v) a little off the cell's centre, off the base diagonal */
            float u = ((float)i + 0.35f) / 2, v = ((float)j + 0.6f) / 2;
            float su = (u - 0.05f) / 0.9f, sv = (v - 0.05f) / 0.9f; /* across the plane */
            mr_vec3 o = mr_v3(-1 + 2 * su, 3, 1 - 2 * sv), d = mr_v3(0, -1, 0);
            fx_kind_stat(&mr_kind_displaced, f.geom, "displaced_tests"); /* clears */
            float t;
            assert_true(dfx_trace(&f, o, d, 0, INFINITY, &t, NULL));
            double alone = fx_kind_stat(&mr_kind_displaced, f.geom, "displaced_tests");
            RTC_ALIGN(32) int valid[8];
            struct RTCRayHit8 rh;
            const mr_vec3 same[8] = {d, d, d, d, d, d, d, d};
            dfx_packet_rays(o, same, 0, INFINITY, valid, &rh);
            struct RTCIntersectContext ic;
            rtcInitIntersectContext(&ic);
            ic.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
            rtcIntersect8(valid, f.scene, &ic, &rh);
            double packet = fx_kind_stat(&mr_kind_displaced, f.geom, "displaced_tests");
            for (int k = 0; k < 8; k++)
                assert_true(rh.ray.tfar[k] == t);
            if (!(alone >= 2 && alone <= 6) || packet != 8 * alone)
                fail_msg("cell (%d, %d): %g micro-triangle tests alone, %g for 8 such rays in a "
                         "packet (2 .. 6 per ray expected)", i, j, alone, packet);
        }
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* A 5 x 4 grid of quads, bumpy, with random normals and UVs repeating 3x. */
static mr_asset *bumpy_grid(uint64_t *s, float uv_repeat)
{
    enum { NX = 6, NY = 5 };
    float P[NX * NY * 3], N[NX * NY * 3], UV[NX * NY * 2];
    uint32_t I[(NX - 1) * (NY - 1) * 6];
    for (int y = 0; y < NY; y++)
        for (int x = 0; x < NX; x++) {
            int v = y * NX + x;
            P[v * 3] = (float)x * 0.4f - 1, P[v * 3 + 1] = rndf(s, -0.15f, 0.15f),
            P[v * 3 + 2] = (float)y * 0.4f - 0.8f;
            mr_vec3 n = mr_v3_normalize_or(mr_v3_add(mr_v3(0, 1.5f, 0), rnd_unit(s)), mr_v3(0, 1, 0));
            N[v * 3] = n.x, N[v * 3 + 1] = n.y, N[v * 3 + 2] = n.z;
            UV[v * 2] = uv_repeat * (float)x / (NX - 1);
            UV[v * 2 + 1] = uv_repeat * (float)y / (NY - 1);
        }
    return dfx_mesh(P, N, UV, NX * NY, I, grid_triangles(NX, NY, I));
}

static void test_bumpy_mesh_against_brute_force(void **state)
{
    (void)state;
    uint64_t seed = 21;
    mr_asset *mesh = bumpy_grid(&seed, 3);
    mr_asset *tex = dfx_texture(16, 9, MR_SAMPLE_U16, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.3f, 0.0f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    assert_int_equal(dfx_random_rays(&f, &seed, 3000), 0);
    /* the same object at a mip level, and with bilinear leaves off: the
     * tessellation is triangles, so only "triangles" is compared */
    dfx_close(&f);
    f.par.level = 2;
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    assert_int_equal(dfx_random_rays(&f, &seed, 2000), 0);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

static void test_sphere_against_brute_force(void **state)
{
    (void)state;
    const char *dir = getenv("MR_SOURCE_DIR");
    char path[1024];
    snprintf(path, sizeof path, "%s/examples/models/sphere960.obj", dir ? dir : ".");
    mr_asset *mesh = NULL;
    mr_error err;
    if (mr_asset_load(path, &mesh, &err) != MR_OK)
        fail_msg("%s", err.msg);
    assert_int_equal(mr_asset_triangle_count(mesh), 960);
    uint64_t seed = 31;
    mr_asset *tex = dfx_texture(40, 30, MR_SAMPLE_U8, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.1f, 0.0f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    assert_int_equal(dfx_random_rays(&f, &seed, 1500), 0);
    /* the poles (y = +-1): each a fan of triangles with two corners at
     * the pole, whose map has no area in space (no local frame: rays are
     * culled by an oriented box, mr_dgrad.ob); rays from around at
     * micro-vertices near them */
    int near_poles = 0, bad = 0;
    for (uint32_t i = 0; i < f.tess.vertex_count && near_poles < 800; i++) {
        const mr_vec3 v = dfx_vertex(&f.tess, i);
        if (fabsf(v.y) < 0.97f)
            continue;
        const mr_vec3 o = mr_v3_add(v, mr_v3_scale(rnd_unit(&seed), 3.0f));
        bad += dfx_check_ray(&f, o, mr_v3_sub(v, o), 0.0f, INFINITY);
        near_poles++;
    }
    assert_true(near_poles == 800);
    assert_int_equal(bad, 0);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* A constant texture is the base mesh moved by offset + scale * value along
 * its unit normals: on the plane, exactly the plane at that height. */
static double constant(uint32_t x, uint32_t y, void *user)
{
    (void)x, (void)y, (void)user;
    return 128;
}

static void test_constant_texture_is_offset_base(void **state)
{
    (void)state;
    mr_asset *mesh = dfx_mesh(PLANE_P, PLANE_N, PLANE_UV, 4, PLANE_I, 2);
    mr_asset *tex = dfx_texture(13, 7, MR_SAMPLE_U8, constant, NULL);
    dfx f = {0};
    dfx_params(&f, 0.255f, 0.1f);
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    float h = (float)(0.1 + 0.255 * (128.0 / 255.0));
    for (uint32_t v = 0; v < f.tess.vertex_count; v++)
        assert_true(fabsf(f.tess.positions[v * 3 + 1] - h) <= 1e-7f);
    uint64_t seed = 5;
    int bad = 0;
    for (int k = 0; k < 500; k++) {
        float x = rndf(&seed, -0.99f, 0.99f), z = rndf(&seed, -0.99f, 0.99f);
        float t;
        mr_vec3 ng;
        assert_true(dfx_trace(&f, mr_v3(x, 3, z), mr_v3(0, -1, 0), 0, INFINITY, &t, &ng));
        bad += fabsf(3 - t - h) > 1e-6f;
        mr_vec3 n = mr_v3_normalize_or(ng, mr_v3(0, 0, 0));
        bad += fabsf(fabsf(n.y) - 1) > 1e-5f;
    }
    assert_int_equal(bad, 0);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* ---- bilinear leaves ---------------------------------------------------------------- */

/* "local": "bilinear" makes a texel a bilinear patch through its four
 * micro-vertices instead of two triangles. The reference: every patch
 * tessellated finely (BL_SUB x BL_SUB quads), by brute force. A plane of
 * two base triangles split along the texture's anti-diagonal x + y = N, so
 * every texel lies whole in one base triangle; those that touch a base
 * edge (the plane's border, the diagonal) are cut like any texel there,
 * into triangles both sides of the edge share, so only the others are
 * patches. Rays fall steeply (at most 11 degrees off vertical) on texels
 * at least one away from any cut one, so their first hits are on
 * patches. */
#define BL_N 12
#define BL_SUB 32

/* Whether texel (i, j) touches no base edge (a patch). */
static bool bl_patch(int i, int j)
{
    return i >= 1 && j >= 1 && i <= BL_N - 2 && j <= BL_N - 2 && abs(i + j - (BL_N - 1)) >= 2;
}

/* Whether texel (i, j) and its eight neighbours are patches. */
static bool bl_deep(int i, int j)
{
    for (int b = -1; b <= 1; b++)
        for (int a = -1; a <= 1; a++)
            if (!bl_patch(i + a, j + b))
                return false;
    return true;
}

static double bl_height(const mr_image *img, const dfx *f, int i, int j)
{
    size_t at = (size_t)(BL_N - 1 - (j % BL_N)) * BL_N + (size_t)(i % BL_N);
    uint8_t s = ((const uint8_t *)img->samples)[at];
    return f->par.offset + f->par.scale * (s / 255.0);
}

static void bl_point(const mr_image *img, const dfx *f, int i, int j, double u, double v,
                     double p[3])
{
    double h00 = bl_height(img, f, i, j), h10 = bl_height(img, f, i + 1, j);
    double h01 = bl_height(img, f, i, j + 1), h11 = bl_height(img, f, i + 1, j + 1);
    p[0] = -1 + 2.0 * (i + u) / BL_N;
    p[1] = (1 - u) * (1 - v) * h00 + u * (1 - v) * h10 + (1 - u) * v * h01 + u * v * h11;
    p[2] = 1 - 2.0 * (j + v) / BL_N;
}

/* Closest hit of the ray with the finely tessellated patches of texels off
 * the base edge: t and the hit sub-triangle's normal. */
static bool bl_brute(const mr_image *img, const dfx *f, mr_vec3 o, mr_vec3 d, float *t, mr_vec3 *ng)
{
    mr_wt_ray r = mr_wt_ray_setup(o, d);
    float tmax = INFINITY;
    bool hit = false;
    for (int j = 0; j < BL_N; j++)
        for (int i = 0; i < BL_N; i++) {
            if (!bl_patch(i, j))
                continue;
            mr_vec3 q[BL_SUB + 1][BL_SUB + 1];
            for (int b = 0; b <= BL_SUB; b++)
                for (int a = 0; a <= BL_SUB; a++) {
                    double p[3];
                    bl_point(img, f, i, j, (double)a / BL_SUB, (double)b / BL_SUB, p);
                    q[b][a] = mr_v3((float)p[0], (float)p[1], (float)p[2]);
                }
            for (int b = 0; b < BL_SUB; b++)
                for (int a = 0; a < BL_SUB; a++) {
                    mr_vec3 tri[2][3] = {{q[b][a], q[b][a + 1], q[b + 1][a]},
                                         {q[b][a + 1], q[b + 1][a + 1], q[b + 1][a]}};
                    for (int k = 0; k < 2; k++) {
                        mr_wt_hit h;
                        if (mr_wt_intersect(&r, tri[k][0], tri[k][1], tri[k][2], 0, tmax, &h)) {
                            tmax = h.t;
                            hit = true;
                            *ng = mr_v3_cross(mr_v3_sub(tri[k][1], tri[k][0]),
                                              mr_v3_sub(tri[k][2], tri[k][0]));
                        }
                    }
                }
        }
    *t = tmax;
    return hit;
}

static void test_bilinear_leaves(void **state)
{
    (void)state;
    static const uint32_t ANTI[] = {0, 1, 3, 1, 2, 3}; /* split along uv (1, 0) - (0, 1) */
    uint64_t seed = 41;
    mr_asset *mesh = dfx_mesh(PLANE_P, PLANE_N, PLANE_UV, 4, ANTI, 2);
    mr_asset *tex = dfx_texture(BL_N, BL_N, MR_SAMPLE_U8, dfx_noise, &seed);
    dfx f = {0};
    dfx_params(&f, 0.2f, 0.0f);
    f.par.local = MR_DLOCAL_BILINEAR;
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    /* The tessellation differs from the patches by at most |twist| / (4
     * BL_SUB^2) in height (twist = h00 - h10 - h01 + h11, at most twice the
     * scale): 9.8e-5; along rays within 11 degrees of vertical onto slopes
     * of at most 0.8 (0.2 over a texel of 0.25) that is at most 1.6e-4 of
     * distance. Two triangles instead of the patch would be up to a quarter
     * of the twist off (0.1). */
    const double tol = 2e-4;
    int rays = 0, bad = 0, bad_normal = 0, packet = 0;
    double worst = 0;
    while (rays < 300) {
        /* a point on a texel whose neighbours are all patches */
        double gx = rndf(&seed, 0, BL_N), gy = rndf(&seed, 0, BL_N);
        if (!bl_deep((int)gx, (int)gy))
            continue;
        mr_vec3 target = mr_v3((float)(-1 + 2 * gx / BL_N), 0.1f, (float)(1 - 2 * gy / BL_N));
        mr_vec3 d = mr_v3(rndf(&seed, -0.2f, 0.2f), -1, rndf(&seed, -0.2f, 0.2f));
        d = mr_v3_normalize_or(d, mr_v3(0, -1, 0));
        mr_vec3 o = mr_v3_sub(target, mr_v3_scale(d, 2.0f));
        float tk, tb;
        mr_vec3 nk, nb;
        bool hk = dfx_trace(&f, o, d, 0, INFINITY, &tk, &nk);
        bool hb = bl_brute(tex->image, &f, o, d, &tb, &nb);
        packet += dfx_packet_check(&f, o, d, 0, INFINITY);
        rays++;
        if (!hk || !hb) {
            print_error("ray %d: kind %s, patches %s\n", rays, hk ? "hit" : "miss",
                        hb ? "hit" : "miss");
            bad++;
            continue;
        }
        double e = fabs((double)tk - (double)tb);
        worst = fmax(worst, e);
        bad += e > tol;
        double c = mr_v3_dot(mr_v3_normalize_or(nk, mr_v3(0, 0, 0)),
                             mr_v3_normalize_or(nb, mr_v3(0, 0, 0)));
        bad_normal += fabs(c) < cos(2.0 * M_PI / 180); /* sub-triangles tilt by ~|twist| / BL_SUB */
    }
    print_message("bilinear leaves: %d rays, worst distance to the finely tessellated patches %.2e "
                  "(tolerance %.0e)\n", rays, worst, tol);
    assert_int_equal(bad, 0);
    assert_int_equal(bad_normal, 0);
    assert_int_equal(packet, 0);
    /* and the patches are not the two triangles: the same rays with
     * "triangles" leaves stray from them by far more than the tolerance */
    dfx_close(&f);
    f.par.local = MR_DLOCAL_TRIANGLES;
    dfx_open(&f, mesh, tex, NULL, NULL, 0);
    double tri_worst = 0;
    for (int k = 0; k < 100; k++) {
        double gx = rndf(&seed, 0, BL_N), gy = rndf(&seed, 0, BL_N);
        if (!bl_deep((int)gx, (int)gy))
            continue;
        mr_vec3 o = mr_v3((float)(-1 + 2 * gx / BL_N), 2, (float)(1 - 2 * gy / BL_N));
        float tk, tb;
        mr_vec3 nk, nb;
        if (dfx_trace(&f, o, mr_v3(0, -1, 0), 0, INFINITY, &tk, &nk) &&
            bl_brute(tex->image, &f, o, mr_v3(0, -1, 0), &tb, &nb))
            tri_worst = fmax(tri_worst, fabs((double)tk - (double)tb));
    }
    print_message("the same rays with triangle leaves: worst distance %.2e\n", tri_worst);
    assert_true(tri_worst > 10 * tol);
    dfx_close(&f);
    mr_device_free(f.dev);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

/* ---- tiling and blending ------------------------------------------------------------ */

static mr_asset *cracked(void)
{
    mr_asset *a = NULL;
    mr_error err;
    if (mr_asset_load("/usr/share/assimp/models/IRRMesh/crackedground_1-6.jpg", &a, &err) != MR_OK)
        fail_msg("%s", err.msg);
    return a;
}

/* Fails unless [lo, hi] holds the heights of grid points (bx + sg i, by +
 * sg j) for 0 <= i, j <= n (and i + j <= n when tri), and the global bound
 * too; *least and *largest their extremes; returns how many it checked. */
static long points_within(const mr_dproc *p, int64_t bx, int64_t by, int64_t sg, int64_t n,
                          bool tri, double lo, double hi, double *least, double *largest)
{
    double glo, ghi;
    mr_dproc_global_heights(p, &glo, &ghi);
    long checked = 0;
    *least = INFINITY, *largest = -INFINITY;
    for (int64_t j = 0; j <= n; j++)
        for (int64_t i = 0; i <= n && !(tri && i + j > n); i++) {
            int64_t gi = bx + sg * i, gj = by + sg * j;
            double h = mr_dproc_height(p, gi, gj);
            if (!(h >= lo && h <= hi && h >= glo && h <= ghi))
                fail_msg("(%lld %lld %lld%s): height %.17g at (%lld %lld) outside [%.17g, %.17g]",
                         (long long)bx, (long long)by, (long long)(sg * n), tri ? ", triforce" : "",
                         h, (long long)gi, (long long)gj, lo, hi);
            *least = fmin(*least, h), *largest = fmax(*largest, h);
            checked++;
        }
    return checked;
}

/* The traversal's nodes are squares of 2^l x 2^l cells (mr_dtrace); their
 * halves, cut by the anti-diagonal, are the triforce nodes of leg 2^l.
 * Over six lattice squares of range 16 (two of them at negative indices),
 * every square of every level holds the heights of its grid points, and
 * so does each of its halves; squares of side up to MR_DPROC_EXACT_LEG are
 * bounded by exactly their grid points' least and largest heights
 * (tiling.h), larger ones more widely; a square larger than a lattice
 * square gets the global bound; a bound made is kept, the same bits; the
 * children of an exact square, made together, have their own bounds. */
static void test_tiling_bounds(void **state)
{
    (void)state;
    mr_asset *ex = cracked();
    mr_dproc p;
    mr_error err;
    assert_int_equal(mr_dproc_init(&p, ex->image, 0.3, 0.7, 1.5, 0.25, 9, 16, 0.2, -0.05, 2, &err),
                     MR_OK);
    assert_int_equal(p.top, 4);
    double glo, ghi;
    mr_dproc_global_heights(&p, &glo, &ghi);
    long checked = 0, exact = 0, wide = 0, children = 0;
    for (int sq = 0; sq < 6; sq++) {
        const int64_t ax = sq * 3 - 5, ay = 2 - sq;
        for (int l = 0; l <= 4; l++) {
            const int64_t n = (int64_t)1 << l, per = 16 / n;
            for (int64_t y = ay * per; y < (ay + 1) * per; y++)
                for (int64_t x = ax * per; x < (ax + 1) * per; x++) {
                    double lo, hi, least, largest, klo, khi;
                    mr_dproc_square_heights(&p, l, x, y, &lo, &hi);
                    assert_true(mr_dproc_square_heights_kept(&p, l, x, y, &klo, &khi));
                    assert_true(klo == lo && khi == hi);
                    checked += points_within(&p, x * n, y * n, 1, n, false, lo, hi, &least,
                                             &largest);
                    if (n <= MR_DPROC_EXACT_LEG) {
                        assert_true(lo == least && hi == largest);
                        exact++;
                    } else {
                        wide += lo < least && hi > largest;
                    }
                    /* its halves (the lower-left one, the upper-right one) */
                    double tlo[2], thi[2];
                    for (int o = 0; o < 2; o++) {
                        int64_t bx = (x + o) * n, by = (y + o) * n, sg = o ? -1 : 1;
                        mr_dproc_tri_heights(&p, bx, by, sg * n, &tlo[o], &thi[o]);
                        checked += points_within(&p, bx, by, sg, n, true, tlo[o], thi[o], &least,
                                                 &largest);
                        if (n <= MR_DPROC_EXACT_LEG)
                            assert_true(tlo[o] == least && thi[o] == largest);
                    }
                    assert_true(lo == fmin(tlo[0], tlo[1]) && hi == fmax(thi[0], thi[1]));
                    if (l >= 1 && n <= MR_DPROC_EXACT_LEG) { /* its children from one tile */
                        double clo[4], chi[4];
                        mr_dproc_child_heights(&p, l, x, y, clo, chi);
                        for (int k = 0; k < 4; k++) {
                            double sl, sh;
                            mr_dproc_square_heights(&p, l - 1, 2 * x + (k & 1), 2 * y + (k >> 1),
                                                    &sl, &sh);
                            assert_true(clo[k] == sl && chi[k] == sh);
                        }
                        children++;
                    }
                }
        }
        double lo, hi;
        mr_dproc_square_heights(&p, 5, ax / 2, ay / 2, &lo, &hi);
        assert_true(lo == glo && hi == ghi);
    }
    assert_true(checked > 10000);
    /* per lattice square, the 256 + 64 + 16 squares of sides 1, 2 and 4
     * exact, the 4 + 1 of sides 8 and 16 bounded more widely */
    _Static_assert(MR_DPROC_EXACT_LEG == 4, "the counts below are for leg 4");
    assert_int_equal(exact, 6 * (256 + 64 + 16));
    assert_int_equal(wide, 6 * (4 + 1));
    assert_int_equal(children, 6 * (64 + 16));
    mr_dproc_free(&p);
    /* a range not a power of two has no squares of lattice squares */
    assert_int_equal(mr_dproc_init(&p, ex->image, 0.3, 0.7, 1.5, 0.25, 9, 12, 0.2, -0.05, 2, &err),
                     MR_ERR_INVALID);
    mr_asset_free(ex);
}

/* A base triangle over about size x size grid cells around (cx, cy) (a
 * flat base: the grid alone matters here). */
static void grid_triangle(uint64_t *s, double size, double cx, double cy, const mr_dheights *hs,
                          mr_dbase *b)
{
    double g[3][2];
    float P[3][3] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}}, N[3][3] = {{0, 0, 1}, {0, 0, 1}, {0, 0, 1}};
    for (int c = 0; c < 3; c++)
        g[c][0] = (rnd01(s) - 0.5) * size + cx, g[c][1] = (rnd01(s) - 0.5) * size + cy;
    const float *pp[3] = {P[0], P[1], P[2]}, *nn[3] = {N[0], N[1], N[2]};
    mr_dbase_init(b, g, pp, nn, hs);
}

/* The larger side of T's grid box. */
static double b_size(const mr_dbase *b)
{
    double w = 0;
    for (int a = 0; a < 2; a++)
        w = fmax(w, fmax(fmax(b->g[0][a], b->g[1][a]), b->g[2][a]) -
                        fmin(fmin(b->g[0][a], b->g[1][a]), b->g[2][a]));
    return w;
}

/* Whether cell (i, j) lies under one of the roots rs. */
static bool proot_covers(const mr_dproots *rs, int64_t i, int64_t j)
{
    for (int k = 0; k < rs->n; k++) {
        const mr_dpnode *n = &rs->r[k];
        if (i >> n->level == n->x && j >> n->level == n->y)
            return true;
    }
    return false;
}

/* Fails unless lo .. hi holds T's corner heights and those of the grid
 * points of every cell where T has micro-triangles (and, rs not NULL, the
 * cell lies under one of T's roots); returns how many it checked. */
static long cells_within(const mr_dbase *b, const mr_dheights *hs, double lo, double hi,
                         const mr_dproots *rs)
{
    long checked = 0;
    for (int c = 0; c < 3; c++)
        assert_true(b->h[c] >= lo && b->h[c] <= hi);
    int64_t i0, i1, j0, j1;
    mr_dbase_cells(b, &i0, &i1, &j0, &j1);
    for (int64_t j = j0; j <= j1; j++)
        for (int64_t i = i0; i <= i1; i++) {
            mr_dcell c;
            mr_dsurf_cell(b, i, j, 2, &c);
            if (c.nt == 0)
                continue;
            if (rs && !proot_covers(rs, i, j))
                fail_msg("cell (%lld %lld) under none of T's %d roots", (long long)i,
                         (long long)j, rs->n);
            for (int q = 0; q < 4; q++) {
                double h = hs->at(hs->src, i + (q & 1), j + (q >> 1));
                if (!(h >= lo && h <= hi))
                    fail_msg("cell (%lld %lld): height %.17g outside [%.17g, %.17g]",
                             (long long)i, (long long)j, h, lo, hi);
                checked++;
            }
        }
    return checked;
}

/* A base triangle's procedural roots and height bound
 * (mr_dtrace_proc_roots; the bound is its Embree box's and every node's
 * cap): the roots, at most four, cover every cell where T has
 * micro-triangles, and the bound holds the heights of those cells' grid
 * points and of T's corners; over a few cells it is far narrower than the
 * global bound it replaced. */
static void test_proc_triangle_roots(void **state)
{
    (void)state;
    mr_asset *ex = cracked();
    uint64_t s = 5;
    for (uint32_t range = 8; range <= 64; range *= 8) {
        mr_dproc p;
        mr_error err;
        assert_int_equal(mr_dproc_init(&p, ex->image, 0.3, 0.7, 1.5, 0.25, 9, range, 0.2, -0.05, 2,
                                       &err),
                         MR_OK);
        mr_dheights hs = mr_dproc_heights(&p);
        double glo, ghi, small_width = 0;
        mr_dproc_global_heights(&p, &glo, &ghi);
        long checked = 0, small = 0, roots = 0;
        for (int k = 0; k < 120; k++) {
            /* a triangle over 2 to 30 cells, or (one in four) up to 600 */
            mr_dbase b;
            grid_triangle(&s, k % 4 ? 2 + 28 * rnd01(&s) : 2 + 600 * rnd01(&s), 1000 * (k - 60),
                          0, &hs, &b);
            double lo, hi;
            mr_dproots rs;
            mr_dtrace_proc_roots(&p, &b, &rs, &lo, &hi);
            assert_true(rs.n >= 1 && rs.n <= 4);
            roots += rs.n;
            checked += cells_within(&b, &hs, lo, hi, &rs);
            if (b_size(&b) < 10) {
                small_width += (hi - lo) / (ghi - glo);
                small++;
            }
        }
        print_message("range %u: %ld grid heights checked, %.2f roots per triangle; triangles "
                      "over < 10 cells: mean bound %.3f of the global one\n", range, checked,
                      (double)roots / 120, small_width / (double)small);
        assert_true(checked > 5000);
        /* measured 0.46 (range 8) and 0.32 (64); the global bound is 1 */
        assert_true(small > 10 && small_width / (double)small < 0.5);
        mr_dproc_free(&p);
    }
    mr_asset_free(ex);
}

/* A base triangle's texture height bound (mr_dtrace_root_heights: its
 * Embree box's) holds the heights of every grid point of every cell where
 * T has micro-triangles, and of T's corners, and is at most its roots'
 * union (what it was before it looked below them). */
static void test_texture_triangle_heights(void **state)
{
    (void)state;
    mr_asset *ex = cracked();
    mr_dgrid g;
    mr_error err;
    assert_int_equal(mr_dgrid_init(&g, ex->image, 0, 0.2, -0.05, 2, &err), MR_OK);
    mr_dheights hs = mr_dgrid_heights(&g);
    uint64_t s = 9;
    long checked = 0;
    double ratio = 0;
    int tris = 0;
    for (int k = 0; k < 150; k++) {
        /* a triangle over 2 to 60 texels */
        mr_dbase b;
        grid_triangle(&s, 2 + 58 * rnd01(&s), 37 * k, -11 * k, &hs, &b);
        if (b.flat)
            continue;
        double lo, hi, rlo = INFINITY, rhi = -INFINITY;
        mr_dtrace_root_heights(&g, &b, &lo, &hi);
        mr_droots rs;
        mr_dtrace_roots(&g, &b, &rs);
        for (int r = 0; r < rs.n; r++) {
            double l, h;
            assert_true(rs.r[r].level <= (int)g.levels);
            mr_dgrid_node_heights(&g, (unsigned)rs.r[r].level, rs.r[r].I, rs.r[r].J, &l, &h);
            rlo = fmin(rlo, l), rhi = fmax(rhi, h);
        }
        for (int c = 0; c < 3; c++)
            rlo = fmin(rlo, b.h[c]), rhi = fmax(rhi, b.h[c]);
        assert_true(lo >= rlo && hi <= rhi);
        checked += cells_within(&b, &hs, lo, hi, NULL);
        if (rhi > rlo) {
            ratio += (hi - lo) / (rhi - rlo);
            tris++;
        }
    }
    print_message("%ld grid heights checked; bound / the roots' bound: mean %.3f\n", checked,
                  ratio / tris);
    assert_true(checked > 10000);
    /* measured 0.71; the roots' union reads 1 */
    assert_true(tris > 100 && ratio / tris < 0.8);
    mr_dgrid_free(&g);
    mr_asset_free(ex);
}

/* A grid point's height, read from the thread's tiles of heights, is the
 * blend's height bit for bit, whichever tile was made first (a tile takes
 * its edges from the neighbours kept) and however many were made in
 * between: points around the origin (negative indices,
 * tiles' edges and corners, which two to four tiles hold) visited in a
 * shuffled order, then again after points far apart have taken every
 * slot of the cache, then a second texture's points (its own id). */
static void test_tiled_heights(void **state)
{
    (void)state;
    mr_asset *ex = cracked();
    mr_dproc p, q;
    mr_error err;
    assert_int_equal(mr_dproc_init(&p, ex->image, 0.3, 0.7, 1.5, 0.25, 9, 16, 0.2, -0.05, 2, &err),
                     MR_OK);
    assert_int_equal(mr_dproc_init(&q, ex->image, 0.1, 0.2, 1.0, 0.25, 5, 16, 0.3, 0.1, 2, &err),
                     MR_OK);
    enum { SIDE = 19 }; /* points -9 .. 9 */
    int order[SIDE * SIDE];
    for (int k = 0; k < SIDE * SIDE; k++)
        order[k] = k;
    uint64_t seed = 3;
    for (int k = SIDE * SIDE - 1; k > 0; k--) {
        int m = (int)(rnd01(&seed) * (k + 1));
        m = m > k ? k : m;
        int t = order[k];
        order[k] = order[m], order[m] = t;
    }
    long checked = 0;
    for (int pass = 0; pass < 3; pass++) {
        const mr_dproc *d = pass == 2 ? &q : &p;
        for (int k = 0; k < SIDE * SIDE; k++) {
            const int64_t i = order[k] % SIDE - 9, j = order[k] / SIDE - 9;
            const double direct = mr_dproc_height_of_blend(d, mr_dproc_blend(d, i, j));
            if (mr_dproc_height(d, i, j) != direct)
                fail_msg("pass %d: height of (%lld %lld) %.17g, the blend's %.17g", pass,
                         (long long)i, (long long)j, mr_dproc_height(d, i, j), direct);
            checked++;
        }
        for (int64_t f = 0; f < 20000; f++) /* every slot taken by far points */
            (void)mr_dproc_height(&p, 100000 + 7 * f, -50000 - 13 * f);
    }
    assert_int_equal(checked, 3 * SIDE * SIDE);
    mr_dproc_free(&q);
    mr_dproc_free(&p);
    mr_asset_free(ex);
}

/* The histogram of the tiled-and-blended heights matches the example's
 * (T^-1 restores it: HN18), and the texture does not repeat at the
 * example's period (a plain repeat correlates 1 with itself there).
 * Figures printed for the README. */
static void test_tiling_histogram_and_period(void **state)
{
    (void)state;
    mr_asset *ex = cracked();
    mr_dproc p;
    mr_error err;
    /* one example tile per texture unit; grid points every 1/64 lattice */
    assert_int_equal(mr_dproc_init(&p, ex->image, 0, 0, 1, 0.25, 3, 64, 1.0, 0.0, 2, &err), MR_OK);
    enum { BINS = 64, N = 512 };
    double hex[BINS] = {0}, hp[BINS] = {0};
    double unit = mr_image_unit(ex->image);
    size_t ne = (size_t)ex->image->width * ex->image->height;
    for (uint32_t y = 0; y < ex->image->height; y++)
        for (uint32_t x = 0; x < ex->image->width; x++) {
            int b = (int)(mr_image_sample(ex->image, x, y) / unit * BINS);
            hex[b < BINS ? b : BINS - 1] += 1.0 / (double)ne;
        }
    /* a patch of the procedural texture sampled in texture space: the grid
     * point nearest each sample (lattice = texture / 0.25, skewed) */
    static double img[N][N];
    for (int y = 0; y < N; y++)
        for (int x = 0; x < N; x++) {
            double g[2];
            mr_dproc_grid_of(&p, (float)(x / 256.0 + 0.5), (float)(y / 256.0 + 0.5), g);
            double h = mr_dproc_height(&p, (int64_t)floor(g[0]), (int64_t)floor(g[1]));
            img[y][x] = h;
            int b = (int)(h * BINS);
            hp[b < 0 ? 0 : b < BINS ? b : BINS - 1] += 1.0 / (N * N);
        }
    /* histogram distance: half the L1 distance (total variation, 0..1) */
    double tv = 0;
    for (int b = 0; b < BINS; b++)
        tv += 0.5 * fabs(hex[b] - hp[b]);
    /* autocorrelation at one example period (256 samples = 1 texture unit) */
    double mean = 0, var = 0, cov = 0;
    int m = 0;
    for (int y = 0; y < N; y++)
        for (int x = 0; x < N; x++)
            mean += img[y][x];
    mean /= N * N;
    for (int y = 0; y < N; y++)
        for (int x = 0; x < N; x++)
            var += (img[y][x] - mean) * (img[y][x] - mean);
    var /= N * N;
    for (int y = 0; y < N; y++)
        for (int x = 0; x + 256 < N; x++, m++)
            cov += (img[y][x] - mean) * (img[y][x + 256] - mean);
    double ac = cov / m / var;
    print_message("tiling and blending of crackedground_1-6.jpg: histogram distance (total "
                  "variation, 64 bins) %.4f, autocorrelation at the example's period %.4f "
                  "(a plain repeat: 1)\n", tv, ac);
    assert_true(tv < 0.1);
    assert_true(fabs(ac) < 0.2);
    mr_dproc_free(&p);
    mr_asset_free(ex);
}

/* Range 8: the squares from the lattice square (side 8) down; range 64
 * adds the large squares' blend bounds and the parent-heights test before
 * them and before the exact ones (mr_dtrace_intersect_packet). */
static void test_procedural_against_brute_force(void **state)
{
    (void)state;
    uint64_t seed = 41;
    mr_asset *mesh = bumpy_grid(&seed, 1);
    mr_asset *ex = cracked();
    static const uint32_t RANGES[] = {8, 64};
    for (size_t k = 0; k < sizeof RANGES / sizeof RANGES[0]; k++) {
        dfx f = {0};
        dfx_params(&f, 0.15f, 0);
        f.par.texture = 0;
        f.par.procedural = true;
        f.par.example = 2;
        f.par.uv_scale = 0.5f;
        f.par.range = RANGES[k];
        dfx_open(&f, mesh, ex, NULL, NULL, 0);
        assert_int_equal(dfx_random_rays(&f, &seed, 1500), 0);
        dfx_close(&f);
        mr_device_free(f.dev);
    }
    mr_asset_free(mesh);
    mr_asset_free(ex);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_affine_arith),
        cmocka_unit_test(test_pyramid_any_size),
        cmocka_unit_test(test_whole_cells_are_cut_cells),
        cmocka_unit_test(test_cells_are_their_cuts),
        cmocka_unit_test(test_boxes_hold_micro_vertices),
        cmocka_unit_test(test_plane_against_brute_force),
        cmocka_unit_test(test_new_pose_new_cells),
        cmocka_unit_test(test_coarse_roots_culled),
        cmocka_unit_test(test_bumpy_mesh_against_brute_force),
        cmocka_unit_test(test_sphere_against_brute_force),
        cmocka_unit_test(test_constant_texture_is_offset_base),
        cmocka_unit_test(test_bilinear_leaves),
        cmocka_unit_test(test_tiling_bounds),
        cmocka_unit_test(test_tiled_heights),
        cmocka_unit_test(test_tiling_histogram_and_period),
        cmocka_unit_test(test_proc_triangle_roots),
        cmocka_unit_test(test_texture_triangle_heights),
        cmocka_unit_test(test_procedural_against_brute_force),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
