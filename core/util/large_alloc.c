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
    if (bytes > SIZE_MAX - HUGE_PAGE)
        return NULL;
    /* whole huge pages, so the advised range is all this block's */
    const size_t size = (bytes + HUGE_PAGE - 1) / HUGE_PAGE * HUGE_PAGE;
    void *p = NULL;
    if (posix_memalign(&p, HUGE_PAGE, size) != 0)
        return NULL;
#ifdef MADV_HUGEPAGE
    (void)madvise(p, size, MADV_HUGEPAGE); /* advice: a kernel without it still gives the memory */
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
