/*
 * test_svo_build.c - compaction, the octree build and the leaf walk
 * (svo_build.h, svo.h), and the octahedral normal encoding.
 *
 * Build checks, per case: an independent recursive walk of the result (not
 * mr_svo_collect_keys) must reach every node exactly once and give exactly
 * the input keys, in order, with their leaf attributes; node_count must
 * equal the number of distinct (level, code prefix) pairs over all proper
 * ancestors of the keys, counted here by sorting; masks must be consistent
 * and breadth-first (children after parents, node 0 the root);
 * mr_svo_collect_keys must agree with the walk; 1, 2 and 4 threads must give
 * identical arrays. Cases: empty, single voxel, root leaf, single coarse key,
 * depth 1 (full and partial), random sparse sets at depths 2..21 with one
 * level and with mixed levels (compacted first), blocks of keys wholly
 * inside one cell, invalid inputs.
 *
 * Normals: tolerance stated at test_normals. A timing run of ~10 M
 * surface-like keys prints sort / compact / build times and bytes per leaf
 * (never asserted).
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "util/clock.h"
#include "util/morton.h"
#include "util/radix_sort.h"
#include "kinds/svo/svo.h"
#include "kinds/svo/svo_build.h"

static uint64_t rng_next(uint64_t *s)
{
    uint64_t z = (*s += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

static double rng_unit(uint64_t *s) { return (double)(rng_next(s) >> 11) * (1.0 / 9007199254740992.0); }

static mr_svo_key key_at(unsigned depth, unsigned level, uint32_t x, uint32_t y, uint32_t z)
{
    mr_svo_key k;
    memset(&k, 0, sizeof k);
    unsigned sh = depth - level;
    k.code = mr_morton_encode(x << sh, y << sh, z << sh);
    k.level = level;
    return k;
}

static const mr_svo_attr palette3[3] = {
    {{255, 0, 0}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}},
    {{0, 255, 0}, 0, {1, 0, 0, 0}, {255, 0, 0, 0}},
    {{0, 0, 255}, 1, {2, 3, 0, 0}, {128, 127, 0, 0}},
};

/* ---- compaction ---- */

static void test_compact_hand_made(void **state)
{
    (void)state;
    /* depth 3: level-1 cells span 64 codes, level-2 cells 8. */
    mr_svo_key k[] = {
        {0, 1},  /* kept: covers codes 0..63 */
        {0, 3},  /* inside it */
        {8, 2},  /* inside it */
        {56, 3}, /* inside it, last code of the cell */
        {64, 3}, /* kept */
        {64, 3}, /* duplicate */
        {72, 2}, /* kept */
        {72, 3}, /* inside 72/2 */
        {79, 3}, /* inside 72/2 */
        {80, 3}, /* kept */
        {448, 1}, /* kept */
        {448, 1}, /* duplicate */
        {511, 3}, /* inside 448/1 */
    };
    const size_t n = sizeof k / sizeof k[0];
    uint32_t from[sizeof k / sizeof k[0]];
    size_t kept = 99;
    mr_error err = {0};
    assert_int_equal(mr_svo_compact(k, n, 3, from, &kept, &err), MR_OK);
    const mr_svo_key want[] = {{0, 1}, {64, 3}, {72, 2}, {80, 3}, {448, 1}};
    const uint32_t want_from[] = {0, 4, 6, 9, 10};
    assert_int_equal(kept, 5);
    for (unsigned i = 0; i < 5; i++) {
        assert_int_equal(k[i].code, want[i].code);
        assert_int_equal(k[i].level, want[i].level);
        assert_int_equal(from[i], want_from[i]);
    }
    /* the root cell swallows everything */
    mr_svo_key r[] = {{0, 0}, {0, 2}, {100, 3}};
    assert_int_equal(mr_svo_compact(r, 3, 3, NULL, &kept, &err), MR_OK);
    assert_int_equal(kept, 1);
    assert_int_equal(r[0].level, 0);
    assert_int_equal(mr_svo_compact(NULL, 0, 3, NULL, &kept, &err), MR_OK);
    assert_int_equal(kept, 0);
}

static void test_compact_invalid(void **state)
{
    (void)state;
    mr_error err;
    size_t kept;
    mr_svo_key unsorted[] = {{8, 3}, {0, 3}};
    mr_svo_key coarse_after[] = {{0, 2}, {0, 1}}; /* same code: coarser must come first */
    mr_svo_key too_deep[] = {{0, 4}};
    mr_svo_key high_bits[] = {{512, 3}};
    mr_svo_key misaligned[] = {{4, 2}};
    mr_svo_key *cases[] = {unsorted, coarse_after, too_deep, high_bits, misaligned};
    const size_t counts[] = {2, 2, 1, 1, 1};
    for (unsigned i = 0; i < 5; i++) {
        memset(&err, 0, sizeof err);
        assert_int_equal(mr_svo_compact(cases[i], counts[i], 3, NULL, &kept, &err), MR_ERR_INVALID);
        assert_true(err.msg[0] != '\0');
    }
    mr_svo_key ok[] = {{0, 3}};
    assert_int_equal(mr_svo_compact(ok, 1, 0, NULL, &kept, &err), MR_ERR_INVALID);
    assert_int_equal(mr_svo_compact(ok, 1, 22, NULL, &kept, &err), MR_ERR_INVALID);
}

/* Cell of key a contains cell of key b. */
static int contains(const mr_svo_key *a, const mr_svo_key *b, unsigned depth)
{
    if (a->level > b->level)
        return 0;
    unsigned sh = 3 * (depth - a->level);
    return (a->code >> sh) == (b->code >> sh);
}

/* Random mixed-level keys: brute force says which survive. */
static void test_compact_random(void **state)
{
    (void)state;
    uint64_t s = 5;
    for (unsigned round = 0; round < 50; round++) {
        const unsigned depth = 1 + round % 4;
        const size_t n = 1 + rng_next(&s) % 300;
        mr_svo_key *k = calloc(n, sizeof *k), *orig = calloc(n, sizeof *orig);
        uint32_t *from = calloc(n, sizeof *from);
        for (size_t i = 0; i < n; i++) {
            unsigned level = (unsigned)(rng_next(&s) % (depth + 1));
            uint32_t m = (1u << level) - 1u;
            uint64_t r = rng_next(&s);
            k[i] = key_at(depth, level, (uint32_t)r & m, (uint32_t)(r >> 20) & m, (uint32_t)(r >> 40) & m);
        }
        assert_int_equal(mr_svo_radix_sort(k, n, NULL, 1, NULL), MR_OK);
        memcpy(orig, k, n * sizeof *k);
        size_t kept;
        assert_int_equal(mr_svo_compact(k, n, depth, from, &kept, NULL), MR_OK);
        size_t j = 0;
        for (size_t i = 0; i < n; i++) {
            int dropped = 0;
            for (size_t e = 0; e < i && !dropped; e++)
                dropped = contains(&orig[e], &orig[i], depth);
            if (dropped)
                continue;
            assert_true(j < kept);
            assert_int_equal(from[j], i);
            assert_int_equal(k[j].code, orig[i].code);
            assert_int_equal(k[j].level, orig[i].level);
            j++;
        }
        assert_int_equal(j, kept);
        free(k);
        free(orig);
        free(from);
    }
}

/* ---- build ---- */

typedef struct {
    const mr_svo *svo;
    unsigned *visits;
    mr_svo_key *keys;
    uint32_t *leaf_idx;
    size_t n;
    size_t cap;
} walk_state;

static void walk(walk_state *w, uint32_t node, unsigned level, uint64_t code)
{
    const mr_svo *o = w->svo;
    assert_true(node < o->node_count);
    assert_true(level < o->depth);
    w->visits[node]++;
    const unsigned cm = o->child_mask[node], lm = o->leaf_mask[node];
    assert_true(cm != 0);
    assert_int_equal(lm & ~cm, 0);
    unsigned ni = 0, nl = 0;
    for (unsigned c = 0; c < 8; c++) {
        if (!(cm & (1u << c)))
            continue;
        uint64_t cc = code | ((uint64_t)c << (3 * (o->depth - level - 1)));
        if (lm & (1u << c)) {
            uint32_t li = o->first_leaf[node] + nl++;
            assert_true(li < o->leaf_count);
            assert_true(w->n < w->cap);
            w->keys[w->n].code = cc;
            w->keys[w->n].level = level + 1;
            w->leaf_idx[w->n++] = li;
        } else {
            uint32_t child = o->first_node[node] + ni++;
            assert_true(child > node); /* breadth-first: children after parents */
            walk(w, child, level + 1, cc);
        }
    }
}

static int pair_cmp(const void *pa, const void *pb)
{
    const uint64_t *a = pa, *b = pb;
    return a[0] != b[0] ? (a[0] < b[0] ? -1 : 1) : (a[1] < b[1] ? -1 : a[1] > b[1]);
}

/* Distinct (level, prefix) over every proper ancestor cell of every key. */
static size_t count_ancestors(const mr_svo_key *k, size_t n, unsigned depth)
{
    size_t m = 0;
    for (size_t i = 0; i < n; i++)
        m += k[i].level;
    if (m == 0)
        return 0;
    uint64_t *p = malloc(2 * m * sizeof *p);
    assert_non_null(p);
    size_t at = 0;
    for (size_t i = 0; i < n; i++)
        for (unsigned L = 0; L < k[i].level; L++) {
            p[2 * at] = L;
            p[2 * at + 1] = k[i].code >> (3 * (depth - L));
            at++;
        }
    qsort(p, m, 2 * sizeof *p, pair_cmp);
    size_t distinct = 0;
    for (size_t i = 0; i < m; i++)
        distinct += i == 0 || p[2 * i] != p[2 * i - 2] || p[2 * i + 1] != p[2 * i - 1];
    free(p);
    return distinct;
}

static void same_svo(const mr_svo *a, const mr_svo *b)
{
    assert_int_equal(a->node_count, b->node_count);
    assert_int_equal(a->leaf_count, b->leaf_count);
    if (a->node_count) {
        assert_memory_equal(a->first_node, b->first_node, a->node_count * sizeof *a->first_node);
        assert_memory_equal(a->first_leaf, b->first_leaf, a->node_count * sizeof *a->first_leaf);
        assert_memory_equal(a->child_mask, b->child_mask, a->node_count);
        assert_memory_equal(a->leaf_mask, b->leaf_mask, a->node_count);
    }
    assert_memory_equal(a->leaves, b->leaves, a->leaf_count * sizeof *a->leaves);
    for (uint32_t i = 0; i < a->leaf_count; i++) {
        assert_int_equal(a->leaf_keys[i].code, b->leaf_keys[i].code);
        assert_int_equal(a->leaf_keys[i].level, b->leaf_keys[i].level);
    }
}

/* Builds keys (sorted, compacted) with 1, 2, 4 threads and checks it all. */
static void build_and_check(const mr_svo_key *keys, size_t n, unsigned depth)
{
    mr_svo_leaf *leaves = calloc(n + 1, sizeof *leaves);
    assert_non_null(leaves);
    for (size_t i = 0; i < n; i++) {
        leaves[i].normal[0] = (uint8_t)(i * 7);
        leaves[i].normal[1] = (uint8_t)(i >> 8);
        leaves[i].attr = (uint16_t)(i % 3);
    }
    mr_svo svo[3];
    /* two threads first: a build's scratch is freed memory of the build
     * before it, and after a one-thread build of the same keys it would
     * already hold the values a missed write leaves unmade */
    const unsigned threads[3] = {2, 1, 4};
    mr_error err = {0};
    for (unsigned t = 0; t < 3; t++) {
        int rc = mr_svo_build(keys, leaves, n, depth, mr_v3(-1, -2, -3), 4.0f, palette3, 3, threads[t], &svo[t], &err);
        if (rc != MR_OK)
            fail_msg("build failed (depth %u, n %zu): %s", depth, n, err.msg);
    }
    const mr_svo *o = &svo[0];
    assert_int_equal(o->depth, depth);
    assert_int_equal(o->palette_count, 3);
    assert_memory_equal(o->palette, palette3, sizeof palette3);
    assert_true(o->size == 4.0f && o->origin.y == -2.0f);
    assert_int_equal(o->leaf_count, n);
    assert_int_equal(o->node_count, count_ancestors(keys, n, depth));
    if (n > 0)
        assert_non_null(o->leaf_keys);

    mr_svo_key *got = calloc(n + 1, sizeof *got);
    uint32_t *idx = calloc(n + 1, sizeof *idx);
    unsigned *visits = calloc(o->node_count + 1, sizeof *visits);
    assert_non_null(got);
    assert_non_null(idx);
    assert_non_null(visits);
    walk_state w = {o, visits, got, idx, 0, n};
    if (o->node_count > 0) {
        walk(&w, 0, 0, 0);
    } else if (n == 1) {
        got[0] = (mr_svo_key){0, 0}; /* root leaf */
        idx[0] = 0;
        w.n = 1;
    }
    assert_int_equal(w.n, n);
    for (uint32_t i = 0; i < o->node_count; i++)
        if (visits[i] != 1)
            fail_msg("node %u reached %u times", i, visits[i]);
    for (size_t i = 0; i < n; i++) {
        if (got[i].code != keys[i].code || got[i].level != keys[i].level)
            fail_msg("depth %u: leaf %zu is %#llx/%u, input %#llx/%u", depth, i, (unsigned long long)got[i].code,
                     got[i].level, (unsigned long long)keys[i].code, keys[i].level);
        assert_memory_equal(&o->leaves[idx[i]], &leaves[i], sizeof leaves[i]);
        assert_int_equal(o->leaf_keys[idx[i]].code, keys[i].code);
        assert_int_equal(o->leaf_keys[idx[i]].level, keys[i].level);
    }
    /* Leaves by (level, code); nodes breadth-first checked in walk(). */
    for (uint32_t i = 1; i < o->leaf_count; i++) {
        const mr_svo_key *a = &o->leaf_keys[i - 1], *b = &o->leaf_keys[i];
        assert_true(a->level < b->level || (a->level == b->level && a->code < b->code));
    }
    /* the library's own walk agrees */
    mr_svo_key *got2 = calloc(n + 1, sizeof *got2);
    uint32_t *idx2 = calloc(n + 1, sizeof *idx2);
    assert_int_equal(mr_svo_collect_keys(o, got2, idx2, &err), MR_OK);
    for (size_t i = 0; i < n; i++) {
        assert_int_equal(got2[i].code, got[i].code);
        assert_int_equal(got2[i].level, got[i].level);
        assert_int_equal(idx2[i], idx[i]);
    }
    same_svo(&svo[0], &svo[1]);
    same_svo(&svo[0], &svo[2]);
    assert_true(mr_svo_memory(o) >= (size_t)o->node_count * 10 + (size_t)o->leaf_count * 4);
    for (unsigned t = 0; t < 3; t++)
        mr_svo_free(&svo[t]);
    free(got);
    free(idx);
    free(got2);
    free(idx2);
    free(visits);
    free(leaves);
}

static void test_build_small_cases(void **state)
{
    (void)state;
    mr_svo svo;
    mr_error err = {0};
    /* empty */
    assert_int_equal(mr_svo_build(NULL, NULL, 0, 5, mr_v3(0, 0, 0), 1.0f, NULL, 0, 1, &svo, &err), MR_OK);
    assert_int_equal(svo.node_count, 0);
    assert_int_equal(svo.leaf_count, 0);
    assert_int_equal(mr_svo_collect_keys(&svo, NULL, NULL, &err), MR_OK);
    mr_svo_free(&svo);
    build_and_check(NULL, 0, 5);

    /* root leaf, depths 1 and 21 */
    mr_svo_key root = {0, 0};
    build_and_check(&root, 1, 1);
    build_and_check(&root, 1, 21);
    assert_int_equal(mr_svo_build(&root, NULL, 1, 4, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_OK);
    assert_int_equal(svo.node_count, 0);
    assert_int_equal(svo.leaf_count, 1);
    mr_svo_free(&svo);

    /* a single finest voxel: a chain of depth nodes */
    for (unsigned depth = 1; depth <= MR_SVO_MAX_DEPTH; depth++) {
        uint32_t m = (1u << depth) - 1u;
        mr_svo_key one = key_at(depth, depth, 5 & m, 3 & m, m);
        build_and_check(&one, 1, depth);
        assert_int_equal(mr_svo_build(&one, NULL, 1, depth, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_OK);
        assert_int_equal(svo.node_count, depth);
        mr_svo_free(&svo);
        /* a single coarse voxel */
        mr_svo_key coarse = key_at(depth, (depth + 1) / 2, 1, 0, 0);
        build_and_check(&coarse, 1, depth);
    }

    /* depth 1: all eight children, and three of them */
    mr_svo_key all8[8], three[3];
    for (unsigned c = 0; c < 8; c++)
        all8[c] = key_at(1, 1, c & 1, (c >> 1) & 1, c >> 2);
    build_and_check(all8, 8, 1);
    three[0] = all8[1];
    three[1] = all8[2];
    three[2] = all8[7];
    build_and_check(three, 3, 1);
    assert_int_equal(mr_svo_build(three, NULL, 3, 1, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_OK);
    assert_int_equal(svo.node_count, 1);
    assert_int_equal(svo.child_mask[0], 0x86);
    assert_int_equal(svo.leaf_mask[0], 0x86);
    assert_int_equal(svo.first_leaf[0], 0);
    mr_svo_free(&svo);

    /* mixed levels by hand, depth 3: a level-1 leaf next to finer ones */
    mr_svo_key mixed[] = {{0, 1}, {64, 3}, {72, 2}, {80, 3}, {448, 1}};
    build_and_check(mixed, 5, 3);
    assert_int_equal(mr_svo_build(mixed, NULL, 5, 3, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_OK);
    /* Root: children 0 and 7 leaves, 1 interior. Level-1 cell 1: children
     * 0 (cell 64, holding leaf 64/3), 1 (leaf 72/2), 2 (cell 80, holding leaf
     * 80/3). Leaves by (level, code): 0/1, 448/1, 72/2, 64/3, 80/3. */
    assert_int_equal(svo.node_count, 4);
    const uint8_t cm[4] = {0x83, 0x07, 0x01, 0x01}, lm[4] = {0x81, 0x02, 0x01, 0x01};
    const uint32_t fl[4] = {0, 2, 3, 4};
    for (unsigned i = 0; i < 4; i++) {
        assert_int_equal(svo.child_mask[i], cm[i]);
        assert_int_equal(svo.leaf_mask[i], lm[i]);
        assert_int_equal(svo.first_leaf[i], fl[i]);
    }
    assert_int_equal(svo.first_node[0], 1);
    assert_int_equal(svo.first_node[1], 2);
    const uint64_t leaf_codes[5] = {0, 448, 72, 64, 80};
    for (unsigned i = 0; i < 5; i++)
        assert_int_equal(svo.leaf_keys[i].code, leaf_codes[i]);
    mr_svo_free(&svo);
}

/* n random keys: one level (depth) or levels in [depth/2, depth]; sorted and
 * compacted (the build's precondition). */
static size_t random_keys(mr_svo_key *k, size_t n, unsigned depth, int mixed, uint64_t seed)
{
    uint64_t s = seed;
    for (size_t i = 0; i < n; i++) {
        unsigned level = mixed ? depth / 2 + (unsigned)(rng_next(&s) % (depth - depth / 2 + 1)) : depth;
        uint32_t m = (1u << level) - 1u;
        uint64_t r = rng_next(&s);
        /* cluster half of them so prefixes are shared as on a surface */
        uint32_t x = (uint32_t)r & m, y = (uint32_t)(r >> 21) & m, z = (uint32_t)(r >> 42) & m;
        if (i & 1) {
            x &= 0x7u | (m >> 3);
            y &= 0x7u;
        }
        k[i] = key_at(depth, level, x, y, z);
    }
    assert_int_equal(mr_svo_radix_sort(k, n, NULL, 2, NULL), MR_OK);
    size_t kept;
    assert_int_equal(mr_svo_compact(k, n, depth, NULL, &kept, NULL), MR_OK);
    return kept;
}

static void test_build_random(void **state)
{
    (void)state;
    const unsigned depths[] = {1, 2, 3, 5, 8, 12, 17, 21};
    const size_t sizes[] = {2, 17, 1000, 50000};
    mr_svo_key *k = malloc(50000 * sizeof *k);
    assert_non_null(k);
    for (unsigned d = 0; d < sizeof depths / sizeof depths[0]; d++)
        for (unsigned s = 0; s < sizeof sizes / sizeof sizes[0]; s++)
            for (int mixed = 0; mixed < 2; mixed++) {
                size_t n = random_keys(k, sizes[s], depths[d], mixed, 100 * d + 10 * s + (unsigned)mixed);
                build_and_check(k, n, depths[d]);
            }
    free(k);
}

/* Keys whose middle blocks lie wholly inside one cell: the build counts and
 * writes its keys a block at a time (MR_SVO_BUILD_BLOCK), and a block that
 * opens no cell at a level adds its keys to the last cell of the blocks
 * before it, after the loop. Keys in the level-4 cell (0, 0, 0), then
 * three blocks' worth inside cell (1, 1, 1) at levels 11 and 12, then keys
 * beyond it (Morton order: a level-4 cell with a coordinate >= 2 comes
 * after (1, 1, 1)): the cell's levels 0-4 are opened in the first block
 * and added to by two whole blocks after it, the last of them two blocks
 * away. */
static void test_build_blocks_in_one_cell(void **state)
{
    (void)state;
    const unsigned depth = 12;
    const size_t inside = 3 * MR_SVO_BUILD_BLOCK + 1000, n = inside + 64;
    mr_svo_key *k = malloc(n * sizeof *k);
    assert_non_null(k);
    uint64_t s = 7;
    size_t m = 0;
    for (unsigned i = 0; i < 32; i++) /* level-9 cells in level-4 cell (0, 0, 0): finest 0..255 */
        k[m++] = key_at(depth, 9, (uint32_t)(rng_next(&s) % 32), (uint32_t)(rng_next(&s) % 32),
                        (uint32_t)(rng_next(&s) % 32));
    for (unsigned i = 0; i < 32; i++) /* level-10 cells with finest x >= 512 */
        k[m++] = key_at(depth, 10, 128 + (uint32_t)(rng_next(&s) % 896), (uint32_t)(rng_next(&s) % 1024),
                        (uint32_t)(rng_next(&s) % 1024));
    for (size_t i = 0; i < inside; i++) { /* level-4 cell (1, 1, 1): finest 256..511 */
        const unsigned level = 11 + (unsigned)(rng_next(&s) % 2), sh = depth - level;
        const uint32_t lo = 256u >> sh, span = 256u >> sh;
        k[m++] = key_at(depth, level, lo + (uint32_t)(rng_next(&s) % span), lo + (uint32_t)(rng_next(&s) % span),
                        lo + (uint32_t)(rng_next(&s) % span));
    }
    assert_int_equal(mr_svo_radix_sort(k, m, NULL, 2, NULL), MR_OK);
    size_t kept;
    assert_int_equal(mr_svo_compact(k, m, depth, NULL, &kept, NULL), MR_OK);
    /* the sorted keys inside the cell, [first, end): blocks 1 and 2 within */
    const unsigned cell_shift = 3 * (depth - 4);
    size_t first = kept, end = 0;
    for (size_t i = 0; i < kept; i++)
        if (k[i].code >> cell_shift == 7u) { /* Morton index of (1, 1, 1) */
            first = i < first ? i : first;
            end = i + 1;
        }
    assert_true(first > 0 && first < MR_SVO_BUILD_BLOCK);
    assert_true(end >= 3 * MR_SVO_BUILD_BLOCK && end < kept);
    build_and_check(k, kept, depth);
    free(k);
}

static void expect_invalid(const mr_svo_key *k, const mr_svo_leaf *leaves, size_t n, unsigned depth,
                           float size, uint32_t palette_count, const char *what)
{
    mr_svo svo;
    mr_error err = {0};
    int rc = mr_svo_build(k, leaves, n, depth, mr_v3(0, 0, 0), size, palette3, palette_count, 2, &svo, &err);
    if (rc != MR_ERR_INVALID)
        fail_msg("%s: expected MR_ERR_INVALID, got %d", what, rc);
    assert_true(err.msg[0] != '\0');
    assert_null(svo.first_node);
    assert_null(svo.leaves);
    assert_int_equal(svo.node_count, 0);
}

static void test_build_invalid(void **state)
{
    (void)state;
    mr_svo_key unsorted[] = {{8, 3}, {0, 3}};
    mr_svo_key dup[] = {{8, 3}, {8, 3}};
    mr_svo_key nested[] = {{0, 1}, {8, 3}};
    mr_svo_key same_code[] = {{0, 1}, {0, 2}};
    mr_svo_key deep[] = {{0, 4}};
    mr_svo_key high[] = {{512, 3}};
    mr_svo_key misaligned[] = {{1, 2}};
    mr_svo_key fine[] = {{0, 3}, {1, 3}};
    expect_invalid(unsorted, NULL, 2, 3, 1.0f, 1, "unsorted");
    expect_invalid(dup, NULL, 2, 3, 1.0f, 1, "duplicate");
    expect_invalid(nested, NULL, 2, 3, 1.0f, 1, "nested");
    expect_invalid(same_code, NULL, 2, 3, 1.0f, 1, "nested, same code");
    expect_invalid(deep, NULL, 1, 3, 1.0f, 1, "level above depth");
    expect_invalid(high, NULL, 1, 3, 1.0f, 1, "code above 3 * depth bits");
    expect_invalid(misaligned, NULL, 1, 3, 1.0f, 1, "misaligned");
    expect_invalid(fine, NULL, 2, 0, 1.0f, 1, "depth 0");
    expect_invalid(fine, NULL, 2, 22, 1.0f, 1, "depth 22");
    expect_invalid(fine, NULL, 2, 3, 0.0f, 1, "size 0");
    expect_invalid(fine, NULL, 2, 3, NAN, 1, "size NaN");
    expect_invalid(fine, NULL, 2, 3, 1.0f, 0, "no palette");
    mr_svo_leaf bad_attr[2] = {{{0, 0}, 0}, {{0, 0}, 3}};
    expect_invalid(fine, bad_attr, 2, 3, 1.0f, 3, "attr beyond palette");
    /* the error names the offending key */
    mr_svo svo;
    mr_error err = {0};
    mr_svo_key third[] = {{0, 3}, {8, 3}, {8, 3}};
    assert_int_equal(mr_svo_build(third, NULL, 3, 3, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "key 2"));
}

/* A hand-broken octree is refused by the walk, not read out of bounds. */
static void test_collect_rejects_broken(void **state)
{
    (void)state;
    mr_svo_key k[] = {{0, 3}, {8, 3}, {64, 3}};
    mr_svo svo;
    mr_error err = {0};
    assert_int_equal(mr_svo_build(k, NULL, 3, 3, mr_v3(0, 0, 0), 1.0f, palette3, 1, 1, &svo, &err), MR_OK);
    svo.first_leaf[svo.node_count - 1] = svo.leaf_count;
    assert_int_equal(mr_svo_collect_keys(&svo, NULL, NULL, &err), MR_ERR_FORMAT);
    svo.first_leaf[svo.node_count - 1] = 0;
    svo.first_node[0] = 0; /* the root as its own child: a cycle */
    assert_int_equal(mr_svo_collect_keys(&svo, NULL, NULL, &err), MR_ERR_FORMAT);
    mr_svo_free(&svo);
}

/* ---- normals ---- */

static double angle_deg(mr_vec3 a, mr_vec3 b)
{
    double d = (double)a.x * b.x + (double)a.y * b.y + (double)a.z * b.z;
    double la = sqrt((double)a.x * a.x + (double)a.y * a.y + (double)a.z * a.z);
    double lb = sqrt((double)b.x * b.x + (double)b.y * b.y + (double)b.z * b.z);
    double c = d / (la * lb);
    c = c > 1.0 ? 1.0 : c < -1.0 ? -1.0 : c;
    return acos(c) * (180.0 / 3.14159265358979323846);
}

/* Tolerance: 0.7 degrees. 8-bit octahedral cells are 2/255 wide in the
 * square, and the square-to-sphere map stretches them by up to ~2 near the
 * octahedron's vertices; the best of the four codes around a direction was
 * measured at most 0.632 degrees off over these 2 M directions (printed
 * below), so 0.7 catches a regression to plain per-axis rounding (measured
 * 0.95 degrees worst) or a wrong fold (tens of degrees) without being flaky. Decoded
 * vectors are unit length to 1e-6 (one float normalisation). */
#define NORMAL_TOL_DEG 0.7
static void test_normals(void **state)
{
    (void)state;
    double worst = 0.0;
    uint64_t s = 11;
    mr_vec3 special[] = {
        {1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1},
        {1, 1, 1}, {-1, -1, -1}, {1, -1, -1}, {-1, 1, -1},
        /* around the -z seam, where the fold flips sign */
        {1e-6f, 0.3f, -0.95f}, {-1e-6f, 0.3f, -0.95f}, {0.3f, 1e-6f, -0.95f}, {0.3f, -1e-6f, -0.95f},
        {1e-6f, 1e-6f, -1}, {-1e-6f, -1e-6f, -1}, {0.7f, 0.7f, -0.1f}, {-0.7f, 0.7f, -1e-6f}, {0.5f, -0.5f, -0.7f},
    };
    const unsigned ns = sizeof special / sizeof special[0];
    for (unsigned i = 0; i < ns + 2000000; i++) {
        mr_vec3 n;
        if (i < ns) {
            n = special[i];
        } else {
            /* uniform on the sphere; every fourth one pushed into z < 0 near the seam */
            double z = 2.0 * rng_unit(&s) - 1.0, a = 2.0 * 3.14159265358979 * rng_unit(&s);
            double r = sqrt(1.0 - z * z);
            if ((i & 3) == 0) {
                z = -fabs(z);
                a = (double)(rng_next(&s) % 4) * 1.5707963267948966 + (rng_unit(&s) - 0.5) * 1e-3;
            }
            n = mr_v3((float)(r * cos(a)), (float)(r * sin(a)), (float)z);
        }
        uint8_t e[2];
        mr_svo_normal_encode(n, e);
        mr_vec3 d = mr_svo_normal_decode(e);
        double len = sqrt((double)d.x * d.x + (double)d.y * d.y + (double)d.z * d.z);
        assert_true(fabs(len - 1.0) < 1e-6);
        double ang = angle_deg(n, d);
        if (ang > worst)
            worst = ang;
        if (ang > NORMAL_TOL_DEG)
            fail_msg("normal (%g, %g, %g) decodes %g degrees off", n.x, n.y, n.z, ang);
        /* non-unit input encodes its direction */
        uint8_t e2[2];
        mr_svo_normal_encode(mr_v3_scale(n, 37.0f), e2);
        assert_true(angle_deg(n, mr_svo_normal_decode(e2)) <= NORMAL_TOL_DEG);
    }
    printf("normal encoding: worst error %.3f degrees over %u vectors\n", worst, ns + 2000000);
    const mr_vec3 bad[] = {{0, 0, 0}, {NAN, 0, 1}, {INFINITY, 0, 0}, {0, -INFINITY, 0}};
    for (unsigned i = 0; i < 4; i++) {
        uint8_t e[2];
        mr_svo_normal_encode(bad[i], e);
        assert_true(angle_deg(mr_svo_normal_decode(e), mr_v3(0, 0, 1)) <= NORMAL_TOL_DEG);
    }
}

/* All lanes at once give each lane the code it gets alone, whatever its
 * neighbours hold (non-finite, zero, huge, tiny, other hemispheres). */
static void test_normals_lanes(void **state)
{
    (void)state;
    uint64_t s = 29;
    const mr_vec3 odd[] = {{0, 0, 0}, {NAN, 0, 1}, {INFINITY, 0, 0}, {0, -INFINITY, 0}, {1e-30f, -1e-30f, 1e-30f},
                           {3e38f, 3e38f, -3e38f}, {-0.0f, -0.0f, -1}, {0, 0, -0.0f}};
    const unsigned nodd = sizeof odd / sizeof odd[0];
    for (unsigned round = 0; round < 200000; round++) {
        float x[MR_SVO_NORMAL_LANES], y[MR_SVO_NORMAL_LANES], z[MR_SVO_NORMAL_LANES];
        mr_vec3 n[MR_SVO_NORMAL_LANES];
        for (int k = 0; k < MR_SVO_NORMAL_LANES; k++) {
            if (rng_next(&s) % 8 == 0) {
                n[k] = odd[rng_next(&s) % nodd];
            } else {
                const double sc = pow(10.0, 6.0 * rng_unit(&s) - 3.0);
                n[k] = mr_v3((float)((2 * rng_unit(&s) - 1) * sc), (float)((2 * rng_unit(&s) - 1) * sc),
                             (float)((2 * rng_unit(&s) - 1) * sc));
            }
            x[k] = n[k].x;
            y[k] = n[k].y;
            z[k] = n[k].z;
        }
        uint8_t lanes[MR_SVO_NORMAL_LANES][2];
        mr_svo_normal_encode_lanes(MR_SVO_NORMAL_LANES, x, y, z, lanes);
        for (int k = 0; k < MR_SVO_NORMAL_LANES; k++) {
            uint8_t one[2];
            mr_svo_normal_encode(n[k], one);
            if (one[0] != lanes[k][0] || one[1] != lanes[k][1])
                fail_msg("lane %d of (%g, %g, %g): (%u, %u) alone, (%u, %u) among the lanes", k, n[k].x, n[k].y,
                         n[k].z, one[0], one[1], lanes[k][0], lanes[k][1]);
        }
    }
}

/* ---- timing ---- */

/* Surface voxels of a few spheres at depth 12 (shell of half-width 0.87
 * voxel around each radius), in shuffled order: ~10 M keys with the prefix
 * sharing of real surfaces, ~1 M by default; MR_SVO_TIMING_SCALE=1 gives the
 * ~10 M of a depth-12 character. It checks the large build completes with
 * every key a leaf; the times it prints are not asserted. */
static void test_build_timing(void **state)
{
    (void)state;
    const unsigned depth = 12;
    const double scale = getenv("MR_SVO_TIMING_SCALE") ? atof(getenv("MR_SVO_TIMING_SCALE")) : 0.1;
    const double radii[6] = {453, 323, 272, 194, 162, 104};
    const double cx[6] = {1000, 3000, 2000, 900, 3300, 2048}, cy[6] = {1000, 1100, 3000, 3100, 3000, 2048},
                 cz[6] = {1200, 2900, 2000, 3000, 1000, 2048};
    size_t cap = (size_t)(12e6 * scale) + 16, n = 0;
    mr_svo_key *k = malloc(cap * sizeof *k);
    uint32_t *pay = malloc(cap * sizeof *pay);
    assert_non_null(k);
    assert_non_null(pay);
    for (unsigned sp = 0; sp < 6 && n < cap; sp++) {
        double r = radii[sp] * sqrt(scale), ri = r - 0.87, ro = r + 0.87;
        for (int x = (int)(cx[sp] - ro); x <= (int)(cx[sp] + ro) && n < cap; x++)
            for (int y = (int)(cy[sp] - ro); y <= (int)(cy[sp] + ro) && n < cap; y++) {
                double dx = x + 0.5 - cx[sp], dy = y + 0.5 - cy[sp], d2 = dx * dx + dy * dy;
                if (d2 > ro * ro)
                    continue;
                double zo = sqrt(ro * ro - d2), zi = d2 < ri * ri ? sqrt(ri * ri - d2) : 0.0;
                /* the column's shell voxels: z - cz in [zi, zo] (upper) or [-zo, -zi] (lower) */
                for (int side = -1; side <= 1; side += 2) {
                    double za = side > 0 ? cz[sp] + zi : cz[sp] - zo, zb = side > 0 ? cz[sp] + zo : cz[sp] - zi;
                    for (int z = (int)floor(za - 0.5); z <= (int)ceil(zb); z++) {
                        double dz = z + 0.5 - cz[sp];
                        if ((side > 0) != (dz >= 0.0) || fabs(dz) < zi || fabs(dz) > zo || n >= cap)
                            continue;
                        k[n].code = mr_morton_encode((uint32_t)x, (uint32_t)y, (uint32_t)z);
                        k[n].level = depth;
                        pay[n] = (uint32_t)n;
                        n++;
                    }
                }
            }
    }
    /* shuffle: voxelizers emit keys in no useful order */
    uint64_t s = 1;
    for (size_t i = n; i > 1; i--) {
        size_t j = rng_next(&s) % i;
        mr_svo_key t = k[i - 1];
        k[i - 1] = k[j];
        k[j] = t;
    }
    mr_error err = {0};
    double t0 = mr_now();
    assert_int_equal(mr_svo_radix_sort_payload(k, pay, n, NULL, NULL, 0, &err), MR_OK);
    double t1 = mr_now();
    size_t kept;
    assert_int_equal(mr_svo_compact(k, n, depth, pay, &kept, &err), MR_OK);
    double t2 = mr_now();
    mr_svo svo;
    if (mr_svo_build(k, NULL, kept, depth, mr_v3(0, 0, 0), 1.0f, palette3, 1, 0, &svo, &err) != MR_OK)
        fail_msg("%s", err.msg);
    double t3 = mr_now();
    size_t bytes = mr_svo_memory(&svo);
    size_t keys_bytes = (size_t)svo.leaf_count * sizeof *svo.leaf_keys;
    printf("timing (depth %u, %zu keys, %zu unique, %u threads): sort %.0f ms, compact %.0f ms, build %.0f ms\n",
           depth, n, kept, 0u, 1e3 * (t1 - t0), 1e3 * (t2 - t1), 1e3 * (t3 - t2));
    printf("  %u nodes (%.3f per leaf), %.2f bytes/leaf (%.2f without leaf_keys)\n", svo.node_count,
           (double)svo.node_count / svo.leaf_count, (double)bytes / svo.leaf_count,
           (double)(bytes - keys_bytes) / svo.leaf_count);
    assert_int_equal(svo.leaf_count, kept);
    mr_svo_free(&svo);
    free(k);
    free(pay);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_compact_hand_made),
        cmocka_unit_test(test_compact_invalid),
        cmocka_unit_test(test_compact_random),
        cmocka_unit_test(test_build_small_cases),
        cmocka_unit_test(test_build_random),
        cmocka_unit_test(test_build_blocks_in_one_cell),
        cmocka_unit_test(test_build_invalid),
        cmocka_unit_test(test_collect_rejects_broken),
        cmocka_unit_test(test_normals),
        cmocka_unit_test(test_normals_lanes),
        cmocka_unit_test(test_build_timing),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
