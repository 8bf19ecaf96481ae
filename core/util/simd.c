/* simd.c - the cap of simd.h. */
#include "util/simd.h"

atomic_int mr_simd_capped;

void mr_simd_cap_avx2(bool cap) { atomic_store(&mr_simd_capped, cap ? 1 : 0); }
