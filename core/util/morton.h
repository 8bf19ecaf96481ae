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

/* Coordinates above MR_MORTON_MAX are masked to their low 21 bits. */
uint64_t mr_morton_encode(uint32_t x, uint32_t y, uint32_t z);
void mr_morton_decode(uint64_t code, uint32_t *x, uint32_t *y, uint32_t *z);

#endif /* MR_MORTON_H */
