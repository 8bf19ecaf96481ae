/*
 * deform.c - per-frame selection, deformation and resampling of one octree
 * instance (deform.h; paper 004, 3.2 "Selection", 3.3 "Direct", "Resize",
 * "Emit", with the REFERENCE.md errata).
 *
 * Selection is level-synchronous: the frontier of one level (the voxels to
 * deform there) is split into fixed chunks of SEL_CHUNK items. Pass 1
 * deforms every item and decides removed / selected / expanded, with
 * per-chunk counts, writing the chunk's selected voxels into the
 * selection packed from its first item's slot, and a list of its expanded
 * ones; a serial prefix sum over the chunks gives each chunk's place in
 * the selection and in the next frontier, a serial pass moves the runs of
 * chunks behind a gap down to their places, and pass 2 writes the
 * children. The voxels' palette entries are blended into a table for the
 * frame once enough voxels need them (select_level), or, on several
 * threads, by the other threads while the top levels, whose frontiers fit
 * one chunk, run on one (top_and_fill).
 * Chunk boundaries depend on the frontier only, so the order of the output
 * is the same for any thread count, and every number is computed by the
 * same operations whichever worker runs it.
 *
 * Resampling is the same pattern over the selected boxes: a bounds pass, a
 * count pass (level and cell ranges per box), a prefix sum, a write pass of
 * keys and source indices, then the shared sort / compact / build.
 *
 * Cell indices are decided with the plane arithmetic of svo_trace.c: a cell
 * boundary at finest-grid position K lies at signed distance
 * (origin - x) + K * size * 2^-21 from a coordinate x, computed in double
 * (K * size * 2^-21 is exact). floor / ceil of (x - origin) / cell give a
 * first guess that rounding can leave one cell off; the guess is then moved
 * until that exact-as-possible test agrees, so an emitted range covers its
 * box in the very arithmetic a ray cast uses to decide whether a point lies
 * in a leaf.
 */
#include "kinds/svo/deform.h"

#include <float.h>
#include <stdatomic.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "util/morton.h"
#include "util/radix_sort.h"
#include "util/large_alloc.h"
#include "kinds/svo/svo_build.h"
#include "util/parallel.h"

#define GRID_BITS MR_SVO_MAX_DEPTH
#define GRID_CELLS (1u << GRID_BITS)
/* Items per chunk: fixed, never derived from the thread count. */
#define SEL_CHUNK 1024u
#define RS_CHUNK 4096u
/* Moved normals a selection chunk remembers (a power of two). */
#define NORMAL_MEMO_BITS 11
#define NORMAL_MEMO (1u << NORMAL_MEMO_BITS)
/* Leaves an entry of the palette from which its normal matrix is kept
 * (sel_ctx.pal_normal). */
#define NORMALS_KEPT_LEAVES 8u
/* How many items ahead pass 1 prefetches their palette entries (4, 8 and
 * 16 measured alike). */
#define PAL_AHEAD 8
/* Palette entries a task of the table's fill. */
#define PAL_GRAIN 256
/* Relative growth of the output cube's edge beyond the largest extent: two
 * finest cells at depth 21, invisible at the depths used, and enough that
 * the far face is never touched after rounding to float. */
#define CUBE_GROWTH 0x1p-20

static inline unsigned lowest_bit(unsigned m) /* m != 0 */
{
    unsigned c = 0;
    while (!(m & (1u << c)))
        c++;
    return c;
}

static inline unsigned highest_bit(unsigned m) /* m != 0 */
{
    unsigned c = 7;
    while (!(m & (1u << c)))
        c--;
    return c;
}

static inline double dmin(double a, double b) { return a < b ? a : b; }
static inline double dmax(double a, double b) { return a > b ? a : b; }

static bool affine_finite(const mr_affine *a)
{
    for (int e = 0; e < 12; e++)
        if (!isfinite(a->m[e]))
            return false;
    return true;
}

/* Child c of interior node n: its index among the leaves (is_leaf) or the
 * interior nodes. Returns false when the index does not fit the octree. */
static bool child_index(const mr_svo *svo, uint32_t n, unsigned c, bool *is_leaf, uint32_t *index)
{
    const unsigned cm = svo->child_mask[n], lm = svo->leaf_mask[n];
    const unsigned below = (1u << c) - 1u;
    uint64_t i;
    if (lm & (1u << c)) {
        *is_leaf = true;
        i = (uint64_t)svo->first_leaf[n] + mr_svo_popcount8(lm & below);
        if (i >= svo->leaf_count)
            return false;
    } else {
        *is_leaf = false;
        i = (uint64_t)svo->first_node[n] + mr_svo_popcount8(cm & ~lm & below);
        /* Breadth-first: children come after their parent, which also rules
         * out cycles in a corrupt octree. */
        if (i >= svo->node_count || i <= n)
            return false;
    }
    *index = (uint32_t)i;
    return true;
}

static bool masks_ok(const mr_svo *svo, uint32_t n)
{
    const unsigned cm = svo->child_mask[n], lm = svo->leaf_mask[n];
    return cm != 0 && (lm & ~cm) == 0;
}

/* n's masks are sound (masks_ok) and child_index would succeed for every
 * child: the last leaf child and the last interior child are inside the
 * octree and the first interior child comes after n. */
static bool children_ok(const mr_svo *svo, uint32_t n)
{
    if (!masks_ok(svo, n))
        return false;
    const unsigned cm = svo->child_mask[n], lm = svo->leaf_mask[n];
    const unsigned leaves = mr_svo_popcount8(lm), nodes = mr_svo_popcount8(cm & ~lm);
    return (leaves == 0 || (uint64_t)svo->first_leaf[n] + leaves - 1 < svo->leaf_count) &&
           (nodes == 0 || ((uint64_t)svo->first_node[n] + nodes - 1 < svo->node_count && svo->first_node[n] > n));
}

/* ------------------------------------------------------------------------ */
/* Workspace                                                                */

/* Every scratch array of a selection or resampling, by slot. A per-frame
 * caller keeps one workspace, so after the first frame nothing is
 * allocated and no fresh page is faulted in (both showed in profiles). */
enum {
    WS_CUR, WS_NEXT, WS_EXPAND, WS_CH_SEL, WS_CH_CHILD, WS_CH_EXPAND, WS_CH_FAIL,
    WS_RS_LO, WS_RS_HI, WS_RS_BAD, WS_RS_CELLS, WS_RS_BITS, WS_RS_LEVEL, WS_RS_RANGE,
    WS_RS_KEYS, WS_RS_KEYS2, WS_RS_PACKED, WS_RS_PACKED2, WS_RS_PAY, WS_RS_PAY2, WS_RS_HIST,
    WS_RS_LEAVES, WS_PALETTE, WS_PAL_NORMAL, WS_RS_WRITTEN,
    WS_SLOTS
};

struct mr_svo_workspace {
    void *p[WS_SLOTS];
    size_t bytes[WS_SLOTS];
    double emit_s, rebuild_s; /* the phases of the last resample through it */
};

int mr_svo_workspace_new(mr_svo_workspace **out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo workspace: NULL output");
    *out = calloc(1, sizeof **out);
    if (!*out)
        return mr_error_set(err, MR_ERR_NOMEM, "svo workspace: out of memory");
    return MR_OK;
}

static void ws_release(mr_svo_workspace *ws)
{
    for (int k = 0; k < WS_SLOTS; k++)
        free(ws->p[k]);
    memset(ws, 0, sizeof *ws);
}

void mr_svo_workspace_free(mr_svo_workspace *ws)
{
    if (!ws)
        return;
    ws_release(ws);
    free(ws);
}

void mr_svo_workspace_resample_times(const mr_svo_workspace *ws, double *emit_s, double *rebuild_s)
{
    *emit_s = ws ? ws->emit_s : 0;
    *rebuild_s = ws ? ws->rebuild_s : 0;
}

size_t mr_svo_workspace_memory(const mr_svo_workspace *ws)
{
    size_t b = 0;
    if (ws)
        for (int k = 0; k < WS_SLOTS; k++)
            b += ws->bytes[k];
    return b;
}

/* Slot `slot` with room for count elements of elem bytes (at least one);
 * contents are not kept when it grows. NULL when out of memory. */
static void *ws_get(mr_svo_workspace *ws, int slot, size_t count, size_t elem)
{
    if (count == 0)
        count = 1;
    if (count > SIZE_MAX / elem)
        return NULL;
    const size_t need = count * elem;
    if (need <= ws->bytes[slot])
        return ws->p[slot];
    /* an eighth more than asked: frames of one scene ask for much the same,
     * and a power of two would hold up to twice what they use */
    const size_t cap = need > SIZE_MAX - need / 8 ? need : need + need / 8;
    void *q = mr_large_alloc(cap);
    if (!q)
        return NULL;
    free(ws->p[slot]);
    ws->p[slot] = q;
    ws->bytes[slot] = cap;
    return q;
}

static void ws_swap(mr_svo_workspace *ws, int a, int b)
{
    void *p = ws->p[a];
    ws->p[a] = ws->p[b];
    ws->p[b] = p;
    size_t n = ws->bytes[a];
    ws->bytes[a] = ws->bytes[b];
    ws->bytes[b] = n;
}

/* ------------------------------------------------------------------------ */
/* Extremes                                                                 */

void mr_svo_extremes_free(mr_svo_extremes *e)
{
    if (!e)
        return;
    free(e->lo_attr);
    free(e->hi_attr);
    free(e->normal);
    memset(e, 0, sizeof *e);
}

static bool lowest_leaf(const mr_svo *svo, uint32_t n, uint32_t *leaf);

int mr_svo_extremes_build(const mr_svo *svo, mr_svo_extremes *out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo extremes: NULL output");
    memset(out, 0, sizeof *out);
    if (!svo)
        return mr_error_set(err, MR_ERR_INVALID, "svo extremes: NULL octree");
    const uint32_t n = svo->node_count;
    if (n == 0)
        return MR_OK;
    if (!svo->first_node || !svo->first_leaf || !svo->child_mask || !svo->leaf_mask ||
        (svo->leaf_count > 0 && !svo->leaves))
        return mr_error_set(err, MR_ERR_INVALID, "svo extremes: octree arrays missing");
    out->lo_attr = malloc((size_t)n * sizeof *out->lo_attr);
    out->hi_attr = malloc((size_t)n * sizeof *out->hi_attr);
    out->normal = malloc((size_t)n * sizeof *out->normal);
    double (*sum)[3] = calloc(n, sizeof *sum);
    if (!out->lo_attr || !out->hi_attr || !out->normal || !sum) {
        free(sum);
        mr_svo_extremes_free(out);
        return mr_error_set(err, MR_ERR_NOMEM, "svo extremes: out of memory (%u nodes)", n);
    }
    out->node_count = n;
    /* Nodes are breadth-first, so every interior child has a larger index
     * than its parent: one reverse pass sees children before parents. */
    for (uint32_t k = n; k-- > 0;) {
        if (!masks_ok(svo, k)) {
            free(sum);
            mr_svo_extremes_free(out);
            return mr_error_set(err, MR_ERR_FORMAT, "svo extremes: node %u has bad child masks", k);
        }
        const unsigned cm = svo->child_mask[k];
        const unsigned side[2] = {lowest_bit(cm), highest_bit(cm)};
        uint16_t attr[2];
        for (int s = 0; s < 2; s++) {
            bool leaf;
            uint32_t ci;
            if (!child_index(svo, k, side[s], &leaf, &ci)) {
                free(sum);
                mr_svo_extremes_free(out);
                return mr_error_set(err, MR_ERR_FORMAT, "svo extremes: node %u child %u out of range", k,
                                    side[s]);
            }
            attr[s] = leaf ? svo->leaves[ci].attr : (s == 0 ? out->lo_attr[ci] : out->hi_attr[ci]);
        }
        out->lo_attr[k] = attr[0];
        out->hi_attr[k] = attr[1];
        for (unsigned c = 0; c < 8; c++) {
            bool leaf;
            uint32_t ci;
            if (!(cm & (1u << c)) || !child_index(svo, k, c, &leaf, &ci))
                continue;
            if (leaf) {
                mr_vec3 v = mr_svo_normal_decode(svo->leaves[ci].normal);
                sum[k][0] += v.x;
                sum[k][1] += v.y;
                sum[k][2] += v.z;
            } else {
                for (int a = 0; a < 3; a++)
                    sum[k][a] += sum[ci][a];
            }
        }
        double len = sqrt(sum[k][0] * sum[k][0] + sum[k][1] * sum[k][1] + sum[k][2] * sum[k][2]);
        uint32_t any;
        if (len > 1e-9)
            mr_svo_normal_encode(mr_v3((float)(sum[k][0] / len), (float)(sum[k][1] / len), (float)(sum[k][2] / len)),
                                 out->normal[k]);
        else if (lowest_leaf(svo, k, &any))
            memcpy(out->normal[k], svo->leaves[any].normal, 2);
        else
            out->normal[k][0] = out->normal[k][1] = 0;
    }
    free(sum);
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Selection                                                                */

/* Four double lanes, lane i the axis i (lane 3 idle): GCC vector types,
 * one register with AVX2 and two SSE2 registers without (sel_pass1 and
 * pal_fill are compiled for both, target_clones). No function takes or
 * returns a 32-byte vector by value: outside AVX that changes the ABI (GCC
 * warns, clang refuses the call in the baseline clone). */
typedef double vdouble __attribute__((vector_size(32)));
typedef int64_t vlong __attribute__((vector_size(32)));
typedef float vfloat __attribute__((vector_size(16)));
typedef int32_t vint __attribute__((vector_size(16)));

/* a where m (all ones), else b */
#define VSEL(m, a, b) ((vdouble)(((m) & (vlong)(a)) | (~(m) & (vlong)(b))))
/* v's lanes a, b, c (lane 3 kept; GCC 12 and clang both have the builtin) */
#define VSHUF(v, a, b, c) __builtin_shufflevector((v), (v), a, b, c, 3)

/* Four doubles anywhere in memory as one vector (a memcpy of 32 bytes
 * became two 16-byte stores to the stack and a 32-byte load: a
 * store-forwarding stall). */
typedef double vdouble_u __attribute__((vector_size(32), aligned(8), may_alias));

/* Three columns of a 3x3 matrix in four lanes each (lane 3 zero), as
 * twelve doubles (the normal table lives in memory the allocator aligns to
 * 16 bytes only). */
static inline void vcols_load(const double in[12], vdouble out[3])
{
    for (int k = 0; k < 3; k++)
        out[k] = *(const vdouble_u *)(in + 4 * k);
}
static inline void vcols_store(const vdouble in[3], double out[12])
{
    for (int k = 0; k < 3; k++)
        *(vdouble_u *)(out + 4 * k) = in[k];
}

/* One voxel to deform: its coordinates at the frontier's level (21 bits
 * each, x | y << 21 | z << 42), its node or leaf index, and whether an
 * ancestor was found well inside the view frustum (then predicate (a) is
 * not tested again below it: frustum_planes). */
typedef struct sel_item {
    uint64_t xyz;
    uint32_t index;
    uint16_t leaf;
    uint16_t inside;
} sel_item;

/* Bit of a level's expand entry (an item's index below it) that gives the
 * item's children `inside`. */
#define EXPAND_INSIDE 0x80000000u

enum {
    FAIL_NONE = 0,
    FAIL_ATTR,     /* a: voxel's palette entry, b: palette count */
    FAIL_FIELD,    /* p: bind point */
    FAIL_CHILD,    /* a: node */
    FAIL_OVERFLOW, /* a: level; the deformed box left the float range */
    FAIL_PALETTE,  /* a: palette entry naming a mesh or joint the deformer lacks */
};

typedef struct sel_fail {
    int kind;
    uint32_t a, b;
    double p[3];
} sel_fail;

/* One palette entry's blended skin matrix for a frame, a cache line each
 * (the table is read in the order of the voxels' entries, which is no
 * order: each entry one miss). */
typedef struct pal_entry {
    mr_affine a;
    bool ok;         /* false: the entry names a mesh or joint the deformer lacks */
    bool has_normal; /* its row of sel_ctx.pal_normal is made */
    char pad[64 - sizeof(mr_affine) - 2 * sizeof(bool)];
} pal_entry;
_Static_assert(sizeof(pal_entry) == 64, "a palette entry is one cache line");

typedef struct sel_ctx {
    const mr_svo *svo;
    const mr_svo_extremes *ex;
    const mr_svo_deformer *d;
    bool view_on, cull;
    double vp[16];
    /* clip-space half spaces p . (x, y, z, 1) >= 0 by coefficient: lane
     * q of planes[e][k] is plane 4k + q's e; plane 7 is (0, 0, 0, 1),
     * which never removes a voxel: predicate (a) tests the seven in two
     * vectors */
    vdouble planes[4][2];
    double width, height, delta;
    unsigned level, max_level;
    double origin[3], cell;
    /* the level being processed */
    const sel_item *items;
    size_t n;
    size_t out_base;                       /* out's count before the level */
    uint32_t *expand;                      /* a chunk's expanded items, from its first slot */
    size_t *chunk_sel, *chunk_child; /* counts, then offsets */
    size_t *chunk_expand;            /* expanded items */
    size_t chunks;                   /* chunks of the level */
    sel_fail *chunk_fail;
    sel_item *next;
    mr_svo_selection *out;
    /* every palette entry's matrix for this frame (pal_fill), once enough
     * voxels need them or the top levels are done (select_level,
     * top_and_fill); NULL before */
    pal_entry *pal;
    /* With pal, where the octree's leaves are many to an entry (at least
     * NORMALS_KEPT_LEAVES; otherwise NULL): the normal matrix of a voxel
     * whose extremes both take an entry, normal_matrix(a, a), made once an
     * entry instead of per voxel (vcols_store). The dancer has 3.8 leaves
     * an entry at depth 8 and 29 at depth 10: kept at depth 8 the table's
     * 96 more bytes an entry made a selection wait on its misses (2.04 ->
     * 2.24 ms a selection, two threads), made per voxel at depth 10 they
     * cost 24.6 -> 26.2 ms. On one thread (instances deformed in parallel)
     * a row is made when a selected voxel first needs it (lazy_normals). */
    double (*pal_normal)[12];
    bool lazy_normals;
} sel_ctx;

/* A palette weight w (0..255) as the blend's factor, w / 255.0: the
 * quotients themselves (the compiler folds each one correctly rounded, as
 * the division does), read instead of dividing once per influence; with
 * the joints' rows widened whole (blend_entry), the table's fill took
 * 0.87-0.90 of its time on one thread. */
#define WEIGHT4(k) (k) / 255.0, ((k) + 1) / 255.0, ((k) + 2) / 255.0, ((k) + 3) / 255.0
#define WEIGHT16(k) WEIGHT4(k), WEIGHT4((k) + 4), WEIGHT4((k) + 8), WEIGHT4((k) + 12)
#define WEIGHT64(k) WEIGHT16(k), WEIGHT16((k) + 16), WEIGHT16((k) + 32), WEIGHT16((k) + 48)
static const double WEIGHT[256] = {WEIGHT64(0), WEIGHT64(64), WEIGHT64(128), WEIGHT64(192)};

/* The blended skin matrix of palette entry at (sum of weight * joint
 * matrix, in double, rounded to float; no weights: the mesh's matrix), or
 * false when the entry names a mesh or joint the deformer lacks. A joint's
 * row (four floats in a row of its mr_affine) is widened in one vector
 * conversion; element by element GCC built it with seven instructions. */
__attribute__((always_inline)) static inline bool blend_entry(const mr_svo_attr *at,
                                                              const mr_svo_deformer *d, mr_affine *out)
{
    if (at->mesh >= d->mesh_count)
        return false;
    const uint32_t jc = d->joint_count ? d->joint_count[at->mesh] : 0;
    /* the twelve elements in three vectors: each element's sum is the
     * scalar acc[e] += w * j[e] over the influences in order */
    vdouble acc[3] = {{0.0, 0.0, 0.0, 0.0}, {0.0, 0.0, 0.0, 0.0}, {0.0, 0.0, 0.0, 0.0}};
    bool any = false;
    for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
        if (at->weights[k] == 0)
            continue;
        if (at->joints[k] >= jc)
            return false;
        const double w = WEIGHT[at->weights[k]];
        const float *j = d->joint[at->mesh][at->joints[k]].m;
        for (int q = 0; q < 3; q++) {
            vfloat row;
            memcpy(&row, j + 4 * q, sizeof row);
            acc[q] += (vdouble){w, w, w, w} * __builtin_convertvector(row, vdouble);
        }
        any = true;
    }
    if (!any) {
        *out = d->mesh[at->mesh];
        return true;
    }
    for (int q = 0; q < 3; q++) { /* each row narrowed whole: the same roundings */
        const vfloat row = __builtin_convertvector(acc[q], vfloat);
        memcpy(out->m + 4 * q, &row, sizeof row);
    }
    return true;
}

/* The normal matrix of a voxel with extreme matrices a0 and a1: the
 * cofactor of their mean (columns c1 x c2, c2 x c0, c0 x c1 of the mean's
 * linear part), negated when the mean's determinant is negative, so a
 * mirroring transform keeps normals outward (a voxel has no winding that
 * would flip with it, unlike a triangle). Lane i of r[k]: row i of column
 * k (lane 3 zero); every element the scalar operations of the formula.
 * Negating the matrix before it is applied gives bit for bit the negated
 * product (rounding to nearest is symmetric). */
__attribute__((always_inline)) static inline void normal_matrix(const mr_affine *a0, const mr_affine *a1,
                                                                vdouble r[3])
{
    vdouble c[3]; /* columns of the mean linear part */
    for (int j = 0; j < 3; j++)
        c[j] = 0.5 * ((vdouble){a0->m[j], a0->m[4 + j], a0->m[8 + j], 0.0} +
                      (vdouble){a1->m[j], a1->m[4 + j], a1->m[8 + j], 0.0});
    /* column k = u x v: lane i the scalar u[i+1] v[i+2] - u[i+2] v[i+1] */
    for (int k = 0; k < 3; k++) {
        const vdouble u = c[(k + 1) % 3], v = c[(k + 2) % 3];
        r[k] = VSHUF(u, 1, 2, 0) * VSHUF(v, 2, 0, 1) - VSHUF(u, 2, 0, 1) * VSHUF(v, 1, 2, 0);
    }
    const vdouble p = c[0] * r[0];
    const double det = p[0] + p[1] + p[2];
    if (det < 0.0)
        for (int k = 0; k < 3; k++)
            r[k] = -r[k];
}

/* Bind normal code in moved by normal matrix r, scaled onto the
 * octahedron (the encoder needs a direction only: the bind direction is
 * taken unnormalised and the moved one scaled in double, so a huge or tiny
 * matrix cannot overflow or underflow the float the encoder takes); false
 * when the matrix collapses the normal, which then keeps its bind code. */
__attribute__((always_inline)) static inline bool moved_direction(const vdouble r[3], const uint8_t in[2],
                                                                  float out[3])
{
    const mr_vec3 n = mr_svo_normal_direction(in);
    const double nx = n.x, ny = n.y, nz = n.z;
    const vdouble m = r[0] * (vdouble){nx, nx, nx, nx} + r[1] * (vdouble){ny, ny, ny, ny} +
                      r[2] * (vdouble){nz, nz, nz, nz};
    const double l1 = fabs(m[0]) + fabs(m[1]) + fabs(m[2]);
    if (!(l1 > 0.0) || !isfinite(l1))
        return false;
    const double inv = 1.0 / l1;
    for (int i = 0; i < 3; i++)
        out[i] = (float)(m[i] * inv);
    return true;
}

/* Moved normals waiting to be encoded MR_SVO_NORMAL_LANES at a time
 * (mr_svo_normal_encode_lanes): each one's direction, where its code goes,
 * and the chunk's memo entry to fill with it (NULL: none). */
typedef struct normal_queue {
    float x[MR_SVO_NORMAL_LANES], y[MR_SVO_NORMAL_LANES], z[MR_SVO_NORMAL_LANES];
    uint8_t *dst[MR_SVO_NORMAL_LANES];
    uint64_t *memo[MR_SVO_NORMAL_LANES];
    uint32_t key[MR_SVO_NORMAL_LANES];
    unsigned n;
} normal_queue;

/* A memo entry: valid bit 48, key bits 16-47, code bits 0-15. */
static inline uint64_t memo_entry(uint32_t key, const uint8_t code[2])
{
    return ((uint64_t)1 << 32 | key) << 16 | code[0] | (uint64_t)code[1] << 8;
}

/* Whether memo entry m holds key's code. */
static inline bool memo_holds(uint64_t m, uint32_t key) { return (m >> 16) == ((uint64_t)1 << 32 | key); }

static void nq_flush(normal_queue *q)
{
    if (q->n == 0)
        return;
    uint8_t code[MR_SVO_NORMAL_LANES][2];
    mr_svo_normal_encode_lanes(q->n, q->x, q->y, q->z, code);
    for (unsigned i = 0; i < q->n; i++) {
        q->dst[i][0] = code[i][0];
        q->dst[i][1] = code[i][1];
        if (q->memo[i])
            *q->memo[i] = memo_entry(q->key[i], code[i]);
    }
    q->n = 0;
}

/* Bind normal code in moved by normal matrix r into out, now (a collapsed
 * normal) or at the queue's next flush; memo (NULL: none) is filled with
 * the code under key. */
__attribute__((always_inline)) static inline void move_normal(normal_queue *q, const vdouble r[3],
                                                              const uint8_t in[2], uint8_t out[2],
                                                              uint64_t *memo, uint32_t key)
{
    float d[3];
    if (!moved_direction(r, in, d)) {
        out[0] = in[0];
        out[1] = in[1];
        if (memo)
            *memo = memo_entry(key, out);
        return;
    }
    const unsigned i = q->n++;
    q->x[i] = d[0];
    q->y[i] = d[1];
    q->z[i] = d[2];
    q->dst[i] = out;
    q->memo[i] = memo;
    q->key[i] = key;
    if (q->n == MR_SVO_NORMAL_LANES)
        nq_flush(q);
}

/* Entry attr's matrices: from the frame's table when it has been filled,
 * else blended into *tmp (the same arithmetic either way, so the frontier
 * size that decides which does not change a result). */
__attribute__((always_inline)) static inline pal_entry *pal_get(const sel_ctx *c, uint32_t attr,
                                                               pal_entry *tmp)
{
    if (c->pal)
        return &c->pal[attr];
    tmp->ok = blend_entry(&c->svo->palette[attr], c->d, &tmp->a);
    return tmp;
}

/* Fills entries [begin, end) of the frame's table (mr_range_fn). */
__attribute__((target_clones("avx2", "default")))
static void pal_fill(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const sel_ctx *c = vctx;
    for (size_t i = begin; i < end; i++) {
        pal_entry *p = &c->pal[i];
        p->ok = blend_entry(&c->svo->palette[i], c->d, &p->a);
        p->has_normal = false;
        if (p->ok && c->pal_normal && !c->lazy_normals) {
            vdouble r[3];
            normal_matrix(&p->a, &p->a, r);
            vcols_store(r, c->pal_normal[i]);
            p->has_normal = true;
        }
    }
}

/* mr_float_down (down) or mr_float_up (!down) of each lane of *v: the
 * nearest float, one step along its bit pattern when it lies on the wrong
 * side. The widening and the mask's narrowing are written lane by lane:
 * GCC 12 makes the first one vcvtps2pd and the second two shuffles, where
 * __builtin_convertvector took two halves through the stack and five
 * shuffles (svo-skinned at depth 10, every leaf, two threads: selection
 * 37.7-39.7 -> 38.3-42.0 M voxels/s, the same bits). */
static inline vfloat vfloat_round(const vdouble *v, bool down)
{
    const vfloat f = __builtin_convertvector(*v, vfloat);
    const vdouble back = {f[0], f[1], f[2], f[3]};
    const vlong wrong64 = down ? back > *v : back < *v; /* -1 or 0 */
    const vint wrong = {(int)wrong64[0], (int)wrong64[1], (int)wrong64[2], (int)wrong64[3]};
    const vint negative2 = ((vint)f >> 31) & 2;                                    /* 2 or 0 */
    /* down: -1 for a positive float, +1 for a negative one; up: the reverse */
    const vint step = down ? negative2 - 1 : 1 - negative2;
    return (vfloat)((vint)f + (wrong & step));
}

/* Arvo's box transform in the mr_affine convention (out_i = m[4i+3] +
 * sum_j m[4i+j] * in_j), grown to hold what it gives: the union of the box
 * through each matrix is the deformed box of Fig. 16. Products and sums in
 * double (a float times a double of at most 46 significant bits); every
 * axis the scalar operations l += min(p, q) in the order j = 0, 1, 2, with
 * min(a, b) = a < b ? a : b and max(a, b) = a > b ? a : b. */
static inline void deform_box_grow(const mr_affine *a, const double lo[3], const double hi[3], vdouble *olo,
                                   vdouble *ohi)
{
    const float *m = a->m;
    vdouble l = {m[3], m[7], m[11], 0.0}, h = l;
    for (int j = 0; j < 3; j++) {
        const vdouble col = {m[j], m[4 + j], m[8 + j], 0.0};
        const vdouble p = col * lo[j], q = col * hi[j];
        l += VSEL(p < q, p, q);
        h += VSEL(p > q, p, q);
    }
    *olo = VSEL(*olo < l, *olo, l);
    *ohi = VSEL(*ohi > h, *ohi, h);
}

/* eq. 3.2.1-3.2.3: whether the larger side, in pixels, of the screen
 * rectangle of box b (lo xyz, hi xyz) is below c->delta; never when a
 * corner lies at or behind the eye plane, which makes the projection
 * unbounded. A corner's clip x, y and w are sums of one product per axis
 * (the corner takes lo or hi there) plus a constant: the 18 products are
 * made once and each corner sums its three in the order (x + y) + z +
 * constant, the order the full dot product of each corner would use.
 * Corners go four at a time, lane k the corner (k & 1, k >> 1, half) with
 * half = 0, then 1 (a lane's operations are the scalar ones; the minimum
 * and maximum over corners are exact in any order). The rectangle only
 * grows, so the answer is no when the first half's already reaches delta:
 * the same answer as measuring all eight. The answer is no as well when
 * two corners alone (lanes 0 and 1 of the first half, apart along x) are
 * delta apart across, measured by the same operations (each product its
 * own statement, as above, so no contraction can round them otherwise):
 * measured first, that answers most interior voxels of a fine selection
 * (delta far below their size) for a quarter of the work (svo-skinned at
 * depth 10, every leaf, one thread: selection 60.7 -> 54.3 ms, 49-53 with
 * no projection at all; two threads 37-38 -> 42 M voxels/s).
 * test_svo_deform's test_screen_space and test_svo_lod's test_flythrough
 * fail if this measures twice the width. */
/* (GCC 12 at -O3 calls each row's vectors below "maybe uninitialized" where
 * they are written, in the avx2 clone of sel_pass1, with initialisers too:
 * a false alarm, silenced for this function only) */
#if defined(__GNUC__) && !defined(__clang__) /* (clang, the fuzzers' compiler, has no such warning) */
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
/* projects_below's first answer: whether corners (lo, lo, lo) and (hi,
 * lo, lo) of box b alone lie delta apart across (then the box does not
 * project below delta). */
__attribute__((always_inline)) static inline bool wide_at_two_corners(const sel_ctx *c, const float b[6])
{
    const double *mx = &c->vp[0], *mw = &c->vp[12];
    /* clip x and w of corners (lo, lo, lo) and (hi, lo, lo) */
    const double x_x0 = mx[0] * (double)b[0], x_x1 = mx[0] * (double)b[3];
    const double x_y = mx[1] * (double)b[1], x_z = mx[2] * (double)b[2];
    const double w_x0 = mw[0] * (double)b[0], w_x1 = mw[0] * (double)b[3];
    const double w_y = mw[1] * (double)b[1], w_z = mw[2] * (double)b[2];
    const double x0 = x_x0 + x_y + x_z + mx[3], x1 = x_x1 + x_y + x_z + mx[3];
    const double w0 = w_x0 + w_y + w_z + mw[3], w1 = w_x1 + w_y + w_z + mw[3];
    const double s0 = 0.5 * x0 / w0 + 0.5, s1 = 0.5 * x1 / w1 + 0.5;
    return c->width * (dmax(s0, s1) - dmin(s0, s1)) >= c->delta;
}

__attribute__((always_inline)) static inline bool projects_below(const sel_ctx *c, const float b[6])
{
    static const int row[3] = {0, 1, 3}; /* clip x, y, w */
    if (wide_at_two_corners(c, b))
        return false;
    vdouble cx[3], cy[3], cz[3][2];       /* per row: products by corner lane */
    for (int r = 0; r < 3; r++) {
        const double *m = &c->vp[4 * row[r]];
        const double x0 = m[0] * (double)b[0], x1 = m[0] * (double)b[3];
        const double y0 = m[1] * (double)b[1], y1 = m[1] * (double)b[4];
        cx[r] = (vdouble){x0, x1, x0, x1};
        cy[r] = (vdouble){y0, y0, y1, y1};
        cz[r][0] = m[2] * (double)b[2] - (vdouble){0}; /* in every lane (x - 0 is x, -0 too) */
        cz[r][1] = m[2] * (double)b[5] - (vdouble){0};
    }
    vdouble xmin = INFINITY - (vdouble){0}, xmax = -xmin, ymin = xmin, ymax = xmax;
    for (int half = 0; half < 2; half++) {
        vdouble cl[3];
        for (int r = 0; r < 3; r++)
            cl[r] = cx[r] + cy[r] + cz[r][half] + c->vp[4 * row[r] + 3];
        const vlong ahead = cl[2] > 0.0;
        if (!(ahead[0] & ahead[1] & ahead[2] & ahead[3]))
            return false;
        const vdouble x = 0.5 * cl[0] / cl[2] + 0.5, y = 0.5 * cl[1] / cl[2] + 0.5;
        xmin = VSEL(x < xmin, x, xmin);
        xmax = VSEL(x > xmax, x, xmax);
        ymin = VSEL(y < ymin, y, ymin);
        ymax = VSEL(y > ymax, y, ymax);
        const double x0 = dmin(dmin(xmin[0], xmin[1]), dmin(xmin[2], xmin[3]));
        const double x1 = dmax(dmax(xmax[0], xmax[1]), dmax(xmax[2], xmax[3]));
        const double y0 = dmin(dmin(ymin[0], ymin[1]), dmin(ymin[2], ymin[3]));
        const double y1 = dmax(dmax(ymax[0], ymax[1]), dmax(ymax[2], ymax[3]));
        if (!(dmax(c->width * (x1 - x0), c->height * (y1 - y0)) < c->delta))
            return false;
    }
    return true;
}
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

/* projects_below for up to four boxes at once, box k in lane k (lanes
 * without a box hold a copy of one that has): the mask of those below.
 * Each lane's operations are projects_below's for its box, corner by
 * corner in the same order ((x + y) + z + constant, then 0.5 x / w +
 * 0.5), and its answer is the one projects_below gives without its early
 * answers: no when a corner lies at or behind the eye plane, else whether
 * the larger side of all eight corners' rectangle is below delta (the
 * early answers are no exactly when this one is: the rectangle only
 * grows with more corners, and rounding keeps the order of differences). */
__attribute__((always_inline)) static inline unsigned projects_below4(const sel_ctx *c, const float *const box[4])
{
    static const int row[3] = {0, 1, 3}; /* clip x, y, w */
    vdouble p[3][3][2]; /* row, axis, lo / hi: the products by box lane */
    for (int a = 0; a < 3; a++)
        for (int h = 0; h < 2; h++) {
            const vdouble v = {box[0][3 * h + a], box[1][3 * h + a], box[2][3 * h + a], box[3][3 * h + a]};
            for (int r = 0; r < 3; r++)
                p[r][a][h] = c->vp[4 * row[r] + a] * v;
        }
    const vdouble inf = INFINITY - (vdouble){0};
    vdouble xmin = inf, xmax = -inf, ymin = inf, ymax = -inf;
    vlong ahead = (vlong){0} == 0;
    for (int k = 0; k < 8; k++) {
        const int hx = k & 1, hy = (k >> 1) & 1, hz = k >> 2;
        vdouble cl[3];
        for (int r = 0; r < 3; r++)
            cl[r] = p[r][0][hx] + p[r][1][hy] + p[r][2][hz] + c->vp[4 * row[r] + 3];
        ahead &= cl[2] > 0.0;
        const vdouble x = 0.5 * cl[0] / cl[2] + 0.5, y = 0.5 * cl[1] / cl[2] + 0.5;
        xmin = VSEL(x < xmin, x, xmin);
        xmax = VSEL(x > xmax, x, xmax);
        ymin = VSEL(y < ymin, y, ymin);
        ymax = VSEL(y > ymax, y, ymax);
    }
    const vdouble wx = c->width * (xmax - xmin), wy = c->height * (ymax - ymin);
    const vlong below = ahead & (VSEL(wx > wy, wx, wy) < c->delta);
    return (unsigned)(below[0] & 1) | (unsigned)(below[1] & 1) << 1 | (unsigned)(below[2] & 1) << 2 |
           (unsigned)(below[3] & 1) << 3;
}

/* The leaf reached from interior node n by always taking the lowest child. */
static bool lowest_leaf(const mr_svo *svo, uint32_t n, uint32_t *leaf)
{
    for (unsigned guard = 0; guard <= GRID_BITS; guard++) {
        if (!masks_ok(svo, n))
            return false;
        bool is_leaf;
        uint32_t ci;
        if (!child_index(svo, n, lowest_bit(svo->child_mask[n]), &is_leaf, &ci))
            return false;
        if (is_leaf) {
            *leaf = ci;
            return true;
        }
        n = ci;
    }
    return false;
}

static void fail_set(sel_fail *f, int kind, uint32_t a, uint32_t b, const double p[3])
{
    if (f->kind != FAIL_NONE)
        return; /* keep the chunk's first */
    f->kind = kind;
    f->a = a;
    f->b = b;
    for (int i = 0; i < 3; i++)
        f->p[i] = p ? p[i] : 0.0;
}

/* The palette entries of an item's two extremes (a leaf's own for both). */
static inline void item_attrs(const sel_ctx *c, const sel_item *it, uint32_t *lo, uint32_t *hi)
{
    if (it->leaf) {
        *lo = *hi = c->svo->leaves[it->index].attr;
    } else {
        *lo = c->ex->lo_attr[it->index];
        *hi = c->ex->hi_attr[it->index];
    }
}

/* The seven frustum planes' values (view_setup's planes: lanes 0-3 of
 * v[0] planes 0-3, lanes 0-2 of v[1] planes 4-6, lane 3 the constant 1)
 * at their largest (most) or smallest (!most) over box b (lo xyz, hi xyz)
 * grown by `grow` times its largest side on every side: per plane
 * pl[3] + sum over a = 0, 1, 2 of max (min) of pl[a] * (lo - g) and
 * pl[a] * (hi + g). */
__attribute__((always_inline)) static inline void frustum_planes(const sel_ctx *c, const float b[6], double grow,
                                                                 bool most, vdouble v[2])
{
    double blo[3], bhi[3], g = 0.0;
    for (int a = 0; a < 3; a++) {
        blo[a] = b[a];
        bhi[a] = b[3 + a];
        g = dmax(g, bhi[a] - blo[a]);
    }
    g *= grow;
    v[0] = c->planes[3][0];
    v[1] = c->planes[3][1];
    for (int a = 0; a < 3; a++) {
        const double l = blo[a] - g, h = bhi[a] + g;
        for (int k = 0; k < 2; k++) {
            const vdouble p = c->planes[a][k] * l, q = c->planes[a][k] * h;
            v[k] += most ? VSEL(p > q, p, q) : VSEL(p < q, p, q);
        }
    }
}

/* A chunk of pass 1 under way: its counts, its first failure, its memo
 * of moved normals and the normals waiting to be encoded. */
typedef struct sel_chunk {
    size_t i0, nsel, nchild, nexpand;
    sel_fail *fail;
    normal_queue queue;
    /* With skinning, a voxel whose extremes share one palette entry
     * (every leaf) has a moved normal that is a function of (entry,
     * bind normal) only, and the voxels of a chunk, neighbours in
     * Morton order, repeat such pairs: the chunk remembers them in a
     * small hash table (the same value either way, so what it holds
     * changes no result; memo_entry). Moved normals are encoded
     * several at a time, the chunk's last ones at its end. */
    uint64_t memo[NORMAL_MEMO];
} sel_chunk;

/* The end of item i's pass 1 once it is known to be selected (its
 * deformed box, a0 and a1 its extremes' matrices, from p0 and p1 with
 * the palette) or not: selected, its box goes to the chunk's next slot
 * of the output with its moved normal; else it is expanded. */
__attribute__((always_inline)) static inline void sel_finish(sel_ctx *c, sel_chunk *k, const sel_item *it, size_t i,
                                                             uint32_t attr0, pal_entry *p0, pal_entry *p1,
                                                             const mr_affine *a0, const mr_affine *a1,
                                                             const float *box, bool selected)
{
    const mr_svo *svo = c->svo;
    if (selected) {
        /* the chunk's selected voxels fill its slots of the output (item
         * i0's slot out_base + i0 and on) from the first: they are written
         * where they stay unless an earlier chunk kept fewer than all of
         * its items (select_ws closes such gaps) */
        const size_t slot = c->out_base + k->i0 + k->nsel;
        float *b = &c->out->box[slot * 6];
        if (b != box)
            memcpy(b, box, 6 * sizeof *b);
        mr_svo_leaf *l = &c->out->leaf[slot];
        c->out->level[slot] = (uint8_t)c->level;
        l->attr = (uint16_t)attr0;
        /* a coarse voxel stands for all its leaves: their mean normal (one
         * leaf's would light the whole voxel by wherever that leaf's
         * surface faces) */
        const uint8_t *bn = it->leaf ? svo->leaves[it->index].normal : c->ex->normal[it->index];
        if (p0 && p0 == p1) {
            const uint32_t key = attr0 | (uint32_t)bn[0] << 16 | (uint32_t)bn[1] << 24;
            uint64_t *m = &k->memo[(key * 2654435761u) >> (32 - NORMAL_MEMO_BITS)];
            if (memo_holds(*m, key)) {
                l->normal[0] = (uint8_t)*m;
                l->normal[1] = (uint8_t)(*m >> 8);
            } else {
                vdouble r[3];
                if (c->pal_normal && p0->has_normal) {
                    vcols_load(c->pal_normal[attr0], r);
                } else {
                    normal_matrix(a0, a0, r);
                    if (c->pal_normal) { /* lazy_normals: its first */
                        vcols_store(r, c->pal_normal[attr0]);
                        p0->has_normal = true;
                    }
                }
                move_normal(&k->queue, r, bn, l->normal, m, key);
            }
        } else {
            vdouble r[3];
            normal_matrix(a0, a1, r);
            move_normal(&k->queue, r, bn, l->normal, NULL, 0);
        }
        k->nsel++;
        return;
    }
    /* expand: check every child now so pass 2 cannot fail */
    if (!children_ok(svo, it->index)) {
        fail_set(k->fail, FAIL_CHILD, it->index, 0, NULL);
        return;
    }
    /* Its descendants need no test of predicate (a) when this box grown by
     * four times its largest side is strictly inside every plane: a
     * descendant's box lies within this one grown by its largest side, as
     * predicate (a) takes it, so its sides are at most three times that
     * one, and grown by its own it stays in the four times grown box,
     * which the test keeps. */
    bool inside = it->inside;
    if (c->view_on && c->cull && !inside) {
        vdouble mn[2];
        frustum_planes(c, box, 4.0, false, mn);
        const vlong in0 = mn[0] > 0.0, in1 = mn[1] > 0.0;
        inside = (in0[0] & in0[1] & in0[2] & in0[3] & in1[0] & in1[1] & in1[2]) != 0;
    }
    c->expand[k->i0 + k->nexpand++] = (uint32_t)i | (inside ? EXPAND_INSIDE : 0u);
    k->nchild += mr_svo_popcount8(svo->child_mask[it->index]);
}

/* Items of pass 1 held until four of them need projects_below, which
 * then takes them together (projects_below4), and the items after the
 * first of those, which must finish after it (slots and expand entries
 * go in item order). Palette table only: their matrices stay in it. */
#define SEL_WAIT 16u
typedef struct sel_wait {
    const sel_item *it;
    size_t i;
    uint32_t attr0;
    pal_entry *p0, *p1;
    bool proj;     /* its selection is projects_below's answer */
    bool selected; /* else, whether it is selected */
    float box[6];
} sel_wait;

__attribute__((always_inline)) static inline void sel_drain(sel_ctx *c, sel_chunk *k, sel_wait *w, unsigned *nwait,
                                                            unsigned *nproj)
{
    const float *box[4];
    unsigned np = 0;
    for (unsigned j = 0; j < *nwait && np < 4; j++)
        if (w[j].proj)
            box[np++] = w[j].box;
    for (unsigned j = np; j < 4; j++)
        box[j] = np ? box[0] : w[0].box; /* idle lanes: a copy */
    const unsigned below = np ? projects_below4(c, box) : 0u;
    for (unsigned j = 0, q = 0; j < *nwait; j++) {
        const bool selected = w[j].proj ? (below >> q++ & 1u) != 0 : w[j].selected;
        sel_finish(c, k, w[j].it, w[j].i, w[j].attr0, w[j].p0, w[j].p1, &w[j].p0->a, &w[j].p1->a, w[j].box,
                   selected);
    }
    *nwait = *nproj = 0;
}

/* A failure of a voxel of pass 1: the voxels held before it finish first
 * (their own failures come first), then the chunk keeps this one unless
 * it has one. */
__attribute__((always_inline)) static inline void sel_fail_held(sel_ctx *c, sel_chunk *k, sel_wait *w,
                                                                unsigned *nwait, unsigned *nproj, int kind,
                                                                uint32_t a, uint32_t b, const double p[3])
{
    if (*nwait)
        sel_drain(c, k, w, nwait, nproj);
    fail_set(k->fail, kind, a, b, p);
}

/* Pass 1: deform and classify items [chunk * SEL_CHUNK, ...). */
__attribute__((target_clones("avx2", "default")))
static void sel_pass1(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sel_ctx *c = vctx;
    const mr_svo *svo = c->svo;
    /* with the palette's table, the projections four voxels at a time */
    const bool batch = c->pal && !c->d->field && c->view_on;
    for (size_t ch = begin; ch < end; ch++) {
        const size_t i0 = ch * SEL_CHUNK, i1 = i0 + SEL_CHUNK < c->n ? i0 + SEL_CHUNK : c->n;
        sel_chunk k;
        k.i0 = i0;
        k.nsel = k.nchild = k.nexpand = 0;
        k.fail = &c->chunk_fail[ch];
        k.fail->kind = FAIL_NONE;
        k.queue.n = 0;
        memset(k.memo, 0, sizeof k.memo);
        sel_wait wait[SEL_WAIT];
        unsigned nwait = 0, nproj = 0;
        for (size_t i = i0; i < i1; i++) {
            const sel_item *it = &c->items[i];
            if (c->pal && i + PAL_AHEAD < i1) { /* (a miss each otherwise: entries in no order) */
                uint32_t lo, hi;
                item_attrs(c, it + PAL_AHEAD, &lo, &hi);
                if (lo < svo->palette_count)
                    __builtin_prefetch(&c->pal[lo]);
                if (hi != lo && hi < svo->palette_count)
                    __builtin_prefetch(&c->pal[hi]);
            }
            const uint32_t xyz[3] = {(uint32_t)(it->xyz & 0x1fffffu), (uint32_t)((it->xyz >> 21) & 0x1fffffu),
                                     (uint32_t)((it->xyz >> 42) & 0x1fffffu)};
            double lo[3], hi[3];
            for (int a = 0; a < 3; a++) {
                lo[a] = c->origin[a] + (double)xyz[a] * c->cell;
                hi[a] = c->origin[a] + (double)(xyz[a] + 1u) * c->cell;
            }
            uint32_t attr0, attr1;
            item_attrs(c, it, &attr0, &attr1);
            if (attr0 >= svo->palette_count || attr1 >= svo->palette_count) {
                sel_fail_held(c, &k, wait, &nwait, &nproj, FAIL_ATTR, attr0 >= svo->palette_count ? attr0 : attr1,
                              svo->palette_count, NULL);
                continue;
            }
            /* the extremes' matrices: a0 and a1 point at them */
            mr_affine f0, f1;
            pal_entry t0, t1;
            pal_entry *p0 = NULL, *p1 = NULL;
            const mr_affine *a0, *a1;
            if (c->d->field) {
                f0 = c->d->field(c->d->field_ctx, mr_v3((float)lo[0], (float)lo[1], (float)lo[2]));
                f1 = c->d->field(c->d->field_ctx, mr_v3((float)hi[0], (float)hi[1], (float)hi[2]));
                if (!affine_finite(&f0) || !affine_finite(&f1)) {
                    sel_fail_held(c, &k, wait, &nwait, &nproj, FAIL_FIELD, 0, 0, affine_finite(&f0) ? hi : lo);
                    continue;
                }
                a0 = &f0;
                a1 = &f1;
            } else {
                p0 = pal_get(c, attr0, &t0);
                if (!p0->ok) {
                    sel_fail_held(c, &k, wait, &nwait, &nproj, FAIL_PALETTE, attr0, 0, NULL);
                    continue;
                }
                p1 = attr1 == attr0 ? p0 : pal_get(c, attr1, &t1);
                if (!p1->ok) {
                    sel_fail_held(c, &k, wait, &nwait, &nproj, FAIL_PALETTE, attr1, 0, NULL);
                    continue;
                }
                a0 = &p0->a;
                a1 = &p1->a;
            }
            vdouble dlo = {INFINITY, INFINITY, INFINITY, 0.0}, dhi = {-INFINITY, -INFINITY, -INFINITY, 0.0};
            deform_box_grow(a0, lo, hi, &dlo, &dhi);
            if (p0 == NULL || p1 != p0)
                deform_box_grow(a1, lo, hi, &dlo, &dhi);
            /* the box behind voxels held, or straight in the chunk's next
             * slot of the output (sel_finish), which a later voxel takes
             * when this one is not selected (it moves to wait[0] if this
             * voxel waits first) */
            float *b = nwait ? wait[nwait].box : &c->out->box[(c->out_base + i0 + k.nsel) * 6];
            const vfloat flo = vfloat_round(&dlo, true), fhi = vfloat_round(&dhi, false);
            memcpy(b, &flo, 3 * sizeof(float));
            memcpy(b + 3, &fhi, 3 * sizeof(float));
            /* every lane finite (the idle one is 0): an exponent of all
             * ones is an infinity or a NaN */
            const vint finite = (((vint)flo & 0x7f800000) != 0x7f800000) & (((vint)fhi & 0x7f800000) != 0x7f800000);
            if (!(finite[0] & finite[1] & finite[2])) {
                sel_fail_held(c, &k, wait, &nwait, &nproj, FAIL_OVERFLOW, c->level, 0, lo);
                continue;
            }
            if (c->view_on && c->cull && !it->inside) {
                /* Predicate (a): the box grown by its largest side (room for
                 * what descendants' own matrices may do) entirely on the
                 * outer side of one plane, or entirely behind the eye. */
                vdouble mx[2];
                frustum_planes(c, b, 1.0, true, mx);
                /* planes 0-5: mx < 0; plane 6 (w > 0): !(mx > 0) */
                const vlong below0 = mx[0] < 0.0, below1 = mx[1] < 0.0, ahead = mx[1] > 0.0;
                const bool outside =
                    (below0[0] | below0[1] | below0[2] | below0[3] | below1[0] | below1[1] | ~ahead[2]) != 0;
                if (outside)
                    continue; /* removed */
            }
            /* The projected size only decides whether an interior voxel
             * above max_level is refined: leaves (most of what is visited)
             * and voxels at max_level are selected whatever it is. */
            const bool must = it->leaf || c->level >= c->max_level;
            bool proj = !must && c->view_on;
            if (!batch) {
                sel_finish(c, &k, it, i, attr0, p0, p1, a0, a1, b, must || (proj && projects_below(c, b)));
                continue;
            }
            /* projects_below's first answer, cheap, keeps a voxel far wider
             * than delta from waiting: it is expanded */
            if (proj && wide_at_two_corners(c, b))
                proj = false;
            if (!proj && nwait == 0) {
                sel_finish(c, &k, it, i, attr0, p0, p1, a0, a1, b, must);
                continue;
            }
            if (nwait == 0)
                memcpy(wait[0].box, b, sizeof wait[0].box);
            sel_wait *w = &wait[nwait++];
            w->it = it;
            w->i = i;
            w->attr0 = attr0;
            w->p0 = p0;
            w->p1 = p1;
            w->proj = proj;
            w->selected = must;
            nproj += proj;
            if (nproj == 4 || nwait == SEL_WAIT)
                sel_drain(c, &k, wait, &nwait, &nproj);
        }
        if (nwait)
            sel_drain(c, &k, wait, &nwait, &nproj);
        nq_flush(&k.queue);
        c->chunk_sel[ch] = k.nsel;
        c->chunk_child[ch] = k.nchild;
        c->chunk_expand[ch] = k.nexpand;
    }
}

/* Pass 2: write the chunk's children at its offsets. */
static void sel_pass2(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sel_ctx *c = vctx;
    const mr_svo *svo = c->svo;
    for (size_t ch = begin; ch < end; ch++) {
        const size_t i0 = ch * SEL_CHUNK;
        size_t k = c->chunk_child[ch];
        for (size_t e = 0; e < c->chunk_expand[ch]; e++) {
            const uint32_t entry = c->expand[i0 + e];
            const sel_item *it = &c->items[entry & ~EXPAND_INSIDE];
            const uint16_t inside = (entry & EXPAND_INSIDE) != 0;
            const uint64_t x = it->xyz & 0x1fffffu, y = (it->xyz >> 21) & 0x1fffffu, z = (it->xyz >> 42) & 0x1fffffu;
            const unsigned cm = svo->child_mask[it->index], lm = svo->leaf_mask[it->index];
            /* child_index's numbering, counted along (checked in pass 1) */
            uint32_t next_leaf = svo->first_leaf[it->index], next_node = svo->first_node[it->index];
            /* the children in increasing c, without a branch on each bit
             * of the mask (random: a misprediction for every other one) */
            const uint64_t base = 2 * x | (2 * y) << 21 | (2 * z) << 42;
            for (unsigned m = cm; m; m &= m - 1) {
                const unsigned ci = (unsigned)__builtin_ctz(m);
                const uint32_t is_leaf = (lm >> ci) & 1u;
                sel_item *o = &c->next[k++];
                o->xyz = base | (uint64_t)(ci & 1u) | (uint64_t)((ci >> 1) & 1u) << 21 | (uint64_t)(ci >> 2) << 42;
                o->index = is_leaf ? next_leaf : next_node;
                o->leaf = (uint16_t)is_leaf;
                o->inside = inside;
                next_leaf += is_leaf;
                next_node += is_leaf ^ 1u;
            }
        }
    }
}

void mr_svo_selection_free(mr_svo_selection *s)
{
    if (!s)
        return;
    free(s->box);
    free(s->leaf);
    free(s->level);
    memset(s, 0, sizeof *s);
}

static int selection_reserve(mr_svo_selection *s, size_t need, mr_error *err)
{
    if (need <= s->capacity)
        return MR_OK;
    size_t cap = s->capacity ? s->capacity : 256;
    while (cap < need)
        cap = cap > SIZE_MAX / 2 ? need : cap * 2;
    if (cap > SIZE_MAX / (6 * sizeof(float)))
        return mr_error_set(err, MR_ERR_NOMEM, "svo select: %zu voxels do not fit in memory", need);
    /* the voxels so far are kept (earlier levels' selections) */
    float *box = mr_large_realloc(s->box, s->capacity * 6 * sizeof *box, cap * 6 * sizeof *box);
    if (box)
        s->box = box;
    mr_svo_leaf *leaf = mr_large_realloc(s->leaf, s->capacity * sizeof *leaf, cap * sizeof *leaf);
    if (leaf)
        s->leaf = leaf;
    uint8_t *level = mr_large_realloc(s->level, s->capacity, cap);
    if (level)
        s->level = level;
    if (!box || !leaf || !level)
        return mr_error_set(err, MR_ERR_NOMEM, "svo select: out of memory (%zu voxels)", need);
    s->capacity = cap;
    return MR_OK;
}

/* Checks that the deformer's matrices are finite (whether the palette's
 * entries name meshes and joints it has is checked where they are used:
 * blend_entry). */
static int check_deformer(const mr_svo *svo, const mr_svo_deformer *d, mr_error *err)
{
    if (d->mesh_count > 0 && !d->mesh)
        return mr_error_set(err, MR_ERR_INVALID, "svo select: deformer has %zu meshes but no mesh matrices",
                            d->mesh_count);
    for (size_t m = 0; m < d->mesh_count; m++) {
        if (!affine_finite(&d->mesh[m]))
            return mr_error_set(err, MR_ERR_INVALID, "svo select: mesh %zu matrix is not finite", m);
        const uint32_t jc = d->joint_count ? d->joint_count[m] : 0;
        if (jc > 0 && (!d->joint || !d->joint[m]))
            return mr_error_set(err, MR_ERR_INVALID, "svo select: mesh %zu has %u joints but no matrices", m,
                                jc);
        for (uint32_t j = 0; j < jc; j++)
            if (!affine_finite(&d->joint[m][j]))
                return mr_error_set(err, MR_ERR_INVALID, "svo select: mesh %zu joint %u matrix is not finite",
                                    m, j);
    }
    if (svo->palette_count > 0 && !svo->palette)
        return mr_error_set(err, MR_ERR_INVALID, "svo select: octree has %u palette entries but no palette",
                            svo->palette_count);
    return MR_OK;
}

static int view_setup(sel_ctx *c, const mr_svo_view *view, mr_error *err)
{
    c->view_on = view && view->enabled;
    c->cull = c->view_on && view->cull;
    if (!c->view_on)
        return MR_OK;
    for (int e = 0; e < 16; e++) {
        if (!isfinite(view->view_proj.m[e]))
            return mr_error_set(err, MR_ERR_INVALID, "svo select: view_proj is not finite");
        c->vp[e] = view->view_proj.m[e];
    }
    if (view->width <= 0 || view->height <= 0 || !(view->delta > 0.0f) || !isfinite(view->delta))
        return mr_error_set(err, MR_ERR_INVALID, "svo select: view needs width, height and delta > 0 (%d x %d, %g)",
                            view->width, view->height, (double)view->delta);
    c->width = view->width;
    c->height = view->height;
    c->delta = view->delta;
    /* Rows of view_proj give clip x, y, z, w as linear functions of the
     * point: w + x, w - x, w + y, w - y, w + z, w - z >= 0, and w > 0. */
    const double *r = c->vp;
    for (int e = 0; e < 4; e++) {
        double pl[8];
        for (int a = 0; a < 3; a++)
            for (int s = 0; s < 2; s++)
                pl[2 * a + s] = r[12 + e] + (s ? -1.0 : 1.0) * r[4 * a + e];
        pl[6] = r[12 + e];
        pl[7] = e == 3 ? 1.0 : 0.0;
        for (int k = 0; k < 2; k++)
            c->planes[e][k] = (vdouble){pl[4 * k], pl[4 * k + 1], pl[4 * k + 2], pl[4 * k + 3]};
    }
    return MR_OK;
}

static int fail_report(const sel_fail *f, mr_error *err)
{
    switch (f->kind) {
    case FAIL_ATTR:
        return mr_error_set(err, MR_ERR_INVALID, "svo select: a voxel names palette entry %u of %u", f->a, f->b);
    case FAIL_PALETTE:
        return mr_error_set(err, MR_ERR_INVALID,
                            "svo select: palette entry %u names a mesh or joint the deformer lacks", f->a);
    case FAIL_FIELD:
        return mr_error_set(err, MR_ERR_INVALID, "svo select: the field gives a non-finite matrix at (%g, %g, %g)",
                            f->p[0], f->p[1], f->p[2]);
    case FAIL_OVERFLOW:
        return mr_error_set(err, MR_ERR_INVALID,
                            "svo select: a deformed voxel box (level %u, bind corner %g %g %g) overflows float",
                            f->a, f->p[0], f->p[1], f->p[2]);
    default:
        return mr_error_set(err, MR_ERR_INVALID, "svo select: malformed octree at node %u", f->a);
    }
}

int mr_svo_select(const mr_svo *svo, const mr_svo_extremes *extremes, const mr_svo_deformer *d,
                  const mr_svo_view *view, unsigned max_level, unsigned threads, mr_svo_selection *out,
                  mr_error *err)
{
    return mr_svo_select_ws(svo, extremes, d, view, max_level, threads, NULL, out, err);
}

/* A selection under way, between its levels (mr_svo_select_ws). */
typedef struct sel_run {
    sel_ctx c;
    mr_svo_workspace *ws;
    unsigned threads;
    sel_item *cur; /* the frontier: n voxels at level */
    size_t n;
    unsigned level;
    uint64_t visited, budget;
    unsigned swaps; /* of WS_CUR and WS_NEXT */
    /* whether select_level may start the frame's palette table (not while
     * top_and_fill fills it beside the levels) */
    bool table_allowed;
    mr_error *err;
} sel_run;

/* The frame's palette table and what goes with it into c (not yet
 * filled): with pal_normal where the octree has NORMALS_KEPT_LEAVES leaves
 * an entry or more, made by pal_fill on several threads and on first use
 * on one (lazy_normals). */
static int table_alloc(sel_run *r, sel_ctx *c)
{
    const mr_svo *svo = c->svo;
    /* one entry more, to start the table on a line */
    void *raw = ws_get(r->ws, WS_PALETTE, (size_t)svo->palette_count + 1, sizeof *c->pal);
    c->pal = raw ? (pal_entry *)(((uintptr_t)raw + 63u) & ~(uintptr_t)63u) : NULL;
    const bool keep_normals = svo->leaf_count / NORMALS_KEPT_LEAVES >= svo->palette_count;
    c->pal_normal = keep_normals ? ws_get(r->ws, WS_PAL_NORMAL, svo->palette_count, sizeof *c->pal_normal) : NULL;
    c->lazy_normals = r->threads == 1;
    if (!c->pal || (keep_normals && !c->pal_normal))
        return mr_error_set(r->err, MR_ERR_NOMEM, "svo select: out of memory (%u palette entries)",
                            svo->palette_count);
    return MR_OK;
}

/* Deforms and classifies the frontier's voxels (level r->level) and makes
 * the next level's frontier of the expanded ones' children. */
static int select_level(sel_run *r)
{
    sel_ctx *c = &r->c;
    const mr_svo *svo = c->svo;
    mr_svo_selection *out = c->out;
    mr_svo_workspace *ws = r->ws;
    const size_t n = r->n;
    const unsigned level = r->level;
    r->visited += n;
    if (n > EXPAND_INSIDE) /* an expand entry's index takes 31 bits */
        return mr_error_set(r->err, MR_ERR_LIMIT, "svo select: more than 2^31 voxels at level %u", level);
    if (r->visited > r->budget)
        return mr_error_set(r->err, MR_ERR_INVALID, "svo select: malformed octree (nodes reached twice)");
    const size_t chunks = (n + SEL_CHUNK - 1) / SEL_CHUNK;
    /* room for every item of the level to be selected: pass 1 writes
     * the voxels it selects straight into the output */
    int rc = selection_reserve(out, out->count + n, r->err);
    if (rc != MR_OK)
        return rc;
    uint32_t *expand = ws_get(ws, WS_EXPAND, n, sizeof *expand);
    size_t *chunk_expand = ws_get(ws, WS_CH_EXPAND, chunks, sizeof *chunk_expand);
    size_t *chunk_sel = ws_get(ws, WS_CH_SEL, chunks, sizeof *chunk_sel);
    size_t *chunk_child = ws_get(ws, WS_CH_CHILD, chunks, sizeof *chunk_child);
    sel_fail *chunk_fail = ws_get(ws, WS_CH_FAIL, chunks, sizeof *chunk_fail);
    if (!expand || !chunk_sel || !chunk_child || !chunk_expand || !chunk_fail)
        return mr_error_set(r->err, MR_ERR_NOMEM, "svo select: out of memory (%zu voxels at level %u)", n, level);
    c->level = level;
    c->cell = (double)svo->size * ldexp(1.0, -(int)level); /* exact */
    c->items = r->cur;
    c->n = n;
    c->out_base = out->count;
    c->expand = expand;
    c->chunk_expand = chunk_expand;
    c->chunks = chunks;
    c->chunk_sel = chunk_sel;
    c->chunk_child = chunk_child;
    c->chunk_fail = chunk_fail;
    /* The frame's palette table once the voxels deformed so far reach
     * a quarter of its entries: a far instance that selects a handful
     * of voxels blends only theirs, a near one blends each entry once
     * instead of once per voxel. */
    if (r->table_allowed && !c->d->field && !c->pal && svo->palette_count > 0 &&
        4 * r->visited >= svo->palette_count) {
        if ((rc = table_alloc(r, c)) != MR_OK)
            return rc;
        mr_parallel_for(r->threads, svo->palette_count, PAL_GRAIN, pal_fill, c);
    }
    mr_parallel_for(r->threads, chunks, 1, sel_pass1, c);
    size_t sel_total = out->count, child_total = 0;
    for (size_t ch = 0; ch < chunks; ch++) {
        if (chunk_fail[ch].kind != FAIL_NONE)
            return fail_report(&chunk_fail[ch], r->err);
        const size_t s = chunk_sel[ch], k = chunk_child[ch];
        chunk_sel[ch] = sel_total;
        chunk_child[ch] = child_total;
        sel_total += s;
        child_total += k;
    }
    if (sel_total > UINT32_MAX)
        return mr_error_set(r->err, MR_ERR_LIMIT, "svo select: more than 2^32 - 1 voxels selected");
    if (child_total > r->budget - r->visited)
        return mr_error_set(r->err, MR_ERR_INVALID, "svo select: malformed octree (nodes reached twice)");
    /* close the gaps chunks that kept fewer than all their items left,
     * in order: a run only moves down, past the runs already placed */
    for (size_t ch = 0; ch < chunks; ch++) {
        const size_t from = c->out_base + ch * SEL_CHUNK, to = chunk_sel[ch];
        const size_t count = (ch + 1 < chunks ? chunk_sel[ch + 1] : sel_total) - to;
        if (count > 0 && from != to) {
            memmove(&out->box[to * 6], &out->box[from * 6], count * 6 * sizeof *out->box);
            memmove(&out->leaf[to], &out->leaf[from], count * sizeof *out->leaf);
            memmove(&out->level[to], &out->level[from], count);
        }
    }
    sel_item *next = ws_get(ws, WS_NEXT, child_total, sizeof *next);
    if (!next)
        return mr_error_set(r->err, MR_ERR_NOMEM, "svo select: out of memory (%zu voxels at level %u)",
                            child_total, level + 1);
    c->next = next;
    mr_parallel_for(r->threads, chunks, 1, sel_pass2, c);
    out->count = sel_total;
    ws_swap(ws, WS_CUR, WS_NEXT);
    r->swaps++;
    r->cur = next;
    r->n = child_total;
    r->level = level + 1;
    return MR_OK;
}

/* The top levels beside the palette table's fill (top_and_fill). */
typedef struct top_fill {
    sel_run *r;
    sel_ctx fill; /* pal_fill's: r's context with the table being filled */
    atomic_bool unwanted; /* the selection ended in its top levels, or failed */
    int rc;
} top_fill;

/* Item 0: the levels of one chunk or less (each on one thread); item k >
 * 0: palette entries [(k - 1) PAL_GRAIN, k PAL_GRAIN), unless the table is
 * no longer wanted (mr_range_fn). */
static void top_and_fill_items(void *vctx, size_t begin, size_t end, unsigned worker)
{
    top_fill *tf = vctx;
    for (size_t k = begin; k < end; k++) {
        if (k == 0) {
            sel_run *r = tf->r;
            int rc = MR_OK;
            while (rc == MR_OK && r->n > 0 && r->n <= SEL_CHUNK)
                rc = select_level(r);
            tf->rc = rc;
            if (rc != MR_OK || r->n == 0)
                atomic_store_explicit(&tf->unwanted, true, memory_order_relaxed);
        } else if (!atomic_load_explicit(&tf->unwanted, memory_order_relaxed)) {
            const size_t b = (k - 1) * PAL_GRAIN, count = tf->fill.svo->palette_count;
            pal_fill(&tf->fill, b, b + PAL_GRAIN < count ? b + PAL_GRAIN : count, worker);
        }
    }
}

/* The top levels of a selection, whose frontiers fit one chunk and so run
 * on one thread, while the other threads fill the frame's palette table,
 * which the levels after them read (they blend their voxels' entries
 * themselves, as before any table); the calling thread joins the fill
 * when it is done with them, unless the selection ended there. The dancer
 * at depth 8, every leaf, two threads: levels 0-5 took 127 us on one
 * thread and the table 167 us on two, one after the other. */
static int top_and_fill(sel_run *r)
{
    top_fill tf = {.r = r, .fill = r->c, .rc = MR_OK};
    atomic_init(&tf.unwanted, false);
    int rc = table_alloc(r, &tf.fill);
    if (rc != MR_OK)
        return rc;
    const size_t items = 1 + (r->c.svo->palette_count + PAL_GRAIN - 1) / PAL_GRAIN;
    r->table_allowed = false;
    mr_parallel_for(r->threads, items, 1, top_and_fill_items, &tf);
    r->table_allowed = true;
    if (tf.rc != MR_OK)
        return tf.rc;
    if (r->n > 0) { /* the table is filled: the levels below read it */
        r->c.pal = tf.fill.pal;
        r->c.pal_normal = tf.fill.pal_normal;
        r->c.lazy_normals = tf.fill.lazy_normals;
    }
    return MR_OK;
}

int mr_svo_select_ws(const mr_svo *svo, const mr_svo_extremes *extremes, const mr_svo_deformer *d,
                     const mr_svo_view *view, unsigned max_level, unsigned threads, mr_svo_workspace *ws,
                     mr_svo_selection *out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo select: NULL output");
    out->count = 0;
    out->visited = 0;
    if (!svo || !extremes || !d)
        return mr_error_set(err, MR_ERR_INVALID, "svo select: NULL octree, extremes or deformer");
    if (svo->depth < 1 || svo->depth > MR_SVO_MAX_DEPTH || !isfinite(svo->size) || !(svo->size > 0.0f) ||
        !isfinite(svo->origin.x) || !isfinite(svo->origin.y) || !isfinite(svo->origin.z))
        return mr_error_set(err, MR_ERR_INVALID, "svo select: bad octree cube or depth");
    if (extremes->node_count != svo->node_count ||
        (svo->node_count > 0 && (!extremes->lo_attr || !extremes->hi_attr)))
        return mr_error_set(err, MR_ERR_INVALID, "svo select: extremes of another octree (%u nodes, octree %u)",
                            extremes->node_count, svo->node_count);
    if ((svo->node_count > 0 && (!svo->first_node || !svo->first_leaf || !svo->child_mask || !svo->leaf_mask)) ||
        (svo->leaf_count > 0 && !svo->leaves) || (svo->node_count == 0 && svo->leaf_count > 1))
        return mr_error_set(err, MR_ERR_INVALID, "svo select: malformed octree");

    sel_run r;
    memset(&r, 0, sizeof r);
    sel_ctx *c = &r.c;
    c->svo = svo;
    c->ex = extremes;
    c->d = d;
    c->out = out;
    c->max_level = max_level < svo->depth ? max_level : svo->depth;
    c->origin[0] = svo->origin.x;
    c->origin[1] = svo->origin.y;
    c->origin[2] = svo->origin.z;
    int rc = view_setup(c, view, err);
    if (rc != MR_OK)
        return rc;
    mr_svo_workspace local;
    memset(&local, 0, sizeof local);
    r.ws = ws ? ws : &local;
    r.threads = threads;
    r.err = err;
    r.table_allowed = true;
    r.budget = (uint64_t)svo->node_count + svo->leaf_count; /* each is visited at most once */
    if (!d->field && (rc = check_deformer(svo, d, err)) != MR_OK)
        goto cleanup;

    if (svo->node_count > 0 || svo->leaf_count == 1) {
        r.cur = ws_get(r.ws, WS_CUR, 1, sizeof *r.cur);
        if (!r.cur) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "svo select: out of memory");
            goto cleanup;
        }
        r.cur[0] = (sel_item){0, 0, svo->node_count == 0, 0};
        r.n = 1;
    }
    /* the top levels beside the table's fill where a second thread is
     * there to fill it (not inside another parallel loop, whose tasks run
     * loops serially) and the octree has more leaves than entries (else
     * the selection may well end before the table pays) */
    const bool beside = (threads ? threads : mr_cpu_count()) >= 2 && !mr_parallel_nested() && !d->field &&
                        svo->palette_count > 0 && svo->leaf_count > svo->palette_count;
    if (r.n > 0 && beside && (rc = top_and_fill(&r)) != MR_OK)
        goto cleanup;
    while (r.n > 0)
        if ((rc = select_level(&r)) != MR_OK)
            goto cleanup;
    out->visited = r.visited;
    rc = MR_OK;

cleanup:
    /* The two level arrays as they were: with an odd number of levels the
     * next frame's widest level would otherwise land in the array that held
     * the narrower ones and grow it, faulting in fresh pages (the dancer at
     * depth 12, every leaf: its second frame selected in 600-690 ms with
     * 733 page faults, most of them 2 MiB, and the frames after it in
     * 350-430 ms with none). */
    if (r.swaps & 1u)
        ws_swap(r.ws, WS_CUR, WS_NEXT);
    if (rc != MR_OK) {
        out->count = 0;
        out->visited = 0;
    }
    if (r.ws == &local)
        ws_release(&local);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* Resampling                                                               */

/* Cells are sorted as packed keys (mr_svo_key_pack, radix_sort.h) while
 * the output octree is at most MR_SVO_KEY_PACK_MAX_DEPTH deep: the 16-byte
 * sort moves twice the bytes and sorts every varying digit of level and
 * code separately, and the per-frame sort is most of a resampling. Deeper
 * output octrees use the 16-byte sort. */
/* Dilated (Morton) bits of one axis: x at bits 0, 3, ..., 60. */
#define MORTON_X 0x1249249249249249ull

typedef struct rs_ctx {
    const mr_svo_selection *sel;
    mr_svo_method method;
    unsigned depth;
    double origin[3]; /* the output cube, as doubles of its floats */
    double size;
    double cell21;    /* size * 2^-21 */
    double cell[GRID_BITS + 1];     /* size * 2^-l (exact) */
    double inv_cell[GRID_BITS + 1]; /* 2^l / size, rounded: first guesses only */
    /* bounds pass, per chunk */
    double (*chunk_lo)[3], (*chunk_hi)[3];
    size_t *chunk_bad; /* first bad box + 1, or 0 */
    /* count / write passes */
    uint8_t *box_level;
    uint32_t *box_range;   /* 6 per box: first cell x, y, z, then end x, y, z */
    uint64_t *chunk_cells; /* counts, then offsets */
    uint64_t *chunk_written; /* the cells rs_write kept, from the chunk's offset */
    uint64_t *chunk_bits;  /* 2 per chunk: OR and AND of its packed keys */
    bool packed;
    mr_svo_key *keys;      /* !packed */
    uint64_t *pk;          /* packed */
    uint32_t *payload;
} rs_ctx;

static void rs_bounds(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    rs_ctx *c = vctx;
    for (size_t ch = begin; ch < end; ch++) {
        const size_t i0 = ch * RS_CHUNK, i1 = i0 + RS_CHUNK < c->sel->count ? i0 + RS_CHUNK : c->sel->count;
        double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        c->chunk_bad[ch] = 0;
        for (size_t i = i0; i < i1; i++) {
            const float *b = &c->sel->box[i * 6];
            bool ok = true; /* (no branch per test: boxes are rarely bad) */
            for (int a = 0; a < 3; a++)
                ok &= (isfinite(b[a]) != 0) & (isfinite(b[3 + a]) != 0) & (b[a] <= b[3 + a]);
            if (!ok) {
                c->chunk_bad[ch] = i + 1;
                break;
            }
            for (int a = 0; a < 3; a++) {
                lo[a] = dmin(lo[a], b[a]);
                hi[a] = dmax(hi[a], b[3 + a]);
            }
        }
        memcpy(c->chunk_lo[ch], lo, sizeof lo);
        memcpy(c->chunk_hi[ch], hi, sizeof hi);
    }
}

/* Signed distance from x to the plane at finest-grid position k: <= 0 when
 * the plane is at or below x (svo_trace.c's arithmetic). */
static inline double plane_s(const rs_ctx *c, int a, double x, uint64_t k)
{
    return (c->origin[a] - x) + (double)k * c->cell21;
}

/* floor(log2(x)) of a positive normal double, from its exponent bits. */
static inline int double_exponent(double x)
{
    uint64_t bits;
    memcpy(&bits, &x, sizeof bits);
    return (int)((bits >> 52) & 0x7ffu) - 1023;
}

/* Level whose cells are the smallest still at least `side` wide (the
 * coarsest that holds it, eq. 3.3.6 / 3.3.10), clamped to the depth. */
static unsigned hold_level(const rs_ctx *c, double side)
{
    if (!(side > 0.0))
        return c->depth;
    /* A first guess from the exponents (floor(log2(size / side)) or one
     * more; a subnormal side guesses low, and far above the depth either
     * way): the loops below end on the one answer from any guess, as
     * cell[] falls with the level. */
    int h = double_exponent(c->size) - double_exponent(side);
    if (h < 0)
        h = 0;
    if (h > (int)c->depth)
        h = (int)c->depth;
    while (h > 0 && c->cell[h] < side)
        h--;
    while (h < (int)c->depth && c->cell[h + 1] >= side)
        h++;
    return (unsigned)h;
}

/* Level whose cells are the largest that fit in `side` (not wider), clamped
 * to the depth: emit's level. The thesis' eq. 3.3.10 takes the smallest
 * cells that hold the side (hold_level), up to twice as wide as the box's
 * smallest side; rounded out to that grid, a deformed box then emits a
 * block up to four times its width, and the deformed surface grew by about
 * a cell on every side (20 % coverage error against the triangles at
 * depth 8; creases closed to one dark pixel). The thesis itself measures
 * that error and names one level of further oversampling as its remedy
 * (3.4, Fig. 25). A box exactly one cell wide (undeformed, or scaled by a
 * power of two) still emits that one cell. */
static unsigned fit_level(const rs_ctx *c, double side)
{
    unsigned h = hold_level(c, side);
    return h < c->depth && c->cell[h] > side ? h + 1 : h;
}

static inline uint64_t clamp_floor(double u, uint64_t lo, uint64_t hi)
{
    const double f = floor(u);
    if (!(f >= (double)lo))
        return lo;
    if (f >= (double)hi)
        return hi;
    return (uint64_t)f;
}

/* Emit range on axis a at level l: cells [*i0, *i1) whose closed boxes
 * cover [lo, hi], i.e. floor(r lo) .. ceil(r hi) - 1, decided by plane_s.
 * The first guesses multiply by the rounded inverse cell; the plane tests
 * move them to the one answer (plane_s is monotonic in k), so the range
 * does not depend on the guess. */
static void emit_range(const rs_ctx *c, int a, unsigned l, double lo, double hi, uint64_t *i0, uint64_t *i1)
{
    const uint64_t n = 1ull << l, span = 1ull << (GRID_BITS - l);
    uint64_t i = clamp_floor((lo - c->origin[a]) * c->inv_cell[l], 0, n - 1);
    while (i > 0 && plane_s(c, a, lo, i * span) > 0.0)
        i--;
    while (i + 1 < n && plane_s(c, a, lo, (i + 1) * span) <= 0.0)
        i++;
    const double v = ceil((hi - c->origin[a]) * c->inv_cell[l]);
    uint64_t j = !(v >= (double)(i + 1)) ? i + 1 : v >= (double)n ? n : (uint64_t)v;
    while (j > i + 1 && plane_s(c, a, hi, (j - 1) * span) >= 0.0)
        j--;
    while (j < n && plane_s(c, a, hi, j * span) < 0.0)
        j++;
    *i0 = i;
    *i1 = j;
}

/* Resize on axis a at level l (= h + 1): the two cells floor(r c - 1/2) and
 * that + 1, kept inside the grid. */
static uint64_t resize_first(const rs_ctx *c, int a, unsigned l, double lo, double hi)
{
    const uint64_t n = 1ull << l;
    const double u = (0.5 * (lo + hi) - c->origin[a]) / c->cell[l];
    return clamp_floor(u - 0.5, 0, n - 2);
}

/* Level and cell ranges (r: first x, y, z, end x, y, z) of box i; returns
 * its number of cells. */
static inline __attribute__((always_inline)) uint64_t rs_plan(const rs_ctx *c, size_t i, unsigned *level,
                                                             uint32_t r[6])
{
    const float *b = &c->sel->box[i * 6];
    double lo[3], hi[3], smin = INFINITY, smax = 0.0, mag = 0.0;
    for (int a = 0; a < 3; a++) {
        lo[a] = b[a];
        hi[a] = b[3 + a];
        smin = dmin(smin, hi[a] - lo[a]);
        smax = dmax(smax, hi[a] - lo[a]);
        mag = dmax(mag, dmax(fabs(lo[a]), fabs(hi[a])));
    }
    /* Boxes were rounded outwards to float, which widens them by up to an
     * ulp of their coordinates at each end: a box that is one cell of level
     * h but for that rounding still fits level h. Without this slack an
     * undeformed or uniformly scaled voxel (a cell exactly) goes one level
     * coarser and resize overhangs the silhouette by a voxel, where the
     * thesis finds resize exact under uniform scale. Emit still covers the
     * whole box (its ranges use lo and hi). */
    const double slack = 4.0 * FLT_EPSILON * mag;
    smax = dmax(smax - slack, 0.0);
    if (c->method == MR_SVO_RESIZE) {
        const unsigned h = hold_level(c, smax), l = h + 1 < c->depth ? h + 1 : c->depth;
        *level = l;
        for (int a = 0; a < 3; a++) {
            r[a] = (uint32_t)resize_first(c, a, l, lo[a], hi[a]);
            r[3 + a] = r[a] + 2;
        }
        return 8;
    }
    unsigned h = fit_level(c, smin + slack);
    for (;;) {
        uint64_t cnt = 1;
        for (int a = 0; a < 3; a++) {
            uint64_t i0, i1;
            emit_range(c, a, h, lo[a], hi[a], &i0, &i1);
            r[a] = (uint32_t)i0;
            r[3 + a] = (uint32_t)i1;
            cnt *= i1 - i0;
        }
        if (cnt <= MR_SVO_EMIT_MAX_CELLS || h == 0) {
            *level = h;
            return cnt;
        }
        h--;
    }
}

/* (AVX2's clone rounds with roundsd, where the baseline's floor is a
 * dozen instructions after each division: the same values) */
__attribute__((target_clones("avx2", "default")))
static void rs_count(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    rs_ctx *c = vctx;
    for (size_t ch = begin; ch < end; ch++) {
        const size_t i0 = ch * RS_CHUNK, i1 = i0 + RS_CHUNK < c->sel->count ? i0 + RS_CHUNK : c->sel->count;
        uint64_t total = 0;
        for (size_t i = i0; i < i1; i++) {
            unsigned l;
            total += rs_plan(c, i, &l, &c->box_range[6 * i]);
            c->box_level[i] = (uint8_t)l;
        }
        c->chunk_cells[ch] = total;
    }
}

/* Packed keys a chunk has kept, direct-mapped (RS_SEEN entries): a cell
 * a neighbouring box of the same chunk already emitted (resize's 2 x 2 x
 * 2 blocks overlap most of their neighbours') is not kept again. Only
 * exact repeats are left out, and of those never the first, which is the
 * one the stable sort puts first among its equals and compaction keeps
 * (a repeat never survives compaction), so the octree is the same bit for
 * bit; a repeat the table has forgotten is sorted and dropped as before.
 * UINT64_MAX is no packed key (at most 3 * 19 + 5 bits). */
#define RS_SEEN_BITS 11u
#define RS_SEEN (1u << RS_SEEN_BITS)

/* The dilated coordinate d of one axis (mask m) moved by one cell whose
 * dilated width is unit: the carry runs through the other axes' bits. */
static inline uint64_t dilated_next(uint64_t d, uint64_t m, uint64_t unit)
{
    return ((d | ~m) + unit) & m;
}

/* Packed key k of box i at *o, kept by moving *o on unless the chunk's
 * table of keys (seen) holds it; written either way, no branch (about half
 * are repeats, in no order a predictor learns). The chunk's OR and AND of
 * its keys take it. */
__attribute__((always_inline)) static inline void put_packed(const rs_ctx *c, uint64_t *seen, uint64_t k,
                                                             uint32_t i, uint64_t *o, uint64_t *bits_or,
                                                             uint64_t *bits_and)
{
    uint64_t *seen_at = &seen[(k * 0x9E3779B97F4A7C15ull) >> (64 - RS_SEEN_BITS)];
    const bool repeat = *seen_at == k;
    *seen_at = k;
    c->pk[*o] = k;
    c->payload[*o] = i;
    *bits_or |= k;
    *bits_and &= k;
    *o += !repeat;
}

static void rs_write(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    rs_ctx *c = vctx;
    uint64_t seen[RS_SEEN];
    for (size_t ch = begin; ch < end; ch++) {
        const size_t i0 = ch * RS_CHUNK, i1 = i0 + RS_CHUNK < c->sel->count ? i0 + RS_CHUNK : c->sel->count;
        uint64_t o = c->chunk_cells[ch], bits_or = 0, bits_and = ~(uint64_t)0;
        if (c->packed)
            memset(seen, 0xff, sizeof seen);
        for (size_t i = i0; i < i1; i++) {
            const unsigned l = c->box_level[i], sh = c->depth - l;
            const uint32_t *r = &c->box_range[6 * i];
            const uint64_t ux = 1ull << (3 * sh), uy = ux << 1, uz = ux << 2;
            const uint64_t mx = MORTON_X, my = MORTON_X << 1, mz = MORTON_X << 2;
            const uint64_t dx0 = mr_morton_spread(r[0] << sh), dy0 = mr_morton_spread(r[1] << sh) << 1;
            uint64_t dz = mr_morton_spread(r[2] << sh) << 2;
            if (c->packed && c->method == MR_SVO_RESIZE) {
                /* resize's 2 x 2 x 2 cells (rs_plan), in the loops' order
                 * below (x fastest, then y, then z), without them */
                const uint64_t dx[2] = {dx0, dilated_next(dx0, mx, ux)};
                const uint64_t dy[2] = {dy0, dilated_next(dy0, my, uy)};
                const uint64_t dzs[2] = {dz, dilated_next(dz, mz, uz)};
                for (unsigned q = 0; q < 8; q++)
                    put_packed(c, seen, mr_svo_key_pack(dx[q & 1u] | dy[(q >> 1) & 1u] | dzs[q >> 2], l),
                               (uint32_t)i, &o, &bits_or, &bits_and);
                continue;
            }
            for (uint32_t z = r[2]; z < r[5]; z++, dz = dilated_next(dz, mz, uz)) {
                uint64_t dy = dy0;
                for (uint32_t y = r[1]; y < r[4]; y++, dy = dilated_next(dy, my, uy)) {
                    uint64_t dx = dx0;
                    for (uint32_t x = r[0]; x < r[3]; x++, dx = dilated_next(dx, mx, ux)) {
                        const uint64_t code = dx | dy | dz;
                        if (c->packed) {
                            put_packed(c, seen, mr_svo_key_pack(code, l), (uint32_t)i, &o, &bits_or, &bits_and);
                        } else {
                            c->keys[o].code = code;
                            c->keys[o].level = l;
                            c->payload[o] = (uint32_t)i;
                            o++;
                        }
                    }
                }
            }
        }
        c->chunk_bits[2 * ch] = bits_or;
        c->chunk_bits[2 * ch + 1] = bits_and;
        c->chunk_written[ch] = o - c->chunk_cells[ch];
    }
}

int mr_svo_resample(const mr_svo_selection *sel, mr_svo_method method, unsigned depth,
                    const mr_svo_attr *palette, uint32_t palette_count, unsigned threads, mr_svo *out,
                    uint64_t *cells, mr_error *err)
{
    return mr_svo_resample_ws(sel, method, depth, palette, palette_count, threads, NULL, out, cells, err);
}

int mr_svo_resample_ws(const mr_svo_selection *sel, mr_svo_method method, unsigned depth,
                       const mr_svo_attr *palette, uint32_t palette_count, unsigned threads,
                       mr_svo_workspace *ws, mr_svo *out, uint64_t *cells, mr_error *err)
{
    if (cells)
        *cells = 0;
    if (ws)
        ws->emit_s = ws->rebuild_s = 0;
    const double t_start = mr_now();
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo resample: NULL output");
    mr_svo_free(out);
    memset(out, 0, sizeof *out);
    if (!sel)
        return mr_error_set(err, MR_ERR_INVALID, "svo resample: NULL selection");
    if (method != MR_SVO_RESIZE && method != MR_SVO_EMIT)
        return mr_error_set(err, MR_ERR_INVALID, "svo resample: method %d is neither resize nor emit", (int)method);
    if (depth < 1 || depth > MR_SVO_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_INVALID, "svo resample: depth %u outside 1..%u", depth, MR_SVO_MAX_DEPTH);
    if (sel->count > 0 && (!sel->box || !sel->leaf))
        return mr_error_set(err, MR_ERR_INVALID, "svo resample: selection arrays missing");
    if (sel->count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "svo resample: more than 2^32 - 1 voxels");
    if (sel->count == 0) {
        /* empty octree over a unit cube, keeping the palette */
        return mr_svo_build_frame(NULL, NULL, 0, depth, mr_v3(0, 0, 0), 1.0f, palette, palette_count, threads, out,
                                  err);
    }

    mr_svo_workspace local;
    memset(&local, 0, sizeof local);
    if (!ws)
        ws = &local;
    rs_ctx c;
    memset(&c, 0, sizeof c);
    c.sel = sel;
    c.method = method;
    c.depth = depth;
    c.packed = depth <= MR_SVO_KEY_PACK_MAX_DEPTH;
    int rc = MR_OK;
    const size_t n = sel->count, chunks = (n + RS_CHUNK - 1) / RS_CHUNK;
    c.chunk_lo = ws_get(ws, WS_RS_LO, chunks, sizeof *c.chunk_lo);
    c.chunk_hi = ws_get(ws, WS_RS_HI, chunks, sizeof *c.chunk_hi);
    c.chunk_bad = ws_get(ws, WS_RS_BAD, chunks, sizeof *c.chunk_bad);
    c.chunk_cells = ws_get(ws, WS_RS_CELLS, chunks, sizeof *c.chunk_cells);
    c.chunk_written = ws_get(ws, WS_RS_WRITTEN, chunks, sizeof *c.chunk_written);
    c.chunk_bits = ws_get(ws, WS_RS_BITS, chunks, 2 * sizeof *c.chunk_bits);
    c.box_level = ws_get(ws, WS_RS_LEVEL, n, 1);
    c.box_range = ws_get(ws, WS_RS_RANGE, n, 6 * sizeof *c.box_range);
    if (!c.chunk_lo || !c.chunk_hi || !c.chunk_bad || !c.chunk_cells || !c.chunk_written || !c.chunk_bits ||
        !c.box_level || !c.box_range) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo resample: out of memory (%zu boxes)", n);
        goto cleanup;
    }

    /* The cube: min corner of all boxes, edge = largest extent grown so the
     * far faces stay strictly beyond every box. */
    mr_parallel_for(threads, chunks, 1, rs_bounds, &c);
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t ch = 0; ch < chunks; ch++) {
        if (c.chunk_bad[ch]) {
            const size_t i = c.chunk_bad[ch] - 1;
            const float *b = &sel->box[i * 6];
            rc = mr_error_set(err, MR_ERR_INVALID, "svo resample: box %zu is not finite or inverted (%g %g %g .. %g %g %g)",
                              i, (double)b[0], (double)b[1], (double)b[2], (double)b[3], (double)b[4],
                              (double)b[5]);
            goto cleanup;
        }
        for (int a = 0; a < 3; a++) {
            lo[a] = dmin(lo[a], c.chunk_lo[ch][a]);
            hi[a] = dmax(hi[a], c.chunk_hi[ch][a]);
        }
    }
    double extent = 0.0, maxabs = 0.0;
    for (int a = 0; a < 3; a++) {
        c.origin[a] = lo[a]; /* a float already */
        extent = dmax(extent, hi[a] - lo[a]);
        maxabs = dmax(maxabs, dmax(fabs(lo[a]), fabs(hi[a])));
    }
    float size = extent > 0.0 ? mr_float_up(extent + extent * CUBE_GROWTH) : mr_float_up(dmax(maxabs, 1.0) * CUBE_GROWTH);
    for (;;) {
        if (!isfinite(size)) {
            rc = mr_error_set(err, MR_ERR_INVALID, "svo resample: the boxes span %g, beyond float range", extent);
            goto cleanup;
        }
        bool clear = true;
        for (int a = 0; a < 3; a++)
            clear = clear && (c.origin[a] - hi[a]) + (double)size > 0.0;
        if (clear)
            break;
        size = nextafterf(size, INFINITY);
    }
    c.size = size;
    c.cell21 = (double)size * (1.0 / (double)GRID_CELLS);
    for (unsigned l = 0; l <= GRID_BITS; l++) {
        c.cell[l] = ldexp(c.size, -(int)l);
        c.inv_cell[l] = 1.0 / c.cell[l];
    }

    mr_parallel_for(threads, chunks, 1, rs_count, &c);
    uint64_t total = 0;
    for (size_t ch = 0; ch < chunks; ch++) {
        const uint64_t t = c.chunk_cells[ch];
        c.chunk_cells[ch] = total;
        total += t;
    }
    if (total > UINT32_MAX) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "svo resample: %llu cells, more than 2^32 - 1",
                          (unsigned long long)total);
        goto cleanup;
    }
    mr_svo_key *keys = ws_get(ws, WS_RS_KEYS, (size_t)total, sizeof *keys);
    uint32_t *payload = ws_get(ws, WS_RS_PAY, (size_t)total, sizeof *payload);
    uint32_t *payload2 = ws_get(ws, WS_RS_PAY2, (size_t)total, sizeof *payload2);
    uint64_t *pk = NULL, *pk2 = NULL;
    mr_svo_key *keys2 = NULL;
    if (c.packed) {
        pk = ws_get(ws, WS_RS_PACKED, (size_t)total, sizeof *pk);
        pk2 = ws_get(ws, WS_RS_PACKED2, (size_t)total, sizeof *pk2);
    } else {
        keys2 = ws_get(ws, WS_RS_KEYS2, (size_t)total, sizeof *keys2);
    }
    if (!keys || !payload || !payload2 || (c.packed ? !pk || !pk2 : !keys2)) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo resample: out of memory (%llu cells)", (unsigned long long)total);
        goto cleanup;
    }
    c.keys = keys;
    c.pk = pk;
    c.payload = payload;
    mr_parallel_for(threads, chunks, 1, rs_write, &c);
    const double t_sort = mr_now();

    size_t sorted = (size_t)total; /* the cells kept */
    if (c.packed) {
        uint64_t bits_or = 0, bits_and = ~(uint64_t)0;
        sorted = 0;
        for (size_t ch = 0; ch < chunks; ch++) {
            bits_or |= c.chunk_bits[2 * ch];
            bits_and &= c.chunk_bits[2 * ch + 1];
            /* each chunk's cells down to the end of the one before, in order */
            const size_t from = (size_t)c.chunk_cells[ch], m = (size_t)c.chunk_written[ch];
            if (from != sorted) {
                memmove(pk + sorted, pk + from, m * sizeof *pk);
                memmove(payload + sorted, payload + from, m * sizeof *payload);
            }
            sorted += m;
        }
        mr_radix_u64 sort = {.keys = pk, .key_scratch = pk2, .payload = payload,
                             .payload_scratch = payload2, .count = sorted,
                             .varying = bits_or ^ bits_and, .unpack = keys, .threads = threads};
        sort.hist = ws_get(ws, WS_RS_HIST, mr_radix_sort_u64_hist_words(&sort), sizeof *sort.hist);
        if (!sort.hist)
            rc = mr_error_set(err, MR_ERR_NOMEM, "svo resample: out of memory (sort histograms)");
        else if ((rc = mr_radix_sort_u64(&sort, err)) == MR_OK)
            payload = sort.sorted_payload;
    } else {
        rc = mr_svo_radix_sort_payload(keys, payload, (size_t)total, keys2, payload2, threads, err);
    }
    if (rc != MR_OK)
        goto cleanup;
    /* the payload array the sort did not end in is free now */
    uint32_t *kept_from = payload == payload2 ? c.payload : payload2;
    size_t kept = 0;
    rc = mr_svo_compact(keys, sorted, depth, kept_from, &kept, err);
    if (rc != MR_OK)
        goto cleanup;
    mr_svo_leaf *leaves = ws_get(ws, WS_RS_LEAVES, kept, sizeof *leaves);
    if (!leaves) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo resample: out of memory (%zu voxels)", kept);
        goto cleanup;
    }
    for (size_t i = 0; i < kept; i++)
        leaves[i] = sel->leaf[payload[kept_from[i]]];
    rc = mr_svo_build_frame(keys, leaves, kept, depth, mr_v3((float)c.origin[0], (float)c.origin[1], (float)c.origin[2]),
                            size, palette, palette_count, threads, out, err);
    if (rc != MR_OK)
        goto cleanup;
    if (cells)
        *cells = total;
    ws->emit_s = t_sort - t_start;
    ws->rebuild_s = mr_now() - t_sort;

cleanup:
    if (rc != MR_OK) {
        mr_svo_free(out);
        memset(out, 0, sizeof *out);
    }
    if (ws == &local)
        ws_release(&local);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* The skinning deformer of a posed asset                                   */

static mr_affine affine_of(const mr_mat4 *m)
{
    mr_affine a;
    memcpy(a.m, m->m, sizeof a.m);
    return a;
}

static mr_mat4 node_global(const mr_pose *pose, int node)
{
    return node >= 0 && (size_t)node < pose->node_count ? pose->global[node] : mr_mat4_identity();
}

int mr_svo_skin_init(mr_svo_skin *s, const mr_asset *asset, mr_error *err)
{
    memset(s, 0, sizeof *s);
    const size_t meshes = asset->mesh_count ? asset->mesh_count : 1;
    size_t joints = 0;
    for (size_t m = 0; m < asset->mesh_count; m++)
        joints += asset->meshes[m].joint_count;
    s->storage = malloc((joints + 1) * sizeof *s->storage);
    s->joint = calloc(meshes, sizeof *s->joint);
    s->joint_count = calloc(meshes, sizeof *s->joint_count);
    s->mesh = calloc(meshes, sizeof *s->mesh);
    s->rest_inverse = calloc(meshes, sizeof *s->rest_inverse);
    mr_pose *rest = NULL;
    int rc = !s->storage || !s->joint || !s->joint_count || !s->mesh || !s->rest_inverse
                 ? mr_error_set(err, MR_ERR_NOMEM, "svo skin: out of memory")
                 : mr_pose_new(asset, &rest, err);
    if (rc >= 0)
        rc = mr_pose_eval(rest, asset, NULL, 0, err);
    for (size_t m = 0, at = 0; rc >= 0 && m < asset->mesh_count; m++) {
        const mr_mesh *mesh = &asset->meshes[m];
        s->joint_count[m] = mesh->joint_count;
        s->joint[m] = mesh->joint_count ? s->storage + at : NULL;
        at += mesh->joint_count;
        /* Rigid meshes were voxelised at their rest placement (voxelize.h). */
        mr_mat4 node = node_global(rest, mesh->node);
        s->rest_inverse[m] = mr_mat4_identity();
        if (mesh->joint_count == 0 && !mr_mat4_inverse(&node, &s->rest_inverse[m]))
            rc = mr_error_set(err, MR_ERR_INVALID, "svo skin: mesh %zu's node has a singular rest transform", m);
    }
    mr_pose_free(rest);
    s->d = (mr_svo_deformer){.mesh_count = asset->mesh_count, .joint = s->joint,
                             .joint_count = s->joint_count, .mesh = s->mesh};
    return rc;
}

void mr_svo_skin_pose(mr_svo_skin *s, const mr_asset *asset, const mr_pose *pose, const mr_mat4 *world)
{
    for (size_t m = 0; m < asset->mesh_count; m++) {
        const mr_mesh *mesh = &asset->meshes[m];
        mr_mat4 node = node_global(pose, mesh->node);
        if (mesh->joint_count == 0)
            node = mr_mat4_mul(&node, &s->rest_inverse[m]);
        mr_mat4 wm = mr_mat4_mul(world, &node);
        s->mesh[m] = affine_of(&wm);
        mr_affine *dst = (mr_affine *)s->joint[m];
        for (uint32_t j = 0; j < mesh->joint_count; j++) {
            mr_mat4 gj = node_global(pose, mesh->joint_nodes[j]);
            mr_mat4 b = mr_mat4_mul(&gj, &mesh->inverse_bind[j]);
            mr_mat4 wb = mr_mat4_mul(world, &b);
            dst[j] = affine_of(&wb);
        }
    }
}

void mr_svo_skin_free(mr_svo_skin *s)
{
    free(s->storage);
    free(s->joint);
    free(s->joint_count);
    free(s->mesh);
    free(s->rest_inverse);
    memset(s, 0, sizeof *s);
}
