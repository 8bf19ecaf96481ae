/*
 * large_alloc.h - allocations of large arrays written whole (per-frame
 * octrees, sort keys, selections): from MR_LARGE_ALLOC_MIN bytes up they
 * are aligned to 2 MiB and their whole 2 MiB pages advised as transparent
 * huge pages, so the kernel faults them in 2 MiB at a time instead of
 * 4 KiB. A job's first frame writes every array fresh, and page faults
 * were most of it: the dancer at depth 12 (resize, every leaf) updated in
 * 27.9 s, 8.2 s with huge pages (README, Benchmarks). Smaller blocks are
 * plain malloc: a huge page is resident whole once touched, and with 2 MiB
 * as the floor the instance jobs of bench_svo peaked ~20 % higher (blocks
 * reused for smaller arrays, tails touched in part), with 16 MiB as
 * before. Where the kernel does not offer huge pages the advice is
 * ignored. Release every block with free().
 */
#ifndef MR_LARGE_ALLOC_H
#define MR_LARGE_ALLOC_H

#include <stddef.h>

#define MR_LARGE_ALLOC_MIN ((size_t)16 << 20)

/* bytes (0: one) of uninitialised memory, or NULL. */
void *mr_large_alloc(size_t bytes);
/* A block of bytes holding the first keep (<= bytes) bytes of p (NULL or
 * a block of at least keep bytes, freed on success; kept on failure, as
 * realloc does), or NULL. */
void *mr_large_realloc(void *p, size_t keep, size_t bytes);

#endif /* MR_LARGE_ALLOC_H */
