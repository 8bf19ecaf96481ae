/*
 * parallel.h - the one way core code uses several cores.
 *
 * mr_parallel_for splits [0, count) into chunks of `grain` items handed out
 * dynamically to `threads` workers (the calling thread is one of them). Work
 * must be independent per item so results do not depend on the thread count
 * or the order chunks are taken in: that is what keeps frames bit-identical
 * for any thread count. (MR_MAX_THREADS and mr_cpu_count are public:
 * microray.h.)
 */
#ifndef MR_PARALLEL_H
#define MR_PARALLEL_H

#include <stddef.h>

#include "microray.h"

/* Called with a half-open range [begin, end) and the worker's index in [0, threads). */
typedef void (*mr_range_fn)(void *ctx, size_t begin, size_t end, unsigned worker);

/* Runs fn over [0, count). threads == 0 means "all online cores". Falls back
 * to running everything on the caller when threads cannot be started. */
void mr_parallel_for(unsigned threads, size_t count, size_t grain, mr_range_fn fn, void *ctx);

#endif
