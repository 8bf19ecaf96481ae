/*
 * test_deflate.c - util/deflate.h, microray's zlib-format compressor for
 * EXR chunks. Every stream is inflated by an independent decoder
 * (libdeflate's, strict about the format: a wrong code, length, distance
 * or checksum is an error) and must give back the input byte for byte:
 *  - edge lengths (0, 1, 2, 3, around 8 and 258, a window and more);
 *  - content of every kind the encoder treats differently: runs of one
 *    value and of 2- and 4-byte patterns, rows repeating at the row
 *    distance, random bytes, text-like bytes (repeats at no candidate
 *    distance: literals and short runs), matches at
 *    exactly the 32 KiB window and just beyond it, long inputs that take
 *    many blocks, and skewed (Fibonacci) symbol counts; the length limit
 *    of the codes (halving counts until the deepest code fits) runs for
 *    the code-length code (7 bits) on most random and pattern inputs here
 *    (seen with a counter while writing this test);
 *  - every row distance (none, small ones equal to the fixed ones, beyond
 *    the window);
 *  - capacity: the exact size fits, a byte less gives 0 and no byte past
 *    the capacity is touched;
 *  - determinism: the same bytes from a fresh and a reused compressor.
 * And on the example's kind of data (mostly runs) it must beat a stored
 * stream by far: a check that the matcher works, not a size goal.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <libdeflate.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "microray.h"
#include "util/deflate.h"
#include "../support/rng_fixture.h"

#define GUARD 64

static mr_deflate *g_def;

/* Compresses in[0, n) with the given row, checks the stream inflates to
 * the input, that the exact size fits and one byte less does not, and
 * that nothing past the capacity is written. Returns the stream size. */
static size_t check_roundtrip(const uint8_t *in, size_t n, size_t row, const char *what)
{
    size_t cap = n + n / 8 + 1024, got, again, got_n = 0;
    uint8_t *out = malloc(cap + GUARD), *back = malloc(n ? n : 1), *tight;
    struct libdeflate_decompressor *dec = libdeflate_alloc_decompressor();
    mr_deflate *fresh = mr_deflate_new();
    enum libdeflate_result rv;

    assert_non_null(out);
    assert_non_null(back);
    assert_non_null(dec);
    assert_non_null(fresh);
    got = mr_deflate_zlib(g_def, in, n, row, out, cap);
    if (got == 0)
        fail_msg("%s (n=%zu row=%zu): no stream in %zu bytes", what, n, row, cap);
    rv = libdeflate_zlib_decompress(dec, out, got, back, n, &got_n);
    if (rv != LIBDEFLATE_SUCCESS || got_n != n || (n && memcmp(back, in, n) != 0))
        fail_msg("%s (n=%zu row=%zu): inflates to something else (result %d, %zu bytes)",
                 what, n, row, (int)rv, got_n);

    /* The same bytes from a fresh compressor and into exactly got bytes;
     * got - 1 bytes are too few, and the guard past them stays intact. */
    tight = malloc(got + GUARD);
    assert_non_null(tight);
    memset(tight, 0xA5, got + GUARD);
    again = mr_deflate_zlib(fresh, in, n, row, tight, got);
    if (again != got || memcmp(tight, out, got) != 0)
        fail_msg("%s (n=%zu row=%zu): a fresh compressor or an exact capacity changed the "
                 "stream", what, n, row);
    memset(tight, 0xA5, got + GUARD);
    assert_int_equal(mr_deflate_zlib(g_def, in, n, row, tight, got - 1), 0);
    for (size_t i = got - 1; i < got + GUARD; i++)
        if (tight[i] != 0xA5)
            fail_msg("%s (n=%zu row=%zu): byte %zu written past a capacity of %zu", what, n,
                     row, i, got - 1);

    free(tight);
    mr_deflate_free(fresh);
    libdeflate_free_decompressor(dec);
    free(back);
    free(out);
    return got;
}

/* Content generators: each fills n bytes from seed s. */
static void fill_random(uint8_t *p, size_t n, uint64_t s)
{
    for (size_t i = 0; i < n; i++)
        p[i] = (uint8_t)rnd(&s);
}

static void fill_runs(uint8_t *p, size_t n, uint64_t s)
{
    for (size_t i = 0; i < n;) {
        size_t len = 1 + rnd(&s) % 700;
        uint8_t v = (uint8_t)rnd(&s);
        for (size_t k = 0; k < len && i < n; k++)
            p[i++] = v;
    }
}

/* Runs of 2- and 4-byte patterns (a float's even bytes, say) broken by
 * short random stretches. */
static void fill_patterns(uint8_t *p, size_t n, uint64_t s)
{
    for (size_t i = 0; i < n;) {
        size_t period = (rnd(&s) % 2) ? 2 : 4, len = rnd(&s) % 1200;
        uint8_t pat[4];
        for (int k = 0; k < 4; k++)
            pat[k] = (uint8_t)rnd(&s);
        for (size_t k = 0; k < len && i < n; k++)
            p[i++] = pat[k % period];
        for (size_t k = rnd(&s) % 9; k > 0 && i < n; k--)
            p[i++] = (uint8_t)rnd(&s);
    }
}

/* An image of width `row`: each row the one above with a few changes. */
static void fill_rows(uint8_t *p, size_t n, size_t row, uint64_t s)
{
    for (size_t i = 0; i < n; i++) {
        if (i < row || rnd(&s) % 23 == 0)
            p[i] = (uint8_t)rnd(&s);
        else
            p[i] = p[i - row];
    }
}

/* Words from a small vocabulary: repeats at arbitrary distances, none of
 * them a candidate's. */
static void fill_words(uint8_t *p, size_t n, uint64_t s)
{
    static const char *words[] = {"microray ", "render ", "frame ", "chunk ", "deflate ",
                                  "EXR ",      "zlib ",   "a ",     "of ",    "pixels "};
    for (size_t i = 0; i < n;) {
        const char *w = words[rnd(&s) % 10];
        for (size_t k = 0; w[k] && i < n; k++)
            p[i++] = (uint8_t)w[k];
    }
}

static void test_edge_lengths(void **state)
{
    static const size_t lens[] = {0, 1, 2, 3, 4, 5, 7, 8, 9, 15, 16, 17, 255, 256, 257, 258,
                                  259, 260, 515, 516, 517, 1000, 32767, 32768, 32769, 70001};
    (void)state;
    uint8_t *buf = malloc(70001);
    assert_non_null(buf);
    for (size_t i = 0; i < sizeof lens / sizeof lens[0]; i++) {
        size_t n = lens[i];
        memset(buf, 'x', n);
        check_roundtrip(buf, n, 0, "one value");
        fill_random(buf, n, 1 + n);
        check_roundtrip(buf, n, 0, "random");
        fill_patterns(buf, n, 7 + n);
        check_roundtrip(buf, n, 5, "patterns");
    }
    free(buf);
}

static void test_content_and_rows(void **state)
{
    static const size_t rows[] = {0, 1, 2, 3, 4, 5, 100, 960, 15360, 32768, 32769, 1u << 20};
    const size_t n = 200000;
    (void)state;
    uint8_t *buf = malloc(n);
    assert_non_null(buf);
    for (size_t r = 0; r < sizeof rows / sizeof rows[0]; r++) {
        size_t row = rows[r];
        uint64_t seed = 100 + r;
        fill_runs(buf, n, seed);
        check_roundtrip(buf, n, row, "runs");
        fill_patterns(buf, n, seed);
        check_roundtrip(buf, n, row, "patterns");
        fill_rows(buf, n, row ? row : 77, seed);
        check_roundtrip(buf, n, row, "rows");
        fill_words(buf, n, seed);
        check_roundtrip(buf, n, row, "words");
        fill_random(buf, n, seed);
        check_roundtrip(buf, n, row, "random");
    }
    free(buf);
}

/* Repeats 32767 and 32768 bytes back (the farthest deflate reaches) and
 * 32769 and 32770 back (beyond it: must not be matched there). */
static void test_window_edge(void **state)
{
    const size_t n = 3 * 32768 + 500;
    (void)state;
    uint8_t *buf = malloc(n);
    assert_non_null(buf);
    for (size_t far = 32767; far <= 32770; far++) {
        fill_random(buf, far, far);
        for (size_t i = far; i < n; i++)
            buf[i] = buf[i - far];
        check_roundtrip(buf, n, 0, "window edge");
        /* As the row distance it is tried everywhere: found in reach. */
        size_t got = check_roundtrip(buf, n, far, "window edge, as the row");
        if (far <= 32768 && got > n / 2)
            fail_msg("a repeat %zu bytes back was not found (%zu bytes)", far, got);
    }
    free(buf);
}

/* Many blocks (more tokens than MR_DEFLATE_BLOCK), and symbol counts in
 * Fibonacci proportions (Huffman's worst case for code depth). */
static void test_blocks_and_deep_codes(void **state)
{
    (void)state;
    size_t n = 4 * MR_DEFLATE_BLOCK + 1234;
    uint8_t *buf = malloc(600000);
    assert_non_null(buf);
    fill_random(buf, n, 99);
    check_roundtrip(buf, n, 0, "random, many blocks");

    {
        /* Odd bytes: 18 symbols, symbol i fib(i) times (1, 1, 2, 3, 5, ...,
         * 2584), shuffled; even bytes random from another range, so that
         * nearly everything is a literal, in one block. */
        uint64_t s = 5;
        size_t fib[18], total = 0, i, k;
        fib[0] = fib[1] = 1;
        for (i = 2; i < 18; i++)
            fib[i] = fib[i - 1] + fib[i - 2];
        for (i = 0; i < 18; i++)
            for (k = 0; k < fib[i]; k++)
                buf[2 * total++ + 1] = (uint8_t)i;
        for (i = total - 1; i > 0; i--) {
            size_t j = rnd(&s) % (i + 1);
            uint8_t t = buf[2 * i + 1];
            buf[2 * i + 1] = buf[2 * j + 1];
            buf[2 * j + 1] = t;
        }
        for (i = 0; i < total; i++)
            buf[2 * i] = (uint8_t)(128 + rnd(&s) % 128);
        assert_true(2 * total < MR_DEFLATE_BLOCK);
        check_roundtrip(buf, 2 * total, 0, "Fibonacci symbol counts");
    }
    free(buf);
}

/* The example's kind of content: after the ZIP predictor, background is
 * runs of 0x80 and of 2-byte patterns, one row like the next. */
static void test_compresses_runs(void **state)
{
    const size_t row = 15360, n = 16 * row;
    (void)state;
    uint8_t *buf = malloc(n);
    assert_non_null(buf);
    for (size_t i = 0; i < n; i++)
        buf[i] = (i % row) < row / 2 ? 0x80 : ((i & 1) ? 0x83 : 0x7d);
    size_t got = check_roundtrip(buf, n, row, "background");
    if (got > n / 200)
        fail_msg("background: %zu bytes for %zu (expected under 0.5 %%)", got, n);
    free(buf);
}

static void test_bad_arguments(void **state)
{
    uint8_t in[4] = {1, 2, 3, 4}, out[64];
    (void)state;
    assert_int_equal(mr_deflate_zlib(NULL, in, 4, 0, out, sizeof out), 0);
    assert_int_equal(mr_deflate_zlib(g_def, NULL, 4, 0, out, sizeof out), 0);
    assert_int_equal(mr_deflate_zlib(g_def, in, 4, 0, NULL, sizeof out), 0);
    assert_int_equal(mr_deflate_zlib(g_def, in, 4, 0, out, 5), 0);
    assert_true(mr_deflate_zlib(g_def, NULL, 0, 0, out, sizeof out) > 0);
}

static int setup(void **state)
{
    (void)state;
    g_def = mr_deflate_new();
    return g_def ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    mr_deflate_free(g_def);
    return 0;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_edge_lengths),
        cmocka_unit_test(test_content_and_rows),
        cmocka_unit_test(test_window_edge),
        cmocka_unit_test(test_blocks_and_deep_codes),
        cmocka_unit_test(test_compresses_runs),
        cmocka_unit_test(test_bad_arguments),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
