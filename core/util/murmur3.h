/*
 * murmur3.h - MurmurHash3_x86_32 (Austin Appleby's public-domain hash, the
 * 32-bit x86 variant) and the Cryptomatte name ids made from it: the
 * published Cryptomatte specification (1.1) hashes every name with
 * MurmurHash3_x86_32, seed 0, and stores the hash as a 32-bit float whose
 * exponent is clamped to 1..254, so no id is a denormal, an Inf or a NaN
 * ("uint32_to_float32"). Written from the algorithm's description; the
 * published test vectors are in tests/unit/test_util.c.
 */
#ifndef MR_MURMUR3_H
#define MR_MURMUR3_H

#include <stddef.h>
#include <stdint.h>

/* MurmurHash3_x86_32 of len bytes (blocks read little-endian, as the
 * reference does on x86). */
uint32_t mr_murmur3_32(const void *data, size_t len, uint32_t seed);

/* The Cryptomatte float bits of a hash: sign and mantissa kept, the
 * exponent clamped to [1, 254]. */
uint32_t mr_cryptomatte_bits(uint32_t hash);

/* The Cryptomatte id of a name (NUL-terminated) as a float and as its bits
 * (what the manifest spells as 8 hex digits). */
float mr_cryptomatte_id(const char *name);
uint32_t mr_cryptomatte_id_bits(const char *name);

#endif
