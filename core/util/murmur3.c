/* murmur3.c - MurmurHash3_x86_32 and Cryptomatte ids (murmur3.h). */
#include "util/murmur3.h"

#include <string.h>

static uint32_t rotl32(uint32_t x, int r)
{
    return (x << r) | (x >> (32 - r));
}

uint32_t mr_murmur3_32(const void *data, size_t len, uint32_t seed)
{
    const uint8_t *p = data;
    const uint32_t c1 = 0xcc9e2d51u, c2 = 0x1b873593u;
    uint32_t h = seed, k;
    size_t blocks = len / 4, i;

    for (i = 0; i < blocks; i++) {
        const uint8_t *b = p + 4 * i;
        k = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
        k *= c1;
        k = rotl32(k, 15);
        k *= c2;
        h ^= k;
        h = rotl32(h, 13);
        h = h * 5u + 0xe6546b64u;
    }
    /* the 1..3 bytes left, as a little-endian partial block */
    k = 0;
    switch (len & 3u) {
    case 3: k ^= (uint32_t)p[4 * blocks + 2] << 16; /* fall through */
    case 2: k ^= (uint32_t)p[4 * blocks + 1] << 8;  /* fall through */
    case 1:
        k ^= (uint32_t)p[4 * blocks];
        k *= c1;
        k = rotl32(k, 15);
        k *= c2;
        h ^= k;
    }
    /* finalisation: the length, then fmix32 */
    h ^= (uint32_t)len;
    h ^= h >> 16;
    h *= 0x85ebca6bu;
    h ^= h >> 13;
    h *= 0xc2b2ae35u;
    h ^= h >> 16;
    return h;
}

uint32_t mr_cryptomatte_bits(uint32_t hash)
{
    uint32_t exponent = (hash >> 23) & 0xffu;
    if (exponent == 0)
        exponent = 1;
    else if (exponent == 255)
        exponent = 254;
    return (hash & 0x807fffffu) | exponent << 23;
}

uint32_t mr_cryptomatte_id_bits(const char *name)
{
    return mr_cryptomatte_bits(mr_murmur3_32(name, strlen(name), 0));
}

float mr_cryptomatte_id(const char *name)
{
    uint32_t bits = mr_cryptomatte_id_bits(name);
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}
