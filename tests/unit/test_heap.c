/*
 * test_heap.c - the heap between frames (util/heap.c): after
 * mr_heap_keep_freed a freed block stays in the process (its pages are not
 * faulted in again by the next frame), and mr_heap_release hands freed
 * memory back once it passes what is kept (256 MiB), not below.
 *
 * Measured on the process' resident set (/proc/self/statm), the thing the
 * policy is about. Blocks of 64 MiB and 384 MiB, every page touched: the
 * checks compare resident growth against half a block, far from the few
 * MiB the rest of the process moves. Under AddressSanitizer (make check)
 * malloc is the sanitizer's and the policy does not apply: skipped there.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "microray.h"

#if defined(__SANITIZE_ADDRESS__)
#define SANITIZED 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define SANITIZED 1
#endif
#endif
#ifndef SANITIZED
#define SANITIZED 0
#endif

#define MIB ((size_t)1 << 20)

static double resident_mib(void)
{
    long pages = 0, resident = 0;
    FILE *f = fopen("/proc/self/statm", "r");
    assert_non_null(f);
    assert_int_equal(fscanf(f, "%ld %ld", &pages, &resident), 2);
    fclose(f);
    return (double)resident * (double)sysconf(_SC_PAGESIZE) / (double)MIB;
}

/* Allocates `bytes`, touches every page, frees it; the resident growth
 * that remains after the free. */
static double kept_after_free(size_t bytes)
{
    const double before = resident_mib();
    unsigned char *p = malloc(bytes);
    assert_non_null(p);
    memset(p, 0x5a, bytes);
    /* keep the compiler from dropping the block */
    assert_int_equal(p[bytes / 2], 0x5a);
    free(p);
    return resident_mib() - before;
}

static void test_freed_memory_stays_then_goes(void **state)
{
    (void)state;
    if (SANITIZED)
        skip();
    mr_heap_keep_freed();
    mr_heap_release(); /* start from a heap without much free memory */
    /* a frame's 64 MiB buffer: kept after its free (glibc alone maps
     * blocks this large and unmaps them on free) */
    const double kept = kept_after_free(64 * MIB);
    assert_true(kept > 32.0);
    /* below the kept amount a release keeps it */
    const double before = resident_mib();
    mr_heap_release();
    assert_true(before - resident_mib() < 32.0);
    /* a large job's 384 MiB: kept after the free, handed back by a release */
    assert_true(kept_after_free(384 * MIB) > 192.0);
    const double full = resident_mib();
    mr_heap_release();
    assert_true(full - resident_mib() > 192.0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_freed_memory_stays_then_goes),
    };
    return cmocka_run_group_tests_name("heap", tests, NULL, NULL);
}
