/*
 * morton.h - 63-bit Morton (Z-order) codes of 21-bit integer coordinates
 * (paper 004, 4.1; REFERENCE.md: the thesis' decode listing, Fig. 31, is
 * wrong, its encode is right). Bit 3i of the code is bit i of x, bit 3i + 1
 * of y, bit 3i + 2 of z, so codes sort voxels in octree child order
 * (child c = x + 2y + 4z, as in svo.h).
 */
#ifndef MR_MORTON_H
#define MR_MORTON_H

#include <stdint.h>

#define MR_MORTON_BITS 21u
#define MR_MORTON_MAX ((1u << MR_MORTON_BITS) - 1u)

/* Bit i of v's low 21 bits -> bit 3i (bits above are dropped), in five
 * shift-and-mask steps (32, 16, 8, 4, 2): one axis of a code. */
static inline uint64_t mr_morton_spread(uint32_t v)
{
    uint64_t s = v & MR_MORTON_MAX;
    s = (s | (s << 32)) & 0x001f00000000ffffull;
    s = (s | (s << 16)) & 0x001f0000ff0000ffull;
    s = (s | (s << 8)) & 0x100f00f00f00f00full;
    s = (s | (s << 4)) & 0x10c30c30c30c30c3ull;
    s = (s | (s << 2)) & 0x1249249249249249ull;
    return s;
}

/* Coordinates above MR_MORTON_MAX are masked to their low 21 bits. */
static inline uint64_t mr_morton_encode(uint32_t x, uint32_t y, uint32_t z)
{
    return mr_morton_spread(x) | (mr_morton_spread(y) << 1) | (mr_morton_spread(z) << 2);
}

void mr_morton_decode(uint64_t code, uint32_t *x, uint32_t *y, uint32_t *z);

#endif /* MR_MORTON_H */
