/* watertight.c - Woop, Benthin and Wald's watertight test (watertight.h). */
#include "math/watertight.h"

#include <float.h>
#include <math.h>

static inline float comp(mr_vec3 v, int k) { return k == 0 ? v.x : k == 1 ? v.y : v.z; }

mr_wt_ray mr_wt_ray_setup(mr_vec3 org, mr_vec3 dir)
{
    mr_wt_ray r;
    r.org = org;
    float ax = fabsf(dir.x), ay = fabsf(dir.y), az = fabsf(dir.z);
    r.kz = ax > ay ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2);
    r.kx = (r.kz + 1) % 3;
    r.ky = (r.kx + 1) % 3;
    /* keep the winding: swapping x and y when the ray runs along -z */
    if (comp(dir, r.kz) < 0) {
        int t = r.kx;
        r.kx = r.ky;
        r.ky = t;
    }
    float dz = comp(dir, r.kz);
    r.sx = comp(dir, r.kx) / dz;
    r.sy = comp(dir, r.ky) / dz;
    r.sz = 1.0f / dz;
    return r;
}

bool mr_wt_intersect(const mr_wt_ray *r, mr_vec3 v0, mr_vec3 v1, mr_vec3 v2, float tmin, float tmax,
                     mr_wt_hit *hit)
{
    /* vertices relative to the origin, sheared so the ray runs along +z */
    const mr_wt_vertex a = mr_wt_shear(r, v0), b = mr_wt_shear(r, v1), c = mr_wt_shear(r, v2);
    return mr_wt_intersect_sheared(&a, &b, &c, tmin, tmax, hit);
}

bool mr_wt_intersect_sheared(const mr_wt_vertex *A, const mr_wt_vertex *B, const mr_wt_vertex *C,
                             float tmin, float tmax, mr_wt_hit *hit)
{
    const float ax = A->x, ay = A->y, bx = B->x, by = B->y, cx = C->x, cy = C->y;
    /* scaled barycentrics: 2D edge functions of the sheared triangle */
    float u = cx * by - cy * bx, v = ax * cy - ay * cx, w = bx * ay - by * ax;
    if (u == 0.0f || v == 0.0f || w == 0.0f) {
        /* exactly on an edge in float: decide in double, which is exact for
         * these products of floats */
        u = (float)((double)cx * by - (double)cy * bx);
        v = (float)((double)ax * cy - (double)ay * cx);
        w = (float)((double)bx * ay - (double)by * ax);
    }
    if ((u < 0 || v < 0 || w < 0) && (u > 0 || v > 0 || w > 0))
        return false;
    float det = u + v + w;
    /* det 0: the ray lies in the triangle's plane, or a degenerate triangle.
     * A subnormal det is the same case blurred by rounding: 1 / det would
     * overflow and give an infinite t and NaN barycentrics. */
    if (!(fabsf(det) >= FLT_MIN))
        return false;

    /* scaled hit distance, compared without dividing */
    float t_scaled = u * A->z + v * B->z + w * C->z;
    if (det < 0) {
        if (t_scaled > tmin * det || t_scaled < tmax * det)
            return false;
    } else if (t_scaled < tmin * det || t_scaled > tmax * det) {
        return false;
    }
    float inv = 1.0f / det;
    float t = t_scaled * inv;
    /* The scaled comparison above can pass a t a few ulps outside
     * [tmin, tmax], and overflow (coordinates beyond ~1e13: t_scaled grows
     * with their cube) can make it infinite: keep the promise of the
     * interval and of finite results. */
    if (!(t >= tmin && t <= tmax && t < INFINITY))
        return false;
    hit->t = t;
    hit->u = v * inv; /* weight of v1 */
    hit->v = w * inv; /* weight of v2 */
    return true;
}

mr_wtd_ray mr_wtd_ray_setup(mr_vec3 org, mr_vec3 dir)
{
    mr_wtd_ray r;
    mr_wt_ray f = mr_wt_ray_setup(org, dir); /* the same axis choice */
    r.org[0] = org.x, r.org[1] = org.y, r.org[2] = org.z;
    r.kx = f.kx, r.ky = f.ky, r.kz = f.kz;
    double dz = comp(dir, r.kz);
    r.sx = comp(dir, r.kx) / dz;
    r.sy = comp(dir, r.ky) / dz;
    r.sz = 1.0 / dz;
    return r;
}

bool mr_wtd_intersect(const mr_wtd_ray *r, mr_vec3 v0, mr_vec3 v1, mr_vec3 v2, float tmin,
                      float tmax, mr_wt_hit *hit)
{
    const mr_wtd_vertex a = mr_wtd_shear(r, v0), b = mr_wtd_shear(r, v1), c = mr_wtd_shear(r, v2);
    return mr_wtd_intersect_sheared(&a, &b, &c, tmin, tmax, hit);
}
