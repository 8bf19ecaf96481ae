/*
 * dmm_trace.h - tessellation-free ray tracing of one displaced micro-mesh
 * base triangle (paper 000, section 6, Algorithms 1-4).
 *
 * A patch is one base triangle with its decoded displacement values, its
 * min/max displacement pyramid (dmm_encode.h, Fig. 11) and one of the two
 * deformations of the paper:
 *  - base (state of the art, Algorithms 2 and 4): the corners are the SKINNED
 *    base vertices and directions; micro-vertex = interpolated point +
 *    d * interpolated direction (eq. 5). A sub-triangle's micro-geometry lies
 *    in the convex hull of its corners displaced by the sub-triangle's
 *    minimum and maximum displacement (the bilinear prismoid), bounded here
 *    by the AABB of those six points;
 *  - interpolated (the paper's method, Algorithms 1 and 3): the corners are
 *    the REST pose and each carries its accumulated skinning matrix M_i; a
 *    micro-vertex is M(w) applied to the rest micro-vertex, M(w) the
 *    barycentric blend (eq. 6-8). For a fixed displacement d the surface
 *    M(w) x_d(w) is a quadratic triangular Bezier patch (eq. 9-11), and so is
 *    its restriction to any sub-triangle (r0, r1, r2) of the domain: its
 *    control points are the blossom c_ij = (M(r_i) x_d(r_j) + M(r_j)
 *    x_d(r_i)) / 2, computed directly from the top-level data (no stack of
 *    split patches; the paper's computeSubPatch). The micro-geometry lies in
 *    the hull of the 12 control points at d = min and d = max (eq. 12-13),
 *    bounded by their AABB.
 * Traversal descends the implicit quadtree of 1:4 sub-triangles (numbered as
 * the pyramid), visiting children nearest entry first and skipping those that
 * start beyond the closest hit so far; at the leaf sublevel (one above the
 * micro-triangles) it evaluates the 6 micro-vertices with exactly the
 * functions the tessellation uses (mr_dmm_vertex) and intersects the 4
 * micro-triangles with the watertight test in double precision
 * (mr_wtd_intersect), each in the tessellation's vertex order; of hits at
 * the same float t the micro-triangle first in row order wins. Hits are
 * therefore those of the tessellation tested triangle by triangle
 * (mr_dmm_intersect_micro), bit for bit. Decimated edges
 * (neighbour one level coarser) move their odd micro-vertices as
 * mr_umesh_triangles does; the collapsed micro-triangles have no area and
 * are never hit.
 *
 * Conservative bounds: boxes are computed in float from the corners and
 * widened by a per-patch pad, 2^-19 of a bound on the magnitude of every
 * coordinate they are computed from (mr_dmm_patch_pad), which covers the
 * single float rounding of each micro-vertex (2^-24 relative) and the box
 * arithmetic with a wide margin, and the double-precision test's own
 * rounding (~1e-16 of the ray's distance, where the float test's ~1e-7
 * would outgrow the pad for a distant camera); the box is widened before
 * the ray origin is subtracted (so the pad survives any origin magnitude)
 * and the slab test widens each axis's far distance by 3 float ulps (Ize,
 * "Robust BVH Ray Traversal", 2013), which keeps a micro-triangle hit at
 * exactly the current closest t inside the boxes it is in. Rays
 * parallel to a slab are handled explicitly, so no 0 * inf NaN can cull a
 * box. The four children of a node are bounded and tested together, one
 * SIMD lane each.
 */
#ifndef MR_DMM_TRACE_H
#define MR_DMM_TRACE_H

#include <stdbool.h>
#include <stdint.h>

#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/micromesh.h"
#include "math/watertight.h"

typedef struct mr_dmm_patch {
    unsigned level;                /* 0..MR_UMESH_MAX_LEVEL */
    unsigned decimate;             /* edges bordering a coarser neighbour (micromesh.h) */
    mr_umesh_tri tri;              /* base: posed; interpolated: rest pose */
    const mr_affine *mats[3];      /* interpolated: the corners' accumulated matrices; base: NULL */
    const mr_dmm_encoded *enc;     /* grid -> displacement (bias, scale) */
    const uint16_t *values;        /* mr_umesh_vertex_count(level) decoded grid values */
    const uint16_t *minv, *maxv;   /* pyramid, at least mr_dmm_trace_pyramid_size(level) entries */
    float pad[3];                  /* optional: mr_dmm_patch_pad's result, cached by the
                                      caller; all 0 = computed on every call */
    const float *root_children;    /* optional: mr_dmm_patch_root_children's result for this
                                      patch and pose, cached by the caller; NULL = made on
                                      every call */
    uint64_t stamp;                /* optional: nonzero when no other patch data or pose
                                      ever had this number with these values: the
                                      traversal then keeps the micro-vertices of
                                      interpolated patches it evaluates, per thread
                                      (mr_dmm_stamp); 0 = evaluated afresh every time */
} mr_dmm_patch;

/* A new nonzero patch stamp, never returned before in this process. */
uint64_t mr_dmm_stamp(void);

/* Per-ray precomputation. */
typedef struct mr_dmm_ray {
    mr_vec3 org, dir;
    float inv[3];      /* 1 / dir, 0 on axes where dir is 0 */
    bool parallel[3];  /* dir component is 0 */
    mr_wtd_ray wt;     /* the micro-triangle test runs in double (watertight.h) */
} mr_dmm_ray;

typedef struct mr_dmm_hit {
    float t;
    float u, v;        /* barycentric weights of base corners 1 and 2 (base-triangle domain) */
    mr_vec3 ng;        /* geometric normal of the micro-triangle hit, unnormalised */
} mr_dmm_hit;

/* Work counters (for benchmarks and tests); may be NULL. */
typedef struct mr_dmm_trace_stats {
    uint64_t boxes;      /* sub-triangle boxes tested */
    uint64_t triangles;  /* micro-triangles tested */
} mr_dmm_trace_stats;

/* Sublevel of the traversal's leaves: level - 1 (level 0: the base triangle). */
unsigned mr_dmm_trace_leaf_sublevel(unsigned level);
/* Pyramid entries the traversal reads: mr_dmm_pyramid_size(leaf sublevel). */
uint32_t mr_dmm_trace_pyramid_size(unsigned level);

/* dir must be finite and non-zero. */
mr_dmm_ray mr_dmm_ray_setup(mr_vec3 org, mr_vec3 dir);

/* Displaced micro-vertex (a, b) of the patch: mr_umesh_eval (base) or
 * mr_umesh_eval_interpolated (interpolated) of its decoded displacement.
 * The one definition both the traversal and the tessellation use. Unchecked:
 * (a, b) must lie on the lattice of the patch's level (<= MR_UMESH_MAX_LEVEL). */
mr_vec3 mr_dmm_vertex(const mr_dmm_patch *p, uint32_t a, uint32_t b);

/* Per-axis widening the patch's boxes need (a bound on its coordinates'
 * magnitude times 2^-19): depends on the patch's data only, so a caller
 * tracing many rays per frame computes it once with the bounds. */
void mr_dmm_patch_pad(const mr_dmm_patch *p, float pad[3]);

/* Floats in a patch's cached root children (mr_dmm_patch.root_children). */
#define MR_DMM_ROOT_CHILDREN_FLOATS 24

/* The boxes of the root's four children (sub-triangles of sublevel 1),
 * which every ray into the patch tests: a caller tracing many rays per
 * frame makes them once with the bounds (the same arithmetic as the
 * traversal's, so the same boxes bit for bit). False, out untouched, for a
 * patch whose root is a leaf (levels 0 and 1) or whose level is beyond
 * MR_UMESH_MAX_LEVEL. */
bool mr_dmm_patch_root_children(const mr_dmm_patch *p, float out[MR_DMM_ROOT_CHILDREN_FLOATS]);

/* Conservative box of the whole patch (what Embree's BVH gets): the root's
 * prism or Bezier box, cut to the box of all its micro-vertices (widened by
 * the pad) where it is over 4 times the posed base triangle's size (corner
 * directions that nearly oppose: a displacement range that holds the
 * micro-vertices near the triangle, times unit corner directions, makes a
 * box many times the surface, entered by every ray that passes it). False
 * when it is not finite. */
bool mr_dmm_patch_bounds(const mr_dmm_patch *p, mr_vec3 *lo, mr_vec3 *hi);

/* Closest hit with tmin <= t <= *tmax; on a hit *tmax becomes its t.
 * Hits are ordered by (t, micro-triangle in row order): of several
 * micro-triangles hit at the same float t (a ray through a shared edge or
 * vertex) the first in row order wins, whatever order the traversal visits
 * them in. take_tmax: whether a hit at exactly the incoming *tmax beats the
 * hit the caller already holds there (a caller ordering its patches the
 * same way: by their index). any_hit: stop at the first hit found (shadow
 * rays). */
bool mr_dmm_intersect(const mr_dmm_patch *p, const mr_dmm_ray *ray, float tmin, float *tmax,
                      bool take_tmax, bool any_hit, mr_dmm_hit *hit, mr_dmm_trace_stats *stats);

/* Up to this many rays traced through one patch together. */
#define MR_DMM_PACKET_MAX 16

/* mr_dmm_intersect for *rays[0 .. n) (n <= MR_DMM_PACKET_MAX) through the
 * patch together: each node's children and boxes are made once and tested
 * against every ray still in the packet, each leaf's micro-triangles made
 * once. Ray k's *tmax[k] shrinks on a hit and hits[k] is filled then (hits
 * may be NULL); returns the mask of rays hit. The hits are
 * mr_dmm_intersect's ray by ray, bit for bit (the same nodes can hold them,
 * and equal-t hits go by row order whatever the order of the visit); with
 * any_hit, a ray stops at its first hit. stats count each node's boxes
 * once, as made, and each ray's micro-triangle tests. */
uint32_t mr_dmm_intersect_packet(const mr_dmm_patch *p, int n, const mr_dmm_ray *const *rays,
                                 const float *tmin, float *const *tmax, const bool *take_tmax,
                                 bool any_hit, mr_dmm_hit *hits, mr_dmm_trace_stats *stats);

/* The same query answered by testing the patch's tessellation triangle by
 * triangle (the exact reference the traversal must equal): verts holds its
 * micro-vertices (3 floats each, micromesh.h index order, as mr_dmm_vertex
 * evaluates them), tris its count surviving micro-triangles
 * (mr_umesh_triangles with its level and decimation). The same test, the
 * same vertex order and the same (t, row order) ordering as
 * mr_dmm_intersect, so both return the same hit, bit for bit, whenever the
 * traversal's boxes hold every micro-triangle the test hits. */
bool mr_dmm_intersect_micro(const mr_dmm_patch *p, const float *verts, const uint32_t *tris,
                            uint32_t count, const mr_dmm_ray *ray, float tmin, float *tmax,
                            bool take_tmax, bool any_hit, mr_dmm_hit *hit);

/* Micro-triangle of the patch containing base-domain point (u, v) after
 * decimation (a micro-triangle that decimation collapsed is replaced by the
 * surviving neighbour that covers (u, v)): its lattice corners (a[k], b[k]),
 * already moved by the decimation, wound like the base triangle. */
void mr_dmm_locate(unsigned level, unsigned decimate, float u, float v, uint32_t a[3],
                   uint32_t b[3]);

#endif /* MR_DMM_TRACE_H */
