/*
 * rng_fixture.h - deterministic random numbers for the numerical tests
 * (xorshift64): the same sequence on every machine, so a failing case can
 * be replayed from its seed. Header-only; include after microray.h and
 * math/mr_math.h.
 */
#ifndef MR_TEST_RNG_FIXTURE_H
#define MR_TEST_RNG_FIXTURE_H

#include <stdint.h>

#include "math/mr_math.h"

static inline uint32_t rnd(uint64_t *s)
{
    *s ^= *s << 13;
    *s ^= *s >> 7;
    *s ^= *s << 17;
    return (uint32_t)(*s >> 11);
}

static inline double rnd01(uint64_t *s) { return (double)(rnd(s) & 0xFFFFFFu) / 16777216.0; }

static inline float rndf(uint64_t *s, float lo, float hi) { return lo + (hi - lo) * (float)rnd01(s); }

static inline mr_vec3 rnd_vec(uint64_t *s, float lo, float hi)
{
    float x = rndf(s, lo, hi), y = rndf(s, lo, hi);
    return mr_v3(x, y, rndf(s, lo, hi));
}

static inline mr_vec3 rnd_unit(uint64_t *s)
{
    for (;;) {
        mr_vec3 v = rnd_vec(s, -1, 1);
        float l = mr_v3_len(v);
        if (l > 0.1f && l <= 1.0f)
            return mr_v3_scale(v, 1.0f / l);
    }
}

#endif
