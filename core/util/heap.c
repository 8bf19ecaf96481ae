/*
 * heap.c - how a rendering process keeps freed memory (microray.h, "the
 * heap between frames").
 *
 * glibc hands blocks above its mmap threshold back to the system when they
 * are freed, and trims the top of the heap once enough of it is free; a
 * frame that allocates the same buffers again (resampled octrees, sort
 * keys, selections) then faults every page back in, zeroed by the kernel.
 * On 912k deformed voxels a frame (svo resize, depth 10) that cost, per
 * frame on one thread, 350 ms of 960 (emission 167 -> 47 ms, rebuild 601
 * -> 251 ms, selection 213 -> 151 ms). Blocks up to 1 GiB now come from the
 * heap and freed memory stays there until mr_heap_release.
 */
#include "microray.h"

#if defined(__GLIBC__)
#include <malloc.h>
#endif

void mr_heap_keep_freed(void)
{
#if defined(__GLIBC__)
    (void)mallopt(M_MMAP_THRESHOLD, 1 << 30);
    (void)mallopt(M_TRIM_THRESHOLD, 1 << 30);
#endif
}

void mr_heap_release(void)
{
#if defined(__GLIBC__)
    (void)malloc_trim(0);
#endif
}
