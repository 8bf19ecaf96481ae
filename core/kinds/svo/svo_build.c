/*
 * svo_build.c - compaction and the parallel octree build (svo_build.h).
 *
 * Build, for n sorted keys with pairwise disjoint cells (codes unique).
 * The octree's interior nodes are the cells that strictly contain a key,
 * stored breadth-first: by level, and by code within a level, so the
 * children of node 0 come first, then those of node 1, ... Sorted disjoint
 * keys meet the cells of each level in code order, the keys of one cell
 * being a contiguous run, so:
 *  1. Each key opens the cells below the deepest one it shares with the
 *     key before it (shared_level: the common leading bits of the two
 *     codes, in whole levels), down to its own level's parent. Per block of
 *     keys, per level, count them (count_fn); a prefix over levels and
 *     blocks gives every block its first position in each level.
 *  2. Per block, write each opened cell at its level's next position with
 *     the one child its key takes (fill_fn), and add each key to its shared
 *     cell's masks: the last cell written at that level, by this block, or
 *     if none yet, the last of the blocks before it, which another thread
 *     may still be writing; such bits wait in the block's pending masks
 *     and are added after the loop.
 *  3. first_node / first_leaf are exclusive prefix sums of the children
 *     counts over the node array (a blocked parallel scan).
 * All steps write to positions fixed by the input alone, so the result does
 * not depend on the thread count. The thesis builds Karras' binary radix
 * tree first (a GPU's way to place cells in parallel); until stop 66 this
 * file did too, at about three times the time of these passes (64
 * instances' rebuild, one thread each). Temporaries: per block of keys
 * 10 bytes a level and 8 more, per block of nodes 8 bytes.
 */
#include "kinds/svo/svo_build.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"
#include "util/large_alloc.h"

#define BLK MR_SVO_BUILD_BLOCK
#define LEVELS (MR_SVO_MAX_DEPTH + 1u)

typedef struct {
    const mr_svo_key *keys;
    const mr_svo_leaf *in_leaves;
    size_t n;
    unsigned depth;
    uint32_t palette_count;
    size_t blocks;    /* over keys */
    uint32_t *node_base; /* blocks * LEVELS */
    uint32_t *leaf_base; /* blocks * LEVELS */
    uint8_t *pending; /* blocks * LEVELS * 2: child and leaf bits for a cell of the blocks before */
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
    /* In sorted order, a key nested in any earlier key is nested in the last
     * kept one: the cells are aligned, so anything between a kept key and a
     * key inside it lies inside it too and was dropped. One pass checks and
     * compacts: a key moves down to a position at or before its own, so
     * keys i - 1 and i are still the input's when key i is checked (an
     * invalid key leaves the keys before it compacted). */
    size_t kept = 0;
    uint64_t end = 0;
    for (size_t i = 0; i < count; i++) {
        const char *why = key_problem(keys, i, depth, 0);
        if (why)
            return mr_error_set(err, MR_ERR_INVALID, "svo compact: key %zu (code %#llx, level %u): %s", i,
                                (unsigned long long)keys[i].code, keys[i].level, why);
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
            const int level = (int)c->keys[f].level;
            for (int L = shared_level(c, f) + 1; L < level; L++)
                nc[L]++;
            lc[level]++;
        }
    }
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
        const uint32_t *first = c->node_base + b * LEVELS;
        uint32_t nrun[LEVELS], lrun[LEVELS];
        memcpy(nrun, first, sizeof nrun);
        memcpy(lrun, c->leaf_base + b * LEVELS, sizeof lrun);
        uint8_t *pending = c->pending + b * LEVELS * 2;
        memset(pending, 0, LEVELS * 2);
        for (size_t f = lo; f < hi; f++) {
            const uint64_t code = c->keys[f].code;
            const int level = (int)c->keys[f].level, s = shared_level(c, f);
            if (s >= 0) {
                const uint8_t bit = (uint8_t)(1u << digit_at(code, D, (unsigned)s + 1));
                const uint8_t leaf = s + 1 == level ? bit : 0;
                if (nrun[s] > first[s]) {
                    o->child_mask[nrun[s] - 1] |= bit;
                    o->leaf_mask[nrun[s] - 1] |= leaf;
                } else { /* the cell is the blocks' before (node first[s] - 1) */
                    pending[2 * s] |= bit;
                    pending[2 * s + 1] |= leaf;
                }
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
    c.node_base = malloc(c.blocks * LEVELS * sizeof *c.node_base);
    c.leaf_base = malloc(c.blocks * LEVELS * sizeof *c.leaf_base);
    c.pending = malloc(c.blocks * LEVELS * 2);
    if (!c.node_base || !c.leaf_base || !c.pending)
        goto nomem;
    mr_parallel_for(threads, c.blocks, 1, count_fn, &c);

    /* Per-level totals, then each block's first position per level. */
    uint64_t node_total = 0, leaf_total = 0;
    for (unsigned L = 0; L < LEVELS; L++) {
        for (size_t b = 0; b < c.blocks; b++) {
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
    mr_parallel_for(threads, c.blocks, 1, fill_fn, &c);
    for (size_t b = 1; b < c.blocks; b++) /* block 0 has no blocks before it */
        for (unsigned L = 0; L < LEVELS; L++) {
            const uint8_t *pending = c.pending + (b * LEVELS + L) * 2;
            if (pending[0]) {
                const uint32_t node = c.node_base[b * LEVELS + L] - 1;
                out->child_mask[node] |= pending[0];
                out->leaf_mask[node] |= pending[1];
            }
        }

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
    free(c.pending);
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
