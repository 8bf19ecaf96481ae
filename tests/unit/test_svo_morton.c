/*
 * test_svo_morton.c - Morton codes (morton.h) and the key radix sort
 * (radix_sort.h).
 *
 * Morton: known answers per axis and bit, round trips over the full 21-bit
 * range (edges, single bits, pseudo-random), child ordering, and a check that
 * the thesis' Fig. 31 decode (x shifted twice, REFERENCE.md) fails while
 * ours passes. Radix sort: against qsort by (code, level, input index) - the
 * stable order, so payloads must match too - for sizes 0, 1, 2, 1000, 10^6,
 * with duplicates, arbitrary 32-bit levels, caller scratch, and identical
 * output for 1, 2 and 7 threads. The 64-bit key sort: against qsort by
 * (key, input index) for arbitrary words, packed voxel keys, a single
 * varying bit and keys that are all equal, with and without unpacking, with
 * its own or the caller's histograms, on one block and on several (1, 2, 3
 * and 7 threads); and packed keys sorted and unpacked equal the 16-byte
 * sort of the same keys, payloads included. Everything is exact integer
 * comparison.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "util/morton.h"
#include "util/radix_sort.h"

static uint64_t rng_next(uint64_t *s)
{
    /* splitmix64: fixed seeds keep every run the same */
    uint64_t z = (*s += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

static void test_known_answers(void **state)
{
    (void)state;
    assert_int_equal(mr_morton_encode(0, 0, 0), 0);
    assert_int_equal(mr_morton_encode(1, 0, 0), 1);
    assert_int_equal(mr_morton_encode(0, 1, 0), 2);
    assert_int_equal(mr_morton_encode(0, 0, 1), 4);
    assert_int_equal(mr_morton_encode(MR_MORTON_MAX, MR_MORTON_MAX, MR_MORTON_MAX), (1ull << 63) - 1);
    for (unsigned b = 0; b < MR_MORTON_BITS; b++) {
        assert_int_equal(mr_morton_encode(1u << b, 0, 0), 1ull << (3 * b));
        assert_int_equal(mr_morton_encode(0, 1u << b, 0), 1ull << (3 * b + 1));
        assert_int_equal(mr_morton_encode(0, 0, 1u << b), 1ull << (3 * b + 2));
    }
    /* Bits above 21 are masked, not smeared into other axes. */
    assert_int_equal(mr_morton_encode(0xffe00000u | 5u, 1u << 21, 0x80000000u), mr_morton_encode(5, 0, 0));
    /* Code bit 63 is no coordinate bit. */
    uint32_t x, y, z;
    mr_morton_decode(1ull << 63, &x, &y, &z);
    assert_int_equal(x | y | z, 0);
}

/* Number of coordinate triples (from a fixed set) that decode(encode())
 * does not return, for the given decoder. */
typedef void (*decode_fn)(uint64_t, uint32_t *, uint32_t *, uint32_t *);

static unsigned round_trip_failures(decode_fn decode, unsigned randoms)
{
    unsigned bad = 0;
    uint32_t edges[3 + MR_MORTON_BITS] = {0, MR_MORTON_MAX, MR_MORTON_MAX - 1};
    for (unsigned b = 0; b < MR_MORTON_BITS; b++)
        edges[3 + b] = 1u << b;
    const unsigned ne = 3 + MR_MORTON_BITS;
    for (unsigned a = 0; a < ne; a++)
        for (unsigned b = 0; b < ne; b++)
            for (unsigned c = 0; c < ne; c++) {
                uint32_t x, y, z;
                decode(mr_morton_encode(edges[a], edges[b], edges[c]), &x, &y, &z);
                bad += x != edges[a] || y != edges[b] || z != edges[c];
            }
    uint64_t s = 42;
    for (unsigned i = 0; i < randoms; i++) {
        uint64_t r = rng_next(&s);
        uint32_t ix = (uint32_t)r & MR_MORTON_MAX, iy = (uint32_t)(r >> 21) & MR_MORTON_MAX,
                 iz = (uint32_t)(r >> 42) & MR_MORTON_MAX;
        uint32_t x, y, z;
        decode(mr_morton_encode(ix, iy, iz), &x, &y, &z);
        bad += x != ix || y != iy || z != iz;
    }
    return bad;
}

/* The thesis' Fig. 31 decode, transcribed (including its bug) only to show
 * that round_trip_failures catches it. */
static uint64_t fig31_contract(uint64_t x)
{
    x = (x >> 2) & 0x1249249249249249ull;
    x = (x | (x >> 2)) & 0x30c30c30c30c30c3ull;
    x = (x | (x >> 4)) & 0x700f00f00f00f00full;
    x = (x | (x >> 8)) & 0x00ff0000ff0000ffull;
    x = (x | (x >> 16)) & 0x7fff00000000ffffull;
    x = (x | (x >> 32)) & 0x00000000ffffffffull;
    return x;
}

static void fig31_decode(uint64_t code, uint32_t *x, uint32_t *y, uint32_t *z)
{
    *x = (uint32_t)fig31_contract(code >> 2);
    *y = (uint32_t)fig31_contract(code >> 1);
    *z = (uint32_t)fig31_contract(code >> 0);
}

static void test_round_trip(void **state)
{
    (void)state;
    assert_int_equal(round_trip_failures(mr_morton_decode, 2000000), 0);
    assert_true(round_trip_failures(fig31_decode, 1000) > 0);
    /* And the other way: every 63-bit code is some triple's code. */
    uint64_t s = 7;
    for (unsigned i = 0; i < 1000000; i++) {
        uint64_t code = rng_next(&s) >> 1;
        uint32_t x, y, z;
        mr_morton_decode(code, &x, &y, &z);
        assert_true(x <= MR_MORTON_MAX && y <= MR_MORTON_MAX && z <= MR_MORTON_MAX);
        assert_int_equal(mr_morton_encode(x, y, z), code);
    }
}

/* Child c = x + 2y + 4z of a cell: codes ordered by c, and every descendant
 * of child c below every descendant of child c + 1 (octree order). */
static void test_child_order(void **state)
{
    (void)state;
    uint64_t s = 3;
    for (unsigned i = 0; i < 100000; i++) {
        uint64_t r = rng_next(&s);
        unsigned level = (unsigned)(r % 20); /* parent level 0..19, children at level + 1 <= 20 */
        unsigned shift = MR_MORTON_BITS - level;
        uint32_t px = (uint32_t)(r >> 8) & ((1u << level) - 1u), py = (uint32_t)(r >> 29) & ((1u << level) - 1u),
                 pz = (uint32_t)(r >> 50) & ((1u << level) - 1u);
        uint64_t parent = mr_morton_encode(px << shift, py << shift, pz << shift);
        uint64_t span = 1ull << (3 * (shift - 1)); /* a child's code range */
        for (unsigned c = 0; c < 8; c++) {
            uint32_t cx = (px * 2 + (c & 1)) << (shift - 1), cy = (py * 2 + ((c >> 1) & 1)) << (shift - 1),
                     cz = (pz * 2 + (c >> 2)) << (shift - 1);
            uint64_t child = mr_morton_encode(cx, cy, cz);
            assert_int_equal(child, parent + c * span);
            /* the child's last finest descendant is still below the next child */
            uint32_t m = (1u << (shift - 1)) - 1u;
            assert_int_equal(mr_morton_encode(cx | m, cy | m, cz | m), parent + (c + 1) * span - 1);
        }
    }
}

/* ---- radix sort ---- */

typedef struct {
    mr_svo_key key;
    uint32_t index;
} ref_entry;

static int ref_cmp(const void *pa, const void *pb)
{
    const ref_entry *a = pa, *b = pb;
    if (a->key.code != b->key.code)
        return a->key.code < b->key.code ? -1 : 1;
    if (a->key.level != b->key.level)
        return a->key.level < b->key.level ? -1 : 1;
    return a->index < b->index ? -1 : a->index > b->index;
}

/* kind 0: depth-12-like codes with few levels and many duplicates; kind 1:
 * full 63-bit codes; kind 2: arbitrary 32-bit levels, few distinct codes. */
static void make_keys(mr_svo_key *k, size_t n, unsigned kind, uint64_t seed)
{
    uint64_t s = seed;
    for (size_t i = 0; i < n; i++) {
        uint64_t r = rng_next(&s);
        memset(&k[i], 0, sizeof k[i]);
        if (kind == 0) {
            k[i].code = (r & ((1ull << 36) - 1)) & ~0xfffull; /* duplicates: 2^24 distinct */
            if (n < 100000)
                k[i].code &= 0xfffffull << 12; /* more duplicates in small sets */
            k[i].level = 12 - (unsigned)((r >> 40) % 3);
        } else if (kind == 1) {
            k[i].code = r >> 1;
            k[i].level = (unsigned)(rng_next(&s) % 22);
        } else {
            k[i].code = (r % 5) << 60;
            k[i].level = (uint32_t)(r >> 20);
        }
    }
}

static void check_sorted_against_qsort(size_t n, unsigned kind, unsigned threads, int with_payload, int own_scratch)
{
    mr_svo_key *keys = calloc(n + 1, sizeof *keys);
    uint32_t *pay = calloc(n + 1, sizeof *pay);
    ref_entry *ref = calloc(n + 1, sizeof *ref);
    mr_svo_key *ks = own_scratch ? calloc(n + 1, sizeof *ks) : NULL;
    uint32_t *ps = own_scratch ? calloc(n + 1, sizeof *ps) : NULL;
    assert_non_null(keys);
    assert_non_null(pay);
    assert_non_null(ref);
    make_keys(keys, n, kind, 1000 + n + kind);
    for (size_t i = 0; i < n; i++) {
        pay[i] = (uint32_t)i;
        ref[i].key = keys[i];
        ref[i].index = (uint32_t)i;
    }
    qsort(ref, n, sizeof *ref, ref_cmp);
    mr_error err = {0};
    int rc = with_payload ? mr_svo_radix_sort_payload(keys, pay, n, ks, ps, threads, &err)
                          : mr_svo_radix_sort(keys, n, ks, threads, &err);
    assert_int_equal(rc, MR_OK);
    for (size_t i = 0; i < n; i++) {
        if (keys[i].code != ref[i].key.code || keys[i].level != ref[i].key.level)
            fail_msg("n=%zu kind=%u threads=%u: key %zu differs", n, kind, threads, i);
        if (with_payload && pay[i] != ref[i].index)
            fail_msg("n=%zu kind=%u threads=%u: payload %zu is %u, stable order says %u", n, kind, threads, i,
                     pay[i], ref[i].index);
    }
    free(keys);
    free(pay);
    free(ref);
    free(ks);
    free(ps);
}

static void test_sort_vs_qsort(void **state)
{
    (void)state;
    const size_t sizes[] = {0, 1, 2, 3, 1000, 70000};
    for (unsigned s = 0; s < sizeof sizes / sizeof sizes[0]; s++)
        for (unsigned kind = 0; kind < 3; kind++)
            for (unsigned t = 1; t <= 2; t++) {
                check_sorted_against_qsort(sizes[s], kind, t, 1, 0);
                check_sorted_against_qsort(sizes[s], kind, t, 0, 1);
            }
    check_sorted_against_qsort(1000000, 0, 2, 1, 0);
    check_sorted_against_qsort(1000000, 1, 2, 0, 1);
}

/* A key set with an odd number of non-constant digits (one code digit)
 * leaves the data in the scratch array; it must come back. */
static void test_sort_odd_passes(void **state)
{
    (void)state;
    mr_svo_key k[5] = {{7, 1}, {3, 1}, {1000, 1}, {3, 1}, {0, 1}};
    mr_svo_key scratch[5];
    uint32_t pay[5] = {0, 1, 2, 3, 4};
    assert_int_equal(mr_svo_radix_sort_payload(k, pay, 5, scratch, NULL, 1, NULL), MR_OK);
    const uint64_t want[5] = {0, 3, 3, 7, 1000};
    const uint32_t want_pay[5] = {4, 1, 3, 0, 2};
    for (unsigned i = 0; i < 5; i++) {
        assert_int_equal(k[i].code, want[i]);
        assert_int_equal(k[i].level, 1);
        assert_int_equal(pay[i], want_pay[i]);
    }
}

static void test_sort_thread_independent(void **state)
{
    (void)state;
    const size_t n = 1000000;
    const unsigned threads[3] = {1, 2, 7};
    mr_svo_key *k[3];
    uint32_t *p[3];
    for (unsigned t = 0; t < 3; t++) {
        k[t] = malloc(n * sizeof *k[t]);
        p[t] = malloc(n * sizeof *p[t]);
        assert_non_null(k[t]);
        assert_non_null(p[t]);
        make_keys(k[t], n, 0, 99);
        for (size_t i = 0; i < n; i++)
            p[t][i] = (uint32_t)i;
        assert_int_equal(mr_svo_radix_sort_payload(k[t], p[t], n, NULL, NULL, threads[t], NULL), MR_OK);
    }
    for (unsigned t = 1; t < 3; t++) {
        for (size_t i = 0; i < n; i++) {
            if (k[t][i].code != k[0][i].code || k[t][i].level != k[0][i].level || p[t][i] != p[0][i])
                fail_msg("threads %u differ from 1 thread at %zu", threads[t], i);
        }
    }
    for (unsigned t = 0; t < 3; t++) {
        free(k[t]);
        free(p[t]);
    }
}

/* ---- 64-bit keys -------------------------------------------------------- */

/* kind 0: arbitrary words; 1: packed voxel keys of a depth-12 octree with
 * three levels and many duplicates; 2: one varying bit (bit 61); 3: all
 * keys equal. */
static void make_u64(uint64_t *k, size_t n, unsigned kind, uint64_t seed)
{
    uint64_t s = seed;
    for (size_t i = 0; i < n; i++) {
        uint64_t r = rng_next(&s);
        if (kind == 0)
            k[i] = r;
        else if (kind == 1)
            k[i] = mr_svo_key_pack((r & ((1ull << 36) - 1)) & ~0xfffull, 12 - (unsigned)((r >> 40) % 3));
        else if (kind == 2)
            k[i] = 0x5ull | ((r & 1) << 61);
        else
            k[i] = 0x123456789ull;
    }
}

/* The reference is ref_cmp's stable order of (key as code, level 0). */
static void check_u64_against_qsort(size_t n, unsigned kind, unsigned threads, bool unpack, bool own_hist)
{
    void *mem[7] = {NULL};
    uint64_t *keys = mem[0] = calloc(n + 1, sizeof *keys);
    uint64_t *ks = mem[1] = calloc(n + 1, sizeof *ks);
    uint32_t *pay = mem[2] = calloc(n + 1, sizeof *pay);
    uint32_t *ps = mem[3] = calloc(n + 1, sizeof *ps);
    ref_entry *ref = mem[4] = calloc(n + 1, sizeof *ref);
    mr_svo_key *out = mem[5] = unpack ? calloc(n + 1, sizeof *out) : NULL;
    assert_true(keys && ks && pay && ps && ref && (!unpack || out));
    make_u64(keys, n, kind, 77 + n + kind);
    uint64_t bits_or = 0, bits_and = ~(uint64_t)0;
    for (size_t i = 0; i < n; i++) {
        pay[i] = (uint32_t)i;
        ref[i] = (ref_entry){{keys[i], 0}, (uint32_t)i};
        bits_or |= keys[i];
        bits_and &= keys[i];
    }
    qsort(ref, n, sizeof *ref, ref_cmp);
    mr_radix_u64 sort = {.keys = keys, .key_scratch = ks, .payload = pay, .payload_scratch = ps,
                         .count = n, .varying = bits_or ^ bits_and, .unpack = out,
                         .threads = threads};
    if (own_hist) {
        sort.hist = mem[6] = malloc((mr_radix_sort_u64_hist_words(&sort) + 1) * sizeof *sort.hist);
        assert_non_null(sort.hist);
    }
    mr_error err = {0};
    assert_int_equal(mr_radix_sort_u64(&sort, &err), MR_OK);
    assert_non_null(sort.sorted_payload);
    assert_true(unpack ? sort.sorted_keys == NULL : sort.sorted_keys != NULL);
    for (size_t i = 0; i < n; i++) {
        const uint64_t want = ref[i].key.code;
        bool same = unpack ? out[i].code == mr_svo_key_unpack(want).code &&
                                 out[i].level == mr_svo_key_unpack(want).level
                           : sort.sorted_keys[i] == want;
        if (!same || sort.sorted_payload[i] != ref[i].index)
            fail_msg("n=%zu kind=%u threads=%u unpack=%d: entry %zu (payload %u) differs from the stable "
                     "order (payload %u)", n, kind, threads, unpack, i, sort.sorted_payload[i], ref[i].index);
    }
    for (int k = 0; k < 7; k++)
        free(mem[k]);
}

static void test_u64_sort_vs_qsort(void **state)
{
    (void)state;
    const size_t sizes[] = {0, 1, 2, 3, 1000, 200000};
    const unsigned threads[] = {1, 2, 3, 7};
    for (unsigned s = 0; s < sizeof sizes / sizeof sizes[0]; s++)
        for (unsigned kind = 0; kind < 4; kind++)
            for (unsigned t = 0; t < sizeof threads / sizeof threads[0]; t++) {
                if (sizes[s] < 100000 && t > 1)
                    continue; /* one block either way */
                check_u64_against_qsort(sizes[s], kind, threads[t], false, t % 2 == 0);
                if (kind != 0) /* arbitrary words are no packed keys */
                    check_u64_against_qsort(sizes[s], kind, threads[t], true, t % 2 == 1);
            }
}

/* The per-frame resampling sorts packed keys below MR_SVO_KEY_PACK_MAX_DEPTH
 * and 16-byte keys beyond: both must give the same order. */
static void test_u64_sort_matches_key_sort(void **state)
{
    (void)state;
    const size_t n = 300000;
    void *mem[7];
    mr_svo_key *k = mem[0] = malloc(n * sizeof *k), *out = mem[1] = malloc(n * sizeof *out);
    uint64_t *pk = mem[2] = malloc(n * sizeof *pk), *pk2 = mem[3] = malloc(n * sizeof *pk2);
    uint32_t *pay = mem[4] = malloc(n * sizeof *pay), *pay2 = mem[5] = malloc(n * sizeof *pay2);
    uint32_t *kp = mem[6] = malloc(n * sizeof *kp);
    assert_true(k && out && pk && pk2 && pay && pay2 && kp);
    make_keys(k, n, 0, 5);
    uint64_t bits_or = 0, bits_and = ~(uint64_t)0;
    for (size_t i = 0; i < n; i++) {
        pk[i] = mr_svo_key_pack(k[i].code, k[i].level);
        bits_or |= pk[i];
        bits_and &= pk[i];
        pay[i] = kp[i] = (uint32_t)i;
    }
    mr_radix_u64 sort = {.keys = pk, .key_scratch = pk2, .payload = pay, .payload_scratch = pay2,
                         .count = n, .varying = bits_or ^ bits_and, .unpack = out, .threads = 2};
    assert_int_equal(mr_radix_sort_u64(&sort, NULL), MR_OK);
    assert_int_equal(mr_svo_radix_sort_payload(k, kp, n, NULL, NULL, 3, NULL), MR_OK);
    for (size_t i = 0; i < n; i++)
        if (out[i].code != k[i].code || out[i].level != k[i].level || sort.sorted_payload[i] != kp[i])
            fail_msg("packed and 16-byte sorts differ at %zu", i);
    for (int m = 0; m < 7; m++)
        free(mem[m]);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_known_answers),
        cmocka_unit_test(test_round_trip),
        cmocka_unit_test(test_child_order),
        cmocka_unit_test(test_sort_vs_qsort),
        cmocka_unit_test(test_sort_odd_passes),
        cmocka_unit_test(test_sort_thread_independent),
        cmocka_unit_test(test_u64_sort_vs_qsort),
        cmocka_unit_test(test_u64_sort_matches_key_sort),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
