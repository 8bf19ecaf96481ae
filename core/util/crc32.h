/*
 * crc32.h - CRC-32 of IEEE 802.3 / zlib (reflected polynomial 0xEDB88320,
 * initial value and final xor all ones; "123456789" gives 0xCBF43926), the
 * checksum of every microray file format. libdeflate's (PCLMULQDQ where the
 * CPU has it): the arrays of a big base mesh or a deep octree run to
 * hundreds of MB, and a table lookup per byte took 0.45 s of loading a
 * 108 MB depth-12 octree.
 */
#ifndef MR_CRC32_H
#define MR_CRC32_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* CRC-32 of n bytes at data (n == 0 gives 0). */
uint32_t mr_crc32(const void *data, size_t n);

/* Whether `stored` is the CRC-32 of n bytes at data: every reader's
 * checksum test. The fuzzing build (`make fuzz-build` defines
 * FUZZING_BUILD_MODE_UNSAFE_FOR_PRODUCTION, libFuzzer's convention) takes
 * every checksum as matching, so a harness's inputs reach the fields behind
 * them (docs/fuzzing.md, fuzz_derived). */
static inline bool mr_crc32_matches(uint32_t stored, const void *data, size_t n)
{
#ifdef FUZZING_BUILD_MODE_UNSAFE_FOR_PRODUCTION
    (void)stored, (void)data, (void)n;
    return true;
#else
    return stored == mr_crc32(data, n);
#endif
}

#endif
