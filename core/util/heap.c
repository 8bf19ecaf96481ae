/*
 * heap.c - how a rendering process keeps freed memory (microray.h, "the
 * heap between frames").
 *
 * glibc hands blocks above its mmap threshold back to the system when they
 * are freed, and trims the top of the heap once enough of it is free; a
 * frame that allocates the same buffers again (resampled octrees, sort
 * keys, selections) then faults every page back in, zeroed by the kernel.
 * On 912k deformed voxels a frame (svo resize, depth 10, one thread) that
 * cost 540 ms of 980 (emission 167 -> 45 ms, rebuild 601 -> 246 ms,
 * selection 213 -> 151 ms), and a new 4096^2 height texture
 * (displaced: its min/max pyramid) took 3-18 ms by where its blocks came
 * from instead of 3-4 ms every time. Blocks up to 1 GiB now come from the
 * heap and freed memory stays there until mr_heap_release, which hands it
 * back only beyond HEAP_KEEP: a render worker's next job (a texture edit,
 * a resubmitted scene) finds the memory of one like the last ready.
 */
#include "microray.h"

#if defined(__GLIBC__)
#include <malloc.h>
#endif

/* Freed bytes mr_heap_release keeps. */
#define HEAP_KEEP ((size_t)256 << 20)

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
    const struct mallinfo2 m = mallinfo2();
    if (m.fordblks > HEAP_KEEP)
        (void)malloc_trim(0);
#endif
}
