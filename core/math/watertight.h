/*
 * watertight.h - watertight ray/triangle intersection (Woop, Benthin, Wald:
 * "Watertight Ray/Triangle Intersection", JCGT 2013).
 *
 * For geometry microray intersects itself (micro-triangles of displaced
 * micro-meshes, voxels' surfaces in user geometry callbacks): a plain
 * Moller-Trumbore test leaks rays through shared edges (REFERENCE.md: 18 of
 * 921,600 primary rays), this test does not. The ray is sheared once into a
 * space where it runs along +z; the 2D edge functions of every triangle are
 * then evaluated from the same sheared vertex values, so two triangles that
 * share an edge compute the same edge function (with opposite sign) and no
 * ray can pass between them. Edge functions that come out exactly 0 in
 * single precision are recomputed in double, as the paper prescribes.
 */
#ifndef MR_WATERTIGHT_H
#define MR_WATERTIGHT_H

#include <float.h>
#include <math.h>
#include <stdbool.h>

#include "math/mr_math.h"

/* Per-ray precomputation, shared by all triangles it is tested against. */
typedef struct mr_wt_ray {
    mr_vec3 org;
    int kx, ky, kz;   /* axis permutation: kz is the dominant direction axis */
    float sx, sy, sz; /* shear constants */
} mr_wt_ray;

typedef struct mr_wt_hit {
    float t;       /* along the (unnormalised) direction given to setup */
    float u, v;    /* barycentric weights of v1 and v2 (v0 gets 1 - u - v) */
} mr_wt_hit;

/* dir must be non-zero and finite. */
mr_wt_ray mr_wt_ray_setup(mr_vec3 org, mr_vec3 dir);

/* True when the ray hits triangle (v0, v1, v2) at tmin <= t <= tmax (either
 * side: no back-face culling); fills *hit, whose t is then finite and in that
 * interval (degenerate and near-degenerate triangles never hit). Hits exactly on an edge or a
 * vertex count, so a ray through a shared edge hits at least one of the two
 * triangles. */
bool mr_wt_intersect(const mr_wt_ray *ray, mr_vec3 v0, mr_vec3 v1, mr_vec3 v2, float tmin,
                     float tmax, mr_wt_hit *hit);

/* mr_wt_intersect in two steps, for triangles that share vertices (a
 * ray's test of a displaced cell's micro-triangles): each vertex sheared
 * into the ray's space once (x, y: the 2D coordinates the edge functions
 * take; z: the distance along the ray, scaled), then each triangle's test
 * from its sheared vertices. The same operations as mr_wt_intersect (which
 * is made of them), so the same results bit for bit. */
typedef struct mr_wt_vertex {
    float x, y, z;
} mr_wt_vertex;

static inline mr_wt_vertex mr_wt_shear(const mr_wt_ray *r, mr_vec3 v)
{
    const float a[3] = {v.x - r->org.x, v.y - r->org.y, v.z - r->org.z};
    const float z = a[r->kz];
    return (mr_wt_vertex){a[r->kx] - r->sx * z, a[r->ky] - r->sy * z, z * r->sz};
}

bool mr_wt_intersect_sheared(const mr_wt_vertex *a, const mr_wt_vertex *b, const mr_wt_vertex *c,
                             float tmin, float tmax, mr_wt_hit *hit);

/* The same test in double precision (what the dmm kind's micro-triangles
 * use). The float test's sheared vertices carry rounding errors of a few
 * float ulps of their distance from the ray origin, so the edges it decides
 * on sit up to ~1e-7 of that distance away from the true edges: more than
 * a box padded relative to the geometry's own coordinates can cover when the
 * origin is far, and enough for two different float tests (Embree's,
 * this one) to decide a ray grazing a silhouette edge differently. In
 * double the shear is ~1e-16 of the distance off, far inside any such pad,
 * so bounds that contain a triangle's float vertices with a pad never cull
 * a ray the test would hit. Watertight in the same way (both triangles of
 * a shared edge compute its edge function from the same values, with
 * opposite sign); hits on an edge or vertex count. t is computed in double
 * and rounded to float once; [tmin, tmax] holds for the float t. */
typedef struct mr_wtd_ray {
    double org[3];
    int kx, ky, kz;
    double sx, sy, sz;
} mr_wtd_ray;

/* dir must be non-zero and finite. */
mr_wtd_ray mr_wtd_ray_setup(mr_vec3 org, mr_vec3 dir);

/* As mr_wt_intersect, in double precision. */
bool mr_wtd_intersect(const mr_wtd_ray *ray, mr_vec3 v0, mr_vec3 v1, mr_vec3 v2, float tmin,
                      float tmax, mr_wt_hit *hit);

/* mr_wtd_intersect in two steps, for triangles that share vertices (a
 * ray's test of a micro-mesh leaf): each vertex sheared into the ray's
 * space once (x, y: the 2D coordinates the edge functions take; z: the
 * scaled distance along the ray), then each triangle's test from its
 * sheared vertices. The same operations as mr_wtd_intersect, so the same
 * results bit for bit. */
typedef struct mr_wtd_vertex {
    double x, y, z;
} mr_wtd_vertex;

/* (Inline: a leaf's tests are the dmm trace's innermost loop.) */
static inline mr_wtd_vertex mr_wtd_shear(const mr_wtd_ray *r, mr_vec3 v)
{
    const double a[3] = {v.x - r->org[0], v.y - r->org[1], v.z - r->org[2]};
    double z = a[r->kz];
    return (mr_wtd_vertex){a[r->kx] - r->sx * z, a[r->ky] - r->sy * z, z * r->sz};
}

/* The second half of mr_wtd_intersect_sheared, for a triangle whose edge
 * functions u, v, w (of a, b, c's sheared x and y) have no two of opposite
 * signs; az, bz, cz: its corners' sheared z. (Its own function for tests
 * that compute the edge functions of several triangles at once.) */
static inline bool mr_wtd_hit_inside(double u, double v, double w, double az, double bz,
                                     double cz, float tmin, float tmax, mr_wt_hit *hit)
{
    double det = u + v + w;
    if (!(fabs(det) >= DBL_MIN)) /* in the triangle's plane, or degenerate */
        return false;
    double t = (u * az + v * bz + w * cz) / det;
    float tf = (float)t;
    if (!(tf >= tmin && tf <= tmax && tf < INFINITY))
        return false;
    hit->t = tf;
    hit->u = (float)(v / det);
    hit->v = (float)(w / det);
    return true;
}

static inline bool mr_wtd_intersect_sheared(const mr_wtd_vertex *a, const mr_wtd_vertex *b,
                                            const mr_wtd_vertex *c, float tmin, float tmax,
                                            mr_wt_hit *hit)
{
    double u = c->x * b->y - c->y * b->x, v = a->x * c->y - a->y * c->x,
           w = b->x * a->y - b->y * a->x;
    /* edge functions of both signs: outside (one branch, not six: most
     * tests miss, in no order a predictor learns) */
    if (((u < 0) | (v < 0) | (w < 0)) & ((u > 0) | (v > 0) | (w > 0)))
        return false;
    return mr_wtd_hit_inside(u, v, w, a->z, b->z, c->z, tmin, tmax, hit);
}

#endif
