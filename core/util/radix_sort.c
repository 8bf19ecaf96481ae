/*
 * radix_sort.c - stable LSD radix sorts of voxel keys (radix_sort.h).
 *
 * One scheme for both layouts. Parallel passes split the array into one
 * fixed contiguous block per worker: each block counts its digits into its
 * own histogram, the offsets are the exclusive prefix over (digit, block),
 * and each block scatters its keys in input order, so the result is the
 * stable order for any block count. A pass whose digit is the same for
 * every key would not move anything and is skipped.
 *
 * 16-byte keys: the 96-bit sort key (code high, level low) is cut into nine
 * 11-bit digits, least significant first: three of the level, six of the
 * code. One reading pass ORs and ANDs all keys; a digit where OR and AND
 * agree is constant (most often all levels are equal and the top code bits
 * are zero).
 *
 * 64-bit keys: the caller names the varying bits; the passes cover them
 * from the lowest to the highest in equal digits of at most U64_MAX_BITS.
 * With a single block every pass's digits are counted in one read (no pass
 * changes the whole array's counts); with several, each pass counts its
 * own input. The last pass may write mr_svo_keys (unpack) instead of words.
 */
#include "util/radix_sort.h"

#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"
#include "util/large_alloc.h"

#ifndef DIGIT_BITS
#define DIGIT_BITS 11u
#endif
#define RADIX (1u << DIGIT_BITS)
#define LEVEL_PASSES ((32u + DIGIT_BITS - 1u) / DIGIT_BITS)
#define PASSES (LEVEL_PASSES + (64u + DIGIT_BITS - 1u) / DIGIT_BITS)
/* Below this many keys per worker, threads cost more than they save. */
#define MIN_PER_BLOCK 32768u
#define MAX_BLOCKS 64u
/* Digits of the 64-bit sort: 2^10 buckets of 8 + 4 bytes stay in L2. */
#define U64_MAX_BITS 10u

/* ---- shared by both layouts ------------------------------------------- */

/* Blocks (workers) for count keys on `threads` (0 = all cores). */
static size_t block_count(size_t count, unsigned threads)
{
    if (threads == 0)
        threads = mr_cpu_count();
    size_t blocks = count / MIN_PER_BLOCK;
    if (blocks > threads)
        blocks = threads;
    if (blocks > MAX_BLOCKS)
        blocks = MAX_BLOCKS;
    return blocks == 0 ? 1 : blocks;
}

static void block_range(size_t count, size_t blocks, size_t b, size_t *begin, size_t *end)
{
    *begin = count * b / blocks;
    *end = count * (b + 1) / blocks;
}

/* Turns digit counts into scatter offsets: the exclusive prefix over
 * (digit, block), block b's counts at h + b * stride. */
static void counts_to_offsets(uint32_t *h, size_t radix, size_t blocks, size_t stride)
{
    uint32_t run = 0;
    for (size_t d = 0; d < radix; d++) {
        for (size_t b = 0; b < blocks; b++) {
            const uint32_t n = h[b * stride + d];
            h[b * stride + d] = run;
            run += n;
        }
    }
}

/* ---- 16-byte keys --------------------------------------------------------- */

typedef struct {
    mr_svo_key *src_k, *dst_k;
    uint32_t *src_p, *dst_p;
    size_t count;
    unsigned blocks;
    unsigned pass;        /* level digits first, then code digits */
    uint32_t *hist;       /* blocks * RADIX counts, then offsets */
    uint64_t *or_code, *and_code; /* per block */
    uint32_t *or_level, *and_level;
} sort_ctx;

static inline uint32_t digit_of(const mr_svo_key *k, unsigned pass)
{
    if (pass < LEVEL_PASSES)
        return (uint32_t)(k->level >> (pass * DIGIT_BITS)) & (RADIX - 1);
    return (uint32_t)(k->code >> ((pass - LEVEL_PASSES) * DIGIT_BITS)) & (RADIX - 1);
}

static void reduce_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sort_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, c->blocks, b, &lo, &hi);
        uint64_t oc = 0, ac = ~(uint64_t)0;
        uint32_t ol = 0, al = ~(uint32_t)0;
        for (size_t i = lo; i < hi; i++) {
            oc |= c->src_k[i].code;
            ac &= c->src_k[i].code;
            ol |= c->src_k[i].level;
            al &= c->src_k[i].level;
        }
        c->or_code[b] = oc;
        c->and_code[b] = ac;
        c->or_level[b] = ol;
        c->and_level[b] = al;
    }
}

static void count_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sort_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, c->blocks, b, &lo, &hi);
        uint32_t *h = c->hist + b * RADIX;
        memset(h, 0, RADIX * sizeof *h);
        const unsigned pass = c->pass;
        for (size_t i = lo; i < hi; i++)
            h[digit_of(&c->src_k[i], pass)]++;
    }
}

static void scatter_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sort_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, c->blocks, b, &lo, &hi);
        uint32_t *off = c->hist + b * RADIX;
        const unsigned pass = c->pass;
        if (c->src_p) {
            for (size_t i = lo; i < hi; i++) {
                uint32_t at = off[digit_of(&c->src_k[i], pass)]++;
                c->dst_k[at] = c->src_k[i];
                c->dst_p[at] = c->src_p[i];
            }
        } else {
            for (size_t i = lo; i < hi; i++)
                c->dst_k[off[digit_of(&c->src_k[i], pass)]++] = c->src_k[i];
        }
    }
}

static void copy_fn(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sort_ctx *c = vctx;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, c->blocks, b, &lo, &hi);
        memcpy(c->dst_k + lo, c->src_k + lo, (hi - lo) * sizeof *c->dst_k);
        if (c->src_p)
            memcpy(c->dst_p + lo, c->src_p + lo, (hi - lo) * sizeof *c->dst_p);
    }
}

int mr_svo_radix_sort(mr_svo_key *keys, size_t count, mr_svo_key *key_scratch,
                      unsigned threads, mr_error *err)
{
    return mr_svo_radix_sort_payload(keys, NULL, count, key_scratch, NULL, threads, err);
}

int mr_svo_radix_sort_payload(mr_svo_key *keys, uint32_t *payload, size_t count,
                              mr_svo_key *key_scratch, uint32_t *payload_scratch,
                              unsigned threads, mr_error *err)
{
    int rc = MR_OK;
    mr_svo_key *own_k = NULL;
    uint32_t *own_p = NULL, *hist = NULL;
    uint64_t *codes = NULL;
    uint32_t *levels = NULL;

    if (count < 2)
        return MR_OK;
    if (!keys)
        return mr_error_set(err, MR_ERR_INVALID, "radix sort: keys is NULL");
    if (threads == 0)
        threads = mr_cpu_count();
    const size_t blocks = block_count(count, threads);
    /* Counts and offsets are 32-bit (payloads index keys with 32 bits too). */
    if (count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "radix sort: %zu keys exceed 2^32 - 1", count);

    if (!key_scratch) {
        own_k = mr_large_alloc(count * sizeof *own_k);
        if (!own_k) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "radix sort: no memory for %zu scratch keys", count);
            goto cleanup;
        }
        key_scratch = own_k;
    }
    if (payload && !payload_scratch) {
        own_p = mr_large_alloc(count * sizeof *own_p);
        if (!own_p) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "radix sort: no memory for %zu scratch payloads", count);
            goto cleanup;
        }
        payload_scratch = own_p;
    }
    hist = malloc(blocks * RADIX * sizeof *hist);
    codes = malloc(2 * blocks * sizeof *codes);
    levels = malloc(2 * blocks * sizeof *levels);
    if (!hist || !codes || !levels) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "radix sort: no memory for histograms");
        goto cleanup;
    }

    sort_ctx c = {.src_k = keys, .dst_k = key_scratch, .src_p = payload,
                  .dst_p = payload ? payload_scratch : NULL, .count = count,
                  .blocks = (unsigned)blocks, .hist = hist,
                  .or_code = codes, .and_code = codes + blocks,
                  .or_level = levels, .and_level = levels + blocks};
    mr_parallel_for(threads, blocks, 1, reduce_fn, &c);
    uint64_t oc = 0, ac = ~(uint64_t)0;
    uint32_t ol = 0, al = ~(uint32_t)0;
    for (size_t b = 0; b < blocks; b++) {
        oc |= c.or_code[b];
        ac &= c.and_code[b];
        ol |= c.or_level[b];
        al &= c.and_level[b];
    }
    const uint64_t varying_code = oc ^ ac;
    const uint32_t varying_level = ol ^ al;

    for (unsigned pass = 0; pass < PASSES; pass++) {
        uint64_t varying = pass < LEVEL_PASSES ? (uint64_t)(varying_level >> (pass * DIGIT_BITS))
                                               : varying_code >> ((pass - LEVEL_PASSES) * DIGIT_BITS);
        if ((varying & (RADIX - 1)) == 0)
            continue; /* every key has the same digit: the pass would not move anything */
        c.pass = pass;
        mr_parallel_for(threads, blocks, 1, count_fn, &c);
        counts_to_offsets(hist, RADIX, blocks, RADIX);
        mr_parallel_for(threads, blocks, 1, scatter_fn, &c);
        mr_svo_key *tk = c.src_k;
        c.src_k = c.dst_k;
        c.dst_k = tk;
        uint32_t *tp = c.src_p;
        c.src_p = c.dst_p;
        c.dst_p = tp;
    }
    if (c.src_k != keys) {
        /* An odd number of passes ran: the result is in the scratch arrays. */
        c.dst_k = keys;
        c.dst_p = payload;
        mr_parallel_for(threads, blocks, 1, copy_fn, &c);
    }

cleanup:
    free(own_k);
    free(own_p);
    free(hist);
    free(codes);
    free(levels);
    return rc;
}

/* ---- 64-bit keys ---------------------------------------------------------- */

typedef struct {
    size_t blocks;
    unsigned passes, shift, bits; /* digit p is bits [shift + p * bits, + bits) */
    size_t radix;                 /* 2^bits */
    bool count_once;              /* one block: all passes counted in one read */
    size_t hist_words;
} u64_plan;

static u64_plan u64_plan_of(const mr_radix_u64 *s)
{
    u64_plan p = {.blocks = block_count(s->count, s->threads)};
    if (s->varying != 0) {
        const unsigned lo = (unsigned)__builtin_ctzll(s->varying);
        const unsigned hi = 64u - (unsigned)__builtin_clzll(s->varying);
        p.passes = (hi - lo + U64_MAX_BITS - 1) / U64_MAX_BITS;
        p.bits = (hi - lo + p.passes - 1) / p.passes;
        p.shift = lo;
    } else if (s->unpack) {
        /* one pass on a constant digit: a stable copy that unpacks */
        p.passes = 1;
        p.bits = 1;
        p.shift = 0;
    }
    p.radix = (size_t)1 << p.bits;
    p.count_once = p.blocks == 1;
    if (p.passes)
        p.hist_words = p.blocks * p.radix * (p.count_once ? p.passes : 1);
    return p;
}

size_t mr_radix_sort_u64_hist_words(const mr_radix_u64 *s)
{
    return s ? u64_plan_of(s).hist_words : 0;
}

typedef struct {
    u64_plan plan;
    uint64_t *key[2];   /* the caller's keys and scratch */
    uint32_t *pay[2];   /* the caller's payload and scratch */
    unsigned from;      /* this pass reads key[from], pay[from], writes the others */
    mr_svo_key *unpack;
    size_t count;
    unsigned pass;
    uint32_t *hist; /* blocks * radix counts (count_once: radix per pass, one block) */
} u64_ctx;

/* Block b's counts of pass q: with count_once every block holds all passes. */
static uint32_t *u64_hist(const u64_ctx *c, size_t b, unsigned q)
{
    const u64_plan *p = &c->plan;
    return p->count_once ? c->hist + (b * p->passes + q) * p->radix : c->hist + b * p->radix;
}

static void u64_count(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    u64_ctx *c = vctx;
    const u64_plan *p = &c->plan;
    const unsigned first = p->count_once ? 0 : c->pass, last = p->count_once ? p->passes - 1 : c->pass;
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, p->blocks, b, &lo, &hi);
        for (unsigned q = first; q <= last; q++) {
            uint32_t *h = u64_hist(c, b, q);
            memset(h, 0, p->radix * sizeof *h);
            const unsigned sh = p->shift + q * p->bits;
            const uint64_t *src = c->key[c->from], mask = p->radix - 1;
            for (size_t i = lo; i < hi; i++)
                h[(src[i] >> sh) & mask]++;
        }
    }
}

static void u64_scatter(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    u64_ctx *c = vctx;
    const unsigned sh = c->plan.shift + c->pass * c->plan.bits;
    const uint64_t mask = c->plan.radix - 1;
    const bool unpack = c->unpack && c->pass + 1 == c->plan.passes;
    const uint64_t *src = c->key[c->from];
    const uint32_t *src_p = c->pay[c->from];
    uint64_t *dst = c->key[c->from ^ 1];
    uint32_t *dst_p = c->pay[c->from ^ 1];
    for (size_t b = begin; b < end; b++) {
        size_t lo, hi;
        block_range(c->count, c->plan.blocks, b, &lo, &hi);
        uint32_t *off = u64_hist(c, b, c->pass);
        if (unpack) {
            for (size_t i = lo; i < hi; i++) {
                const uint64_t k = src[i];
                const uint32_t at = off[(k >> sh) & mask]++;
                c->unpack[at] = mr_svo_key_unpack(k);
                dst_p[at] = src_p[i];
            }
        } else {
            for (size_t i = lo; i < hi; i++) {
                const uint64_t k = src[i];
                const uint32_t at = off[(k >> sh) & mask]++;
                dst[at] = k;
                dst_p[at] = src_p[i];
            }
        }
    }
}

int mr_radix_sort_u64(mr_radix_u64 *s, mr_error *err)
{
    if (!s)
        return mr_error_set(err, MR_ERR_INVALID, "radix sort: no sort given");
    s->sorted_keys = s->keys;
    s->sorted_payload = s->payload;
    if (s->count > 0 && (!s->keys || !s->key_scratch || !s->payload || !s->payload_scratch))
        return mr_error_set(err, MR_ERR_INVALID, "radix sort: key or payload arrays missing");
    /* Counts and offsets are 32-bit (payloads index keys with 32 bits too). */
    if (s->count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "radix sort: %zu keys exceed 2^32 - 1", s->count);
    u64_ctx c = {.plan = u64_plan_of(s), .key = {s->keys, s->key_scratch},
                 .pay = {s->payload, s->payload_scratch}, .unpack = s->unpack,
                 .count = s->count, .hist = s->hist};
    const u64_plan *p = &c.plan;
    if (p->passes == 0)
        return MR_OK; /* nothing varies and nothing to unpack: sorted as it is */
    uint32_t *own = NULL;
    if (!c.hist) {
        c.hist = own = malloc(p->hist_words * sizeof *own);
        if (!own)
            return mr_error_set(err, MR_ERR_NOMEM, "radix sort: no memory for histograms");
    }
    const unsigned threads = s->threads ? s->threads : mr_cpu_count();
    if (p->count_once)
        u64_count(&c, 0, 1, 0);
    for (unsigned q = 0; q < p->passes; q++) {
        c.pass = q;
        if (!p->count_once)
            mr_parallel_for(threads, p->blocks, 1, u64_count, &c);
        /* one block with count_once: the blocks' stride does not matter */
        counts_to_offsets(u64_hist(&c, 0, q), p->radix, p->blocks, p->radix);
        mr_parallel_for(threads, p->blocks, 1, u64_scatter, &c);
        c.from ^= 1;
    }
    s->sorted_keys = s->unpack ? NULL : c.key[c.from];
    s->sorted_payload = c.pay[c.from];
    free(own);
    return MR_OK;
}
