/*
 * svo_build.c - compaction and the parallel octree build (svo_build.h).
 *
 * Build, for n sorted keys with pairwise disjoint cells (codes unique):
 *  1. Binary radix tree (Karras 2012's layout, built in linear passes
 *     with a stack: radix_tree_halves): node i's range, split and common prefix length in
 *     bits of the 3D-bit codes. Each node writes its own prefix length into
 *     its two children ("parent prefix"), so no parent pointers are kept.
 *  2. Octree interior nodes are the cells that strictly contain a key. A
 *     radix node with prefix length p whose parent has length q owns the
 *     cells of levels L with q < 3L <= p (they hold >= 2 keys); a radix leaf
 *     (a key of level l) owns the single-key chain q < 3L, L < l. Every
 *     interior cell has exactly one owner. Cells of one level ordered by
 *     code are the owners ordered by any index inside their ranges, and
 *     internal node i's range contains key i, so both owners at index f are
 *     ranked by f: per-block per-level counts plus a prefix over blocks give
 *     each cell its breadth-first position directly, in parallel.
 *  3. Each cell's masks come from its owner: a chain cell has one child; the
 *     deepest cell of a radix node finds its (<= 8) children by descending
 *     the radix nodes whose prefix ends inside the next level's 3 bits.
 *  4. Breadth-first order lists the children of node 0, then of node 1, ...
 *     so first_node / first_leaf are exclusive prefix sums of the children
 *     counts over the node array (a blocked parallel scan).
 * All steps write to positions fixed by the input alone, so the result does
 * not depend on the thread count. Temporaries: 7 bytes per key.
 *
 * On one thread (or keys too few for two blocks) steps 1-3 are one serial
 * pass instead (serial_count, serial_fill): the same cells in the same
 * positions, without the radix tree, about three times faster; a frame's
 * instances are each rebuilt on one thread.
 */
#include "kinds/svo/svo_build.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"
#include "util/large_alloc.h"

#define BLK 16384u
#define LEVELS (MR_SVO_MAX_DEPTH + 1u)
#define LEAF_LEFT 0x40u
#define LEAF_RIGHT 0x80u
#define PREFIX_MASK 0x3fu

typedef struct {
    const mr_svo_key *keys;
    const mr_svo_leaf *in_leaves;
    size_t n;
    unsigned depth;
    uint32_t palette_count;
    uint32_t *split;  /* n - 1: Karras split gamma */
    uint8_t *info;    /* n - 1: prefix bits | LEAF_LEFT | LEAF_RIGHT */
    int8_t *pd_int;   /* n - 1: parent's prefix bits, -1 at the root */
    int8_t *pd_leaf;  /* n */
    size_t blocks;    /* over keys */
    uint32_t *node_base; /* blocks * LEVELS */
    uint32_t *leaf_base; /* blocks * LEVELS */
    size_t *bad;      /* blocks: first invalid key or SIZE_MAX */
    size_t node_blocks;
    uint32_t *scan;   /* node_blocks * 2 */
    mr_svo *out;
} build_ctx;

/* Cell edge of a level-l voxel in finest-level code units (2^(3(D-l))). */
static inline uint64_t cell_span(unsigned depth, uint32_t level)
{
    return (uint64_t)1 << (3u * (depth - level));
}

/* Child index (0..7) of a code's cell at level l >= 1. */
static inline unsigned digit_at(uint64_t code, unsigned depth, unsigned level)
{
    return (unsigned)(code >> (3u * (depth - level))) & 7u;
}

/* Why key i cannot be a compacted key (NULL if it can): checks of the key
 * itself and of its order against key i - 1. */
static const char *key_problem(const mr_svo_key *keys, size_t i, unsigned depth, int need_disjoint)
{
    const mr_svo_key *k = &keys[i];
    if (k->level > depth)
        return "level above the octree depth";
    if (3u * depth < 64u && (k->code >> (3u * depth)) != 0)
        return "code has bits at or above 3 * depth";
    if (k->code & (cell_span(depth, k->level) - 1u))
        return "code not aligned to its level (low bits set)";
    if (i == 0)
        return NULL;
    const mr_svo_key *p = &keys[i - 1];
    if (p->level > depth)
        return NULL; /* reported at i - 1 */
    if (k->code < p->code || (k->code == p->code && k->level < p->level))
        return "keys not sorted by (code, level)";
    if (need_disjoint && k->code < p->code + cell_span(depth, p->level))
        return k->code == p->code && k->level == p->level ? "duplicate key (not compacted)"
                                                          : "key nested in the previous key (not compacted)";
    return NULL;
}

int mr_svo_compact(mr_svo_key *keys, size_t count, unsigned depth, uint32_t *kept_from,
                   size_t *out_count, mr_error *err)
{
    if (out_count)
        *out_count = 0;
    if (depth < 1 || depth > MR_SVO_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_INVALID, "svo compact: depth %u not in 1..%u", depth, MR_SVO_MAX_DEPTH);
    if (count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "svo compact: %zu keys exceed 2^32 - 1", count);
    if (count > 0 && !keys)
        return mr_error_set(err, MR_ERR_INVALID, "svo compact: keys is NULL");
    for (size_t i = 0; i < count; i++) {
        const char *why = key_problem(keys, i, depth, 0);
        if (why)
            return mr_error_set(err, MR_ERR_INVALID, "svo compact: key %zu (code %#llx, level %u): %s", i,
                                (unsigned long long)keys[i].code, keys[i].level, why);
    }
    /* In sorted order, a key nested in any earlier key is nested in the last
     * kept one: the cells are aligned, so anything between a kept key and a
     * key inside it lies inside it too and was dropped. */
    size_t kept = 0;
    uint64_t end = 0;
    for (size_t i = 0; i < count; i++) {
        if (kept > 0 && keys[i].code < end)
            continue;
        end = keys[i].code + cell_span(depth, keys[i].level);
        if (kept_from)
            kept_from[kept] = (uint32_t)i;
        keys[kept++] = keys[i];
    }
    if (out_count)
        *out_count = kept;
    return MR_OK;
}

/* ---- build ------------------------------------------------------------ */

static void block_keys(const build_ctx *c, size_t b, size_t *lo, size_t *hi)
{
    *lo = b * BLK;
    *hi = *lo + BLK < c->n ? *lo + BLK : c->n;
}

static void validate_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_keys(c, b, &lo, &hi);
        c->bad[b] = SIZE_MAX;
        for (size_t i = lo; i < hi; i++) {
            if (key_problem(c->keys, i, c->depth, 1) ||
                (c->in_leaves && c->in_leaves[i].attr >= c->palette_count) ||
                (!c->in_leaves && c->palette_count == 0)) {
                c->bad[b] = i;
                break;
            }
        }
    }
}

/* Writes internal node `node` of the radix tree: it splits keys [first,
 * last] between keys gamma and gamma + 1, whose codes share their leading
 * `prefix` bits. */
static inline void radix_node(build_ctx *c, size_t node, size_t first, size_t last, size_t gamma, int prefix)
{
    const int bits = prefix - (64 - 3 * (int)c->depth); /* top bits every code has zero */
    uint8_t info = (uint8_t)bits;
    if (first == gamma) {
        info |= LEAF_LEFT;
        c->pd_leaf[gamma] = (int8_t)bits;
    } else {
        c->pd_int[gamma] = (int8_t)bits;
    }
    if (last == gamma + 1) {
        info |= LEAF_RIGHT;
        c->pd_leaf[gamma + 1] = (int8_t)bits;
    } else {
        c->pd_int[gamma + 1] = (int8_t)bits;
    }
    c->split[node] = (uint32_t)gamma;
    c->info[node] = info;
}

typedef struct split_entry {
    uint32_t split;
    int8_t d;
} split_entry;

/* d of split p: the leading bits keys p and p + 1 share; -1 for the split
 * after the last key, which closes every open one. */
static inline int split_d(const build_ctx *c, size_t p)
{
    return p + 1 < c->n ? __builtin_clzll(c->keys[p].code ^ c->keys[p + 1].code) : -1;
}

/* Pops the splits on the stack (above `bottom`) whose d exceeds d, split p
 * being their right neighbour and the entry below each its left. */
static void close_splits(build_ctx *c, split_entry *stack, int *top, int bottom, size_t p, int d)
{
    while (*top > bottom && stack[*top - 1].d > d) {
        const size_t q = stack[--*top].split;
        const int dl = *top > 0 ? stack[*top - 1].d : -1; /* left neighbour's prefix */
        const size_t first = *top > 0 ? (size_t)stack[*top - 1].split + 1 : 0, last = p;
        radix_node(c, dl > d ? first : d > dl ? last : 0, first, last, q, stack[*top].d);
    }
}

/* The stack pass over splits [from, to), every one of them below n - 1:
 * each closes what it can, then waits on the stack for its right
 * neighbour. */
static void walk_splits(build_ctx *c, split_entry *stack, int *top, size_t from, size_t to)
{
    for (size_t p = from; p < to; p++) {
        const int d = split_d(c, p);
        close_splits(c, stack, top, 0, p, d);
        stack[(*top)++] = (split_entry){(uint32_t)p, (int8_t)d};
    }
}

/* The binary radix tree of the n >= 2 sorted unique keys, in Karras'
 * numbering. Internal nodes are the n - 1 splits: split p lies
 * between keys p and p + 1, whose codes share d(p) leading bits. Its node
 * covers the keys back to the nearest split on the left with a shorter
 * common prefix (l) and on to the nearest on the right (r): [l + 1, r].
 * (Two splits with equal d have a shorter one between them: the bit after
 * the prefix rises once in a sorted run.) Its parent is whichever of l and
 * r has the longer prefix; as the parent's right child the node is
 * numbered by its first key, as its left child by its last (the root: 0),
 * which is Karras' numbering (each node's range has its number at one end).
 * A stack of splits with rising d finds both neighbours: a split is popped
 * by its right one, and the one below it is its left. d rises strictly up
 * the stack, so it holds at most 64 splits. Linear, where Karras' binary
 * searches per node jumped across the keys.
 *
 * One pass over the splits is serial (1.0-1.6 ms of a depth-8 resample's
 * build on two threads, whose other steps took 0.3-1.2 ms each), so the
 * tree is made from two halves of the splits walked at once. The left
 * half [0, m) is walked as one pass walks it and leaves its stack. The
 * right half [m, n - 1)
 * starts on an empty stack: a split it pops with nothing below it needs its
 * left neighbour from the left half, and the left half's open splits with a
 * larger d would be popped by the same right neighbour, so such a pop is
 * kept as pending (and so is the half's first split, which pops left
 * splits only). The serial merge then replays the pending pops on the left
 * stack, in order, and closes what is left, the right half's stack on top.
 * Every node is written once, by the same arithmetic: the same tree. A
 * pending pop's split has a smaller d than the one before it, so there are
 * at most 65. */

typedef struct pending_pop {
    bool has_q;   /* false: the right half's first split, popping nothing of its own */
    split_entry q; /* the split popped with nothing below it */
    uint32_t p;   /* its right neighbour */
    int8_t d;     /* d of p */
} pending_pop;

typedef struct radix_halves {
    build_ctx *c;
    size_t m;
    split_entry left[65], right[65];
    int left_top, right_top;
    pending_pop pending[66];
    int npending;
} radix_halves;

static void radix_half(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    radix_halves *h = vctx;
    build_ctx *c = h->c;
    for (size_t half = begin; half < end; half++) {
        if (half == 0) {
            walk_splits(c, h->left, &h->left_top, 0, h->m);
            continue;
        }
        split_entry *stack = h->right;
        int top = 0;
        for (size_t p = h->m; p + 1 < c->n; p++) {
            const int d = split_d(c, p);
            close_splits(c, stack, &top, 1, p, d);
            if (top == 0 || (top == 1 && stack[0].d > d)) {
                pending_pop *pp = &h->pending[h->npending++];
                pp->has_q = top == 1;
                if (pp->has_q)
                    pp->q = stack[0];
                pp->p = (uint32_t)p;
                pp->d = (int8_t)d;
                top = 0;
            }
            stack[top++] = (split_entry){(uint32_t)p, (int8_t)d};
        }
        h->right_top = top;
    }
}

static void radix_tree_halves(build_ctx *c, unsigned threads)
{
    radix_halves h = {.c = c, .m = (c->n - 1) / 2};
    mr_parallel_for(threads, 2, 1, radix_half, &h);
    split_entry *stack = h.left;
    int top = h.left_top;
    for (int i = 0; i < h.npending; i++) {
        const pending_pop *pp = &h.pending[i];
        if (pp->has_q) {
            stack[top++] = pp->q;
            close_splits(c, stack, &top, top - 1, pp->p, pp->d);
        }
        close_splits(c, stack, &top, 0, pp->p, pp->d);
    }
    for (int i = 0; i < h.right_top; i++)
        stack[top++] = h.right[i];
    close_splits(c, stack, &top, 0, c->n - 1, -1);
}

/* Levels of the interior cells owned by internal node i / leaf f
 * (empty when lo > hi). (q + 3) / 3 is the least L with 3L > q, q >= -1. */
static inline void internal_levels(const build_ctx *c, size_t i, int *lo, int *hi)
{
    *lo = (c->pd_int[i] + 3) / 3;
    *hi = (int)(c->info[i] & PREFIX_MASK) / 3;
}

static inline void leaf_levels(const build_ctx *c, size_t f, int *lo, int *hi)
{
    *lo = (c->pd_leaf[f] + 3) / 3;
    *hi = (int)c->keys[f].level - 1;
}

static void count_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_keys(c, b, &lo, &hi);
        uint32_t *nc = c->node_base + b * LEVELS, *lc = c->leaf_base + b * LEVELS;
        memset(nc, 0, LEVELS * sizeof *nc);
        memset(lc, 0, LEVELS * sizeof *lc);
        for (size_t f = lo; f < hi; f++) {
            int a, z;
            if (f + 1 < c->n) {
                internal_levels(c, f, &a, &z);
                for (int L = a; L <= z; L++)
                    nc[L]++;
            }
            leaf_levels(c, f, &a, &z);
            for (int L = a; L <= z; L++)
                nc[L]++;
            lc[c->keys[f].level]++;
        }
    }
}

/* Masks of internal node i's deepest cell (level L): its children are the
 * radix elements below i that first reach level L + 1. */
static void split_cell(const build_ctx *c, size_t i, unsigned L, uint8_t *child, uint8_t *leaf)
{
    const unsigned D = c->depth;
    uint32_t stack[16]; /* element << 1 | is_leaf; the descent is <= 2 radix levels deep */
    unsigned sp = 0;
    uint8_t cm = 0, lm = 0;
    uint32_t g = c->split[i];
    stack[sp++] = ((g + 1) << 1) | ((c->info[i] & LEAF_RIGHT) ? 1u : 0u);
    stack[sp++] = (g << 1) | ((c->info[i] & LEAF_LEFT) ? 1u : 0u);
    while (sp > 0) {
        uint32_t e = stack[--sp];
        uint32_t x = e >> 1;
        unsigned bit = 1u << digit_at(c->keys[x].code, D, L + 1);
        if (e & 1u) {
            cm |= (uint8_t)bit;
            if (c->keys[x].level == L + 1)
                lm |= (uint8_t)bit;
        } else if ((c->info[x] & PREFIX_MASK) >= 3u * (L + 1)) {
            cm |= (uint8_t)bit;
        } else if (sp + 2 <= 16) {
            uint32_t gx = c->split[x];
            stack[sp++] = ((gx + 1) << 1) | ((c->info[x] & LEAF_RIGHT) ? 1u : 0u);
            stack[sp++] = (gx << 1) | ((c->info[x] & LEAF_LEFT) ? 1u : 0u);
        }
    }
    *child = cm;
    *leaf = lm;
}

static void fill_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = vctx;
    mr_svo *o = c->out;
    const unsigned D = c->depth;
    uint8_t plus_z[2];
    mr_svo_normal_encode(mr_v3(0.0f, 0.0f, 1.0f), plus_z);
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_keys(c, b, &lo, &hi);
        uint32_t nrun[LEVELS], lrun[LEVELS];
        memcpy(nrun, c->node_base + b * LEVELS, sizeof nrun);
        memcpy(lrun, c->leaf_base + b * LEVELS, sizeof lrun);
        for (size_t f = lo; f < hi; f++) {
            const uint64_t code = c->keys[f].code;
            int a, z;
            if (f + 1 < c->n) {
                internal_levels(c, f, &a, &z);
                for (int L = a; L <= z; L++) {
                    uint32_t pos = nrun[L]++;
                    if (L < z) {
                        o->child_mask[pos] = (uint8_t)(1u << digit_at(code, D, (unsigned)L + 1));
                        o->leaf_mask[pos] = 0;
                    } else {
                        split_cell(c, f, (unsigned)L, &o->child_mask[pos], &o->leaf_mask[pos]);
                    }
                }
            }
            const uint32_t level = c->keys[f].level;
            leaf_levels(c, f, &a, &z);
            for (int L = a; L <= z; L++) {
                uint32_t pos = nrun[L]++;
                uint8_t bit = (uint8_t)(1u << digit_at(code, D, (unsigned)L + 1));
                o->child_mask[pos] = bit;
                o->leaf_mask[pos] = (uint32_t)L + 1 == level ? bit : 0;
            }
            uint32_t lp = lrun[level]++;
            if (o->leaf_keys)
                o->leaf_keys[lp] = c->keys[f];
            if (c->in_leaves) {
                o->leaves[lp] = c->in_leaves[f];
            } else {
                o->leaves[lp].normal[0] = plus_z[0];
                o->leaves[lp].normal[1] = plus_z[1];
                o->leaves[lp].attr = 0;
            }
        }
    }
}

/* The serial build (one thread, a loop nested in another, or keys too few
 * for a second block): sorted disjoint keys meet their interior cells in
 * code order within each level, so one pass counts the cells each level
 * gets and a second writes them, with the same arrays and positions as
 * the radix tree's owners give (count_fn, fill_fn). Each key opens the
 * cells below the deepest one it shares with the key before it, and adds
 * itself to that shared cell's masks. */

/* The deepest level whose cell keys f - 1 and f share, -1 for f = 0. It
 * is above both keys' levels: sorted disjoint keys share no cell of
 * either one's level. */
static inline int shared_level(const build_ctx *c, size_t f)
{
    if (f == 0)
        return -1;
    const uint64_t x = c->keys[f].code ^ c->keys[f - 1].code;
    /* codes have no bits above 3 * depth (validate_fn) */
    const unsigned bits = (unsigned)(x ? __builtin_clzll(x) : 64) - (64u - 3u * c->depth);
    return (int)(bits / 3u);
}

static void serial_count(build_ctx *c)
{
    uint32_t *nc = c->node_base, *lc = c->leaf_base;
    memset(nc, 0, LEVELS * sizeof *nc);
    memset(lc, 0, LEVELS * sizeof *lc);
    for (size_t f = 0; f < c->n; f++) {
        const int level = (int)c->keys[f].level;
        for (int L = shared_level(c, f) + 1; L < level; L++)
            nc[L]++;
        lc[level]++;
    }
}

static void serial_fill(build_ctx *c)
{
    mr_svo *o = c->out;
    const unsigned D = c->depth;
    uint8_t plus_z[2];
    mr_svo_normal_encode(mr_v3(0.0f, 0.0f, 1.0f), plus_z);
    uint32_t nrun[LEVELS], lrun[LEVELS];
    memcpy(nrun, c->node_base, sizeof nrun);
    memcpy(lrun, c->leaf_base, sizeof lrun);
    for (size_t f = 0; f < c->n; f++) {
        const uint64_t code = c->keys[f].code;
        const int level = (int)c->keys[f].level, s = shared_level(c, f);
        if (s >= 0) {
            /* the shared cell is the last one written at its level */
            const uint8_t bit = (uint8_t)(1u << digit_at(code, D, (unsigned)s + 1));
            o->child_mask[nrun[s] - 1] |= bit;
            if (s + 1 == level)
                o->leaf_mask[nrun[s] - 1] |= bit;
        }
        for (int L = s + 1; L < level; L++) {
            const uint32_t pos = nrun[L]++;
            const uint8_t bit = (uint8_t)(1u << digit_at(code, D, (unsigned)L + 1));
            o->child_mask[pos] = bit;
            o->leaf_mask[pos] = L + 1 == level ? bit : 0;
        }
        const uint32_t lp = lrun[level]++;
        if (o->leaf_keys)
            o->leaf_keys[lp] = c->keys[f];
        if (c->in_leaves) {
            o->leaves[lp] = c->in_leaves[f];
        } else {
            o->leaves[lp].normal[0] = plus_z[0];
            o->leaves[lp].normal[1] = plus_z[1];
            o->leaves[lp].attr = 0;
        }
    }
}

static void block_nodes(const build_ctx *c, size_t b, size_t *lo, size_t *hi)
{
    *lo = b * BLK;
    *hi = *lo + BLK < c->out->node_count ? *lo + BLK : c->out->node_count;
}

static void scan_sum_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = vctx;
    const mr_svo *o = c->out;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_nodes(c, b, &lo, &hi);
        uint32_t ni = 0, nl = 0;
        for (size_t p = lo; p < hi; p++) {
            ni += mr_svo_popcount8(o->child_mask[p] & (uint8_t)~o->leaf_mask[p]);
            nl += mr_svo_popcount8(o->leaf_mask[p]);
        }
        c->scan[2 * b] = ni;
        c->scan[2 * b + 1] = nl;
    }
}

static void scan_fill_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = vctx;
    mr_svo *o = c->out;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_nodes(c, b, &lo, &hi);
        uint32_t ni = c->scan[2 * b], nl = c->scan[2 * b + 1];
        for (size_t p = lo; p < hi; p++) {
            o->first_node[p] = ni;
            o->first_leaf[p] = nl;
            ni += mr_svo_popcount8(o->child_mask[p] & (uint8_t)~o->leaf_mask[p]);
            nl += mr_svo_popcount8(o->leaf_mask[p]);
        }
    }
}

static int build(const mr_svo_key *keys, const mr_svo_leaf *leaves, size_t count, unsigned depth,
                 mr_vec3 origin, float size, const mr_svo_attr *palette, uint32_t palette_count,
                 bool per_frame, unsigned threads, mr_svo *out, mr_error *err)
{
    int rc = MR_OK;
    build_ctx c;
    memset(&c, 0, sizeof c);
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo build: out is NULL");
    memset(out, 0, sizeof *out);
    if (depth < 1 || depth > MR_SVO_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_INVALID, "svo build: depth %u not in 1..%u", depth, MR_SVO_MAX_DEPTH);
    if (!(size > 0.0f) || !isfinite(size) || !isfinite(origin.x) || !isfinite(origin.y) || !isfinite(origin.z))
        return mr_error_set(err, MR_ERR_INVALID, "svo build: cube needs a finite origin and a finite size > 0");
    if (palette_count > MR_SVO_MAX_PALETTE || (palette_count > 0 && !palette))
        return mr_error_set(err, MR_ERR_INVALID, "svo build: palette of %u entries (max %u) %s", palette_count,
                            MR_SVO_MAX_PALETTE, palette ? "" : "is NULL");
    if (count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "svo build: %zu keys exceed 2^32 - 1", count);
    if (count > 0 && !keys)
        return mr_error_set(err, MR_ERR_INVALID, "svo build: keys is NULL");

    out->depth = depth;
    out->origin = origin;
    out->size = size;
    c.keys = keys;
    c.in_leaves = leaves;
    c.n = count;
    c.depth = depth;
    c.palette_count = palette_count;
    c.out = out;
    c.blocks = (count + BLK - 1) / BLK;

    if (palette_count > 0 && per_frame) {
        /* only the owner writes a palette (svo.h): the cast does not */
        out->palette = (mr_svo_attr *)palette;
        out->palette_borrowed = true;
        out->palette_count = palette_count;
    } else if (palette_count > 0) {
        out->palette = malloc(palette_count * sizeof *out->palette);
        if (!out->palette)
            goto nomem;
        memcpy(out->palette, palette, palette_count * sizeof *out->palette);
        out->palette_count = palette_count;
    }
    if (count == 0)
        return MR_OK;

    c.bad = malloc(c.blocks * sizeof *c.bad);
    if (!c.bad)
        goto nomem;
    mr_parallel_for(threads, c.blocks, 1, validate_fn, &c);
    for (size_t b = 0; b < c.blocks; b++) {
        if (c.bad[b] == SIZE_MAX)
            continue;
        size_t i = c.bad[b];
        const char *why = key_problem(keys, i, depth, 1);
        if (!why)
            why = palette_count == 0 ? "keys need a palette" : "leaf attr beyond the palette";
        rc = mr_error_set(err, MR_ERR_INVALID, "svo build: key %zu (code %#llx, level %u): %s", i,
                          (unsigned long long)keys[i].code, keys[i].level, why);
        goto cleanup;
    }
    const bool serial = threads == 1 || c.blocks == 1 || mr_parallel_nested();
    const size_t level_blocks = serial ? 1 : c.blocks; /* blocks with counts of their own */
    c.node_base = malloc(level_blocks * LEVELS * sizeof *c.node_base);
    c.leaf_base = malloc(level_blocks * LEVELS * sizeof *c.leaf_base);
    if (!c.node_base || !c.leaf_base)
        goto nomem;
    if (serial) {
        serial_count(&c);
    } else {
        const size_t ni = count - 1; /* count > BLK */
        c.split = mr_large_alloc(ni * sizeof *c.split);
        c.info = mr_large_alloc(ni);
        c.pd_int = mr_large_alloc(ni);
        c.pd_leaf = mr_large_alloc(count);
        if (!c.split || !c.info || !c.pd_int || !c.pd_leaf)
            goto nomem;
        c.pd_int[0] = -1; /* the radix root has no parent */
        c.pd_leaf[0] = -1;
        radix_tree_halves(&c, threads);
        mr_parallel_for(threads, c.blocks, 1, count_fn, &c);
    }

    /* Per-level totals, then each block's first position per level. */
    uint64_t node_total = 0, leaf_total = 0;
    for (unsigned L = 0; L < LEVELS; L++) {
        for (size_t b = 0; b < level_blocks; b++) {
            uint32_t nn = c.node_base[b * LEVELS + L], nl = c.leaf_base[b * LEVELS + L];
            c.node_base[b * LEVELS + L] = (uint32_t)node_total;
            c.leaf_base[b * LEVELS + L] = (uint32_t)leaf_total;
            node_total += nn;
            leaf_total += nl;
            if (node_total > UINT32_MAX) {
                rc = mr_error_set(err, MR_ERR_LIMIT, "svo build: more than 2^32 - 1 octree nodes");
                goto cleanup;
            }
        }
    }
    out->node_count = (uint32_t)node_total;
    out->leaf_count = (uint32_t)leaf_total;
    if (node_total > 0) {
        out->first_node = mr_large_alloc(node_total * sizeof *out->first_node);
        out->first_leaf = mr_large_alloc(node_total * sizeof *out->first_leaf);
        out->child_mask = mr_large_alloc(node_total);
        out->leaf_mask = mr_large_alloc(node_total);
        if (!out->first_node || !out->first_leaf || !out->child_mask || !out->leaf_mask)
            goto nomem;
    }
    out->leaves = mr_large_alloc(leaf_total * sizeof *out->leaves);
    if (!per_frame)
        out->leaf_keys = mr_large_alloc(leaf_total * sizeof *out->leaf_keys);
    if (!out->leaves || (!per_frame && !out->leaf_keys))
        goto nomem;
    if (serial)
        serial_fill(&c);
    else
        mr_parallel_for(threads, c.blocks, 1, fill_fn, &c);

    if (node_total > 0) {
        c.node_blocks = (node_total + BLK - 1) / BLK;
        c.scan = malloc(2 * c.node_blocks * sizeof *c.scan);
        if (!c.scan)
            goto nomem;
        mr_parallel_for(threads, c.node_blocks, 1, scan_sum_fn, &c);
        uint32_t ni_run = 1, nl_run = 0; /* node 0 is nobody's child */
        for (size_t b = 0; b < c.node_blocks; b++) {
            uint32_t a = c.scan[2 * b], z = c.scan[2 * b + 1];
            c.scan[2 * b] = ni_run;
            c.scan[2 * b + 1] = nl_run;
            ni_run += a;
            nl_run += z;
        }
        /* Every node but the root is one node's interior child and every
         * leaf one node's leaf child; anything else is a bug here. */
        if (ni_run != out->node_count || nl_run != out->leaf_count) {
            rc = mr_error_set(err, MR_ERR_INVALID, "svo build: internal error: %u nodes / %u leaves reached of %u / %u",
                              ni_run, nl_run, out->node_count, out->leaf_count);
            goto cleanup;
        }
        mr_parallel_for(threads, c.node_blocks, 1, scan_fill_fn, &c);
    }
    /* The leaves' box, from the nodes: a walk that skips what the box
     * already holds visits a small part of the tree, where decoding every
     * key's Morton code took 3-4 % of a resize frame. */
    rc = mr_svo_fit_occupied(out, err);
    goto cleanup;

nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "svo build: out of memory for %zu keys", count);
cleanup:
    free(c.bad);
    free(c.split);
    free(c.info);
    free(c.pd_int);
    free(c.pd_leaf);
    free(c.node_base);
    free(c.leaf_base);
    free(c.scan);
    if (rc < 0)
        mr_svo_free(out);
    return rc;
}

int mr_svo_build(const mr_svo_key *keys, const mr_svo_leaf *leaves, size_t count,
                 unsigned depth, mr_vec3 origin, float size,
                 const mr_svo_attr *palette, uint32_t palette_count,
                 unsigned threads, mr_svo *out, mr_error *err)
{
    return build(keys, leaves, count, depth, origin, size, palette, palette_count, false, threads, out, err);
}

int mr_svo_build_frame(const mr_svo_key *keys, const mr_svo_leaf *leaves, size_t count, unsigned depth,
                       mr_vec3 origin, float size, const mr_svo_attr *palette, uint32_t palette_count,
                       unsigned threads, mr_svo *out, mr_error *err)
{
    return build(keys, leaves, count, depth, origin, size, palette, palette_count, true, threads, out, err);
}
