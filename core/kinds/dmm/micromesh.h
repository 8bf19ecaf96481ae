/*
 * micromesh.h - topology and evaluation of one displaced micro-mesh (DMM)
 * base triangle (paper 000, "Ray Tracing Animated Displaced Micro-Meshes",
 * section 3, eq. 5).
 *
 * A base triangle (corners v0, v1, v2 with direction vectors n0, n1, n2) is
 * subdivided 1:4 recursively to level L in 0..MR_UMESH_MAX_LEVEL: n = 2^L
 * segments per edge, 4^L micro-triangles, (n+1)(n+2)/2 micro-vertices.
 *
 * Micro-vertex (a, b), a, b >= 0, a + b <= n, sits at barycentric
 * coordinates u = a/n (weight of v1), v = b/n (weight of v2), 1-u-v (weight
 * of v0): the convention of watertight.h's hits. Vertices are numbered row by
 * row (b = 0 first), index = b(n+1) - b(b-1)/2 + a. Micro-triangles are
 * numbered row by row too; within row b the upright ones (a,b) (a+1,b) (a,b+1)
 * and the inverted ones (a+1,b) (a+1,b+1) (a,b+1) alternate, all wound like
 * the base triangle (v0, v1, v2). This is not NVIDIA's bird-curve order; a
 * hierarchical encoder will need its own mapping on top.
 *
 * Displaced micro-vertex (eq. 5 without animation):
 *   P = sum w_i v_i + d * sum w_i n_i,
 * the direction is NOT normalised after interpolation (REFERENCE.md:
 * normalising changes the displacement magnitude and breaks the prismoid and
 * Bezier bounds).
 *
 * Watertightness (issue 4, part 2): a micro-vertex on a base edge is computed
 * from that edge's data alone - its two endpoints (position and direction)
 * put in a canonical order (by bit pattern), and the edge parameter, which is
 * dyadic and therefore exact both ways (t and 1 - t). So both triangles that
 * share an edge get bit-identical micro-vertices whatever their vertex order
 * and whatever the compiler does with contraction, provided the caller gives
 * the same displacement for the vertex on both sides (the baker measures it
 * from the same bit-identical point and direction, so it does).
 *
 * Neighbours of different levels: as in NVIDIA's micromesh format, levels of
 * neighbours differ by at most one and the finer side's edge is decimated.
 * With bit k of decimate_mask set, edge k (0: v0->v1, 1: v1->v2, 2: v2->v0)
 * borders a triangle one level coarser: each odd micro-vertex of that edge is
 * collapsed onto the even one before it (walking the edge in the triangle's
 * own direction). This is a half-edge collapse: two micro-triangles per odd
 * vertex become degenerate and are dropped, the rest re-triangulate the strip,
 * and the fine side's boundary consists of exactly the coarse side's edges
 * (same vertex bits), so a watertight ray test cannot pass between them.
 *
 * Numerics: every evaluation is done in double and rounded once to float.
 * Weights are k/n with n <= 32, so each product weight * float is exact in
 * double; with zero displacement the result is the exact barycentric point
 * rounded to float up to a single double rounding of the sum, i.e. within one
 * float ulp of max |v_i| per component (tested).
 */
#ifndef MR_MICROMESH_H
#define MR_MICROMESH_H

#include <stdbool.h>
#include <stdint.h>

#include "math/mr_math.h"
#include "microray.h"

#define MR_UMESH_MAX_LEVEL 5u

/* One base triangle: corner positions and (unit at the corners, in practice)
 * displacement directions. */
typedef struct mr_umesh_tri {
    mr_vec3 pos[3];
    mr_vec3 dir[3];
} mr_umesh_tri;

/* Segments per edge, 2^level (0 for level > MR_UMESH_MAX_LEVEL). */
uint32_t mr_umesh_segments(unsigned level);
/* (n+1)(n+2)/2, or 0 for level > MR_UMESH_MAX_LEVEL. */
uint32_t mr_umesh_vertex_count(unsigned level);
/* 4^level, or 0 for level > MR_UMESH_MAX_LEVEL. */
uint32_t mr_umesh_triangle_count(unsigned level);

/* Index of micro-vertex (a, b); UINT32_MAX when a + b > n or level is bad. */
uint32_t mr_umesh_vertex_index(unsigned level, uint32_t a, uint32_t b);
/* The same without the checks: (a, b) on the lattice of level <=
 * MR_UMESH_MAX_LEVEL (rows 0..b-1 hold n+1, n, ..., n-b+2 vertices). */
static inline uint32_t mr_umesh_vertex_index_at(unsigned level, uint32_t a, uint32_t b)
{
    const uint32_t n = 1u << level;
    return b * (n + 1) - b * (b - 1) / 2 + a;
}
/* Inverse of mr_umesh_vertex_index; false for an index out of range. */
bool mr_umesh_vertex_coords(unsigned level, uint32_t index, uint32_t *a, uint32_t *b);
/* Barycentric (u, v) = (a/n, b/n) of a micro-vertex (exact in float). */
bool mr_umesh_vertex_bary(unsigned level, uint32_t index, float *u, float *v);

/* Which base edge a micro-vertex lies on: 0, 1, 2 for the open edge (corners
 * excluded), 3 for a corner (then *k is the corner 0..2), -1 for interior.
 * For an edge, *k is the step along the edge in the triangle's direction
 * (edge 0 from v0 to v1, 1 from v1 to v2, 2 from v2 to v0), 1 <= *k < n. */
int mr_umesh_vertex_edge(unsigned level, uint32_t a, uint32_t b, uint32_t *k);

/* Lattice corners (ta[k], tb[k]) of the upright micro-triangle at (a, b),
 * or of the inverted one right of it, in mr_umesh_triangle's vertex order. */
void mr_umesh_lattice_triangle(uint32_t a, uint32_t b, bool inverted, uint32_t ta[3],
                               uint32_t tb[3]);

/* Vertex indices of micro-triangle tri (row order, see above); false when
 * tri >= 4^level. */
bool mr_umesh_triangle(unsigned level, uint32_t tri, uint32_t idx[3]);

/* The vertex a micro-vertex is collapsed onto by edge decimation (itself when
 * no decimated edge moves it). decimate_mask bits 0..2 name edges 0..2; it
 * has no effect at level 0. Returns UINT32_MAX for a bad index. */
uint32_t mr_umesh_vertex_remap(unsigned level, unsigned decimate_mask, uint32_t index);
/* The same on lattice coordinates: (*a, *b) becomes the vertex it collapses
 * onto; unchanged for coordinates outside the lattice. */
void mr_umesh_remap_coords(unsigned level, unsigned decimate_mask, uint32_t *a, uint32_t *b);

/* Writes the micro-triangles that survive decimation (vertex indices already
 * remapped) to out (3 * 4^level entries suffice) and returns their count.
 * With decimate_mask 0 this is every triangle of mr_umesh_triangle. */
uint32_t mr_umesh_triangles(unsigned level, unsigned decimate_mask, uint32_t *out);

/* mr_umesh_triangles of every level up to a largest one and every
 * decimation mask, computed once: what a mesh of mixed levels looks its
 * triangles up in (tris[l][m], count[l][m] of them; NULL above the largest
 * level, and for masks other than 0 at level 0). */
typedef struct mr_umesh_topology {
    uint32_t count[MR_UMESH_MAX_LEVEL + 1][8];
    uint32_t *tris[MR_UMESH_MAX_LEVEL + 1][8];
} mr_umesh_topology;

/* Fills *t (zeroed first) for levels 0..max_level; MR_ERR_INVALID for a bad
 * level, MR_ERR_NOMEM (then *t holds nothing). */
int mr_umesh_topology_init(mr_umesh_topology *t, unsigned max_level, mr_error *err);
void mr_umesh_topology_free(mr_umesh_topology *t);

/* The edges of a mesh of base triangles, for levels that may differ by at
 * most one across a shared edge (an adaptive bake, per-triangle levels of
 * detail): every triangle's edge k (0: corner 0 -> 1, as above) keyed by
 * its vertex pair, sorted so the triangles sharing an edge are adjacent. */
typedef struct mr_umesh_edge {
    uint32_t lo, hi, tri, k;
} mr_umesh_edge;
typedef struct mr_umesh_edges {
    mr_umesh_edge *e;
    size_t count;        /* 3 per triangle */
    uint32_t triangles;
    uint32_t *group;     /* per entry of e: the first entry of its group (same vertex pair) */
    uint32_t *at;        /* triangle t's edge k is entry at[3 t + k] of e */
    uint32_t *order;     /* scratch of mr_umesh_balance: 2 per triangle */
} mr_umesh_edges;

/* The edges of the nt triangles idx (3 vertex indices each). MR_ERR_NOMEM;
 * *out needs no free on failure. */
int mr_umesh_edges_init(mr_umesh_edges *out, const uint32_t *idx, uint32_t nt, mr_error *err);
void mr_umesh_edges_free(mr_umesh_edges *e);

/* The end of the group of entries of e->e sharing entry i's vertex pair
 * (they start at e->group[i]). */
size_t mr_umesh_edges_group_end(const mr_umesh_edges *e, size_t i);

/* Per triangle, the edges it shares with another triangle (bit k: edge k):
 * the only edges a neighbour's level can decimate. */
void mr_umesh_edges_shared(const mr_umesh_edges *e, uint8_t *shared);

/* Balances per-triangle levels: raises the coarse side of every shared
 * edge joining levels more than one apart until none does, to the least
 * levels that satisfy it (a triangle ends at the largest of its own level
 * and every other's less its distance in shared edges), then sets each
 * triangle's decimation mask (bit k: edge k borders a triangle one level
 * coarser). level and decimate hold one entry per triangle. One sweep from
 * the finest level down: a triangle is raised at most once, since a level
 * processed later asks less of it. */
void mr_umesh_balance(const mr_umesh_edges *e, uint8_t *level, uint8_t *decimate);

/* Undisplaced point and interpolated (unnormalised) direction at micro-vertex
 * (a, b), following the edge rule above. Fails (MR_ERR_INVALID) for a bad
 * level or coordinates. */
int mr_umesh_frame(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b,
                   mr_vec3 *point, mr_vec3 *dir, mr_error *err);

/* Displaced micro-vertex (a, b): point + disp * dir, evaluated in double and
 * rounded once. Same failure cases as mr_umesh_frame. */
int mr_umesh_eval(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b, float disp,
                  mr_vec3 *out, mr_error *err);

/* mr_umesh_eval without the checks, for callers whose (a, b) lie on the
 * level's lattice by construction (the traversal): the same evaluation. */
mr_vec3 mr_umesh_eval_at(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b,
                         float disp);
/* mr_umesh_eval_at for count vertices (a[k], b[k]) with displacements
 * disp[k] into out[k]: the same bits, evaluated together (AVX2 where the
 * CPU has it; the traversal's leaves, six vertices each). */
void mr_umesh_eval_many(const mr_umesh_tri *tri, unsigned level, int count, const uint32_t *a,
                        const uint32_t *b, const float *disp, mr_vec3 *out);

/* Micro-vertex (a, b) under interpolated matrices (paper 000, eq. 6-7): the
 * rest-pose displaced point x = sum w_i v_i + disp * sum w_i n_i (tri holds
 * the REST pose) moved by M(w) = sum w_i M_i, the barycentric blend of the
 * corners' accumulated matrices. All in double, rounded once; M follows the
 * edge rule like positions, so shared-edge vertices stay bit-identical. With
 * three equal matrices this is M applied to mr_umesh_eval's point (up to one
 * rounding). Same failure cases as mr_umesh_frame. */
int mr_umesh_eval_interpolated(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                               unsigned level, uint32_t a, uint32_t b, float disp, mr_vec3 *out,
                               mr_error *err);
/* mr_umesh_eval_interpolated without the checks (as mr_umesh_eval_at). */
mr_vec3 mr_umesh_eval_interpolated_at(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                                      unsigned level, uint32_t a, uint32_t b, float disp);
/* mr_umesh_eval_interpolated_at for count vertices, as mr_umesh_eval_many
 * is mr_umesh_eval_at's: the same bits. */
void mr_umesh_eval_interpolated_many(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                                     unsigned level, int count, const uint32_t *a,
                                     const uint32_t *b, const float *disp, mr_vec3 *out);

/* All micro-vertices of a triangle: disp holds one displacement per
 * micro-vertex (vertex index order) or is NULL for zero displacement; out gets
 * mr_umesh_vertex_count(level) positions, decimated vertices already moved
 * onto the vertices they collapse to. Non-finite input fails with
 * MR_ERR_INVALID. */
int mr_umesh_eval_all(const mr_umesh_tri *tri, unsigned level, unsigned decimate_mask,
                      const float *disp, mr_vec3 *out, mr_error *err);

#endif /* MR_MICROMESH_H */
