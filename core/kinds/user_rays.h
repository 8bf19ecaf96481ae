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

#endif
