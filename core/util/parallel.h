/*
 * parallel.h - the one way core code uses several cores: mr_parallel_for
 * and mr_range_fn, with MR_MAX_THREADS and mr_cpu_count, are public and
 * documented in microray.h ("cores and the parallel loop"), since clients
 * (the benchmarks' baselines) run on the same loop. Core files include this
 * header to say they use it.
 */
#ifndef MR_PARALLEL_H
#define MR_PARALLEL_H

#include "microray.h"

/* Whether the calling thread runs a task of a loop on several threads: a
 * loop it calls then runs serially on it (microray.h). */
bool mr_parallel_nested(void);

/* Test hooks. Workers the pool has started; pause-loop iterations a
 * waiting worker or caller spins before it sleeps (0: sleep at once;
 * negative: the default, MR_POOL_SPIN in parallel.c). */
unsigned mr_parallel_pool_workers(void);
void mr_parallel_pool_spin(int iterations);

#endif
