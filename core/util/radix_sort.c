/*
 * radix_sort.c - stable LSD radix sort of mr_svo_key by (code, level), see
 * radix_sort.h.
 *
 * The 96-bit sort key (code high, level low) is cut into nine 11-bit digits,
 * least significant first: three of the level, six of the code. One reading
 * pass ORs and ANDs all keys; a digit where OR and AND agree is constant and
 * its pass is skipped (most often all levels are equal and the top code bits
 * are zero). Parallel passes split the array into one fixed contiguous block
 * per worker: each block counts its digits into its own histogram, the
 * offsets are the exclusive prefix over (digit, block), and each block
 * scatters its keys in input order, so the result is the stable order for
 * any block count.
 */
#include "util/radix_sort.h"

#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"

#ifndef DIGIT_BITS
#define DIGIT_BITS 11u
#endif
#define RADIX (1u << DIGIT_BITS)
#define LEVEL_PASSES ((32u + DIGIT_BITS - 1u) / DIGIT_BITS)
#define PASSES (LEVEL_PASSES + (64u + DIGIT_BITS - 1u) / DIGIT_BITS)
/* Below this many keys per worker, threads cost more than they save. */
#define MIN_PER_BLOCK 32768u
#define MAX_BLOCKS 64u

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

static void block_range(const sort_ctx *c, size_t b, size_t *begin, size_t *end)
{
    *begin = c->count * b / c->blocks;
    *end = c->count * (b + 1) / c->blocks;
}

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
        block_range(c, b, &lo, &hi);
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
        block_range(c, b, &lo, &hi);
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
        block_range(c, b, &lo, &hi);
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
        block_range(c, b, &lo, &hi);
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
    size_t blocks = count / MIN_PER_BLOCK;
    if (blocks > threads)
        blocks = threads;
    if (blocks > MAX_BLOCKS)
        blocks = MAX_BLOCKS;
    if (blocks == 0)
        blocks = 1;
    /* Counts and offsets are 32-bit (payloads index keys with 32 bits too). */
    if (count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_LIMIT, "radix sort: %zu keys exceed 2^32 - 1", count);

    if (!key_scratch) {
        own_k = malloc(count * sizeof *own_k);
        if (!own_k) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "radix sort: no memory for %zu scratch keys", count);
            goto cleanup;
        }
        key_scratch = own_k;
    }
    if (payload && !payload_scratch) {
        own_p = malloc(count * sizeof *own_p);
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
        uint32_t run = 0;
        for (unsigned d = 0; d < RADIX; d++) {
            for (size_t b = 0; b < blocks; b++) {
                uint32_t n = hist[b * RADIX + d];
                hist[b * RADIX + d] = run;
                run += n;
            }
        }
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
