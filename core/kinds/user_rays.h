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

static inline mr_ray_key mr_ray_key_of(void *ray, unsigned N, unsigned i)
{
    mr_ray_key k;
    for (unsigned c = 0; c < 3; c++) {
        k.bits[c] = *mr_ray_u(ray, N, MR_RAY_ORG + c, i);
        k.bits[3 + c] = *mr_ray_u(ray, N, MR_RAY_DIR + c, i);
    }
    return k;
}

/* A direction that can hit something: not zero, every component finite. */
static inline bool mr_ray_dir_ok(mr_vec3 d)
{
    return (d.x != 0 || d.y != 0 || d.z != 0) && isfinite(d.x) && isfinite(d.y) && isfinite(d.z);
}

/* Lanes of the widest packet the renderer hands Embree (rtcIntersect16:
 * 8x2 primary rays, integrator.c). */
#define MR_RAY_CACHE_LANES 16

/* Defines `static bool name(void *ray, unsigned N, unsigned i, type *out)`:
 * ray i of an N-packet set up by setup(origin, direction) into *out; false
 * when its direction cannot hit anything. Embree enters a ray's (or a
 * packet's) primitives one after another, so each thread keeps the last
 * set-up of each lane (MR_RAY_CACHE_LANES of them) and redoes it only when
 * the lane's origin or direction changed (a set-up is a pure function of
 * the two; a ray that cannot hit is never kept, so a kept one needs no
 * check). */
#define MR_RAY_SETUP_CACHE(name, type, setup)                                                    \
    static bool name(void *ray, unsigned N, unsigned i, type *out)                               \
    {                                                                                             \
        static _Thread_local struct {                                                             \
            mr_ray_key key;                                                                       \
            bool kept;                                                                            \
            type r;                                                                               \
        } last[MR_RAY_CACHE_LANES];                                                               \
        const unsigned lane = i % MR_RAY_CACHE_LANES;                                             \
        if (!last[lane].kept || !mr_ray_key_matches(ray, N, i, &last[lane].key)) {                \
            const mr_vec3 o = mr_v3(*mr_ray_f(ray, N, MR_RAY_ORG, i),                             \
                                    *mr_ray_f(ray, N, MR_RAY_ORG + 1, i),                         \
                                    *mr_ray_f(ray, N, MR_RAY_ORG + 2, i));                        \
            const mr_vec3 d = mr_v3(*mr_ray_f(ray, N, MR_RAY_DIR, i),                             \
                                    *mr_ray_f(ray, N, MR_RAY_DIR + 1, i),                         \
                                    *mr_ray_f(ray, N, MR_RAY_DIR + 2, i));                        \
            if (!mr_ray_dir_ok(d))                                                                \
                return false;                                                                     \
            last[lane].r = setup(o, d);                                                           \
            last[lane].key = mr_ray_key_of(ray, N, i);                                            \
            last[lane].kept = true;                                                               \
        }                                                                                         \
        *out = last[lane].r;                                                                      \
        return true;                                                                              \
    }

#endif
