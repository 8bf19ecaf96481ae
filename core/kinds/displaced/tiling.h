/*
 * tiling.h - procedural heights by tiling and blending an example image
 * (thesis 4.1 and chapter 5; Heitz and Neyret 2018), on the grid of
 * dsurf.h, with the bounds its traversal needs.
 *
 * Spaces. A mesh's texture coordinates uv go to the texture space of the
 * example uv' = offset + (uv - 0.5) scale (eq. 4.5); lattice coordinates l
 * satisfy uv' = l_x e1 + l_y e2 with e1 = (s, 0), e2 = (s/2, s sqrt(3)/2)
 * and s the triangle size (eq. 4.6: lattice triangles are equilateral in
 * texture space); grid coordinates are g = range l, so a lattice square is
 * range x range cells and the two lattice triangles of square (a, b) are
 * split by its anti-diagonal, which the grid's cell diagonals continue.
 *
 * Height of grid point q (a function of q alone, so every base triangle
 * that uses it computes the same bits): p = q / range in lattice triangle
 * v1 v2 v3 (the lower one when frac(p_x) + frac(p_y) <= 1), barycentric
 * weights w_k, each vertex hashed (with the seed) to an offset o_k in
 * [0, 1)^2 of texture space; G_k = the Gaussianised example, bilinear and
 * repeating, at uv'(p) + o_k; the variance-preserving blend
 *     B = (sum w_k G_k - 1/2) / sqrt(sum w_k^2) + 1/2         (eq. 4.8)
 * and height = offset + scale T^-1(B), T^-1 the inverse histogram
 * transform (eq. 4.4) as a monotone look-up table (linear between 4096
 * entries). Gaussianisation (eq. 4.3): each example sample's rank
 * u = (rank + 1/2) / N goes to 1/2 + sigma sqrt(2) erfinv(2u - 1), sigma =
 * 1/6 (HN19); equal samples share their mean rank.
 *
 * Bounds (5.3.1, 5.4.2-5.4.3, with the errata fixed): over a sub-triangle
 * of a lattice triangle (the triforce nodes) the weights range between
 * their values at its three vertices (they are linear and its edges are
 * parallel to the lattice triangle's); each G_k lies between the min and
 * max of the Gaussianised example's pyramid over the sub-triangle's
 * footprint moved by o_k (at most four nodes, the root-selection trick);
 * the numerator sum w_k G_k - 1/2 by interval arithmetic, the denominator
 * by intervals of the squares clamped to [1/sqrt 3, 1], the quotient's
 * four corner values (5.17-5.20), then T^-1 (monotone). Larger regions
 * use the global bound: sum w_k G_k is a convex combination, so it lies in
 * [Gmin, Gmax], and dividing Gmin - 1/2 < 0 by the smallest denominator
 * gives the lowest blend (5.1-5.2 written out). Every bound is widened by
 * 1e-12 before T^-1, which covers the double rounding of the evaluation.
 * Small nodes (leg at most MR_DPROC_EXACT_LEG) are bounded exactly
 * instead, by the least and largest height of their grid points: the
 * surface over each cell half is linear between its three grid points.
 * The blend bound is as wide as the example's samples under three tiles,
 * so near the leaves it let rays into several times the nodes and cells
 * they meet (procedural sphere at range 8: 7.5 -> 3.5 micro-triangle tests
 * per ray with exact cell halves alone).
 */
#ifndef MR_TILING_H
#define MR_TILING_H

#include <stdint.h>

#include "asset/image.h"
#include "kinds/displaced/dgrid.h"

#define MR_TILING_LUT 4096
/* Triforce nodes of leg up to this (and squares of this side) get the
 * exact bound of their grid points; past it the blend bound costs less
 * than the heights. Measured when the walk's nodes were the triforce
 * triangles, trace ms by this leg (2 / 4 / 8), builds interleaved:
 * plane at range 64, 640x360: 86 / 78 / 78-81; at range 512: 720 / 684 /
 * 828-860, and at 160x90, where fewer rays share a node: 125 / 123 /
 * 229-249; procedural sphere at range 64, 640x360: 41 at 4, 40 at 8 (55
 * with exact cell halves alone). */
#define MR_DPROC_EXACT_LEG 4
#define MR_TILING_SIGMA (1.0 / 6.0)

typedef struct mr_dproc {
    uint64_t id;               /* unique in the process: keys the per-thread caches */
    mr_image *gauss;           /* the Gaussianised example (float samples) */
    mr_dgrid gex;              /* its repeating grid and min/max pyramid */
    float lut[MR_TILING_LUT];  /* T^-1 on [lut_lo, lut_hi], in example values (0..1) */
    double lut_lo, lut_hi;
    double lut_per_blend;      /* entries per unit of blend: (MR_TILING_LUT - 1) / (lut_hi -
                                  lut_lo), a product where a quotient cost 3 % of a dense
                                  procedural frame */
    double range, inv_range;
    int top;                   /* log2 range: the level of a lattice square's cell square */
    double uv_off[2], uv_scale;
    double tri;                /* lattice triangle size */
    uint32_t seed;
    double scale, offset;      /* height = offset + scale * example value */
    double blend_lo, blend_hi; /* the global blend bound */
} mr_dproc;

/* Sets up the procedural texture of example image ex (borrowed only during
 * the call) at range, a power of two. MR_ERR_NOMEM, MR_ERR_INVALID. */
int mr_dproc_init(mr_dproc *p, const mr_image *ex, double uv_off_u, double uv_off_v,
                  double uv_scale, double triangle_size, uint32_t seed, uint32_t range,
                  double scale, double offset, unsigned threads, mr_error *err);
void mr_dproc_free(mr_dproc *p);
size_t mr_dproc_memory(const mr_dproc *p);

/* Grid coordinates of mesh texture coordinates (u, v). */
void mr_dproc_grid_of(const mr_dproc *p, float u, float v, double g[2]);

/* The height of grid point (i, j) and the blend it comes from. */
double mr_dproc_height(const mr_dproc *p, int64_t i, int64_t j);
double mr_dproc_blend(const mr_dproc *p, int64_t i, int64_t j);
/* The heights of the grid points, as dsurf.h reads them. */
mr_dheights mr_dproc_heights(const mr_dproc *p);
/* T^-1 then the height formula (monotone in b). */
double mr_dproc_height_of_blend(const mr_dproc *p, double b);

/* Height bounds over the triforce node with right-angle vertex (bx, by)
 * and signed leg s (grid units; vertices (bx, by), (bx + s, by),
 * (bx, by + s)), which must lie in one lattice triangle. */
void mr_dproc_tri_heights(const mr_dproc *p, int64_t bx, int64_t by, int64_t s, double *lo,
                          double *hi);
/* Height bounds over the square of n = 2^level x 2^level grid cells with
 * index (x, y) (cells [x n, x n + n) x [y n, y n + n)): up to a lattice
 * square (level <= top), the union of its two triforce halves' bounds
 * (the lower-left node (x n, y n, n) and the upper-right one ((x + 1) n,
 * (y + 1) n, -n): the square's anti-diagonal continues the lattice
 * triangles' and the triforce subdivision's, so each half lies in one
 * lattice triangle); above it, the global bound. The traversal's nodes
 * are these squares: a triforce node's rectangle is its whole square, so
 * the two halves, walked as nodes, doubled the nodes a ray entered
 * (procedural sphere at range 64: 6.8 nodes a ray against 3.1 for a
 * texture of like density). Kept per thread. */
void mr_dproc_square_heights(const mr_dproc *p, int level, int64_t x, int64_t y, double *lo,
                             double *hi);
/* The bounds of the four children of square (level, x, y), 1 <= level <=
 * log2 MR_DPROC_EXACT_LEG and level <= top (child k: (2 x + (k & 1), 2 y
 * + (k >> 1))), as mr_dproc_square_heights gives them (exact), made from
 * the one tile of heights that holds them all. */
void mr_dproc_child_heights(const mr_dproc *p, int level, int64_t x, int64_t y, double lo[4],
                            double hi[4]);
/* The same bound when this thread has it at hand (made before and still
 * kept), else false: nothing is made. */
bool mr_dproc_square_heights_kept(const mr_dproc *p, int level, int64_t x, int64_t y, double *lo,
                                  double *hi);
/* The global height bound (any region). */
void mr_dproc_global_heights(const mr_dproc *p, double *lo, double *hi);

/* Levels of detail ("tolerance_px"): how far the heights of coarse (the
 * same texture at range fine->range / 2^k) stray from those of fine over
 * n grid-space triangles (tri: 6 doubles each, three points in fine's grid
 * coordinates): the largest difference of the two height fields, each
 * linear over its grid cells' halves. A coarse cell is 2^k x 2^k fine
 * cells and its anti-diagonal continues theirs, so the difference is
 * linear on every fine cell half and largest at a fine grid point; every
 * fine grid point of each triangle's bounding box is visited (its
 * neighbourhood too: a superset). Coarse grid points are fine ones, with
 * the same heights (a height is a function of the lattice point q / range,
 * the same number at both ranges). */
double mr_dproc_distance(const mr_dproc *fine, const mr_dproc *coarse, const double *tri, size_t n,
                         unsigned threads);

#endif
