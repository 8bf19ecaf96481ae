/*
 * test_large_alloc.c - large_alloc.h: blocks from MR_LARGE_ALLOC_MIN up are
 * 2 MiB aligned and their whole 2 MiB pages advised as huge pages (the
 * kernel marks such a range "hg" in /proc/self/smaps wherever it has
 * transparent huge pages at all),
 * smaller ones are plain; every block is writable over its whole size, the
 * realloc keeps the bytes it is told to keep across every change of class,
 * and free() releases them all (ASan and LeakSanitizer check that).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <cmocka.h>

#include "util/large_alloc.h"

#define MIB ((size_t)1 << 20)

static void fill(uint8_t *p, size_t n, unsigned seed)
{
    for (size_t i = 0; i < n; i++)
        p[i] = (uint8_t)(i * 131u + seed);
}

static void check(const uint8_t *p, size_t n, unsigned seed)
{
    for (size_t i = 0; i < n; i++)
        if (p[i] != (uint8_t)(i * 131u + seed))
            fail_msg("byte %zu of %zu: %u, expected %u", i, n, p[i], (uint8_t)(i * 131u + seed));
}

/* Whether the mapping holding p carries the huge-page advice ("hg" among
 * its VmFlags); -1 when smaps cannot tell (no such file or mapping). */
static int advised_huge(const void *p)
{
    FILE *f = fopen("/proc/self/smaps", "r");
    if (!f)
        return -1;
    char line[512];
    bool inside = false;
    int found = -1;
    const uintptr_t a = (uintptr_t)p;
    while (fgets(line, sizeof line, f)) {
        unsigned long lo, hi;
        if (sscanf(line, "%lx-%lx ", &lo, &hi) == 2) { /* a mapping's first line */
            inside = a >= lo && a < hi;
            continue;
        }
        if (inside && strncmp(line, "VmFlags:", 8) == 0) {
            found = strstr(line, " hg") != NULL;
            break;
        }
    }
    fclose(f);
    return found;
}

static void test_small_blocks_are_plain(void **state)
{
    (void)state;
    const size_t sizes[] = {0, 1, 4096, MR_LARGE_ALLOC_MIN - 1};
    for (size_t k = 0; k < sizeof sizes / sizeof sizes[0]; k++) {
        uint8_t *p = mr_large_alloc(sizes[k]);
        assert_non_null(p);
        fill(p, sizes[k], 7);
        check(p, sizes[k], 7);
        free(p);
    }
}

static void test_large_blocks_are_aligned_and_advised(void **state)
{
    (void)state;
    const bool thp = access("/sys/kernel/mm/transparent_hugepage/enabled", F_OK) == 0;
    const size_t sizes[] = {MR_LARGE_ALLOC_MIN, MR_LARGE_ALLOC_MIN + 1, MR_LARGE_ALLOC_MIN + 3 * MIB + 3};
    for (size_t k = 0; k < sizeof sizes / sizeof sizes[0]; k++) {
        uint8_t *p = mr_large_alloc(sizes[k]);
        assert_non_null(p);
        assert_int_equal((uintptr_t)p % (2 * MIB), 0);
        fill(p, sizes[k], 3);
        check(p, sizes[k], 3);
        const int hg = advised_huge(p);
        if (thp) /* a kernel with transparent huge pages records the advice */
            assert_int_equal(hg, 1);
        free(p);
    }
    assert_null(mr_large_alloc(SIZE_MAX - 1));
}

static void test_realloc_keeps_what_it_is_told(void **state)
{
    (void)state;
    /* small -> large -> larger -> small, each keeping the bytes before */
    const size_t large = MR_LARGE_ALLOC_MIN + MIB, larger = 2 * MR_LARGE_ALLOC_MIN + 5;
    uint8_t *p = mr_large_alloc(1000);
    assert_non_null(p);
    fill(p, 1000, 11);
    p = mr_large_realloc(p, 1000, large);
    assert_non_null(p);
    assert_int_equal((uintptr_t)p % (2 * MIB), 0);
    check(p, 1000, 11);
    fill(p, large, 12);
    p = mr_large_realloc(p, large, larger);
    assert_non_null(p);
    check(p, large, 12);
    fill(p, larger, 13);
    /* keep larger than the new size: the new size's bytes */
    p = mr_large_realloc(p, larger, 5000);
    assert_non_null(p);
    check(p, 5000, 13);
    /* NULL starts a block */
    uint8_t *q = mr_large_realloc(NULL, 0, large);
    assert_non_null(q);
    fill(q, large, 1);
    check(q, large, 1);
    free(q);
    free(p);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_small_blocks_are_plain),
        cmocka_unit_test(test_large_blocks_are_aligned_and_advised),
        cmocka_unit_test(test_realloc_keeps_what_it_is_told),
    };
    return cmocka_run_group_tests_name("large_alloc", tests, NULL, NULL);
}
