/*
 * large_alloc.c - huge-page-advised allocations (large_alloc.h).
 */
#include "util/large_alloc.h"

#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>

#define HUGE_PAGE ((size_t)2 << 20)

void *mr_large_alloc(size_t bytes)
{
    if (bytes < MR_LARGE_ALLOC_MIN)
        return malloc(bytes ? bytes : 1);
    if (bytes > SIZE_MAX / 2) /* no machine has it; a sanitizer's allocator would abort on it */
        return NULL;
    void *p = NULL;
    if (posix_memalign(&p, HUGE_PAGE, bytes) != 0)
        return NULL;
#ifdef MADV_HUGEPAGE
    /* the whole huge pages inside the block only: rounding the block up
     * to them made a job's peak memory grow by up to 2 MiB an array (52
     * MiB in bench_svo's instance jobs), where a tail of small pages
     * costs only its few faults; advice: a kernel without it still gives
     * the memory */
    (void)madvise(p, bytes / HUGE_PAGE * HUGE_PAGE, MADV_HUGEPAGE);
#endif
    return p;
}

void *mr_large_realloc(void *p, size_t keep, size_t bytes)
{
    if (keep > bytes)
        keep = bytes;
    if (bytes < MR_LARGE_ALLOC_MIN)
        return realloc(p, bytes ? bytes : 1);
    void *q = mr_large_alloc(bytes);
    if (!q)
        return NULL;
    if (p && keep)
        memcpy(q, p, keep);
    free(p);
    return q;
}
