/*
 * le.h - little-endian fields of microray's files (.mrdmm, baked DMM,
 * .mrsvo) and cache keys, one copy for every format. Values are assembled
 * byte by byte, so neither the host's byte order nor the buffer's
 * alignment matters; floats travel as their IEEE-754 bit patterns, so a
 * round trip is bit-exact (NaN payloads and -0 included).
 */
#ifndef MR_LE_H
#define MR_LE_H

#include <stdint.h>
#include <string.h>

static inline void mr_le_put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static inline void mr_le_put_u32(uint8_t *p, uint32_t v)
{
    for (int i = 0; i < 4; i++)
        p[i] = (uint8_t)(v >> (8 * i));
}

static inline void mr_le_put_u64(uint8_t *p, uint64_t v)
{
    for (int i = 0; i < 8; i++)
        p[i] = (uint8_t)(v >> (8 * i));
}

static inline uint32_t mr_f32_bits(float f)
{
    uint32_t v;
    memcpy(&v, &f, sizeof v);
    return v;
}

static inline void mr_le_put_f32(uint8_t *p, float f) { mr_le_put_u32(p, mr_f32_bits(f)); }

static inline void mr_le_put_f64(uint8_t *p, double d)
{
    uint64_t v;
    memcpy(&v, &d, sizeof v);
    mr_le_put_u64(p, v);
}

static inline uint16_t mr_le_get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | (unsigned)p[1] << 8);
}

static inline uint32_t mr_le_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static inline uint64_t mr_le_get_u64(const uint8_t *p)
{
    return mr_le_get_u32(p) | (uint64_t)mr_le_get_u32(p + 4) << 32;
}

static inline float mr_le_get_f32(const uint8_t *p)
{
    uint32_t v = mr_le_get_u32(p);
    float f;
    memcpy(&f, &v, sizeof f);
    return f;
}

static inline double mr_le_get_f64(const uint8_t *p)
{
    uint64_t v = mr_le_get_u64(p);
    double d;
    memcpy(&d, &v, sizeof d);
    return d;
}

#endif
