/*
 * dtrace.h - tracing the displaced surface of dsurf.h without tessellating
 * it: per-base-triangle bounds by affine arithmetic, the D-BVH traversal of
 * the height texture's min/max pyramid (thesis Algorithm 4, 4.2.3-4.2.7) and
 * the local intersection at its leaves; and the fixed-step ray marcher the
 * thesis compares against (6.1).
 *
 * Bounds (4.2.4): a node is a rectangle R of grid space (a pyramid node, a
 * period of the texture, a block of periods), cut down to T's bounding box.
 * On R, P and N are affine in the rectangle's two parameters (e_u, e_v):
 * exactly the affine forms of math/affine_arith.h, so [P] and [N] carry no
 * K term but rounding. N is normalised by the interval 1 / sqrt([N].[N])
 * when that interval stays away from 0 (and the result is clamped to
 * [-1, 1]); otherwise (opposing or vanishing normals) each component of the
 * unit normal is bounded by [-1, 1], which also contains the zero
 * displacement of a vanishing normal. [h] is the node's height interval
 * (pyramid), [S] = [P] + [h] [N / |N|] (eq. 4.17), and the box is its
 * interval widened by the triangle's pad (dtrace.c: 2^-36 of a bound on
 * every magnitude the micro-vertices are computed from, which covers their
 * double rounding and grid points computed a rounding outside R) and
 * rounded outward to float. Each micro-vertex then lies in the box of every
 * node whose rectangle holds its grid point, and so does each
 * micro-triangle of a cell: that is what makes the traversal miss nothing
 * the tessellation would hit.
 *
 * Embree's per-triangle boxes (4.2.6-4.2.7): T split into three
 * parallelograms (corner k with half its two edges), each bounded as above
 * with the heights of the triangle's roots, boxes merged.
 *
 * Faster, and used for every triangle with area in space: the traversal
 * works in T's local frame, x = P(q) + z f (f the unit face normal), an
 * affine map of (grid x, grid y, z) inverted once per triangle and frame
 * (the ray is mapped once per call; the map keeps its parameter t). A
 * micro-vertex of grid point q and height h lies at (q + h (a, b), h c)
 * there, (a, b, c) the unit normal in the frame's basis, bounded once per
 * triangle (dtrace.c local_frame): a node is the box [rectangle + [h] a] x
 * [rectangle + [h] b] x [[h] c], a three-slab test. Where T's normal turns
 * enough to move the surface a quarter cell sideways, a and b are bounded
 * over the node's own rectangle instead (rect_normals: inv N is affine in
 * the grid point), so small nodes are not widened by the turn over all of
 * T. On a plane (normal = face normal) a = b = 0 and the boxes are exact.
 * The local boxes are widened by the image under the inverse map of 4
 * float roundings of the largest coordinate (a micro-vertex is rounded to
 * float once); triangles whose map is badly conditioned (no area in space,
 * such as a sphere's pole triangles) use the 3D boxes.
 *
 * Traversal: the pyramid seen as an infinite quadtree over the repeating
 * grid (levels 0..L inside one period, whose top node covers the period;
 * above L, blocks of 2^(l-L) x 2^(l-L) periods whose heights are the
 * texture's range), entered at up to 4 roots: the nodes of the lowest level
 * at which T's cells span at most two nodes in each direction (4.2.7).
 * A node whose rectangle T does not overlap is discarded by a
 * triangle-rectangle separating-axis test (the thesis' early texel
 * discard) with a margin of 1e-9 of the grid coordinates' size, so no
 * node whose cells hold a piece of T is dropped; the others are bounded,
 * hit-tested (slab test in double, Ize's robust widening) and visited
 * nearest first, skipping those beyond the closest hit so far. Leaves are
 * cells: their micro-triangles (dsurf.h) are evaluated by the very function
 * the tessellation uses and tested with the watertight test, so the hits
 * are the tessellated reference's, vertex for vertex. "bilinear": a cell
 * wholly inside T is the bilinear patch through its four displaced corners
 * instead (ray-patch intersection, Reshetov 2019); cut cells keep their
 * micro-triangles, so neighbouring base triangles still close up.
 */
#ifndef MR_DTRACE_H
#define MR_DTRACE_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>

#include "kinds/displaced/dgrid.h"
#include "kinds/displaced/dsurf.h"
#include "math/watertight.h"

/* Per base triangle and frame: P and N as affine functions of the grid
 * point (P(q) = P0 + Px (x - g0x) + Py (y - g0y)), and the box pad. */
typedef struct mr_dgrad {
    double P0[3], Px[3], Py[3];
    double N0[3], Nx[3], Ny[3];
    double nxlen, nylen;   /* |Nx|, |Ny| (Euclidean): how fast |N| can change */
    bool constant_normal;  /* the three corner normals are equal: N0 is the unit normal */
    double pad;
    double hlo, hhi;       /* T's height bound (mr_dtrace_root_heights, _proc_roots) */
    double gx0, gx1, gy0, gy1; /* T's grid box, widened by the grid margin */
    /* Constant normal and a well-shaped map: x = P(q) + h n is affine in
     * (q, h), so nodes are tested as boxes in (grid x, grid y, height)
     * space, the ray mapped there once per call (dtrace.c). */
    bool local;
    double inv[3][3];      /* (q - g0, z) = inv (x - P0) */
    double nb[3][2];       /* bounds of inv N / |N| over T */
    double lpad[3];        /* pad of the local boxes */
    /* A node's own normal bounds (rect_normals, dtrace.c), where nrect:
     * the grid rows of inv N as affine functions of the grid point (value
     * at T's grid vertex 0 g0, then per unit of x and of y), their
     * rounding slack, and 1 / the least |N| over T. */
    bool nrect;
    double nl[2][3], nslack[2], inv_ndist, g0[2];
    /* A packet's footprint (dtrace.c packet_footprint), where local: T's
     * local box (its grid box with its heights) and how far a micro-vertex
     * can sit from its grid point along grid x and y (T's largest height
     * times the normal's bound, plus the local boxes' pad). */
    double tlo[3], thi[3], reach[2];
    bool ob; /* the oriented box below is set */
    union {
        /* Where local: T's edges in the grid; a hit lies on the side of
         * edge k's line where en[k] . (x, y) <= ec[k], which holds T grown
         * by reach (and a rounding margin); dtrace.c tri_lanes. */
        struct {
            double en[3][2], ec[3];
        };
        /* Without a local frame (a map of no area in space: a UV sphere's
         * pole, where a fan's triangles have two corners at the pole), a
         * box of T's surface in an oriented frame (rows of ob_axis: T's
         * longest edge, the normal, their cross product): rays that miss
         * it skip T's walk (dtrace.c oriented_box). */
        struct {
            double ob_axis[3][3], ob_lo[3], ob_hi[3];
        };
    };
} mr_dgrad;

/* The most grid cells a base triangle's local boxes may be padded by (the
 * float rounding of its micro-vertices, mr_dgrad.lpad): past it its cells
 * are finer than floats can place a micro-vertex, the micro-triangles
 * degenerate, and every ray would enter the square of that many leaf
 * boxes (UVs spanning 10^7 repeats hung a frame). The kind refuses such a
 * surface in its rest pose (a pose that shrinks a triangle pads more cells,
 * but has no more cells to visit); real ones are thousands of times below
 * (the plane at range 512, by lpad's formula: about 5e-4 cells). */
#define MR_DTRACE_MAX_PAD_CELLS 4.0

typedef enum mr_dlocal { MR_DLOCAL_TRIANGLES = 0, MR_DLOCAL_BILINEAR } mr_dlocal;

/* A node of the texture's infinite quadtree: level <= the pyramid's top, a
 * node (I, J) of period (tx, ty); above it, a block (tx, ty) of periods. */
typedef struct mr_dnode {
    int level;
    int64_t tx, ty;
    uint32_t I, J;
} mr_dnode;

/* A base triangle's roots (4.2.7): the nodes of the lowest level at which
 * its cells span at most two per axis. They depend on its texture
 * coordinates only, so they are found once, not per ray. */
typedef struct mr_droots {
    int n;
    mr_dnode r[4];
} mr_droots;

/* A node of the procedural source: the square of 2^level x 2^level grid
 * cells with index (x, y), its heights bounded by
 * mr_dproc_square_heights (tiling.h). */
typedef struct mr_dpnode {
    int level;
    int64_t x, y;
} mr_dpnode;

/* A base triangle's procedural roots (mr_dtrace_proc_roots). */
typedef struct mr_dproots {
    int n;
    mr_dpnode r[4];
} mr_dproots;

/* What a traversal reads about one object. */
typedef struct mr_dscene {
    const mr_dbase *bases;
    const mr_dgrad *grads;
    const mr_dgrid *grid;      /* texture source, or NULL */
    const mr_droots *roots;    /* texture source: each base triangle's roots (or NULL: found
                                  per call) */
    const struct mr_dproc *proc; /* procedural source (tiling.h), or NULL */
    const mr_dproots *proots;  /* procedural source: each base triangle's roots */
    mr_dheights heights;
    mr_dlocal local;
    unsigned march_steps;      /* ray marcher */
    uint64_t pose;             /* this pose of the bases: mr_dscene_new_pose() after each
                                  posing (0: none; the traversal then keeps no cells) */
} mr_dscene;

/* A pose id no scene has had (the traversal's per-thread cell cache). */
uint64_t mr_dscene_new_pose(void);

typedef struct mr_dray {
    double o[3], d[3], inv[3];
    bool par[3];
    mr_wt_ray wt;
} mr_dray;

typedef struct mr_dhit {
    float t;
    float b1, b2;      /* base-triangle barycentrics of the hit's grid point */
    mr_vec3 ng;        /* geometric normal of the micro-surface hit, unnormalised */
} mr_dhit;

/* Work counters, summed by the caller; cells: cells cut into
 * micro-triangles (made, not taken from the thread's cache). */
typedef struct mr_dstats {
    uint64_t calls, nodes, cells, triangles;
} mr_dstats;

/* d finite and non-zero. */
mr_dray mr_dray_setup(mr_vec3 o, mr_vec3 d);

/* The gradient data of base triangle b for this frame (after mr_dbase_pose):
 * needs the triangle's height range hlo..hhi (its roots'). */
void mr_dgrad_init(mr_dgrad *gr, const mr_dbase *b, double hlo, double hhi);
/* T's roots, and its heights (the texture source): the tightest bound of
 * the levels over T from its roots down while they number at most 256, as
 * mr_dtrace_proc_roots, and T's corner heights. */
void mr_dtrace_roots(const mr_dgrid *g, const mr_dbase *b, mr_droots *out);
void mr_dtrace_root_heights(const mr_dgrid *g, const mr_dbase *b, double *hlo, double *hhi);
/* T's roots and heights from the procedural source: the nodes over T (those
 * the overlap test passes), a level at a time from the lattice squares
 * while they number at most 256; the roots are the deepest level of at
 * most four, the heights the tightest of the levels' bounds (the exact
 * ones of tiling.h near the leaves) and T's corner heights. Fixed by T's
 * grid coordinates, so found once. The traversal caps every node's bound
 * by these heights: only T's part of a node is traced. */
void mr_dtrace_proc_roots(const struct mr_dproc *p, const mr_dbase *b, mr_dproots *out,
                          double *hlo, double *hhi);

/* Conservative box of the displaced surface over the grid rectangle
 * [x0, x1] x [y0, y1] (cut to T's box here) with heights [hlo, hhi]: false
 * when the rectangle misses T's box. */
bool mr_dtrace_rect_box(const mr_dbase *b, const mr_dgrad *gr, double x0, double x1, double y0,
                        double y1, double hlo, double hhi, float lo[3], float hi[3]);
/* Conservative box of the whole displaced triangle (three parallelograms). */
void mr_dtrace_tri_box(const mr_dbase *b, const mr_dheights *hs, const mr_dgrad *gr, float lo[3],
                       float hi[3]);

/* T's local frame (gr->local): the box of a grid rectangle with heights
 * [hlo, hhi], and a point's local coordinates (tests). */
void mr_dtrace_local_box(const mr_dgrad *gr, double x0, double x1, double y0, double y1,
                         double hlo, double hhi, double lo[3], double hi[3]);
void mr_dtrace_local_point(const mr_dgrad *gr, const mr_dbase *b, mr_vec3 x, double out[3]);

/* Whether T (in grid space) may overlap [x0, x1] x [y0, y1] (conservative). */
bool mr_dtrace_overlaps(const mr_dbase *b, const mr_dgrad *gr, double x0, double x1, double y0,
                       double y1);

/* Closest hit of the ray with base triangle t's displaced surface at
 * tmin <= t <= *tmax (texture source); *tmax shrinks on a hit; any: the
 * first hit found will do. */
bool mr_dtrace_intersect(const mr_dscene *s, uint32_t t, const mr_dray *r, float tmin, float *tmax,
                         bool any, mr_dhit *hit, mr_dstats *st);

/* Up to this many rays traced through one base triangle together. */
#define MR_DPACKET_MAX 16

/* A callback's packet of rays as Embree hands it (structure of arrays):
 * lane k's origin o[a][k] and direction d[a][k] (a = x, y, z) and its span
 * tmin[k] .. tmax[k]. A ray that goes alone (mr_dtrace_intersect: on a
 * triangle without packets, or parallel to an axis of T's local frame) is
 * set up by setup(ctx, n, k): mr_dray_setup of the same origin and
 * direction, valid for the rest of the call, or NULL when the ray cannot
 * hit anything. */
typedef struct mr_drays {
    int n;
    const float *o[3], *d[3];
    const float *tmin;
    float *tmax;
    const mr_dray *(*setup)(void *ctx, unsigned n, unsigned k);
    void *ctx;
} mr_drays;

/* The closest hits of the rays of `lanes` (rays->n <= MR_DPACKET_MAX) with
 * base triangle t's displaced surface, each at tmin[k] <= t <= tmax[k]
 * (shrunk on a hit, hits[k] filled): returns the mask of rays hit. The
 * rays first go into T's local frame straight from the packet, and those
 * that do not enter T's box there are done: T's Embree box is axis-aligned
 * in the world, much looser (the sphere of 960 faces: 40 % of the calls
 * had no ray in T's box); a packed ray is set up for the micro-triangle
 * test only when it reaches a cell. A texture's rays traverse together:
 * each node's box is made once and tested against every ray still in the
 * packet, each cell's micro-triangles made once and tested against each
 * ray that reaches it. The packet starts not at T's roots but at the few
 * nodes (at most four, of the lowest level that allows) over its
 * footprint: the grid points its hits can lie over, from where its rays
 * cross T's box (dtrace.c packet_start; the texture plane at 50 texels per
 * unit: 3.1 node boxes a ray -> 0.6). The hits are mr_dtrace_intersect's
 * ray by ray, bit for bit (a tie between micro-triangles goes to the same
 * one whatever the order of the visit). Procedural source: a square's
 * blend bound (or the exact bound of a 4 x 4 square), when not at hand,
 * is first tested with its parent's heights where the parent's are
 * tighter than T's, and made only for the rays that enter that box
 * (plane at range 512, 160x90, when the nodes were triforce triangles:
 * half of the exact ones were not made; 89 -> 67 ms). */
uint32_t mr_dtrace_intersect_packet(const mr_dscene *s, uint32_t t, const mr_drays *rays,
                                    uint32_t lanes, mr_dhit hits[MR_DPACKET_MAX], mr_dstats *st);

/* The same surface found by marching: s->march_steps equal steps over the
 * ray's span in T's box, the first sign change of the height above the
 * surface refined by one secant step. An approximation (the comparator of
 * the thesis' 6.1), not exact. */
bool mr_dtrace_march(const mr_dscene *s, uint32_t t, const mr_dray *r, float tmin, float *tmax,
                     mr_dhit *hit, mr_dstats *st);

#endif
