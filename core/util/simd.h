/*
 * simd.h - which of the processor's vector extensions the hand-written
 * paths above AVX2 may use. Each such path does its baseline's operations
 * lane by lane, so what it computes does not depend on this; tests cap it
 * to run the AVX2 paths on a processor with AVX-512 and compare.
 */
#ifndef MR_UTIL_SIMD_H
#define MR_UTIL_SIMD_H

#include <stdatomic.h>
#include <stdbool.h>

/* Nonzero: no path above AVX2 (mr_simd_cap_avx2). */
extern atomic_int mr_simd_capped;

/* Whether the paths written for AVX-512 (F) may run: the processor has it
 * and nothing capped it. */
static inline bool mr_simd_avx512(void)
{
#if defined(__x86_64__) && defined(__GNUC__)
    return !atomic_load_explicit(&mr_simd_capped, memory_order_relaxed) &&
           __builtin_cpu_supports("avx512f");
#else
    return false;
#endif
}

/* Caps the paths at AVX2 (true) or lets them use all the processor has
 * (false, the default). For tests; call it between renders. */
void mr_simd_cap_avx2(bool cap);

#endif
