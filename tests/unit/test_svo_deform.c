/*
 * test_svo_deform.c - per-frame selection, deformation and resampling of an
 * octree instance (core/kinds/svo/deform.h) on real octrees (the BCN rig
 * voxelised with mr_svo_voxelize) and hand-built tiny ones
 * (tests/support/svo_fixture.h).
 *
 * Coverage is checked with the library's ray caster as a point query:
 * mr_svo_intersect(out, p, (1, 1, 1), 0, 0) hits exactly when p lies in a
 * closed leaf box of the output octree (svo_trace.h). Points are floats, as
 * the boxes are, so the check is exact: no tolerance.
 *
 * Cases: extremes against a brute-force walk; the identity (selection =
 * leaves, emit covers every leaf cell completely, resize covers every leaf
 * centre, its neighbourhood and every corner shared by 8 leaves); the
 * matrix convention of Fig. 16 (a 90-degree turn about z takes +x to +y);
 * emit covering every deformed box under a shear and a twist field; resize
 * emitting exactly 8 cells per box and being exact under a uniform scale
 * of 2; screen-space refinement and culling; a real pose of the rig against
 * mr_skin_mesh; identical results for 1, 2 and 3 threads.
 */
/* the fixture's ray-checking half is not used here */
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-function"
#include "../support/svo_fixture.h"
#pragma GCC diagnostic pop

#include "../support/bcn_fixture.h"
#include "anim/pose.h"
#include "kinds/svo/deform.h"
#include "kinds/svo/voxelize.h"
#include "../support/svo_rig.h"

/* ---- helpers */

/* The skinning deformer of pose placed by object (deform.h's mr_svo_skin,
 * the one the svo kind uses). */
static void skin_posed(mr_svo_skin *r, const mr_asset *a, const mr_pose *pose, const mr_mat4 *object)
{
    mr_error err = {0};
    assert_int_equal(mr_svo_skin_init(r, a, &err), MR_OK);
    mr_svo_skin_pose(r, a, pose, object);
}

static mr_svo *voxelize(const mr_asset *a, unsigned depth)
{
    mr_svo_voxelize_params p = {.depth = depth, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    mr_svo *s = NULL;
    mr_error err = {0};
    if (mr_svo_voxelize(a, &p, &s, &err) != MR_OK)
        fail_msg("voxelize: %s", err.msg);
    return s;
}

static void extremes(const mr_svo *s, mr_svo_extremes *e)
{
    mr_error err = {0};
    if (mr_svo_extremes_build(s, e, &err) != MR_OK)
        fail_msg("extremes: %s", err.msg);
}

static void select_ok(const mr_svo *s, const mr_svo_extremes *e, const mr_svo_deformer *d, const mr_svo_view *v,
                      unsigned max_level, unsigned threads, mr_svo_selection *out)
{
    mr_error err = {0};
    if (mr_svo_select(s, e, d, v, max_level, threads, out, &err) != MR_OK)
        fail_msg("select: %s", err.msg);
}

static void resample_ok(const mr_svo_selection *sel, mr_svo_method m, unsigned depth, const mr_svo *src,
                        unsigned threads, mr_svo *out, uint64_t *cells)
{
    mr_error err = {0};
    if (mr_svo_resample(sel, m, depth, src->palette, src->palette_count, threads, out, cells, &err) != MR_OK)
        fail_msg("resample: %s", err.msg);
    assert_null(out->leaf_keys);
    /* the palette is the source's, shared and not counted again (a copy
     * per instance was most of what an instance held) */
    assert_ptr_equal(out->palette, src->palette);
    assert_true(out->palette_borrowed);
    assert_int_equal(mr_svo_memory(out), (size_t)out->node_count * (2 * sizeof(uint32_t) + 2) +
                                             (size_t)out->leaf_count * sizeof(mr_svo_leaf));
}

static bool covered(const mr_svo *s, float x, float y, float z)
{
    return mr_svo_intersect(s, mr_v3(x, y, z), mr_v3(1, 1, 1), 0.0f, 0.0f, NULL);
}

/* Every leaf key (Morton order, so sorted by code) of s. */
static mr_svo_key *leaf_keys(const mr_svo *s, uint32_t **leaf_index)
{
    mr_svo_key *k = malloc((s->leaf_count ? s->leaf_count : 1) * sizeof *k);
    uint32_t *li = malloc((s->leaf_count ? s->leaf_count : 1) * sizeof *li);
    assert_true(k && li);
    mr_error err = {0};
    if (mr_svo_collect_keys(s, k, li, &err) != MR_OK)
        fail_msg("collect: %s", err.msg);
    if (leaf_index)
        *leaf_index = li;
    else
        free(li);
    return k;
}

static long find_key(const mr_svo_key *k, uint32_t n, uint64_t code, uint32_t level)
{
    uint32_t lo = 0, hi = n;
    while (lo < hi) {
        uint32_t m = lo + (hi - lo) / 2;
        if (k[m].code < code || (k[m].code == code && k[m].level < level))
            lo = m + 1;
        else
            hi = m;
    }
    return lo < n && k[lo].code == code && k[lo].level == level ? (long)lo : -1;
}

/* The cell of key k of s, in double. */
static void key_cell(const mr_svo *s, const mr_svo_key *k, double lo[3], double hi[3], uint32_t xyz[3])
{
    mr_morton_decode(k->code, &xyz[0], &xyz[1], &xyz[2]);
    const double o[3] = {s->origin.x, s->origin.y, s->origin.z};
    const double cell = (double)s->size * ldexp(1.0, -(int)k->level);
    for (int a = 0; a < 3; a++) {
        xyz[a] >>= s->depth - k->level;
        lo[a] = o[a] + xyz[a] * cell;
        hi[a] = o[a] + (xyz[a] + 1.0) * cell;
    }
}

static bool selections_equal(const mr_svo_selection *a, const mr_svo_selection *b)
{
    return a->count == b->count && a->visited == b->visited &&
           (a->count == 0 || (!memcmp(a->box, b->box, a->count * 6 * sizeof(float)) &&
                              !memcmp(a->leaf, b->leaf, a->count * sizeof(mr_svo_leaf)) &&
                              !memcmp(a->level, b->level, a->count)));
}

static bool svos_equal(const mr_svo *a, const mr_svo *b)
{
    if (a->depth != b->depth || a->node_count != b->node_count || a->leaf_count != b->leaf_count ||
        a->palette_count != b->palette_count || memcmp(&a->origin, &b->origin, sizeof a->origin) ||
        memcmp(&a->size, &b->size, sizeof a->size))
        return false;
    const size_t n = a->node_count;
    return (n == 0 || (!memcmp(a->first_node, b->first_node, n * 4) && !memcmp(a->first_leaf, b->first_leaf, n * 4) &&
                       !memcmp(a->child_mask, b->child_mask, n) && !memcmp(a->leaf_mask, b->leaf_mask, n))) &&
           (a->leaf_count == 0 || !memcmp(a->leaves, b->leaves, a->leaf_count * sizeof(mr_svo_leaf))) &&
           (a->palette_count == 0 || !memcmp(a->palette, b->palette, a->palette_count * sizeof(mr_svo_attr)));
}

static double angle_deg(mr_vec3 a, mr_vec3 b)
{
    double d = (double)mr_v3_dot(a, b) / ((double)mr_v3_len(a) * mr_v3_len(b));
    return acos(d > 1 ? 1 : d < -1 ? -1 : d) * 180.0 / 3.14159265358979323846;
}

/* OpenGL perspective, camera at the origin looking down -z (view = I). */
static mr_mat4 perspective(double fovy_deg, double aspect, double n, double f)
{
    const double t = 1.0 / tan(fovy_deg * 3.14159265358979323846 / 360.0);
    mr_mat4 m;
    memset(&m, 0, sizeof m);
    m.m[0] = (float)(t / aspect);
    m.m[5] = (float)t;
    m.m[10] = (float)((f + n) / (n - f));
    m.m[11] = (float)(2 * f * n / (n - f));
    m.m[14] = -1.0f;
    return m;
}

/* ---- extremes */

static uint64_t ex_seed;

static int ex_cls(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx;
    if (level == 0)
        return FX_SPLIT;
    const uint64_t h = fx_hash(ex_seed, level, x, y, z) % 100;
    /* the highest child of a split cell always exists (no empty nodes) */
    return h < 30 ? FX_LEAF : h < 75 ? FX_SPLIT : ((x & y & z) & 1u) ? FX_LEAF : FX_EMPTY;
}

static uint16_t walk_extreme(const mr_svo *s, uint32_t n, bool high)
{
    for (;;) {
        const unsigned cm = s->child_mask[n], lm = s->leaf_mask[n];
        unsigned c = high ? 7 : 0;
        while (!(cm & (1u << c)))
            c = high ? c - 1 : c + 1;
        const unsigned below = (1u << c) - 1u;
        if (lm & (1u << c))
            return s->leaves[s->first_leaf[n] + (uint32_t)__builtin_popcount(lm & below)].attr;
        n = s->first_node[n] + (uint32_t)__builtin_popcount(cm & ~lm & below);
    }
}

/* The sum of the unit normals of every leaf below node n (recursively). */
static mr_vec3 walk_normal_sum(const mr_svo *s, uint32_t n)
{
    mr_vec3 sum = mr_v3(0, 0, 0);
    const unsigned cm = s->child_mask[n], lm = s->leaf_mask[n];
    for (unsigned c = 0; c < 8; c++) {
        if (!(cm & (1u << c)))
            continue;
        const unsigned below = (1u << c) - 1u;
        mr_vec3 v = (lm & (1u << c))
                        ? mr_svo_normal_decode(s->leaves[s->first_leaf[n] + (uint32_t)__builtin_popcount(lm & below)].normal)
                        : walk_normal_sum(s, s->first_node[n] + (uint32_t)__builtin_popcount(cm & ~lm & below));
        sum = mr_v3_add(sum, v);
    }
    return sum;
}

static void test_extremes(void **state)
{
    (void)state;
    for (uint64_t seed = 1; seed <= 20; seed++) {
        ex_seed = seed;
        svo_fx fx;
        fx_build(&fx, 1 + (unsigned)(seed % 6), mr_v3(0, 0, 0), 1.0f, ex_cls, NULL);
        for (uint32_t i = 0; i < fx.svo.leaf_count; i++) {
            fx.svo.leaves[i].attr = (uint16_t)((i * 7919u) % 1000u);
            /* normals all over the upper half sphere, so no sum cancels */
            const double a = 0.37 * i, b = 0.05 + 1.4 * fmod(0.61 * i, 1.0);
            mr_svo_normal_encode(mr_v3((float)(sin(b) * cos(a)), (float)(sin(b) * sin(a)), (float)cos(b)),
                                 fx.svo.leaves[i].normal);
        }
        mr_svo_extremes e;
        extremes(&fx.svo, &e);
        assert_int_equal(e.node_count, fx.svo.node_count);
        for (uint32_t n = 0; n < fx.svo.node_count; n++) {
            assert_int_equal(e.lo_attr[n], walk_extreme(&fx.svo, n, false));
            assert_int_equal(e.hi_attr[n], walk_extreme(&fx.svo, n, true));
            /* the node's normal is its leaves' mean, within the octahedral
             * encoding's ~1 degree */
            const mr_vec3 mean = mr_v3_normalize_or(walk_normal_sum(&fx.svo, n), mr_v3(0, 0, 0));
            assert_true(angle_deg(mr_svo_normal_decode(e.normal[n]), mean) < 1.5);
        }
        mr_svo_extremes_free(&e);
        fx_free(&fx);
    }
}

/* ---- identity */

/* Identity rig, no view: one selected voxel per leaf, its box the leaf's
 * cell. Boxes are rounded outward to float from the double cell, so they
 * match within one float ulp of the coordinates. */
static void check_identity_selection(const mr_svo *s, const mr_svo_selection *sel)
{
    uint32_t *li;
    mr_svo_key *k = leaf_keys(s, &li);
    assert_int_equal(sel->count, s->leaf_count);
    assert_int_equal(sel->visited, (uint64_t)s->node_count + s->leaf_count);
    uint8_t *seen = calloc(s->leaf_count, 1);
    assert_non_null(seen);
    double worst = 0;
    for (size_t i = 0; i < sel->count; i++) {
        const float *b = &sel->box[i * 6];
        const unsigned l = sel->level[i];
        const double cell = (double)s->size * ldexp(1.0, -(int)l);
        const double o[3] = {s->origin.x, s->origin.y, s->origin.z};
        uint32_t xyz[3];
        for (int a = 0; a < 3; a++)
            xyz[a] = (uint32_t)floor((0.5 * ((double)b[a] + b[3 + a]) - o[a]) / cell);
        const unsigned sh = s->depth - l;
        const long f = find_key(k, s->leaf_count, mr_morton_encode(xyz[0] << sh, xyz[1] << sh, xyz[2] << sh), l);
        assert_true(f >= 0);
        assert_int_equal(seen[f], 0);
        seen[f] = 1;
        double lo[3], hi[3];
        uint32_t kx[3];
        key_cell(s, &k[f], lo, hi, kx);
        for (int a = 0; a < 3; a++) {
            const double ulp = ldexp(1.0, -23) * fmax(fabs(lo[a]), fabs(hi[a]));
            worst = fmax(worst, fmax(fabs(b[a] - lo[a]), fabs(b[3 + a] - hi[a])) / ulp);
            assert_true(b[a] <= lo[a] && b[3 + a] >= hi[a]);
            assert_true(lo[a] - b[a] <= ulp && b[3 + a] - hi[a] <= ulp);
        }
        const mr_svo_leaf *src = &s->leaves[li[f]];
        assert_int_equal(sel->leaf[i].attr, src->attr);
        /* identity cofactor: the normal is re-encoded, within the ~1 degree
         * of the encoding (svo.h) */
        assert_true(angle_deg(mr_svo_normal_decode(sel->leaf[i].normal), mr_svo_normal_decode(src->normal)) < 1.5);
    }
    print_message("identity: %zu voxels, boxes within %.2f float ulp of the cells\n", sel->count, worst);
    free(seen);
    free(k);
    free(li);
}

static void test_identity(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 7;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    extremes(s, &e);
    rig r;
    rig_uniform(&r, a, affine_identity());
    mr_svo_selection sel = {0};
    select_ok(s, &e, &r.d, NULL, D, 2, &sel);
    check_identity_selection(s, &sel);

    uint32_t *li;
    mr_svo_key *k = leaf_keys(s, &li);
    const double o[3] = {s->origin.x, s->origin.y, s->origin.z};

    /* Emit: every leaf cell completely covered, corners included (with the
     * thesis' ceil alignment 0.1-10 % of it would not be: REFERENCE.md). */
    mr_svo out = {0};
    uint64_t cells = 0;
    resample_ok(&sel, MR_SVO_EMIT, D + 1, s, 2, &out, &cells);
    assert_true(cells >= sel.count);
    for (uint32_t i = 0; i < s->leaf_count; i++) {
        double lo[3], hi[3];
        uint32_t xyz[3];
        key_cell(s, &k[i], lo, hi, xyz);
        assert_true(covered(&out, (float)(0.5 * (lo[0] + hi[0])), (float)(0.5 * (lo[1] + hi[1])),
                            (float)(0.5 * (lo[2] + hi[2]))));
        for (unsigned c = 0; c < 8; c++)
            if (!covered(&out, (float)((c & 1) ? hi[0] : lo[0]), (float)((c & 2) ? hi[1] : lo[1]),
                         (float)((c & 4) ? hi[2] : lo[2])))
                fail_msg("emit: corner %u of leaf %u not covered", c, i);
    }
    print_message("identity emit: %u leaves -> %llu cells -> %u voxels\n", s->leaf_count,
                  (unsigned long long)cells, out.leaf_count);

    /* Resize: 8 cells per box; the box's own cells cover its centre +- a
     * quarter cell (their level's cells are at least half the box), and a
     * corner shared by 8 leaves is covered by one of them (per axis the two
     * neighbours' cell pairs meet or overlap). Silhouette corners may be
     * eroded by up to a quarter cell: resize approximates (REFERENCE.md). */
    resample_ok(&sel, MR_SVO_RESIZE, D + 1, s, 2, &out, &cells);
    assert_int_equal(cells, 8 * sel.count);
    const double cell = (double)s->size * ldexp(1.0, -(int)D);
    size_t inner = 0;
    for (uint32_t i = 0; i < s->leaf_count; i++) {
        double lo[3], hi[3];
        uint32_t xyz[3];
        key_cell(s, &k[i], lo, hi, xyz);
        for (unsigned c = 0; c < 9; c++) {
            double p[3];
            for (int ax = 0; ax < 3; ax++)
                p[ax] = 0.5 * (lo[ax] + hi[ax]) + (c == 8 ? 0.0 : (((c >> ax) & 1) ? 0.25 : -0.25) * cell);
            if (!covered(&out, (float)p[0], (float)p[1], (float)p[2]))
                fail_msg("resize: leaf %u point %u not covered", i, c);
        }
        /* the leaf's high corner, when all 8 leaves around it exist */
        bool all = xyz[0] + 1 < (1u << D) && xyz[1] + 1 < (1u << D) && xyz[2] + 1 < (1u << D);
        for (unsigned c = 1; c < 8 && all; c++)
            all = find_key(k, s->leaf_count,
                           mr_morton_encode(xyz[0] + (c & 1), xyz[1] + ((c >> 1) & 1), xyz[2] + (c >> 2)), D) >= 0;
        if (all) {
            inner++;
            if (!covered(&out, (float)(o[0] + (xyz[0] + 1.0) * cell), (float)(o[1] + (xyz[1] + 1.0) * cell),
                         (float)(o[2] + (xyz[2] + 1.0) * cell)))
                fail_msg("resize: corner shared by 8 leaves (leaf %u) not covered", i);
        }
    }
    assert_true(inner > 0);
    print_message("identity resize: %u voxels, %zu inner corners checked\n", out.leaf_count, inner);

    mr_svo_free(&out);
    free(k);
    free(li);
    mr_svo_selection_free(&sel);
    rig_free(&r);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- Fig. 16 convention */

static const mr_svo_attr rigid_palette[2] = {
    {{200, 100, 50}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}},
    {{10, 20, 30}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}},
};

/* depth 2, cube [-2, 2]^3: one leaf, cell (3, 2, 2) = [1, 2] x [0, 1] x [0, 1] */
static int one_leaf_cls(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx;
    if (level == 0)
        return FX_SPLIT;
    if (level == 1)
        return x == 1 && y == 1 && z == 1 ? FX_SPLIT : FX_EMPTY;
    return x == 3 && y == 2 && z == 2 ? FX_LEAF : FX_EMPTY;
}

static mr_affine rot_z90_field(void *ctx, mr_vec3 p)
{
    (void)ctx;
    (void)p;
    return affine_rows(0, -1, 0, 10, 1, 0, 0, 20, 0, 0, 1, 30);
}

static void test_fig16_convention(void **state)
{
    (void)state;
    svo_fx fx;
    fx_build(&fx, 2, mr_v3(-2, -2, -2), 4.0f, one_leaf_cls, NULL);
    assert_int_equal(fx.svo.leaf_count, 1);
    fx.svo.palette = (mr_svo_attr *)rigid_palette;
    fx.svo.palette_count = 2;
    fx.svo.leaves[0].attr = 1;
    mr_svo_normal_encode(mr_v3(1, 0, 0), fx.svo.leaves[0].normal);
    mr_svo_extremes e;
    extremes(&fx.svo, &e);

    /* p' = A p with A = Rz(90 deg) (row-major, translation in column 3):
     * (x, y, z) -> (-y + 10, x + 20, z + 30). The cell's centre (1.5, 0.5,
     * 0.5) at +x goes to (-0.5, 1.5, 0.5) + t, at +y; the transposed listing
     * would put it at (0.5, -1.5, 0.5) + t. Every product is exact. */
    const mr_affine A = rot_z90_field(NULL, mr_v3(0, 0, 0));
    mr_svo_deformer rigid = {.mesh_count = 1, .mesh = &A};
    mr_svo_deformer field = {.field = rot_z90_field};
    const mr_svo_deformer *ds[2] = {&rigid, &field};
    for (int k = 0; k < 2; k++) {
        mr_svo_selection sel = {0};
        select_ok(&fx.svo, &e, ds[k], NULL, 2, 1, &sel);
        assert_int_equal(sel.count, 1);
        assert_int_equal(sel.level[0], 2);
        const float want[6] = {9, 21, 30, 10, 22, 31};
        for (int i = 0; i < 6; i++)
            assert_true(sel.box[i] == want[i]);
        assert_int_equal(sel.leaf[0].attr, 1);
        const mr_vec3 n = mr_svo_normal_decode(sel.leaf[0].normal);
        assert_true(angle_deg(n, mr_v3(0, 1, 0)) < 1.5);

        /* the root as one selected voxel (max_level 0): deformed cube
         * [-2, 2]^3 -> [8, 12] x [18, 22] x [28, 32], palette entry of its
         * lowest descendant leaf */
        select_ok(&fx.svo, &e, ds[k], NULL, 0, 1, &sel);
        assert_int_equal(sel.count, 1);
        assert_int_equal(sel.level[0], 0);
        const float root[6] = {8, 18, 28, 12, 22, 32};
        for (int i = 0; i < 6; i++)
            assert_true(sel.box[i] == root[i]);
        assert_int_equal(sel.leaf[0].attr, 1);
        mr_svo_selection_free(&sel);
    }
    mr_svo_extremes_free(&e);
    fx_free(&fx);
}

/* ---- shear and twist */

typedef struct twist_ctx {
    double centre[3], rate; /* radians per unit of y */
} twist_ctx;

static mr_affine twist_field(void *ctx, mr_vec3 p)
{
    const twist_ctx *t = ctx;
    const double th = t->rate * ((double)p.y - t->centre[1]);
    const double c = cos(th), s = sin(th);
    /* rotation about the vertical axis through the centre */
    const double cx = t->centre[0], cz = t->centre[2];
    return affine_rows((float)c, 0, (float)s, (float)(cx - c * cx - s * cz), 0, 1, 0, 0, (float)-s, 0, (float)c,
                       (float)(cz + s * cx - c * cz));
}

static mr_affine shear_field(void *ctx, mr_vec3 p)
{
    (void)p;
    const float k = *(const float *)ctx;
    return affine_rows(1, k, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0);
}

/* Every deformed box of sel lies in the output: its 8 corners, centre and
 * random interior points (floats inside the float box). */
static void check_boxes_covered(const mr_svo *out, const mr_svo_selection *sel, uint64_t seed)
{
    fx_rng rng = {seed};
    for (size_t i = 0; i < sel->count; i++) {
        const float *b = &sel->box[i * 6];
        for (unsigned c = 0; c < 13; c++) {
            float p[3];
            for (int a = 0; a < 3; a++) {
                if (c < 8)
                    p[a] = ((c >> a) & 1) ? b[3 + a] : b[a];
                else if (c == 8)
                    p[a] = (float)(0.5 * ((double)b[a] + b[3 + a]));
                else
                    p[a] = (float)fx_range(&rng, b[a], b[3 + a]);
                p[a] = p[a] < b[a] ? b[a] : p[a] > b[3 + a] ? b[3 + a] : p[a];
            }
            if (!covered(out, p[0], p[1], p[2]))
                fail_msg("box %zu [%.9g %.9g %.9g .. %.9g %.9g %.9g]: point %u (%.9g %.9g %.9g) not covered", i,
                         (double)b[0], (double)b[1], (double)b[2], (double)b[3], (double)b[4], (double)b[5], c,
                         (double)p[0], (double)p[1], (double)p[2]);
        }
    }
}

static void test_emit_covers_shear_twist(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 6;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    extremes(s, &e);
    float shear = 1.6f;
    twist_ctx tw = {{s->origin.x + 0.5 * s->size, s->origin.y + 0.5 * s->size, s->origin.z + 0.5 * s->size},
                    0.8 * 6.283185307179586 / s->size};
    mr_svo_deformer ds[2] = {{.field = shear_field, .field_ctx = &shear}, {.field = twist_field, .field_ctx = &tw}};
    for (int k = 0; k < 2; k++) {
        mr_svo_selection sel = {0};
        select_ok(s, &e, &ds[k], NULL, D, 2, &sel);
        assert_int_equal(sel.count, s->leaf_count);
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, MR_SVO_EMIT, D + 2, s, 2, &out, &cells);
        check_boxes_covered(&out, &sel, 77 + (uint64_t)k);
        print_message("%s: %zu boxes, emit %llu cells -> %u voxels\n", k ? "twist" : "shear", sel.count,
                      (unsigned long long)cells, out.leaf_count);
        /* resize: exactly 8 cells per box, before compaction */
        resample_ok(&sel, MR_SVO_RESIZE, D + 2, s, 2, &out, &cells);
        assert_int_equal(cells, 8 * sel.count);
        assert_true(out.leaf_count <= cells);
        /* and a depth that clamps both methods still covers with emit */
        resample_ok(&sel, MR_SVO_EMIT, D - 2, s, 2, &out, &cells);
        check_boxes_covered(&out, &sel, 99);
        mr_svo_free(&out);
        mr_svo_selection_free(&sel);
    }
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- uniform scale: resize is exact */

static uint64_t sc_seed;

/* Random sparse octree whose leaves include the lowest and highest finest
 * cells, so the occupied region spans the whole cube. */
static int scale_cls(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    const unsigned depth = *(const unsigned *)ctx;
    const uint32_t top = (1u << level) - 1u;
    if (level == 0 || (x == 0 && y == 0 && z == 0) || (x == top && y == top && z == top))
        return level == depth ? FX_LEAF : FX_SPLIT;
    const uint64_t h = fx_hash(sc_seed, level, x, y, z) % 100;
    /* a split cell always keeps its lowest child (svo.h: no empty nodes) */
    return h < 25 ? FX_LEAF : h < 60 ? FX_SPLIT : ((x | y | z) & 1u) ? FX_EMPTY : FX_LEAF;
}

typedef struct key_attr {
    mr_svo_key key;
    uint16_t attr;
} key_attr;

static int key_attr_cmp(const void *pa, const void *pb)
{
    const key_attr *a = pa, *b = pb;
    if (a->key.code != b->key.code)
        return a->key.code < b->key.code ? -1 : 1;
    return (a->key.level > b->key.level) - (a->key.level < b->key.level);
}

static void test_uniform_scale_resize_exact(void **state)
{
    (void)state;
    for (unsigned D = 2; D <= 6; D++) {
        sc_seed = D * 31u;
        svo_fx fx;
        fx_build(&fx, D, mr_v3(-0.75f, 0.5f, -3.0f), 1.5f, scale_cls, &D);
        fx.svo.palette = (mr_svo_attr *)rigid_palette;
        fx.svo.palette_count = 2;
        for (uint32_t i = 0; i < fx.svo.leaf_count; i++)
            fx.svo.leaves[i].attr = (uint16_t)(i & 1);
        mr_svo_extremes e;
        extremes(&fx.svo, &e);
        /* scale 2 about the origin plus a dyadic translation: every bind
         * corner maps to an exactly representable float */
        const mr_affine S2 = affine_rows(2, 0, 0, 0.25f, 0, 2, 0, -1.5f, 0, 0, 2, 8.0f);
        mr_svo_deformer d = {.mesh_count = 1, .mesh = &S2};
        mr_svo_selection sel = {0};
        select_ok(&fx.svo, &e, &d, NULL, D, 2, &sel);
        assert_int_equal(sel.count, fx.svo.leaf_count);
        mr_svo out = {0};
        uint64_t cells = 0;
        resample_ok(&sel, MR_SVO_RESIZE, D + 1, &fx.svo, 2, &out, &cells);
        assert_int_equal(cells, 8 * sel.count);
        /* the output cube starts at the scaled cube corner */
        assert_true(out.origin.x == -1.25f && out.origin.y == -0.5f && out.origin.z == 2.0f);
        /* exact: the output voxels are the children of the scaled source
         * cells (same integer grid, one level finer), nothing else */
        key_attr *want = malloc(8 * sel.count * sizeof *want);
        assert_non_null(want);
        size_t nw = 0;
        for (uint32_t i = 0; i < fx.svo.leaf_count; i++) {
            const fx_box *b = &fx.boxes[i];
            for (unsigned c = 0; c < 8; c++) {
                const unsigned l = b->level + 1, sh = D + 1 - l;
                want[nw].key.code = mr_morton_encode((2 * b->xyz[0] + (c & 1)) << sh,
                                                     (2 * b->xyz[1] + ((c >> 1) & 1)) << sh,
                                                     (2 * b->xyz[2] + (c >> 2)) << sh);
                want[nw].key.level = l;
                want[nw].attr = fx.svo.leaves[i].attr;
                nw++;
            }
        }
        qsort(want, nw, sizeof *want, key_attr_cmp);
        uint32_t *perm = NULL;
        mr_svo_key *got = leaf_keys(&out, &perm);
        assert_int_equal(out.leaf_count, nw);
        for (size_t i = 0; i < nw; i++) {
            assert_true(got[i].code == want[i].key.code);
            assert_int_equal(got[i].level, want[i].key.level);
            /* each output voxel keeps its source leaf's palette entry */
            assert_int_equal(out.leaves[perm[i]].attr, want[i].attr);
        }
        /* Box positions: the cube edge is the extent grown by 2^-20
         * (deform.c), so a voxel boundary moves by at most 2^-20 of the
         * edge from the scaled source boundary. */
        for (size_t i = 0; i < nw; i++) {
            double lo[3], hi[3];
            uint32_t xyz[3];
            key_cell(&out, &got[i], lo, hi, xyz);
            const double o2[3] = {-1.25, -0.5, 2.0}, c2 = 2.0 * 1.5 * ldexp(1.0, -(int)got[i].level);
            for (int a = 0; a < 3; a++) {
                assert_true(fabs(lo[a] - (o2[a] + xyz[a] * c2)) <= 3.0 * 0x1p-20);
                assert_true(fabs(hi[a] - (o2[a] + (xyz[a] + 1.0) * c2)) <= 3.0 * 0x1p-20);
            }
        }
        free(want);
        free(got);
        free(perm);
        mr_svo_free(&out);
        mr_svo_selection_free(&sel);
        mr_svo_extremes_free(&e);
        fx_free(&fx);
    }
}

/* Every leaf of a full depth-3 cube (512 leaves), its normal leaning off
 * +z by its index, under one joint per palette entry: entry k turns by
 * (k mod 4) quarter turns about z. */
static int full_cls(void *ctx, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    (void)ctx, (void)level, (void)x, (void)y, (void)z;
    return FX_SPLIT;
}

static mr_affine quarter_turns(int q, float tx)
{
    static const float c[4] = {1, 0, -1, 0}, s[4] = {0, 1, 0, -1};
    return affine_rows(c[q], -s[q], 0, tx, s[q], c[q], 0, 0, 0, 0, 1, 0);
}

/* Each selected leaf's normal is its bind normal turned by its own entry's
 * matrix, within the octahedral code's 1 degree (a neighbouring entry's is
 * 90 degrees off): with few entries and many leaves to each (the selection
 * keeps each entry's normal matrix in its table, made at once on two
 * threads, when first needed on one) and with an entry for every few
 * leaves (made per voxel). */
static void test_moved_normals(void **state)
{
    (void)state;
    svo_fx fx;
    fx_build(&fx, 3, mr_v3(0, 0, 0), 8.0f, full_cls, NULL);
    assert_int_equal(fx.svo.leaf_count, 512);
    enum { ENTRIES_MAX = 256 };
    mr_svo_attr palette[ENTRIES_MAX];
    mr_affine joints[ENTRIES_MAX];
    for (int k = 0; k < ENTRIES_MAX; k++) {
        palette[k] = (mr_svo_attr){{10, 20, 30}, 0, {(uint16_t)k, 0, 0, 0}, {255, 0, 0, 0}};
        joints[k] = quarter_turns(k % 4, (float)k);
    }
    for (uint32_t i = 0; i < fx.svo.leaf_count; i++) {
        const double a = 0.1 + 0.01 * (i % 97), b = 0.3 * (i % 7);
        mr_svo_normal_encode(mr_v3((float)(sin(a) * cos(b)), (float)(sin(a) * sin(b)), (float)cos(a)),
                             fx.svo.leaves[i].normal);
    }
    fx.svo.palette = palette;
    const uint32_t joint_count = ENTRIES_MAX;
    const mr_affine *joint_sets[1] = {joints};
    const mr_affine mesh = affine_identity();
    const mr_svo_deformer d = {.mesh_count = 1, .joint = joint_sets, .joint_count = &joint_count, .mesh = &mesh};
    const uint32_t entries[2] = {2, ENTRIES_MAX}; /* 256 leaves an entry; 2 */
    for (int e = 0; e < 2; e++) {
        fx.svo.palette_count = entries[e];
        for (uint32_t i = 0; i < fx.svo.leaf_count; i++)
            fx.svo.leaves[i].attr = (uint16_t)(i % entries[e]);
        mr_svo_extremes ex;
        extremes(&fx.svo, &ex);
        for (unsigned threads = 1; threads <= 2; threads++) {
            mr_svo_selection sel = {0};
            select_ok(&fx.svo, &ex, &d, NULL, 3, threads, &sel);
            assert_int_equal(sel.count, 512);
            /* the selection keeps the leaves' order (a full cube: leaf i
             * is the ith selected) */
            for (uint32_t i = 0; i < sel.count; i++) {
                const mr_svo_leaf *src = &fx.svo.leaves[i];
                assert_int_equal(sel.leaf[i].attr, src->attr);
                const mr_affine *m = &joints[src->attr];
                const mr_vec3 n = mr_svo_normal_decode(src->normal);
                const mr_vec3 want = mr_v3(m->m[0] * n.x + m->m[1] * n.y, m->m[4] * n.x + m->m[5] * n.y, n.z);
                const double off = angle_deg(mr_svo_normal_decode(sel.leaf[i].normal), want);
                if (!(off < 1.5))
                    fail_msg("%u entries, %u threads: leaf %u (entry %u) %.1f degrees off", entries[e], threads, i,
                             src->attr, off);
            }
            mr_svo_selection_free(&sel);
        }
        mr_svo_extremes_free(&ex);
    }
    fx_free(&fx);
}

/* ---- screen space */

/* Whether predicate (a) removes a voxel of deformed box b (lo xyz, hi
 * xyz): grown by its largest side, wholly on the outer side of one of the
 * frustum's planes w + x, w - x, w + y, w - y, w + z, w - z >= 0 or
 * nowhere ahead of the eye (w > 0), each plane at the grown box's corner
 * where it is largest (the selection's operations, in its order). */
static bool removed_by_cull(const mr_mat4 *vp, const float b[6])
{
    double g = 0.0;
    for (int a = 0; a < 3; a++)
        g = fmax(g, (double)b[3 + a] - (double)b[a]);
    for (int p = 0; p < 7; p++) {
        double pl[4];
        for (int e = 0; e < 4; e++)
            pl[e] = p < 6 ? vp->m[12 + e] + (p & 1 ? -1.0 : 1.0) * vp->m[4 * (p / 2) + e] : vp->m[12 + e];
        double most = pl[3];
        for (int a = 0; a < 3; a++) {
            const double lo = pl[a] * ((double)b[a] - g), hi = pl[a] * ((double)b[3 + a] + g);
            most += lo > hi ? lo : hi;
        }
        if (p < 6 ? most < 0.0 : !(most > 0.0))
            return true;
    }
    return false;
}

/* Whether deformed box b (lo xyz, hi xyz) projects to fewer than delta
 * pixels across on a width x height screen (eq. 3.2.3, all eight corners
 * ahead of the eye), by the selection's operations in its order: each
 * corner's clip x, y, w as ((x term + y term) + z term) + constant, then
 * 0.5 x / w + 0.5. */
static bool box_projects_below(const mr_mat4 *vp, const float b[6], double width, double height, double delta)
{
    static const int row[3] = {0, 1, 3};
    double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
    for (int k = 0; k < 8; k++) {
        double cl[3];
        for (int r = 0; r < 3; r++) {
            const float *m = &vp->m[4 * row[r]];
            const double px = (double)m[0] * b[(k & 1) ? 3 : 0], py = (double)m[1] * b[(k & 2) ? 4 : 1];
            const double pz = (double)m[2] * b[(k & 4) ? 5 : 2];
            cl[r] = px + py + pz + (double)m[3];
        }
        if (!(cl[2] > 0.0))
            return false;
        const double x = 0.5 * cl[0] / cl[2] + 0.5, y = 0.5 * cl[1] / cl[2] + 0.5;
        x0 = fmin(x0, x), x1 = fmax(x1, x), y0 = fmin(y0, y), y1 = fmax(y1, y);
    }
    return fmax(width * (x1 - x0), height * (y1 - y0)) < delta;
}

/* Every voxel of sel above the octree's depth D (an interior voxel: the
 * leaves sit at D) projects below the view's delta, as eq. 3.2.3 keeps
 * it; returns how many there are. */
static size_t check_coarse_below(const mr_svo_selection *sel, const mr_svo_view *v, unsigned D)
{
    size_t coarse = 0;
    for (size_t i = 0; i < sel->count; i++) {
        if (sel->level[i] >= D)
            continue;
        coarse++;
        assert_true(box_projects_below(&v->view_proj, &sel->box[6 * i], v->width, v->height, v->delta));
    }
    return coarse;
}

static void test_screen_space(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 7;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    extremes(s, &e);
    const double h = 0.5 * s->size;
    const double c[3] = {s->origin.x + h, s->origin.y + h, s->origin.z + h};
    mr_svo_view v = {.enabled = true, .view_proj = perspective(60, 640.0 / 480.0, 0.1, 1e4), .width = 640,
                     .height = 480, .delta = 1.0f, .cull = true};
    /* the cube's centre placed at (0, 0, -dist) */
#define PLACE(dx, dz)                                                                                            \
    affine_rows(1, 0, 0, (float)((dx) - c[0]), 0, 1, 0, (float)-c[1], 0, 0, 1, (float)((dz) - c[2]))
    rig near_r, far_r, back_r, side_r;
    rig_uniform(&near_r, a, PLACE(0, -3));
    rig_uniform(&far_r, a, PLACE(0, -300));
    rig_uniform(&back_r, a, PLACE(0, 10));
    rig_uniform(&side_r, a, PLACE(2.2, -3)); /* half out of the right edge */
    mr_svo_selection near = {0}, far = {0}, coarse = {0}, back = {0}, side = {0}, tmp = {0};

    select_ok(s, &e, &near_r.d, &v, D, 2, &near);
    size_t at_leaf = 0;
    for (size_t i = 0; i < near.count; i++)
        at_leaf += near.level[i] == D;
    select_ok(s, &e, &far_r.d, &v, D, 2, &far);
    unsigned far_max = 0;
    for (size_t i = 0; i < far.count; i++)
        far_max = far.level[i] > far_max ? far.level[i] : far_max;
    print_message("near: %zu voxels (%zu leaves, visited %llu); far: %zu voxels, deepest level %u (visited %llu)\n",
                  near.count, at_leaf, (unsigned long long)near.visited, far.count, far_max,
                  (unsigned long long)far.visited);
    /* near: a leaf voxel spans ~2 pixels, so nearly everything refines to
     * the leaves; far: ~0.02 pixels, coarse voxels only */
    assert_true(at_leaf >= 0.9 * near.count);
    assert_true(near.count >= 0.9 * s->leaf_count);
    assert_true(far.count > 0 && far.count * 50 < near.count);
    assert_true(far_max + 3 <= D);
    assert_true(far.visited < near.visited);

    /* larger delta: fewer voxels */
    v.delta = 8.0f;
    select_ok(s, &e, &near_r.d, &v, D, 2, &coarse);
    assert_true(coarse.count > 0 && coarse.count * 4 < near.count);
    /* each coarse voxel kept because its box projects below delta, all
     * eight corners measured (four voxels a time in the selection) */
    assert_true(check_coarse_below(&coarse, &v, D) > 100);
    /* where the near dancer's leaves start to merge (171 .. 3,420 coarse
     * voxels at levels 5 and 6, decided after the frame's palette table
     * is made, four voxels at a time) */
    for (float d = 4.0f; d < 5.75f; d += 0.5f) {
        v.delta = d;
        select_ok(s, &e, &near_r.d, &v, D, 2, &tmp);
        assert_true(check_coarse_below(&tmp, &v, D) > 100);
    }
    v.delta = 1.0f;
    assert_true(check_coarse_below(&far, &v, D) > 0);

    /* culling: behind the camera, removed at the root; in view, kept
     * whole; half out of view, only part kept */
    select_ok(s, &e, &back_r.d, &v, D, 2, &back);
    assert_int_equal(back.count, 0);
    assert_int_equal(back.visited, 1);
    v.cull = false;
    select_ok(s, &e, &near_r.d, &v, D, 2, &tmp);
    assert_int_equal(tmp.count, near.count);
    select_ok(s, &e, &side_r.d, &v, D, 2, &tmp);
    v.cull = true;
    select_ok(s, &e, &side_r.d, &v, D, 2, &side);
    print_message("half out of view: %zu voxels culled to %zu\n", tmp.count, side.count);
    assert_true(side.count > 0 && side.count < tmp.count);
    /* none kept that predicate (a) removes, though below a voxel found
     * well inside the frustum it is not tested again; and the selection
     * without culling has such voxels, so this could fail */
    size_t outside = 0;
    for (size_t i = 0; i < tmp.count; i++)
        outside += removed_by_cull(&v.view_proj, &tmp.box[6 * i]);
    assert_true(outside > 0);
    for (size_t i = 0; i < side.count; i++)
        assert_false(removed_by_cull(&v.view_proj, &side.box[6 * i]));
    /* wholly past each of the frustum's planes (left, right, below, above,
     * beyond the far plane at 1e4): removed at the root, each plane in its
     * lane of predicate (a)'s two vectors */
    const double out_of_view[5][3] = {{-40, 0, -3}, {40, 0, -3}, {0, -40, -3}, {0, 40, -3}, {0, 0, -3e4}};
    for (int k = 0; k < 5; k++) {
        rig out_r;
        const double *o = out_of_view[k];
        rig_uniform(&out_r, a,
                    affine_rows(1, 0, 0, (float)(o[0] - c[0]), 0, 1, 0, (float)(o[1] - c[1]), 0, 0, 1,
                                (float)(o[2] - c[2])));
        select_ok(s, &e, &out_r.d, &v, D, 2, &tmp);
        assert_int_equal(tmp.count, 0);
        assert_int_equal(tmp.visited, 1);
        rig_free(&out_r);
    }
    /* without a camera behind it counts as unbounded, so everything refines */
    v.cull = false;
    select_ok(s, &e, &back_r.d, &v, D, 2, &tmp);
    assert_int_equal(tmp.count, s->leaf_count);

    mr_svo_selection *all[6] = {&near, &far, &coarse, &back, &side, &tmp};
    for (int i = 0; i < 6; i++)
        mr_svo_selection_free(all[i]);
    rig_free(&near_r);
    rig_free(&far_r);
    rig_free(&back_r);
    rig_free(&side_r);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
#undef PLACE
}

/* ---- skinning with the real rig */

static void pose_at(const mr_asset *a, double t, mr_pose **pose)
{
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, pose, &err), MR_OK);
    mr_pose_desc desc;
    memset(&desc, 0, sizeof desc);
    desc.has_clip = true;
    desc.clip_index = 0;
    desc.has_time = true;
    desc.time = t;
    desc.speed = 1.0;
    desc.loop = true;
    if (mr_pose_eval(*pose, a, &desc, 0.0, &err) != MR_OK)
        fail_msg("pose: %s", err.msg);
}

/* Boxes bucketed on a grid (cells of edge g, each box entered in every cell
 * its box grown by tol touches) for nearest-box queries. */
typedef struct box_grid {
    double lo[3], g;
    int n[3];
    uint32_t *start, *items;
} box_grid;

static int grid_cell(const box_grid *G, int a, double x)
{
    int i = (int)floor((x - G->lo[a]) / G->g);
    return i < 0 ? 0 : i >= G->n[a] ? G->n[a] - 1 : i;
}

static void grid_build(box_grid *G, const mr_svo_selection *sel, double g, double tol)
{
    memset(G, 0, sizeof *G);
    double hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int a = 0; a < 3; a++)
        G->lo[a] = INFINITY;
    for (size_t i = 0; i < sel->count; i++)
        for (int a = 0; a < 3; a++) {
            G->lo[a] = fmin(G->lo[a], sel->box[i * 6 + a] - tol);
            hi[a] = fmax(hi[a], sel->box[i * 6 + 3 + a] + tol);
        }
    G->g = g;
    size_t cells = 1;
    for (int a = 0; a < 3; a++) {
        G->n[a] = (int)ceil((hi[a] - G->lo[a]) / g) + 1;
        cells *= (size_t)G->n[a];
    }
    G->start = calloc(cells + 1, sizeof *G->start);
    assert_non_null(G->start);
    for (int pass = 0; pass < 2; pass++) {
        if (pass == 1) {
            for (size_t i = 1; i <= cells; i++)
                G->start[i] += G->start[i - 1];
            G->items = malloc((G->start[cells] + 1) * sizeof *G->items);
            assert_non_null(G->items);
        }
        for (size_t i = 0; i < sel->count; i++) {
            int c0[3], c1[3];
            for (int a = 0; a < 3; a++) {
                c0[a] = grid_cell(G, a, sel->box[i * 6 + a] - tol);
                c1[a] = grid_cell(G, a, sel->box[i * 6 + 3 + a] + tol);
            }
            for (int z = c0[2]; z <= c1[2]; z++)
                for (int y = c0[1]; y <= c1[1]; y++)
                    for (int x = c0[0]; x <= c1[0]; x++) {
                        const size_t cell = ((size_t)z * G->n[1] + (size_t)y) * G->n[0] + (size_t)x;
                        if (pass == 0)
                            G->start[cell + 1]++;
                        else
                            G->items[G->start[cell]++] = (uint32_t)i;
                    }
        }
        if (pass == 1) /* starts were advanced to the ends: shift back */
            for (size_t i = cells; i > 0; i--)
                G->start[i] = G->start[i - 1];
        if (pass == 1)
            G->start[0] = 0;
    }
}

static double grid_nearest(const box_grid *G, const mr_svo_selection *sel, const double p[3])
{
    const size_t cell = ((size_t)grid_cell(G, 2, p[2]) * G->n[1] + (size_t)grid_cell(G, 1, p[1])) * G->n[0] +
                        (size_t)grid_cell(G, 0, p[0]);
    double best = INFINITY;
    for (uint32_t k = G->start[cell]; k < G->start[cell + 1]; k++) {
        const float *b = &sel->box[G->items[k] * 6];
        double d2 = 0;
        for (int a = 0; a < 3; a++) {
            const double d = p[a] < b[a] ? b[a] - p[a] : p[a] > b[3 + a] ? p[a] - b[3 + a] : 0.0;
            d2 += d * d;
        }
        best = fmin(best, sqrt(d2));
    }
    return best;
}

/* Voxels of the rig posed by its clip land on the skinned mesh. Every
 * vertex lies in (the closed cell of) a voxel, whose box is deformed by the
 * voxel's own blended matrix: weights of the nearest triangle's closest
 * point to the cell centre, top 4, quantised to 1/255. A vertex is moved
 * by its own weights, so the two differ by the change of weights across at
 * most a cell diagonal plus quantisation. Tolerance: 1.5 bind-space cell
 * diagonals (the pose keeps scale ~1). */
static void test_skinned_rig(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    const unsigned D = 8;
    mr_svo *s = voxelize(a, D);
    mr_svo_extremes e;
    extremes(s, &e);
    mr_pose *pose;
    pose_at(a, 0.37 * a->clips[0].duration, &pose);
    const mr_mat4 I = mr_mat4_identity();
    mr_svo_skin r;
    skin_posed(&r, a, pose, &I);
    mr_svo_selection sel = {0};
    select_ok(s, &e, &r.d, NULL, D, 2, &sel);
    assert_int_equal(sel.count, s->leaf_count);

    const double diag = sqrt(3.0) * (double)s->size * ldexp(1.0, -(int)D), tol = 1.5 * diag;
    box_grid G;
    grid_build(&G, &sel, 2.0 * tol, tol);
    double worst = 0, moved = 0;
    size_t checked = 0;
    for (size_t m = 0; m < a->mesh_count; m++) {
        const mr_mesh *me = &a->meshes[m];
        float *p = malloc(me->vertex_count * 3 * sizeof *p);
        assert_non_null(p);
        mr_skin_mesh(a, m, pose, &I, p, NULL, 2);
        for (uint32_t v = 0; v < me->vertex_count; v++) {
            const double q[3] = {p[v * 3], p[v * 3 + 1], p[v * 3 + 2]};
            const double d = grid_nearest(&G, &sel, q);
            worst = fmax(worst, d);
            for (int k = 0; k < 3; k++)
                moved = fmax(moved, fabs(q[k] - me->positions[v * 3 + k]));
            if (!(d <= tol))
                fail_msg("mesh %zu vertex %u: %.4g from the nearest box (tolerance %.4g)", m, v, d, tol);
            checked++;
        }
        free(p);
    }
    print_message("skinned: %zu vertices, worst %.3f voxel diagonals from a box (pose moves vertices up to %.3g, "
                  "%.0f diagonals)\n",
                  checked, worst / diag, moved, moved / diag);
    assert_true(moved > 5 * diag); /* the pose really moves the mesh */
    free(G.start);
    free(G.items);
    mr_svo_selection_free(&sel);
    mr_svo_skin_free(&r);
    mr_pose_free(pose);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* The dancer voxelised at depth D, skinned at a fraction of its clip and
 * placed 4 units in front of the camera of perspective() (the view of the
 * thread, repeat and workspace tests). */
typedef struct posed_dancer {
    mr_asset *a;
    mr_svo *s;
    mr_svo_extremes e;
    mr_pose *pose;
    mr_svo_skin r;
} posed_dancer;

static void posed_open(posed_dancer *f, unsigned D, double clip_fraction)
{
    f->a = bcn_load();
    f->s = voxelize(f->a, D);
    extremes(f->s, &f->e);
    pose_at(f->a, clip_fraction * f->a->clips[0].duration, &f->pose);
    const mr_svo *s = f->s;
    const double h = 0.5 * s->size;
    const mr_mat4 place = {{1, 0, 0, (float)(-s->origin.x - h), 0, 1, 0, (float)(-s->origin.y - h), 0, 0, 1,
                            (float)(-s->origin.z - h - 4.0), 0, 0, 0, 1}};
    skin_posed(&f->r, f->a, f->pose, &place);
}

/* Its camera: 256 x 256, screen-space selection at delta 1, culling on. */
static mr_svo_view posed_view(void)
{
    return (mr_svo_view){.enabled = true, .view_proj = perspective(50, 1.0, 0.1, 100), .width = 256,
                         .height = 256, .delta = 1.0f, .cull = true};
}

static void posed_close(posed_dancer *f)
{
    mr_svo_skin_free(&f->r);
    mr_pose_free(f->pose);
    mr_svo_extremes_free(&f->e);
    mr_svo_voxelize_free(f->s);
    mr_asset_free(f->a);
}

/* ---- thread counts */

static void test_threads(void **state)
{
    (void)state;
    const unsigned D = 8;
    posed_dancer f;
    posed_open(&f, D, 0.61);
    const mr_svo *s = f.s;
    const mr_svo_view v = posed_view();
    mr_svo_selection sel[3] = {{0}};
    for (unsigned t = 1; t <= 3; t++)
        select_ok(s, &f.e, &f.r.d, &v, D, t, &sel[t - 1]);
    assert_true(sel[0].count > 1000);
    assert_true(selections_equal(&sel[0], &sel[1]));
    assert_true(selections_equal(&sel[0], &sel[2]));
    /* reusing a selection's buffers gives the same again */
    select_ok(s, &f.e, &f.r.d, &v, D, 2, &sel[2]);
    assert_true(selections_equal(&sel[0], &sel[2]));
    for (int m = 0; m < 2; m++) {
        const mr_svo_method method = m ? MR_SVO_EMIT : MR_SVO_RESIZE;
        mr_svo o[3] = {{0}};
        uint64_t cells[3];
        for (unsigned t = 1; t <= 3; t++)
            resample_ok(&sel[0], method, D + 1, s, t, &o[t - 1], &cells[t - 1]);
        assert_true(o[0].leaf_count > 0);
        assert_true(cells[0] == cells[1] && cells[0] == cells[2]);
        assert_true(svos_equal(&o[0], &o[1]));
        assert_true(svos_equal(&o[0], &o[2]));
        for (int t = 0; t < 3; t++)
            mr_svo_free(&o[t]);
    }
    for (int t = 0; t < 3; t++)
        mr_svo_selection_free(&sel[t]);
    posed_close(&f);
}

/* On two threads a selection runs its top levels (frontiers of one chunk)
 * while the other thread fills the frame's palette table (deform.c,
 * top_and_fill): selections that end within those levels, that go past
 * them, and that fail within them give what one thread gives, and a
 * workspace that saw the failure selects as a fresh one. */
static void test_top_levels_beside_the_table(void **state)
{
    (void)state;
    const unsigned D = 8;
    posed_dancer f;
    posed_open(&f, D, 0.37);
    const mr_svo *s = f.s;
    assert_true(s->leaf_count > s->palette_count); /* the octree takes that path */
    mr_svo_view v = posed_view();
    mr_svo_selection one = {0}, two = {0};
    /* ending at level 3 (every voxel there selected), at a coarse delta
     * (a few levels) and at delta 1 (to the leaves) */
    const unsigned max_level[3] = {3, D, D};
    const float delta[3] = {1.0f, 64.0f, 1.0f};
    for (int k = 0; k < 3; k++) {
        v.delta = delta[k];
        select_ok(s, &f.e, &f.r.d, &v, max_level[k], 1, &one);
        select_ok(s, &f.e, &f.r.d, &v, max_level[k], 2, &two);
        unsigned deepest = 0;
        for (size_t i = 0; i < two.count; i++)
            deepest = two.level[i] > deepest ? two.level[i] : deepest;
        print_message("max level %u, delta %g: %zu voxels, deepest level %u, visited %llu\n", max_level[k],
                      (double)delta[k], two.count, deepest, (unsigned long long)two.visited);
        assert_true(two.count > 0);
        assert_true(selections_equal(&one, &two));
        /* the first two end within the top levels (fewer voxels in all
         * than a chunk's 1,024, so every frontier fits one), the third
         * goes on past them */
        if (k < 2)
            assert_true(two.visited < 1024);
        else
            assert_true(two.visited > 10000);
    }
    /* a palette entry naming a joint the deformer lacks: the same failure
     * on one and two threads, and the workspace that saw it then selects
     * as a fresh one */
    v.delta = 1.0f;
    uint32_t *counts = malloc(f.r.d.mesh_count * sizeof *counts);
    assert_non_null(counts);
    memcpy(counts, f.r.d.joint_count, f.r.d.mesh_count * sizeof *counts);
    counts[0] = counts[0] / 2;
    mr_svo_deformer bad = f.r.d;
    bad.joint_count = counts;
    mr_svo_workspace *ws = NULL;
    mr_error err = {0};
    assert_int_equal(mr_svo_workspace_new(&ws, &err), MR_OK);
    for (int k = 0; k < 2; k++) { /* stopping at level 3: failing within the top levels */
        const unsigned ml = k ? D : 3;
        mr_error err1 = {0}, err2 = {0};
        assert_int_equal(mr_svo_select(s, &f.e, &bad, &v, ml, 1, &one, &err1), MR_ERR_INVALID);
        assert_int_equal(mr_svo_select_ws(s, &f.e, &bad, &v, ml, 2, ws, &two, &err2), MR_ERR_INVALID);
        print_message("a missing joint, max level %u: %s\n", ml, err2.msg);
        assert_non_null(strstr(err2.msg, "palette entry"));
        assert_string_equal(err1.msg, err2.msg);
        assert_int_equal(two.count, 0);
    }
    select_ok(s, &f.e, &f.r.d, &v, D, 1, &one);
    assert_int_equal(mr_svo_select_ws(s, &f.e, &f.r.d, &v, D, 2, ws, &two, &err), MR_OK);
    assert_true(selections_equal(&one, &two));
    mr_svo_workspace_free(ws);
    free(counts);
    mr_svo_selection_free(&one);
    mr_svo_selection_free(&two);
    posed_close(&f);
}

/* ---- repeated cells */

/* sel with a copy of voxel i at 2i + 1 (adjacent: repeats within one
 * resampling chunk) or at count + i (after all: repeats in other chunks),
 * the copy with another palette entry and normal. */
static void with_copies(const mr_svo_selection *sel, bool adjacent, uint32_t palette_count, mr_svo_selection *out)
{
    const size_t n = sel->count;
    out->count = out->capacity = 2 * n;
    out->box = malloc(2 * n * 6 * sizeof *out->box);
    out->leaf = malloc(2 * n * sizeof *out->leaf);
    out->level = malloc(2 * n);
    assert_non_null(out->box);
    assert_non_null(out->leaf);
    assert_non_null(out->level);
    for (size_t i = 0; i < n; i++)
        for (int copy = 0; copy < 2; copy++) {
            const size_t at = adjacent ? 2 * i + (size_t)copy : (size_t)copy * n + i;
            memcpy(&out->box[6 * at], &sel->box[6 * i], 6 * sizeof *out->box);
            out->level[at] = sel->level[i];
            out->leaf[at] = sel->leaf[i];
            if (copy) {
                out->leaf[at].attr = (uint16_t)((sel->leaf[i].attr + 1u) % palette_count);
                out->leaf[at].normal[0] ^= 0x55;
                out->leaf[at].normal[1] ^= 0x55;
            }
        }
}

/* A cell emitted again by a later voxel (resize's 2 x 2 x 2 blocks overlap
 * their neighbours'; the resampling leaves repeats out before its sort)
 * takes the first voxel's leaf, wherever the repeat comes: every voxel
 * followed by a copy of itself with another leaf, or all the copies after
 * all the voxels, resamples to the same octree bit for bit. Fails if a
 * repeat's leaf wins anywhere or a cell that is no repeat is left out. */
static void test_repeated_cells(void **state)
{
    (void)state;
    const unsigned D = 8;
    posed_dancer f;
    posed_open(&f, D, 0.23);
    const mr_svo *s = f.s;
    const mr_svo_view v = posed_view();
    mr_svo_selection sel = {0}, twice[2] = {{0}};
    select_ok(s, &f.e, &f.r.d, &v, D, 2, &sel);
    assert_true(sel.count > 3 * 4096); /* several resampling chunks */
    assert_true(s->palette_count > 1);
    for (int k = 0; k < 2; k++)
        with_copies(&sel, k == 0, s->palette_count, &twice[k]);
    for (int m = 0; m < 2; m++) {
        const mr_svo_method method = m ? MR_SVO_EMIT : MR_SVO_RESIZE;
        mr_svo ref = {0}, got = {0};
        uint64_t cells = 0, cells2 = 0;
        resample_ok(&sel, method, D + 2, s, 2, &ref, &cells);
        assert_true(ref.leaf_count > 0 && cells > ref.leaf_count);
        for (int k = 0; k < 2; k++) {
            resample_ok(&twice[k], method, D + 2, s, 2, &got, &cells2);
            assert_int_equal(cells2, 2 * cells);
            assert_true(svos_equal(&ref, &got));
            mr_svo_free(&got);
        }
        mr_svo_free(&ref);
    }
    for (int k = 0; k < 2; k++)
        mr_svo_selection_free(&twice[k]);
    mr_svo_selection_free(&sel);
    posed_close(&f);
}

/* ---- workspaces */

/* A workspace kept across calls (as per frame) gives exactly what the calls
 * without one give, whatever the calls before it left in it: a large
 * selection, a small one, a failed call, and resampling at depth 20 (above
 * the packed sort's 19: the shared sort) between depth-9 ones. */
static void test_workspace(void **state)
{
    (void)state;
    const unsigned D = 8;
    posed_dancer f;
    posed_open(&f, D, 0.37);
    const mr_svo *s = f.s;
    const mr_svo_view near = posed_view();
    mr_svo_view far = near;
    far.width = far.height = 16;
    mr_svo_workspace *ws = NULL;
    mr_error err = {0};
    assert_int_equal(mr_svo_workspace_new(&ws, &err), MR_OK);
    const mr_svo_view *views[3] = {&near, &far, &near};
    const unsigned depths[3] = {D + 1, 20, D + 1};
    for (int k = 0; k < 3; k++) {
        mr_svo_selection ref = {0}, got = {0};
        select_ok(s, &f.e, &f.r.d, views[k], D, 1, &ref);
        assert_int_equal(mr_svo_select_ws(s, &f.e, &f.r.d, views[k], D, 2, ws, &got, &err), MR_OK);
        assert_true(ref.count > 0);
        assert_true(selections_equal(&ref, &got));
        for (int m = 0; m < 2; m++) {
            const mr_svo_method method = m ? MR_SVO_EMIT : MR_SVO_RESIZE;
            mr_svo o_ref = {0}, o_got = {0};
            uint64_t c_ref = 0, c_got = 0;
            resample_ok(&ref, method, depths[k], s, 1, &o_ref, &c_ref);
            assert_int_equal(mr_svo_resample_ws(&got, method, depths[k], s->palette, s->palette_count, 2, ws,
                                                &o_got, &c_got, &err),
                             MR_OK);
            assert_true(c_ref == c_got && o_ref.leaf_count > 0);
            assert_true(svos_equal(&o_ref, &o_got));
            mr_svo_free(&o_ref);
            mr_svo_free(&o_got);
        }
        /* a failing call leaves the workspace usable */
        mr_svo_view bad = near;
        bad.delta = 0.0f;
        assert_int_equal(mr_svo_select_ws(s, &f.e, &f.r.d, &bad, D, 2, ws, &got, &err), MR_ERR_INVALID);
        assert_int_equal(got.count, 0);
        mr_svo_selection_free(&ref);
        mr_svo_selection_free(&got);
    }
    assert_true(mr_svo_workspace_memory(ws) > 0);
    mr_svo_workspace_free(ws);
    mr_svo_workspace_free(NULL);
    assert_int_equal(mr_svo_workspace_new(NULL, &err), MR_ERR_INVALID);
    posed_close(&f);
}

/* A workspace kept across frames stops growing after the first: calling
 * again with the same octree and view allocates nothing more. Every leaf
 * (no camera) makes nine levels at depth 8, an odd number: the level arrays
 * swapped at each level must come back to their places, or the next call
 * puts its widest level in the other array and grows that one too. */
static void test_workspace_steady(void **state)
{
    (void)state;
    const unsigned D = 8;
    posed_dancer f;
    posed_open(&f, D, 0.37);
    const mr_svo_view every = {.enabled = false}, near = posed_view();
    const mr_svo_view *views[2] = {&every, &near};
    for (int v = 0; v < 2; v++) {
        mr_svo_workspace *ws = NULL;
        mr_error err = {0};
        assert_int_equal(mr_svo_workspace_new(&ws, &err), MR_OK);
        size_t bytes[3];
        for (int call = 0; call < 3; call++) {
            mr_svo_selection sel = {0};
            assert_int_equal(mr_svo_select_ws(f.s, &f.e, &f.r.d, views[v], D, 2, ws, &sel, &err), MR_OK);
            assert_true(sel.count > 0);
            if (v == 0)
                assert_int_equal(sel.count, f.s->leaf_count);
            bytes[call] = mr_svo_workspace_memory(ws);
            mr_svo_selection_free(&sel);
        }
        assert_true(bytes[0] > 0);
        assert_int_equal(bytes[1], bytes[0]);
        assert_int_equal(bytes[2], bytes[0]);
        mr_svo_workspace_free(ws);
    }
    posed_close(&f);
}

/* ---- validation */

static void test_invalid_input(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_svo *s = voxelize(a, 4);
    mr_svo_extremes e;
    extremes(s, &e);
    rig r;
    rig_uniform(&r, a, affine_identity());
    mr_svo_selection sel = {0};
    mr_error err = {0};
    assert_int_equal(mr_svo_select(NULL, &e, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_select(s, NULL, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_select(s, &e, NULL, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, 4, 1, NULL, &err), MR_ERR_INVALID);
    /* a palette entry naming a joint the deformer lacks: the message names
     * the entry */
    uint32_t entry = UINT32_MAX;
    for (uint32_t p = 0; p < s->palette_count && entry == UINT32_MAX; p++)
        if (s->palette[p].weights[0] > 0 && s->palette[p].joints[0] > 0 && s->palette[p].mesh == 0)
            entry = p;
    assert_true(entry != UINT32_MAX);
    const uint32_t saved = r.joint_count[0];
    r.joint_count[0] = s->palette[entry].joints[0];
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "palette entry"));
    print_message("missing joint: %s\n", err.msg);
    assert_int_equal(sel.count, 0);
    r.joint_count[0] = saved;
    /* a mesh the deformer lacks */
    r.d.mesh_count = 1;
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "palette entry"));
    r.d.mesh_count = a->mesh_count;
    /* non-finite joint matrix */
    r.joint[1][0].m[5] = NAN;
    assert_int_equal(mr_svo_select(s, &e, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);
    r.joint[1][0] = affine_identity();
    /* a bad view */
    mr_svo_view v = {.enabled = true, .view_proj = perspective(60, 1, 0.1, 10), .width = 0, .height = 10,
                     .delta = 1};
    assert_int_equal(mr_svo_select(s, &e, &r.d, &v, 4, 1, &sel, &err), MR_ERR_INVALID);
    v.width = 10;
    v.view_proj.m[3] = INFINITY;
    assert_int_equal(mr_svo_select(s, &e, &r.d, &v, 4, 1, &sel, &err), MR_ERR_INVALID);
    /* extremes of another octree */
    mr_svo_extremes bad = e;
    bad.node_count--;
    assert_int_equal(mr_svo_select(s, &bad, &r.d, NULL, 4, 1, &sel, &err), MR_ERR_INVALID);

    /* resample */
    select_ok(s, &e, &r.d, NULL, 4, 1, &sel);
    mr_svo out = {0};
    assert_int_equal(mr_svo_resample(&sel, (mr_svo_method)7, 5, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_DIRECT, 5, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_EMIT, 0, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_EMIT, 22, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    sel.box[6 * 3 + 4] = NAN;
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_EMIT, 5, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    assert_int_equal(out.leaf_count, 0);
    assert_null(out.leaves);
    sel.box[6 * 3 + 4] = INFINITY;
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_RESIZE, 5, s->palette, s->palette_count, 1, &out, NULL, &err),
                     MR_ERR_INVALID);
    /* palette too small for the voxels' entries: the build refuses it */
    select_ok(s, &e, &r.d, NULL, 4, 1, &sel);
    assert_int_equal(mr_svo_resample(&sel, MR_SVO_RESIZE, 5, s->palette, 1, 1, &out, NULL, &err), MR_ERR_INVALID);

    mr_svo_selection_free(&sel);
    rig_free(&r);
    mr_svo_extremes_free(&e);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_extremes),
        cmocka_unit_test(test_identity),
        cmocka_unit_test(test_fig16_convention),
        cmocka_unit_test(test_moved_normals),
        cmocka_unit_test(test_emit_covers_shear_twist),
        cmocka_unit_test(test_uniform_scale_resize_exact),
        cmocka_unit_test(test_screen_space),
        cmocka_unit_test(test_skinned_rig),
        cmocka_unit_test(test_threads),
        cmocka_unit_test(test_top_levels_beside_the_table),
        cmocka_unit_test(test_repeated_cells),
        cmocka_unit_test(test_workspace),
        cmocka_unit_test(test_workspace_steady),
        cmocka_unit_test(test_invalid_input),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
