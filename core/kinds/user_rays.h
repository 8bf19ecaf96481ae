/*
 * user_rays.h - the rays and hits a user geometry's callbacks get from
 * Embree (the kinds that intersect their own primitives). Embree's RTCRayN
 * / RTCHitN accessors are C++ only; the layout is structure-of-arrays
 * (rtcore_ray.h): field f of ray i of an N-packet is element f * N + i,
 * the hit following the ray's 12 fields.
 */
#ifndef MR_USER_RAYS_H
#define MR_USER_RAYS_H

#include <embree3/rtcore.h>
#include <math.h>
#include <stdbool.h>
#include <stdint.h>

#include "math/mr_math.h"

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

enum { MR_RAY_ORG = 0, MR_RAY_TNEAR = 3, MR_RAY_DIR = 4, MR_RAY_TFAR = 8, MR_RAY_FIELDS = 12 };
enum { MR_HIT_NG = 0, MR_HIT_U = 3, MR_HIT_V = 4, MR_HIT_PRIM = 5, MR_HIT_GEOM = 6,
       MR_HIT_INST = 7 };

static inline float *mr_ray_f(void *ray, unsigned N, unsigned field, unsigned i)
{
    return (float *)ray + field * N + i;
}

static inline unsigned *mr_ray_u(void *ray, unsigned N, unsigned field, unsigned i)
{
    return (unsigned *)ray + field * N + i;
}

/* The hit of ray i of an intersect callback's packet: normal ng, (u, v),
 * and the callback's primitive, geometry and instance. */
static inline void mr_ray_write_hit(const struct RTCIntersectFunctionNArguments *args, unsigned i,
                                    mr_vec3 ng, float u, float v)
{
    unsigned N = args->N;
    void *hit = (float *)args->rayhit + MR_RAY_FIELDS * N;
    *mr_ray_f(hit, N, MR_HIT_NG, i) = ng.x;
    *mr_ray_f(hit, N, MR_HIT_NG + 1, i) = ng.y;
    *mr_ray_f(hit, N, MR_HIT_NG + 2, i) = ng.z;
    *mr_ray_f(hit, N, MR_HIT_U, i) = u;
    *mr_ray_f(hit, N, MR_HIT_V, i) = v;
    *mr_ray_u(hit, N, MR_HIT_PRIM, i) = args->primID;
    *mr_ray_u(hit, N, MR_HIT_GEOM, i) = args->geomID;
    *mr_ray_u(hit, N, MR_HIT_INST, i) = args->context->instID[0];
}

/* Origin and direction of a ray (x, y, z each) as bit patterns. */
typedef struct mr_ray_key {
    uint32_t bits[6];
} mr_ray_key;

/* Whether ray i of an N-packet has the origin and direction of k, bit for
 * bit: read straight from the packet and compared field by field (a key
 * assembled on the stack first and compared whole stalls the load on the
 * stores that made it). */
static inline bool mr_ray_key_matches(void *ray, unsigned N, unsigned i, const mr_ray_key *k)
{
    bool same = true;
    for (unsigned c = 0; c < 3; c++) {
        same &= *mr_ray_u(ray, N, MR_RAY_ORG + c, i) == k->bits[c];
        same &= *mr_ray_u(ray, N, MR_RAY_DIR + c, i) == k->bits[3 + c];
    }
    return same;
}

/* Writes ray i's key into *k in place (a key made on the stack and copied
 * whole is read back in pieces wider than the stores that made it). */
static inline void mr_ray_key_store(void *ray, unsigned N, unsigned i, mr_ray_key *k)
{
    for (unsigned c = 0; c < 3; c++) {
        k->bits[c] = *mr_ray_u(ray, N, MR_RAY_ORG + c, i);
        k->bits[3 + c] = *mr_ray_u(ray, N, MR_RAY_DIR + c, i);
    }
}

/* Field f, f + 1, f + 2 of ray i of an N-packet as a vector (mr_v3_gather). */
static inline mr_vec3 mr_ray_v3(void *ray, unsigned N, unsigned f, unsigned i)
{
    return mr_v3_gather(mr_ray_f(ray, N, f, i), mr_ray_f(ray, N, f + 1, i),
                        mr_ray_f(ray, N, f + 2, i));
}

/* The lanes Embree marks valid (-1) in an N-packet, as a bit mask. */
static inline uint32_t mr_valid_lanes(unsigned N, const int *valid)
{
    uint32_t all = 0;
    for (unsigned i = 0; i < N; i++)
        all |= (uint32_t)(valid[i] == -1) << i;
    return all;
}

/* mr_rays_in_box's outward move of the slab distances, relative. */
#define MR_RAYS_IN_BOX_OUT 0x1p-20f

#if defined(__x86_64__) && defined(__GNUC__)
/* mr_rays_in_box (below) eight lanes at a time (N a multiple of 8), for CPUs
 * with AVX2: the SSE loop's operations lane by lane. */
__attribute__((target("avx2"))) static inline uint32_t
mr_rays_in_box_avx2(void *ray, unsigned N, const int *valid, const float lo[3], const float hi[3])
{
    const __m256 zero = _mm256_setzero_ps(), vup = _mm256_set1_ps(1.0f + MR_RAYS_IN_BOX_OUT),
                 vdown = _mm256_set1_ps(1.0f - MR_RAYS_IN_BOX_OUT), one = _mm256_set1_ps(1.0f);
    uint32_t in = 0;
    for (unsigned k = 0; k < N; k += 8) {
        const __m256 v = _mm256_castsi256_ps(_mm256_loadu_si256((const __m256i *)(valid + k)));
        if (!_mm256_movemask_ps(v))
            continue;
        __m256 entry = _mm256_loadu_ps(mr_ray_f(ray, N, MR_RAY_TNEAR, k));
        __m256 exit = _mm256_loadu_ps(mr_ray_f(ray, N, MR_RAY_TFAR, k));
        __m256 out = zero;
        for (unsigned a = 0; a < 3; a++) {
            const __m256 o = _mm256_loadu_ps(mr_ray_f(ray, N, MR_RAY_ORG + a, k));
            const __m256 d = _mm256_loadu_ps(mr_ray_f(ray, N, MR_RAY_DIR + a, k));
            const __m256 l = _mm256_set1_ps(lo[a]), h = _mm256_set1_ps(hi[a]);
            const __m256 par = _mm256_cmp_ps(d, zero, _CMP_EQ_OQ);
            out = _mm256_or_ps(out, _mm256_and_ps(par, _mm256_or_ps(_mm256_cmp_ps(o, l, _CMP_LT_OS),
                                                                    _mm256_cmp_ps(o, h, _CMP_GT_OS))));
            const __m256 inv = _mm256_div_ps(one, d);
            const __m256 t1 = _mm256_mul_ps(_mm256_sub_ps(l, o), inv);
            const __m256 t2 = _mm256_mul_ps(_mm256_sub_ps(h, o), inv);
            __m256 near = _mm256_min_ps(t1, t2), far = _mm256_max_ps(t1, t2);
            const __m256 npos = _mm256_cmp_ps(near, zero, _CMP_GT_OS),
                         fpos = _mm256_cmp_ps(far, zero, _CMP_GT_OS);
            near = _mm256_mul_ps(near, _mm256_blendv_ps(vup, vdown, npos));
            far = _mm256_mul_ps(far, _mm256_blendv_ps(vdown, vup, fpos));
            entry = _mm256_blendv_ps(_mm256_max_ps(near, entry), entry, par);
            exit = _mm256_blendv_ps(_mm256_min_ps(far, exit), exit, par);
        }
        const __m256 keep = _mm256_andnot_ps(out, _mm256_cmp_ps(entry, exit, _CMP_NGT_US));
        in |= (uint32_t)_mm256_movemask_ps(_mm256_and_ps(keep, v)) << k;
    }
    return in;
}
#endif

/* The lanes of an N-packet (N = 1 or a multiple of 4, at most 32) among
 * `valid` (Embree's -1 per lane) whose ray can meet a point of the box
 * lo..hi at a distance within its [tnear, tfar], as a bit mask. Embree
 * hands a user primitive the rays that entered a leaf of its tree, which
 * holds several primitives: most of them miss this one's box (3 in 4 on
 * a micro-mesh's base triangles). The test is conservative: the slab
 * distances (lo - o) * (1 / d), each within three roundings (under 2^-22
 * relative) of their exact value, are moved outwards by 2^-20 of
 * themselves (a product, so an infinite distance stays infinite), an axis
 * along which the ray does not move constrains only by its origin,
 * exactly, and a lane whose numbers are not finite (a NaN distance) is
 * kept, as before. Four lanes at a time in SSE, eight with AVX2. */
static inline uint32_t mr_rays_in_box(void *ray, unsigned N, const int *valid, const float lo[3],
                                      const float hi[3])
{
    const float up = 1.0f + MR_RAYS_IN_BOX_OUT, down = 1.0f - MR_RAYS_IN_BOX_OUT;
    uint32_t in = 0;
#if defined(__x86_64__) && defined(__GNUC__)
    if (N % 8 == 0 && __builtin_cpu_supports("avx2"))
        return mr_rays_in_box_avx2(ray, N, valid, lo, hi);
#endif
#if defined(__SSE2__)
    if (N % 4 == 0) {
        const __m128 zero = _mm_setzero_ps(), vup = _mm_set1_ps(up), vdown = _mm_set1_ps(down);
        for (unsigned k = 0; k < N; k += 4) {
            const __m128 v = _mm_castsi128_ps(_mm_loadu_si128((const __m128i *)(valid + k)));
            if (!_mm_movemask_ps(v))
                continue;
            __m128 entry = _mm_loadu_ps(mr_ray_f(ray, N, MR_RAY_TNEAR, k));
            __m128 exit = _mm_loadu_ps(mr_ray_f(ray, N, MR_RAY_TFAR, k));
            __m128 out = zero;
            for (unsigned a = 0; a < 3; a++) {
                const __m128 o = _mm_loadu_ps(mr_ray_f(ray, N, MR_RAY_ORG + a, k));
                const __m128 d = _mm_loadu_ps(mr_ray_f(ray, N, MR_RAY_DIR + a, k));
                const __m128 l = _mm_set1_ps(lo[a]), h = _mm_set1_ps(hi[a]);
                const __m128 par = _mm_cmpeq_ps(d, zero);
                out = _mm_or_ps(out, _mm_and_ps(par, _mm_or_ps(_mm_cmplt_ps(o, l),
                                                               _mm_cmpgt_ps(o, h))));
                const __m128 inv = _mm_div_ps(_mm_set1_ps(1.0f), d);
                const __m128 t1 = _mm_mul_ps(_mm_sub_ps(l, o), inv);
                const __m128 t2 = _mm_mul_ps(_mm_sub_ps(h, o), inv);
                __m128 near = _mm_min_ps(t1, t2), far = _mm_max_ps(t1, t2);
                const __m128 npos = _mm_cmpgt_ps(near, zero), fpos = _mm_cmpgt_ps(far, zero);
                near = _mm_mul_ps(near, _mm_or_ps(_mm_and_ps(npos, vdown), _mm_andnot_ps(npos, vup)));
                far = _mm_mul_ps(far, _mm_or_ps(_mm_and_ps(fpos, vup), _mm_andnot_ps(fpos, vdown)));
                /* parallel lanes: no constraint but `out`; max/min return
                 * their second operand when the first is NaN */
                entry = _mm_or_ps(_mm_and_ps(par, entry), _mm_andnot_ps(par, _mm_max_ps(near, entry)));
                exit = _mm_or_ps(_mm_and_ps(par, exit), _mm_andnot_ps(par, _mm_min_ps(far, exit)));
            }
            /* kept: entry <= exit, or either NaN */
            const __m128 keep = _mm_andnot_ps(out, _mm_cmpngt_ps(entry, exit));
            const int m = _mm_movemask_ps(_mm_and_ps(keep, v));
            in |= (uint32_t)m << k;
        }
        return in;
    }
#endif
    for (unsigned i = 0; i < N; i++) {
        if (valid[i] != -1)
            continue;
        float entry = *mr_ray_f(ray, N, MR_RAY_TNEAR, i), exit = *mr_ray_f(ray, N, MR_RAY_TFAR, i);
        bool out = false;
        for (unsigned a = 0; a < 3; a++) {
            const float o = *mr_ray_f(ray, N, MR_RAY_ORG + a, i), d = *mr_ray_f(ray, N, MR_RAY_DIR + a, i);
            if (d == 0) {
                out |= o < lo[a] || o > hi[a];
                continue;
            }
            const float inv = 1.0f / d, t1 = (lo[a] - o) * inv, t2 = (hi[a] - o) * inv;
            float near = t1 < t2 ? t1 : t2, far = t1 < t2 ? t2 : t1;
            near *= near > 0 ? down : up;
            far *= far > 0 ? up : down;
            entry = near > entry ? near : entry;
            exit = far < exit ? far : exit;
        }
        in |= (uint32_t)(!out && !(entry > exit)) << i;
    }
    return in;
}

/* Lanes of the widest packet the renderer hands Embree (rtcIntersect16:
 * 4x4 primary rays, integrator.c). */
#define MR_RAY_CACHE_LANES 16

/* Defines `static const type *name(void *ray, unsigned N, unsigned i)`:
 * ray i of an N-packet set up by setup(origin, direction), or NULL when
 * its direction cannot hit anything. Embree enters a ray's (or a packet's)
 * primitives one after another, so each thread keeps the last set-up of
 * each lane (MR_RAY_CACHE_LANES of them) and redoes it only when the
 * lane's origin or direction changed (a set-up is a pure function of the
 * two; a ray that cannot hit is never kept, so a kept one needs no check).
 * The set-up returned is the kept one, not a copy: it stays as it is until
 * this thread sets up the same lane again, so a callback may hold one for
 * each of its lanes. */
#define MR_RAY_SETUP_CACHE_REF(name, type, setup)                                                \
    static const type *name(void *ray, unsigned N, unsigned i)                                   \
    {                                                                                             \
        static _Thread_local struct {                                                             \
            mr_ray_key key;                                                                       \
            bool kept;                                                                            \
            type r;                                                                               \
        } last[MR_RAY_CACHE_LANES];                                                               \
        const unsigned lane = i % MR_RAY_CACHE_LANES;                                             \
        if (!last[lane].kept || !mr_ray_key_matches(ray, N, i, &last[lane].key)) {                \
            const mr_vec3 o = mr_ray_v3(ray, N, MR_RAY_ORG, i);                                   \
            const mr_vec3 d = mr_ray_v3(ray, N, MR_RAY_DIR, i);                                   \
            if (!mr_v3_is_dir(d))                                                                 \
                return NULL;                                                                      \
            last[lane].r = setup(o, d);                                                           \
            mr_ray_key_store(ray, N, i, &last[lane].key);                                         \
            last[lane].kept = true;                                                               \
        }                                                                                         \
        return &last[lane].r;                                                                     \
    }

#endif
