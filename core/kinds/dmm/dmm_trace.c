/*
 * dmm_trace.c - tessellation-free traversal of a DMM patch (dmm_trace.h).
 *
 * Recursion depth is at most MR_UMESH_MAX_LEVEL, so the quadtree is walked
 * recursively with every node's state on the C stack (no restart, no
 * epsilon pushes). Lattice points carry their interpolated frame (point,
 * direction and, for interpolated patches, matrix) in float, computed
 * directly from the three base corners (no error accumulates down the
 * tree); boxes are widened by a per-patch pad that covers float rounding.
 * Micro-vertices are evaluated exactly as the tessellation does.
 */
#include <float.h>
#include <math.h>
#include <pthread.h>
#include <string.h>
#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define LEAF_LANES 1 /* leaf_test_avx2 */
#elif defined(__SSE__)
#include <xmmintrin.h>
#endif

#include "kinds/dmm/dmm_trace.h"
#include "util/thread_block.h"

/* Widening of every box, relative to the patch's magnitude bound (see
 * patch_pad): covers the final float rounding of a micro-vertex (2^-24
 * relative) plus the few float roundings of the box arithmetic, with a
 * factor 4 to spare. */
#define BOX_PAD 0x1p-19f
/* Far-distance widening of the slab test: 1 + 2 * gamma(3) in float. */
#define SLAB_FAR_SCALE (1.0f + 2.0f * 3.0f * FLT_EPSILON)
/* A patch box over this many times its base triangle's size is cut to its
 * micro-vertices' box (loose, mr_dmm_patch_bounds). */
#define BOX_LOOSE 4.0f

/* A lattice point of the patch with its interpolated frame, in float (the
 * boxes are made conservative by the pad; micro-vertices themselves are
 * evaluated exactly by micromesh.h). */
typedef struct lattice_pt {
    uint32_t a, b;
    float p[3], n[3]; /* base patches only */
} lattice_pt;

typedef struct fbox {
    float lo[3], hi[3];
} fbox;

typedef struct trace_ctx {
    const mr_dmm_patch *patch;
    const mr_dmm_ray *ray;
    unsigned leaf;      /* leaf sublevel */
    uint32_t segments;  /* 2^level */
    float pad[3];       /* per-axis box widening */
    float tmin, tmax;
    uint32_t best_key;  /* micro-triangle (row order) of the hit at tmax; see test_triangle */
    bool any_hit, found;
    mr_dmm_hit *hit;
    mr_dmm_trace_stats *stats;
} trace_ctx;

unsigned mr_dmm_trace_leaf_sublevel(unsigned level) { return level ? level - 1 : 0; }

uint32_t mr_dmm_trace_pyramid_size(unsigned level)
{
    return mr_dmm_pyramid_size(mr_dmm_trace_leaf_sublevel(level));
}

mr_dmm_ray mr_dmm_ray_setup(mr_vec3 org, mr_vec3 dir)
{
    mr_dmm_ray r = {.org = org, .dir = dir};
    const float d[3] = {dir.x, dir.y, dir.z};
    for (int k = 0; k < 3; k++) {
        r.parallel[k] = d[k] == 0.0f;
        r.inv[k] = r.parallel[k] ? 0.0f : 1.0f / d[k];
    }
    r.wt = mr_wtd_ray_setup(org, dir);
    return r;
}

/* The decoded displacement of micro-vertex (a, b) of patch p. */
static float vertex_disp(const mr_dmm_patch *p, uint32_t a, uint32_t b)
{
    return mr_dmm_value_to_float(p->enc, p->values[mr_umesh_vertex_index_at(p->level, a, b)]);
}

mr_vec3 mr_dmm_vertex(const mr_dmm_patch *p, uint32_t a, uint32_t b)
{
    const float d = vertex_disp(p, a, b);
    return p->mats[0] ? mr_umesh_eval_interpolated_at(&p->tri, p->mats, p->level, a, b, d)
                      : mr_umesh_eval_at(&p->tri, p->level, a, b, d);
}

/* Larger of two (no NaN care: non-finite patches are refused before tracing);
 * fmaxf would be a library call here. */
static inline float larger(float a, float b) { return a > b ? a : b; }

static float comp(mr_vec3 v, int k) { return k == 0 ? v.x : k == 1 ? v.y : v.z; }

/* Displacement bounds for boxes: the displacement of grid value V itself,
 * as the micro-vertices take it (monotone in V, so the pyramid's values
 * bound theirs). Not bias + scale * V in float: where the bias is large
 * against the displacement (an encoding whose range reaches far from
 * this patch's) that sum cancels, and its error, 2^-24 of |bias| rather
 * than of |d|, outgrew the pad (Testwuson.X: bias -11.3, a root range of
 * 1.6e-5 bounded 3.3e-7 short). */
static float disp_bound(const trace_ctx *c, uint16_t v)
{
    return mr_dmm_value_to_float(c->patch->enc, v);
}

/* Bound on |coordinate| of anything the patch's boxes are computed from,
 * per axis, times BOX_PAD. Displacements are bounded by the root range. */
void mr_dmm_patch_pad(const mr_dmm_patch *p, float pad[3])
{
    trace_ctx ctx = {.patch = p};
    const trace_ctx *c = &ctx;
    float dm = larger(fabsf(disp_bound(c, p->minv[0])), fabsf(disp_bound(c, p->maxv[0])));
    float x[3];
    for (int k = 0; k < 3; k++) {
        float pm = 0, nm = 0;
        for (int i = 0; i < 3; i++) {
            pm = larger(pm, fabsf(comp(p->tri.pos[i], k)));
            nm = larger(nm, fabsf(comp(p->tri.dir[i], k)));
        }
        x[k] = pm + dm * nm;
    }
    for (int r = 0; r < 3; r++) {
        float mag = x[r];
        if (p->mats[0]) {
            mag = 0;
            for (int i = 0; i < 3; i++) {
                const float *m = p->mats[i]->m + r * 4;
                mag = larger(mag, fabsf(m[0]) * x[0] + fabsf(m[1]) * x[1] + fabsf(m[2]) * x[2] +
                                     fabsf(m[3]));
            }
        }
        pad[r] = mag * BOX_PAD + FLT_MIN;
    }
}

static void patch_pad(trace_ctx *c)
{
    const float *given = c->patch->pad;
    if (given[0] > 0 && given[1] > 0 && given[2] > 0)
        memcpy(c->pad, given, sizeof c->pad);
    else
        mr_dmm_patch_pad(c->patch, c->pad);
}

static void grow(fbox *b, const float x[3])
{
    for (int k = 0; k < 3; k++) {
        b->lo[k] = x[k] < b->lo[k] ? x[k] : b->lo[k];
        b->hi[k] = x[k] > b->hi[k] ? x[k] : b->hi[k];
    }
}

static fbox empty_box(void)
{
    return (fbox){{INFINITY, INFINITY, INFINITY}, {-INFINITY, -INFINITY, -INFINITY}};
}

static void widen(const trace_ctx *c, fbox *b)
{
    for (int k = 0; k < 3; k++) {
        b->lo[k] -= c->pad[k];
        b->hi[k] += c->pad[k];
    }
}

/* For interpolated patches a sub-triangle's micro-geometry at displacement d
 * is the quadratic patch with control points (blossom) c_ij = S_ij + d T_ij,
 * S_ij = (M(r_i) p(r_j) + M(r_j) p(r_i)) / 2 (affine) and
 * T_ij = (L(r_i) n(r_j) + L(r_j) n(r_i)) / 2 (L the linear part): eq. 11 and
 * 13 at the sub-triangle's corners r. Matrices are only applied at the root
 * (the top-level patch); below it the blossom's bilinearity gives every
 * control point of the children from the parent's six by averaging
 * (B(m_ab, x) = (B(a, x) + B(b, x)) / 2 for an edge midpoint m_ab): exact
 * midpoint subdivision of the top-level patch, one float rounding per
 * average, which the pad covers. A node's blossoms: [0..2] = (i, i),
 * [3] = (0, 1), [4] = (1, 2), [5] = (2, 0). */
typedef struct blossom {
    float s[3], t[3];
} blossom;

static void half_apply(const float m[12], const mr_vec3 p, const mr_vec3 n, float s[3], float t[3])
{
    for (int r = 0; r < 3; r++) {
        s[r] = m[r * 4] * p.x + m[r * 4 + 1] * p.y + m[r * 4 + 2] * p.z + m[r * 4 + 3];
        t[r] = m[r * 4] * n.x + m[r * 4 + 1] * n.y + m[r * 4 + 2] * n.z;
    }
}

/* The top-level patch: eq. 11 for positions and directions at corners i, j. */
static blossom top_blossom(const mr_dmm_patch *p, int i, int j)
{
    blossom b;
    half_apply(p->mats[i]->m, p->tri.pos[j], p->tri.dir[j], b.s, b.t);
    if (i != j) {
        float s[3], t[3];
        half_apply(p->mats[j]->m, p->tri.pos[i], p->tri.dir[i], s, t);
        for (int r = 0; r < 3; r++) {
            b.s[r] = 0.5f * (b.s[r] + s[r]);
            b.t[r] = 0.5f * (b.t[r] + t[r]);
        }
    }
    return b;
}

/* Written in place (returning the struct made the compiler store it in
 * pieces and reload it whole: a store-forwarding stall per blossom). */
static inline void average(blossom *b, const blossom *x, const blossom *y)
{
    for (int r = 0; r < 3; r++) {
        b->s[r] = 0.5f * (x->s[r] + y->s[r]);
        b->t[r] = 0.5f * (x->t[r] + y->t[r]);
    }
}

static void grow_blossom(fbox *box, const blossom *b, float dmin, float dmax)
{
    float lo[3], hi[3];
    for (int r = 0; r < 3; r++) {
        lo[r] = b->s[r] + dmin * b->t[r];
        hi[r] = b->s[r] + dmax * b->t[r];
    }
    grow(box, lo);
    grow(box, hi);
}

static void grow_prism(fbox *box, const lattice_pt *x, float dmin, float dmax)
{
    float lo[3], hi[3];
    for (int r = 0; r < 3; r++) {
        lo[r] = x->p[r] + dmin * x->n[r];
        hi[r] = x->p[r] + dmax * x->n[r];
    }
    grow(box, lo);
    grow(box, hi);
}

/* Box of the micro-geometry over sub-triangle (L[0], L[1], L[2]) whose
 * displacements lie in [dmin, dmax]; bl holds the blossoms of its corner
 * pairs (interpolated patches): bl[0..2] = (i, i), bl[3] = (0, 1),
 * bl[4] = (1, 2), bl[5] = (2, 0). */
static fbox node_box(const trace_ctx *c, const lattice_pt *const L[3], const blossom *const bl[6],
                     float dmin, float dmax)
{
    fbox b = empty_box();
    if (!c->patch->mats[0])
        for (int k = 0; k < 3; k++)
            grow_prism(&b, L[k], dmin, dmax);
    else
        for (int k = 0; k < 6; k++)
            grow_blossom(&b, bl[k], dmin, dmax);
    widen(c, &b);
    return b;
}



/* A micro-triangle's geometric normal (unnormalised): the float cross
 * product of its edges, as the tessellation's users compute it. Where that
 * overflows (coordinates beyond ~1e19, which the double-precision test
 * still hits), the same cross product in double, scaled by its largest
 * component, so a hit never carries a non-finite normal. */
static mr_vec3 micro_normal(mr_vec3 v0, mr_vec3 v1, mr_vec3 v2)
{
    mr_vec3 n = mr_v3_cross(mr_v3_sub(v1, v0), mr_v3_sub(v2, v0));
    if (isfinite(n.x) && isfinite(n.y) && isfinite(n.z))
        return n;
    double e1[3] = {(double)v1.x - v0.x, (double)v1.y - v0.y, (double)v1.z - v0.z};
    double e2[3] = {(double)v2.x - v0.x, (double)v2.y - v0.y, (double)v2.z - v0.z};
    double c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                   e1[0] * e2[1] - e1[1] * e2[0]};
    double m = fmax(fabs(c[0]), fmax(fabs(c[1]), fabs(c[2])));
    if (!(m > 0) || !isfinite(m))
        return mr_v3(0, 0, 0);
    return mr_v3((float)(c[0] / m), (float)(c[1] / m), (float)(c[2] / m));
}

/* Children of sub-triangle (P0, P1, P2) with edge midpoints m01, m12, m20,
 * in pyramid order (dmm_encode.h): (P0, m01, m20), (m01, P1, m12),
 * (m20, m12, P2), (m12, m20, m01). Indices into {P0, P1, P2, m01, m12, m20}. */
static const int CHILD[4][3] = {{0, 3, 5}, {3, 1, 4}, {5, 4, 2}, {4, 5, 3}};

/* Edge midpoints by averaging the endpoints' frames: one rounding per
 * level, at most MR_UMESH_MAX_LEVEL of them, well inside BOX_PAD. */
static void midpoints(const lattice_pt *const P[3], lattice_pt m[3])
{
    for (int e = 0; e < 3; e++) {
        const lattice_pt *x = P[e], *y = P[(e + 1) % 3];
        m[e].a = (x->a + y->a) / 2;
        m[e].b = (x->b + y->b) / 2;
        for (int k = 0; k < 3; k++) {
            m[e].p[k] = 0.5f * (x->p[k] + y->p[k]);
            m[e].n[k] = 0.5f * (x->n[k] + y->n[k]);
        }
    }
}

/* Micro-vertices the traversal evaluated, per thread, for interpolated
 * patches with a stamp: neighbouring leaves share vertices, and the next
 * packets of rays reach the same leaves (4,096 entries hold 44-62 % of
 * the leaf vertices a frame of the bench's dancer and wuson asks for,
 * 16,384 hardly more).
 * Direct-mapped on (values, stamp, level, a, b); an entry holds what
 * mr_dmm_vertex returns for exactly that (its bits, made by
 * leaf_vertices), so a hit gives the same bits. A stamp kept across a
 * pose would trace last frame's vertices: test_dmm_accuracy's frames
 * against the exact reference then differ. */
#define VERTEX_CACHE_BITS 12
typedef struct vertex_entry {
    const uint16_t *values;
    uint64_t stamp;
    uint32_t key; /* level, a, b */
    mr_vec3 v;
} vertex_entry;
/* A thread's cache (128 KB) is on the heap (thread_block.h): thread-local
 * storage comes out of every thread's stack. Zeroed: no entry's stamp is
 * 0, the stamp of patches that are not kept. */
static mr_thread_block vertex_block = MR_THREAD_BLOCK_INIT;
static _Thread_local void *my_vertices;

uint64_t mr_dmm_stamp(void)
{
    static _Atomic uint64_t next = 1;
    return next++;
}

/* The micro-vertices at[0 .. n) of patch p into v (n <= 6): mr_dmm_vertex's
 * evaluation, those of a leaf together (mr_umesh_eval_many,
 * mr_umesh_eval_interpolated_many: the same bits). Interpolated patches
 * with a stamp go through the thread's vertex cache first: a base
 * patch's vertex (two blends) costs about what a look-up that misses the
 * cache's lines does, an interpolated one more (the matrices' blend too;
 * the cache bought ~3 % on the wuson at stop 39, nothing measurable on
 * the dancer). */
static void leaf_vertices(const mr_dmm_patch *p, int n, const lattice_pt *const at[6],
                          mr_vec3 v[6])
{
    uint32_t a[6], b[6];
    float d[6];
    vertex_entry *cache =
        p->mats[0] && p->stamp
            ? mr_thread_block_get(&vertex_block, &my_vertices,
                                  sizeof(vertex_entry) << VERTEX_CACHE_BITS)
            : NULL;
    if (!cache) { /* (nothing kept: no stamp, or no memory) */
        for (int k = 0; k < n; k++) {
            a[k] = at[k]->a, b[k] = at[k]->b;
            d[k] = vertex_disp(p, a[k], b[k]);
        }
        if (p->mats[0])
            mr_umesh_eval_interpolated_many(&p->tri, p->mats, p->level, n, a, b, d, v);
        else
            mr_umesh_eval_many(&p->tri, p->level, n, a, b, d, v);
        return;
    }
    /* through the cache: the misses evaluated together, then kept */
    int slot[6], misses = 0; /* slot[i]: where in v miss i goes */
    vertex_entry *entry[6];
    uint32_t keys[6];
    for (int k = 0; k < n; k++) {
        const uint32_t ak = at[k]->a, bk = at[k]->b;
        const uint32_t key = p->level << 24 | ak << 12 | bk; /* a, b <= 2^MR_UMESH_MAX_LEVEL */
        const uint64_t h =
            ((uintptr_t)p->values ^ p->stamp * 0x9E3779B97F4A7C15ull) + key * 0xC2B2AE3Du;
        vertex_entry *e =
            &cache[(h * 0x9E3779B97F4A7C15ull) >> (64 - VERTEX_CACHE_BITS)];
        if (e->values == p->values && e->stamp == p->stamp && e->key == key) {
            v[k] = e->v;
            continue;
        }
        entry[misses] = e;
        keys[misses] = key;
        a[misses] = ak, b[misses] = bk;
        d[misses] = vertex_disp(p, ak, bk);
        slot[misses++] = k;
    }
    if (!misses)
        return;
    mr_vec3 out[6];
    mr_umesh_eval_interpolated_many(&p->tri, p->mats, p->level, misses, a, b, d, out);
    for (int i = 0; i < misses; i++) {
        v[slot[i]] = out[i];
        entry[i]->values = p->values; /* two misses in one entry: the last kept */
        entry[i]->stamp = p->stamp;
        entry[i]->key = keys[i];
        entry[i]->v = out[i];
    }
}

/* A leaf's micro-triangles: made once, tested against each ray that
 * reaches the leaf. The watertight test's rounding depends on which vertex
 * comes first, so each micro-triangle is rotated (winding kept) to start
 * where the tessellation (mr_umesh_triangle) starts it: at the corner with
 * the smallest b, then the smallest a; its hits are then bit-identical to
 * the tessellated micro-mesh's under the same test. Which corner that is,
 * and the micro-triangle's place in row order (what orders equal-t hits),
 * depend on the leaf alone: worked out here, not per ray. */
typedef struct leaf_tris {
    int count;                /* 1 (level 0: the base triangle) or 4 */
    lattice_pt mid[3], moved[6];
    /* pts: the corners as the quadtree has them; at: after edge decimation
     * (v was evaluated there; a collapsed micro-triangle has two equal
     * vertices, so a zero determinant and no hit) */
    const lattice_pt *pts[6], *at[6];
    mr_vec3 v[6];
    uint8_t corner[4][3]; /* micro-triangle k: indices into pts, at, v, rotated */
    uint32_t key[4];      /* micro-triangle k's index in row order */
#ifdef LEAF_LANES
    /* for leaf_test_avx2 (lanes_made): coordinate j of micro-triangle k's
     * corner i (v[corner[k][i]]) in lane k of lanes[i][j], in double */
    bool lanes_made;
    double lanes[3][3][4] __attribute__((aligned(32)));
#endif
} leaf_tris;

/* Micro-triangle k of lt with corners (indices) c: its rotation and row
 * index. Row index: its first corner (smallest b, then a) and whether the
 * second corner is a row up (inverted) or not (upright). */
static void leaf_order(leaf_tris *lt, int k, const int c[3], uint32_t segments)
{
    const lattice_pt *const *P = lt->pts;
    int s = 0;
    for (int i = 1; i < 3; i++)
        if (P[c[i]]->b < P[c[s]]->b || (P[c[i]]->b == P[c[s]]->b && P[c[i]]->a < P[c[s]]->a))
            s = i;
    for (int i = 0; i < 3; i++)
        lt->corner[k][i] = (uint8_t)c[(s + i) % 3];
    uint32_t a0 = P[c[s]]->a, b0 = P[c[s]]->b;
    lt->key[k] = b0 * (2 * segments - b0) + 2 * a0 - (P[c[(s + 1) % 3]]->b > b0 ? 1u : 0u);
}

static uint32_t level_start(unsigned sublevel) { return ((1u << (2 * sublevel)) - 1) / 3; }

/* Which corner each micro-triangle of a leaf starts at and its row index
 * (leaf_order) depend on the leaf's lattice corners alone, which its
 * level and its id in the quadtree (as the traversal numbers them: child k
 * of node id is 4 id + k, corners by CHILD) fix: worked out once for
 * every leaf of levels 1..MR_UMESH_MAX_LEVEL (4^(level - 1) each, from
 * level_start(level - 1)) instead of at every leaf made (3 % of a
 * level-2 dancer's frame). */
typedef struct leaf_shape {
    uint8_t corner[4][3];
    uint32_t key[4];
} leaf_shape;
static leaf_shape leaf_shapes[((1u << (2 * MR_UMESH_MAX_LEVEL)) - 1) / 3];
static pthread_once_t leaf_shapes_once = PTHREAD_ONCE_INIT;

static void shapes_node(unsigned level, unsigned sublevel, uint32_t id, const lattice_pt *const P[3])
{
    lattice_pt m[3];
    midpoints(P, m);
    const lattice_pt *pts[6] = {P[0], P[1], P[2], &m[0], &m[1], &m[2]};
    if (sublevel + 1 == level) { /* a leaf */
        leaf_tris lt;
        memcpy(lt.pts, pts, sizeof pts);
        for (int k = 0; k < 4; k++)
            leaf_order(&lt, k, CHILD[k], mr_umesh_segments(level));
        leaf_shape *sh = &leaf_shapes[level_start(level - 1) + id];
        memcpy(sh->corner, lt.corner, sizeof sh->corner);
        memcpy(sh->key, lt.key, sizeof sh->key);
        return;
    }
    for (int k = 0; k < 4; k++) {
        const lattice_pt *L[3] = {pts[CHILD[k][0]], pts[CHILD[k][1]], pts[CHILD[k][2]]};
        shapes_node(level, sublevel + 1, 4 * id + (uint32_t)k, L);
    }
}

static void shapes_build(void)
{
    for (unsigned level = 1; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t n = mr_umesh_segments(level);
        lattice_pt P[3] = {{.a = 0, .b = 0}, {.a = n, .b = 0}, {.a = 0, .b = n}};
        shapes_node(level, 0, 0, (const lattice_pt *const[3]){&P[0], &P[1], &P[2]});
    }
}

#ifdef LEAF_LANES
/* A leaf's four micro-triangles' corners in lanes (lt->lanes), for
 * leaf_test_avx2: made once per leaf, read by every ray that tests it. */
static void leaf_lanes(leaf_tris *lt)
{
    lt->lanes_made = lt->count == 4 && __builtin_cpu_supports("avx2");
    if (!lt->lanes_made)
        return;
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 4; k++) {
            const mr_vec3 v = lt->v[lt->corner[k][i]];
            lt->lanes[i][0][k] = v.x;
            lt->lanes[i][1][k] = v.y;
            lt->lanes[i][2][k] = v.z;
        }
}

#endif

/* Patch p's leaf with corners P, number id at sublevel p->level - 1 (level
 * 0: the base triangle itself), into lt. */
static void leaf_make(const mr_dmm_patch *p, const lattice_pt *const P[3], uint32_t segments,
                      uint32_t id, leaf_tris *lt)
{
    if (p->level == 0) {
        lt->count = 1;
        for (int k = 0; k < 3; k++)
            lt->pts[k] = lt->at[k] = P[k];
        leaf_vertices(p, 3, lt->at, lt->v);
        leaf_order(lt, 0, (const int[3]){0, 1, 2}, segments);
#ifdef LEAF_LANES
        lt->lanes_made = false;
#endif
        return;
    }
    lt->count = 4;
    /* Lattice coordinates are all the micro-triangle test needs here. */
    for (int e = 0; e < 3; e++) {
        const lattice_pt *x = P[e], *y = P[(e + 1) % 3];
        lt->mid[e].a = (x->a + y->a) / 2;
        lt->mid[e].b = (x->b + y->b) / 2;
    }
    const lattice_pt *pts[6] = {P[0], P[1], P[2], &lt->mid[0], &lt->mid[1], &lt->mid[2]};
    /* Decimated edges: a collapsed vertex moves to the even vertex before it
     * on the same base edge, a corner of this leaf (leaf edges on a base edge
     * start at even steps), so the leaf's box still bounds it. */
    for (int k = 0; k < 6; k++) {
        lt->pts[k] = lt->at[k] = pts[k];
        if (p->decimate) {
            lt->moved[k].a = pts[k]->a, lt->moved[k].b = pts[k]->b;
            mr_umesh_remap_coords(p->level, p->decimate, &lt->moved[k].a, &lt->moved[k].b);
            lt->at[k] = &lt->moved[k];
        }
    }
    leaf_vertices(p, 6, lt->at, lt->v);
    pthread_once(&leaf_shapes_once, shapes_build);
    const leaf_shape *sh = &leaf_shapes[level_start(p->level - 1) + id];
    memcpy(lt->corner, sh->corner, sizeof lt->corner);
    memcpy(lt->key, sh->key, sizeof lt->key);
#ifdef LEAF_LANES
    leaf_lanes(lt);
#endif
}

/* Micro-triangle k of lt hit at h (a hit's t is finite and within [tmin,
 * tmax]: watertight.h): kept, unless a hit at the same t is. */
static void take_hit(trace_ctx *c, const leaf_tris *lt, int k, const mr_wt_hit *h)
{
    const uint8_t *q = lt->corner[k];
    /* Equal t (a ray through a shared edge or vertex hits both sides at the
     * same float t): the micro-triangle first in row order wins, whatever
     * order the traversal met them in, as in mr_dmm_intersect_micro. */
    uint32_t key = lt->key[k];
    if (h->t == c->tmax && !(key < c->best_key))
        return;
    c->found = true;
    c->tmax = h->t;
    c->best_key = key;
    if (!c->hit)
        return;
    const lattice_pt *L[3] = {lt->at[q[0]], lt->at[q[1]], lt->at[q[2]]};
    float w0 = 1.0f - h->u - h->v, n = (float)c->segments;
    c->hit->t = h->t;
    c->hit->u = (w0 * (float)L[0]->a + h->u * (float)L[1]->a + h->v * (float)L[2]->a) / n;
    c->hit->v = (w0 * (float)L[0]->b + h->u * (float)L[1]->b + h->v * (float)L[2]->b) / n;
    c->hit->ng = micro_normal(lt->v[q[0]], lt->v[q[1]], lt->v[q[2]]);
}

/* Tests micro-triangle k of lt, whose vertices the ray has sheared (sh). */
static void test_triangle(trace_ctx *c, const leaf_tris *lt, int k, const mr_wtd_vertex sh[6])
{
    if (c->stats)
        c->stats->triangles++;
    const uint8_t *q = lt->corner[k];
    mr_wt_hit h;
    if (mr_wtd_intersect_sheared(&sh[q[0]], &sh[q[1]], &sh[q[2]], c->tmin, c->tmax, &h))
        take_hit(c, lt, k, &h);
}

/* The ray's test of a leaf's micro-triangles: their (up to six) vertices
 * sheared into the ray's space once, for all of them (mr_wtd_shear: the
 * same results as testing each alone). */
static void leaf_test_plain(trace_ctx *c, const leaf_tris *lt)
{
    mr_wtd_vertex sh[6];
    for (int k = 0; k < (lt->count == 1 ? 3 : 6); k++)
        sh[k] = mr_wtd_shear(&c->ray->wt, lt->v[k]);
    for (int k = 0; k < lt->count && !(c->any_hit && c->found); k++)
        test_triangle(c, lt, k, sh);
}

#ifdef LEAF_LANES
/* leaf_test for the four micro-triangles at once, one per AVX2 lane: each
 * lane shears its corners (mr_wtd_shear's operations) and takes their
 * edge functions (mr_wtd_intersect_sheared's), and the lanes inside go on,
 * in micro-triangle order as leaf_test_plain's, to the rest of the test
 * (mr_wtd_hit_inside) and take_hit: the same hits and counts, bit for
 * bit. */
__attribute__((target("avx2"))) static void leaf_test_avx2(trace_ctx *c, const leaf_tris *lt)
{
    const mr_wtd_ray *r = &c->ray->wt;
    const __m256d sx = _mm256_set1_pd(r->sx), sy = _mm256_set1_pd(r->sy),
                  sz = _mm256_set1_pd(r->sz);
    __m256d x[3], y[3], z[3];
    for (int i = 0; i < 3; i++) {
        __m256d a[3];
        for (int j = 0; j < 3; j++)
            a[j] = _mm256_sub_pd(_mm256_load_pd(lt->lanes[i][j]), _mm256_set1_pd(r->org[j]));
        const __m256d d = a[r->kz];
        x[i] = _mm256_sub_pd(a[r->kx], _mm256_mul_pd(sx, d));
        y[i] = _mm256_sub_pd(a[r->ky], _mm256_mul_pd(sy, d));
        z[i] = _mm256_mul_pd(d, sz);
    }
    const __m256d u = _mm256_sub_pd(_mm256_mul_pd(x[2], y[1]), _mm256_mul_pd(y[2], x[1])),
                  v = _mm256_sub_pd(_mm256_mul_pd(x[0], y[2]), _mm256_mul_pd(y[0], x[2])),
                  w = _mm256_sub_pd(_mm256_mul_pd(x[1], y[0]), _mm256_mul_pd(y[1], x[0]));
    const __m256d zero = _mm256_setzero_pd();
    const __m256d neg = _mm256_or_pd(_mm256_or_pd(_mm256_cmp_pd(u, zero, _CMP_LT_OQ),
                                                  _mm256_cmp_pd(v, zero, _CMP_LT_OQ)),
                                     _mm256_cmp_pd(w, zero, _CMP_LT_OQ));
    const __m256d pos = _mm256_or_pd(_mm256_or_pd(_mm256_cmp_pd(u, zero, _CMP_GT_OQ),
                                                  _mm256_cmp_pd(v, zero, _CMP_GT_OQ)),
                                     _mm256_cmp_pd(w, zero, _CMP_GT_OQ));
    /* edge functions of both signs: outside */
    const unsigned inside = ~(unsigned)_mm256_movemask_pd(_mm256_and_pd(neg, pos)) & 0xFu;
    double U[4], V[4], W[4], Z[3][4];
    if (inside) {
        _mm256_storeu_pd(U, u);
        _mm256_storeu_pd(V, v);
        _mm256_storeu_pd(W, w);
        for (int i = 0; i < 3; i++)
            _mm256_storeu_pd(Z[i], z[i]);
    }
    for (int k = 0; k < 4 && !(c->any_hit && c->found); k++) {
        if (c->stats)
            c->stats->triangles++;
        mr_wt_hit h;
        if ((inside >> k & 1u) &&
            mr_wtd_hit_inside(U[k], V[k], W[k], Z[0][k], Z[1][k], Z[2][k], c->tmin, c->tmax, &h))
            take_hit(c, lt, k, &h);
    }
}
#endif

static void leaf_test(trace_ctx *c, const leaf_tris *lt)
{
#ifdef LEAF_LANES
    if (lt->lanes_made) {
        leaf_test_avx2(c, lt);
        return;
    }
#endif
    leaf_test_plain(c, lt);
}

static void leaf(trace_ctx *c, uint32_t id, const lattice_pt *const P[3])
{
    leaf_tris lt;
    leaf_make(c->patch, P, c->segments, id, &lt);
    leaf_test(c, &lt);
}

/* EDGE: the corner pairs of the 4 children (indices into {P0, P1, P2, m01,
 * m12, m20}) that are edges of some child, i.e. the blossoms a node needs
 * besides the 6 diagonal ones, in this order: (0,3) (3,5) (5,0) (3,1) (1,4)
 * (4,3) (5,4) (4,2) (2,5). */
/* Per child k: its blossom slots {diag c0, diag c1, diag c2, (c0,c1),
 * (c1,c2), (c2,c0)} as indices into the node's 15 blossoms (the 6 diagonal
 * ones, then the 9 of EDGE): worked out by hand from CHILD and EDGE. */
static const int CHILD_BLOSSOM[4][6] = {
    {0, 3, 5, 6, 7, 8}, {3, 1, 4, 9, 10, 11}, {5, 4, 2, 12, 13, 14}, {4, 5, 3, 12, 7, 11}};

/* The four children's boxes are computed and tested together, one vector
 * lane per child (GCC vector extensions: SSE on x86-64, plain code
 * elsewhere). */
typedef float v4f __attribute__((vector_size(16)));
typedef int32_t v4i __attribute__((vector_size(16)));

static inline v4f vsplat(float x) { return (v4f){x, x, x, x}; }

/* a < b ? a : b and a > b ? a : b per lane: minps / maxps exactly (GCC
 * does not make them of the masks, which took three instructions each). */
static inline v4f vmin(v4f a, v4f b)
{
#if defined(__SSE__)
    return (v4f)_mm_min_ps((__m128)a, (__m128)b);
#else
    v4i m = a < b;
    return (v4f)((m & (v4i)a) | (~m & (v4i)b));
#endif
}

static inline v4f vmax(v4f a, v4f b)
{
#if defined(__SSE__)
    return (v4f)_mm_max_ps((__m128)a, (__m128)b);
#else
    v4i m = a > b;
    return (v4f)((m & (v4i)a) | (~m & (v4i)b));
#endif
}

typedef struct child_boxes {
    v4f lo[3], hi[3];
} child_boxes;

/* Grows lanes' boxes by x + dmin t and x + dmax t (x, t gathered per lane). */
static inline void grow_lanes(child_boxes *b, int r, v4f x, v4f t, v4f dmin, v4f dmax)
{
    v4f u = x + dmin * t, w = x + dmax * t;
    b->lo[r] = vmin(b->lo[r], vmin(u, w));
    b->hi[r] = vmax(b->hi[r], vmax(u, w));
}

static void child_boxes_prism(const lattice_pt *const pts[6], v4f dmin, v4f dmax,
                              child_boxes *b)
{
    for (int r = 0; r < 3; r++) {
        b->lo[r] = vsplat(INFINITY);
        b->hi[r] = vsplat(-INFINITY);
        for (int i = 0; i < 3; i++) {
            const lattice_pt *x0 = pts[CHILD[0][i]], *x1 = pts[CHILD[1][i]],
                             *x2 = pts[CHILD[2][i]], *x3 = pts[CHILD[3][i]];
            grow_lanes(b, r, (v4f){x0->p[r], x1->p[r], x2->p[r], x3->p[r]},
                       (v4f){x0->n[r], x1->n[r], x2->n[r], x3->n[r]}, dmin, dmax);
        }
    }
}

static void child_boxes_bezier(const blossom *const bl[15], v4f dmin, v4f dmax, child_boxes *b)
{
    for (int r = 0; r < 3; r++) {
        b->lo[r] = vsplat(INFINITY);
        b->hi[r] = vsplat(-INFINITY);
        for (int i = 0; i < 6; i++) {
            const blossom *x0 = bl[CHILD_BLOSSOM[0][i]], *x1 = bl[CHILD_BLOSSOM[1][i]],
                          *x2 = bl[CHILD_BLOSSOM[2][i]], *x3 = bl[CHILD_BLOSSOM[3][i]];
            grow_lanes(b, r, (v4f){x0->s[r], x1->s[r], x2->s[r], x3->s[r]},
                       (v4f){x0->t[r], x1->t[r], x2->t[r], x3->t[r]}, dmin, dmax);
        }
    }
}

/* Slab test of the ray against the four boxes widened by the pad: entry
 * distance per lane, INFINITY for a miss. */
static void slab4(const trace_ctx *c, const child_boxes *b, float entry[4])
{
    const mr_dmm_ray *r = c->ray;
    const float o[3] = {r->org.x, r->org.y, r->org.z};
    v4f t0 = vsplat(c->tmin), t1 = vsplat(c->tmax * SLAB_FAR_SCALE);
    for (int a = 0; a < 3; a++) {
        /* widened first, then relative to the origin: fl(lo - pad) <= lo,
         * so the box tested holds the unwidened one whatever the origin's
         * magnitude (pad + o rounded first could lose the pad) */
        v4f lo = (b->lo[a] - vsplat(c->pad[a])) - vsplat(o[a]);
        v4f hi = (b->hi[a] + vsplat(c->pad[a])) - vsplat(o[a]);
        if (r->parallel[a]) {
            /* outside the slab: t1 = -inf on that lane */
            v4i out = (lo > vsplat(0.0f)) | (hi < vsplat(0.0f));
            t1 = (v4f)((out & (v4i)vsplat(-INFINITY)) | (~out & (v4i)t1));
            continue;
        }
        v4f u = lo * vsplat(r->inv[a]), w = hi * vsplat(r->inv[a]);
        t0 = vmax(t0, vmin(u, w));
        t1 = vmin(t1, vmax(u, w) * vsplat(SLAB_FAR_SCALE));
    }
    /* one 16-byte store: the callers read the four as one vector, which
     * four 4-byte stores cannot forward */
    const v4i in = t0 <= t1;
    const v4f e = (v4f)((in & (v4i)t0) | (~in & (v4i)vsplat(INFINITY)));
    memcpy(entry, &e, sizeof e);
}

/* The blossoms a node's children need, computed into `store`. */
typedef struct node_blossoms {
    blossom mc[3][3]; /* (midpoint e of corners e, e+1; corner i) */
    blossom md[3];    /* (m_e, m_e) */
    blossom mm[3];    /* (m01, m20), (m12, m01), (m20, m12) */
} node_blossoms;

/* The 15 blossoms of a node's six points {P0, P1, P2, m01, m12, m20} (the 6
 * diagonal ones, then those of EDGE) from the node's own six (B, see
 * struct blossom), as pointers into B and store. */
static void subdivide(const blossom *const B[6], node_blossoms *store, const blossom *out[15])
{
    /* corner pairs: (i, i) = B[i]; (0,1) = B[3], (1,2) = B[4], (2,0) = B[5] */
    const blossom *C[3][3] = {{B[0], B[3], B[5]}, {B[3], B[1], B[4]}, {B[5], B[4], B[2]}};
    for (int e = 0; e < 3; e++)
        for (int i = 0; i < 3; i++)
            average(&store->mc[e][i], C[e][i], C[(e + 1) % 3][i]);
    for (int e = 0; e < 3; e++)
        average(&store->md[e], &store->mc[e][e], &store->mc[e][(e + 1) % 3]);
    average(&store->mm[0], &store->mc[0][2], &store->mc[0][0]); /* m20 = (P2 + P0) / 2 */
    average(&store->mm[1], &store->mc[1][0], &store->mc[1][1]); /* m01 = (P0 + P1) / 2 */
    average(&store->mm[2], &store->mc[2][1], &store->mc[2][2]); /* m12 = (P1 + P2) / 2 */
    for (int i = 0; i < 3; i++) {
        out[i] = B[i];
        out[3 + i] = &store->md[i];
    }
    /* EDGE order: (P0,m01) (m01,m20) (m20,P0) (m01,P1) (P1,m12) (m12,m01)
     * (m20,m12) (m12,P2) (P2,m20); midpoints m01 = 0, m12 = 1, m20 = 2 */
    out[6] = &store->mc[0][0];
    out[7] = &store->mm[0];
    out[8] = &store->mc[2][0];
    out[9] = &store->mc[0][1];
    out[10] = &store->mc[1][1];
    out[11] = &store->mm[1];
    out[12] = &store->mm[2];
    out[13] = &store->mc[1][2];
    out[14] = &store->mc[2][2];
}

/* A node's four children: their corners, blossoms (interpolated patches)
 * and boxes, made once however many rays then test them. */
typedef struct node_children {
    lattice_pt mid[3];
    const lattice_pt *pts[6];
    node_blossoms store;
    const blossom *bl[15];
    child_boxes boxes;
} node_children;

_Static_assert(sizeof(child_boxes) == MR_DMM_ROOT_CHILDREN_FLOATS * sizeof(float),
               "the root's children's boxes fit the patch's cache");

/* Whether the children of a node of `sublevel` need their blossoms
 * (interpolated patches): for their own children's boxes. A leaf's
 * micro-vertices come from the lattice. */
static bool children_need_blossoms(const trace_ctx *c, unsigned sublevel)
{
    return c->patch->mats[0] != NULL && sublevel + 1 < c->leaf;
}

static void make_children(const trace_ctx *c, unsigned sublevel, uint32_t id,
                          const lattice_pt *const P[3], const blossom *const B[6],
                          node_children *nc)
{
    bool bezier = c->patch->mats[0] != NULL;
    midpoints(P, nc->mid);
    const lattice_pt *pts[6] = {P[0], P[1], P[2], &nc->mid[0], &nc->mid[1], &nc->mid[2]};
    memcpy(nc->pts, pts, sizeof pts);
    if (c->stats)
        c->stats->boxes += 4;
    const float *kept = sublevel == 0 ? c->patch->root_children : NULL;
    if (kept) { /* the boxes made with the patch's bounds */
        if (children_need_blossoms(c, sublevel))
            subdivide(B, &nc->store, nc->bl);
        memcpy(&nc->boxes, kept, sizeof nc->boxes);
        return;
    }
    uint32_t first = level_start(sublevel + 1) + 4 * id;
    const uint16_t *mn = c->patch->minv + first, *mx = c->patch->maxv + first;
    v4f dmin = {disp_bound(c, mn[0]), disp_bound(c, mn[1]), disp_bound(c, mn[2]),
                disp_bound(c, mn[3])};
    v4f dmax = {disp_bound(c, mx[0]), disp_bound(c, mx[1]), disp_bound(c, mx[2]),
                disp_bound(c, mx[3])};
    if (bezier) {
        subdivide(B, &nc->store, nc->bl);
        child_boxes_bezier(nc->bl, dmin, dmax, &nc->boxes);
    } else {
        child_boxes_prism(nc->pts, dmin, dmax, &nc->boxes);
    }
}

/* Sub-triangle `id` of `sublevel` whose box the ray already enters; B its
 * blossoms (interpolated patches, where its children's boxes need them:
 * else NULL, or NULLs). */
static void visit(trace_ctx *c, unsigned sublevel, uint32_t id, const lattice_pt *const P[3],
                  const blossom *const B[6])
{
    if (sublevel == c->leaf) {
        leaf(c, id, P);
        return;
    }
    const bool child_blossoms = children_need_blossoms(c, sublevel);
    node_children nc;
    make_children(c, sublevel, id, P, B, &nc);
    const lattice_pt *const *pts = nc.pts;
    const blossom *const *bl = nc.bl;
    float t[4], entry[4];
    int order[4], count = 0;
    slab4(c, &nc.boxes, t);
    for (int k = 0; k < 4; k++) {
        if (t[k] == INFINITY)
            continue;
        /* insertion by entry distance: nearest first */
        int at = count++;
        while (at > 0 && entry[at - 1] > t[k]) {
            entry[at] = entry[at - 1];
            order[at] = order[at - 1];
            at--;
        }
        entry[at] = t[k];
        order[at] = k;
    }
    for (int i = 0; i < count; i++) {
        if (entry[i] > c->tmax * SLAB_FAR_SCALE || (c->any_hit && c->found))
            break;
        int k = order[i];
        const lattice_pt *L[3] = {pts[CHILD[k][0]], pts[CHILD[k][1]], pts[CHILD[k][2]]};
        const blossom *CB[6];
        for (int m = 0; m < 6 && child_blossoms; m++)
            CB[m] = bl[CHILD_BLOSSOM[k][m]];
        visit(c, sublevel + 1, 4 * id + (uint32_t)k, L, child_blossoms ? CB : NULL);
    }
}

/* visit for the rays `live` of a packet (mr_dmm_intersect_packet), each
 * with its own context in cs: the children and their boxes are made once,
 * each ray tests them (slab4) and goes on into those it enters within its
 * own tmax, nearest entry of any ray first; leaves are made once and
 * tested against each ray that reaches them. Each ray visits every node it
 * would visit alone that can hold a hit within its tmax, and equal-t hits
 * are ordered by row (test_triangle), so its hit is what it gets alone. */
static void visit_packet(trace_ctx *cs, uint32_t live, unsigned sublevel, uint32_t id,
                         const lattice_pt *const P[3], const blossom *const B[6])
{
    const trace_ctx *c = &cs[__builtin_ctz(live)]; /* the patch, its leaf level and pads */
    if (sublevel == c->leaf) {
        leaf_tris lt;
        leaf_make(c->patch, P, c->segments, id, &lt);
        for (uint32_t m = live; m; m &= m - 1)
            leaf_test(&cs[__builtin_ctz(m)], &lt);
        return;
    }
    const bool child_blossoms = children_need_blossoms(c, sublevel);
    node_children nc;
    make_children(c, sublevel, id, P, B, &nc);
    float t[MR_DMM_PACKET_MAX][4], near[4] = {INFINITY, INFINITY, INFINITY, INFINITY};
    uint32_t enters[4] = {0};
    for (uint32_t m = live; m; m &= m - 1) {
        int r = __builtin_ctz(m);
        slab4(&cs[r], &nc.boxes, t[r]);
        for (int k = 0; k < 4; k++) { /* no branch: which boxes a ray enters is anyone's guess */
            enters[k] |= (uint32_t)(t[r][k] != INFINITY) << r;
            near[k] = t[r][k] < near[k] ? t[r][k] : near[k]; /* a miss's INFINITY changes nothing */
        }
    }
    int order[4], count = 0;
    for (int k = 0; k < 4; k++) {
        if (!enters[k])
            continue;
        int at = count++;
        while (at > 0 && near[order[at - 1]] > near[k]) {
            order[at] = order[at - 1];
            at--;
        }
        order[at] = k;
    }
    for (int i = 0; i < count; i++) {
        int k = order[i];
        uint32_t go = 0;
        for (uint32_t m = enters[k]; m; m &= m - 1) {
            int r = __builtin_ctz(m);
            if (!(t[r][k] > cs[r].tmax * SLAB_FAR_SCALE || (cs[r].any_hit && cs[r].found)))
                go |= 1u << r;
        }
        if (!go)
            continue;
        const lattice_pt *L[3] = {nc.pts[CHILD[k][0]], nc.pts[CHILD[k][1]], nc.pts[CHILD[k][2]]};
        const blossom *CB[6];
        for (int m = 0; m < 6 && child_blossoms; m++)
            CB[m] = nc.bl[CHILD_BLOSSOM[k][m]];
        visit_packet(cs, go, sublevel + 1, 4 * id + (uint32_t)k, L, child_blossoms ? CB : NULL);
    }
}

/* The base triangle as the traversal's root: its corners P (L points at
 * them) and, with blossoms (interpolated patches), its six blossoms bl (B
 * points at them; NULL without). */
typedef struct root_node {
    lattice_pt P[3];
    const lattice_pt *L[3];
    blossom bl[6];
    const blossom *B[6];
} root_node;

static void root_make(const trace_ctx *c, bool blossoms, root_node *r)
{
    const mr_dmm_patch *p = c->patch;
    uint32_t n = c->segments;
    const uint32_t a[3] = {0, n, 0}, b[3] = {0, 0, n};
    for (int i = 0; i < 3; i++) {
        r->P[i].a = a[i];
        r->P[i].b = b[i];
        for (int k = 0; k < 3; k++) {
            r->P[i].p[k] = comp(p->tri.pos[i], k);
            r->P[i].n[k] = comp(p->tri.dir[i], k);
        }
        r->L[i] = &r->P[i];
    }
    for (int i = 0; i < 3 && blossoms; i++) {
        r->bl[i] = top_blossom(p, i, i);
        r->bl[3 + i] = top_blossom(p, i, (i + 1) % 3);
    }
    for (int i = 0; i < 6; i++)
        r->B[i] = blossoms ? &r->bl[i] : NULL;
}

/* Whether a traversal of an interpolated patch needs the root's blossoms:
 * for its children's boxes, unless the patch holds them, and for their
 * own children's. */
static bool root_blossoms_needed(const trace_ctx *c)
{
    return c->patch->mats[0] != NULL && (!c->patch->root_children || children_need_blossoms(c, 0));
}

/* Whether box b is over BOX_LOOSE times the size of the posed base
 * triangle with corners x[0..2] (the sum of the extents of either box): a
 * triangle across a thin part whose corner directions nearly oppose, where
 * the bake's distances, divided by a direction interpolated to almost
 * nothing, make displacement ranges that the corners' unit directions turn
 * into boxes many times the surface (Testwuson.X: boxes 25 units wide on a
 * character 1.5 tall, entered by every ray of their rows). */
static bool loose(const float *const x[3], const fbox *b)
{
    float box = 0, tri = 0;
    for (int k = 0; k < 3; k++) {
        float lo = x[0][k], hi = lo;
        for (int i = 1; i < 3; i++) {
            lo = x[i][k] < lo ? x[i][k] : lo;
            hi = x[i][k] > hi ? x[i][k] : hi;
        }
        box += b->hi[k] - b->lo[k];
        tri += hi - lo;
    }
    return box > BOX_LOOSE * tri;
}

bool mr_dmm_patch_root_children(const mr_dmm_patch *p, float out[MR_DMM_ROOT_CHILDREN_FLOATS])
{
    if (p->level > MR_UMESH_MAX_LEVEL || mr_dmm_trace_leaf_sublevel(p->level) == 0)
        return false;
    mr_dmm_patch own = *p;
    own.root_children = NULL; /* made, not read */
    trace_ctx c = {.patch = &own,
                   .leaf = mr_dmm_trace_leaf_sublevel(p->level),
                   .segments = mr_umesh_segments(p->level)};
    root_node r;
    root_make(&c, p->mats[0] != NULL, &r);
    node_children nc;
    make_children(&c, 0, 0, r.L, r.B, &nc);
    memcpy(out, &nc.boxes, sizeof nc.boxes);
    return true;
}

bool mr_dmm_patch_bounds(const mr_dmm_patch *p, mr_vec3 *lo, mr_vec3 *hi)
{
    trace_ctx c = {.patch = p, .segments = mr_umesh_segments(p->level)};
    patch_pad(&c);
    root_node r;
    root_make(&c, p->mats[0] != NULL, &r);
    fbox b = node_box(&c, r.L, r.B, disp_bound(&c, p->minv[0]), disp_bound(&c, p->maxv[0]));
    /* the posed corners: base patches' own, interpolated ones' blossoms
     * (i, i) at d = 0 (M_i p_i) */
    const float *corner[3] = {r.P[0].p, r.P[1].p, r.P[2].p};
    if (p->mats[0])
        for (int i = 0; i < 3; i++)
            corner[i] = r.bl[i].s;
    if (loose(corner, &b)) {
        /* the micro-triangles lie in their vertices' box: cut to it (every
         * micro-vertex, those a decimated edge collapses too) */
        fbox v = empty_box();
        for (uint32_t vb = 0; vb <= c.segments; vb++)
            for (uint32_t va = 0; va + vb <= c.segments; va++) {
                mr_vec3 x = mr_dmm_vertex(p, va, vb);
                grow(&v, (const float[3]){x.x, x.y, x.z});
            }
        widen(&c, &v);
        for (int k = 0; k < 3; k++) {
            b.lo[k] = v.lo[k] > b.lo[k] ? v.lo[k] : b.lo[k];
            b.hi[k] = v.hi[k] < b.hi[k] ? v.hi[k] : b.hi[k];
        }
    }
    *lo = mr_v3(b.lo[0], b.lo[1], b.lo[2]);
    *hi = mr_v3(b.hi[0], b.hi[1], b.hi[2]);
    return isfinite(lo->x) && isfinite(lo->y) && isfinite(lo->z) && isfinite(hi->x) &&
           isfinite(hi->y) && isfinite(hi->z);
}

bool mr_dmm_intersect(const mr_dmm_patch *p, const mr_dmm_ray *ray, float tmin, float *tmax,
                      bool take_tmax, bool any_hit, mr_dmm_hit *hit, mr_dmm_trace_stats *stats)
{
    if (p->level > MR_UMESH_MAX_LEVEL || !(tmin <= *tmax))
        return false;
    trace_ctx c = {.patch = p,
                   .ray = ray,
                   .leaf = mr_dmm_trace_leaf_sublevel(p->level),
                   .segments = mr_umesh_segments(p->level),
                   .tmin = tmin,
                   .tmax = *tmax,
                   .best_key = take_tmax ? UINT32_MAX : 0,
                   .any_hit = any_hit,
                   .hit = hit,
                   .stats = stats};
    patch_pad(&c);
    root_node r;
    root_make(&c, root_blossoms_needed(&c), &r);
    /* The caller's BVH has tested the patch box; the root needs no test. */
    visit(&c, 0, 0, r.L, r.B);
    if (c.found)
        *tmax = c.tmax;
    return c.found;
}

uint32_t mr_dmm_intersect_packet(const mr_dmm_patch *p, int n, const mr_dmm_ray *const *rays,
                                 const float *tmin, float *const *tmax, const bool *take_tmax,
                                 bool any_hit, mr_dmm_hit *hits, mr_dmm_trace_stats *stats)
{
    if (p->level > MR_UMESH_MAX_LEVEL || n <= 0 || n > MR_DMM_PACKET_MAX)
        return 0;
    trace_ctx cs[MR_DMM_PACKET_MAX];
    uint32_t live = 0;
    trace_ctx shared = {.patch = p};
    patch_pad(&shared);
    const float *pad = shared.pad;
    for (int k = 0; k < n; k++) {
        cs[k] = (trace_ctx){.patch = p,
                            .ray = rays[k],
                            .leaf = mr_dmm_trace_leaf_sublevel(p->level),
                            .segments = mr_umesh_segments(p->level),
                            .pad = {pad[0], pad[1], pad[2]},
                            .tmin = tmin[k],
                            .tmax = *tmax[k],
                            .best_key = take_tmax[k] ? UINT32_MAX : 0,
                            .any_hit = any_hit,
                            .hit = hits ? &hits[k] : NULL,
                            .stats = stats};
        if (tmin[k] <= *tmax[k])
            live |= 1u << k;
    }
    if (!live)
        return 0;
    root_node r;
    root_make(&cs[0], root_blossoms_needed(&cs[0]), &r);
    visit_packet(cs, live, 0, 0, r.L, r.B);
    uint32_t hit = 0;
    for (uint32_t m = live; m; m &= m - 1) {
        int k = __builtin_ctz(m);
        if (cs[k].found) {
            *tmax[k] = cs[k].tmax;
            hit |= 1u << k;
        }
    }
    return hit;
}

bool mr_dmm_intersect_micro(const mr_dmm_patch *p, const float *verts, const uint32_t *tris,
                            uint32_t count, const mr_dmm_ray *ray, float tmin, float *tmax,
                            bool take_tmax, bool any_hit, mr_dmm_hit *hit)
{
    if (p->level > MR_UMESH_MAX_LEVEL || !(tmin <= *tmax))
        return false;
    float best = *tmax;
    uint32_t best_key = take_tmax ? UINT32_MAX : 0, found = UINT32_MAX;
    mr_wt_hit best_h = {0};
    for (uint32_t k = 0; k < count; k++) {
        const uint32_t *i = tris + 3 * (size_t)k;
        mr_vec3 v[3];
        for (int j = 0; j < 3; j++)
            v[j] = mr_v3(verts[3 * (size_t)i[j]], verts[3 * (size_t)i[j] + 1],
                         verts[3 * (size_t)i[j] + 2]);
        mr_wt_hit h;
        if (!mr_wtd_intersect(&ray->wt, v[0], v[1], v[2], tmin, best, &h) ||
            (h.t == best && !(k < best_key)))
            continue;
        best = h.t;
        best_key = k;
        found = k;
        best_h = h;
        if (any_hit)
            break;
    }
    if (found == UINT32_MAX)
        return false;
    *tmax = best;
    if (!hit)
        return true;
    /* the hit record exactly as test_triangle writes it */
    const uint32_t *i = tris + 3 * (size_t)found;
    mr_vec3 v[3];
    uint32_t a[3], b[3];
    for (int j = 0; j < 3; j++) {
        v[j] = mr_v3(verts[3 * (size_t)i[j]], verts[3 * (size_t)i[j] + 1],
                     verts[3 * (size_t)i[j] + 2]);
        mr_umesh_vertex_coords(p->level, i[j], &a[j], &b[j]);
    }
    float w0 = 1.0f - best_h.u - best_h.v, n = (float)mr_umesh_segments(p->level);
    hit->t = best_h.t;
    hit->u = (w0 * (float)a[0] + best_h.u * (float)a[1] + best_h.v * (float)a[2]) / n;
    hit->v = (w0 * (float)b[0] + best_h.u * (float)b[1] + best_h.v * (float)b[2]) / n;
    hit->ng = micro_normal(v[0], v[1], v[2]);
    return true;
}

static bool decimated_tri(unsigned level, unsigned decimate, uint32_t a[3], uint32_t b[3])
{
    for (int k = 0; k < 3; k++)
        mr_umesh_remap_coords(level, decimate, &a[k], &b[k]);
    for (int k = 0; k < 3; k++)
        if (a[k] == a[(k + 1) % 3] && b[k] == b[(k + 1) % 3])
            return false;
    return true;
}

/* Smallest barycentric weight of lattice point (x, y) in triangle (a, b):
 * >= 0 inside. */
static float inside_weight(const uint32_t a[3], const uint32_t b[3], float x, float y)
{
    float w[3], area = 0;
    for (int k = 0; k < 3; k++) {
        int i = (k + 1) % 3, j = (k + 2) % 3;
        w[k] = ((float)a[i] - x) * ((float)b[j] - y) - ((float)a[j] - x) * ((float)b[i] - y);
        area += w[k];
    }
    float m = w[0] < w[1] ? w[0] : w[1];
    m = m < w[2] ? m : w[2];
    return area > 0 ? m / area : -INFINITY;
}

void mr_dmm_locate(unsigned level, unsigned decimate, float u, float v, uint32_t a[3],
                   uint32_t b[3])
{
    uint32_t n = mr_umesh_segments(level);
    if (n == 0)
        n = 1;
    float x = u * (float)n, y = v * (float)n;
    x = x > 0 ? x : 0;
    y = y > 0 ? y : 0;
    uint32_t ia = x < (float)n ? (uint32_t)x : n - 1, ib = y < (float)n ? (uint32_t)y : n - 1;
    if (ia + ib > n - 1) {
        /* outside the triangle by rounding: pull back onto the last row */
        if (ia > n - 1 - ib)
            ia = n - 1 - ib;
    }
    float fx = x - (float)ia, fy = y - (float)ib;
    mr_umesh_lattice_triangle(ia, ib, !(fx + fy <= 1.0f || ia + ib + 1 > n - 1), a, b);
    if (!decimate || level == 0 || decimated_tri(level, decimate, a, b))
        return;
    /* Collapsed: the surviving micro-triangles around it cover its domain;
     * take the one that contains (x, y) best (the largest smallest
     * barycentric weight, which also absorbs rounding at their borders). */
    float best = -INFINITY;
    for (uint32_t jb = ib ? ib - 1 : 0; jb <= ib + 1 && jb < n; jb++)
        for (uint32_t ja = ia ? ia - 1 : 0; ja <= ia + 1 && ja + jb < n; ja++)
            for (int inv = 0; inv < 2 && !(inv && ja + jb + 1 > n - 1); inv++) {
                uint32_t ca[3], cb[3];
                mr_umesh_lattice_triangle(ja, jb, inv, ca, cb);
                if (!decimated_tri(level, decimate, ca, cb))
                    continue;
                float w = inside_weight(ca, cb, x, y);
                if (w > best) {
                    best = w;
                    memcpy(a, ca, sizeof ca);
                    memcpy(b, cb, sizeof cb);
                }
            }
}
