/*
 * morton.c - decoding 63-bit Morton codes (morton.h, where the encode is,
 * inline): the encode's five shift-and-mask steps run in reverse. The
 * thesis' encode (Fig. 31) is this one; its decode shifts x twice, so the
 * decode here is written from the encode's masks, not from the listing.
 */
#include "util/morton.h"

/* Bit 3i -> bit i (other bits ignored): the inverse of mr_morton_spread. */
static uint32_t compact3(uint64_t v)
{
    v &= 0x1249249249249249ull;
    v = (v | (v >> 2)) & 0x10c30c30c30c30c3ull;
    v = (v | (v >> 4)) & 0x100f00f00f00f00full;
    v = (v | (v >> 8)) & 0x001f0000ff0000ffull;
    v = (v | (v >> 16)) & 0x001f00000000ffffull;
    v = (v | (v >> 32)) & MR_MORTON_MAX;
    return (uint32_t)v;
}

void mr_morton_decode(uint64_t code, uint32_t *x, uint32_t *y, uint32_t *z)
{
    uint32_t cx = compact3(code), cy = compact3(code >> 1), cz = compact3(code >> 2);
    if (x)
        *x = cx;
    if (y)
        *y = cy;
    if (z)
        *z = cz;
}
