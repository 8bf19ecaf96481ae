/*
 * map.h - the detailed mesh follows the node grid (paper 001, 3.2-3.3):
 * vertices are bound to nodes once, at rest, and placed from the current
 * node positions every frame.
 *
 * one_to_one (3.2): each vertex sits on its nearest surface node and takes
 * the node's approximate normal (eq. 3), the jagged look of the paper's
 * Fig. 2a; where that normal does not hold (a weak sum, or more than 60
 * degrees from the vertex normal at rest) the vertex normal comes from the
 * constant triangle basis (counted as a fallback).
 *
 * triangle_basis (3.3.1): each vertex is bound to a triangle of three
 * surface nodes (p1, p2, p3) that are pairwise 18-neighbours, chosen
 * among those around its nearest surface node: the one its projection
 * falls into (least outside), best facing the vertex normal. The
 * reference point r = sum w_i p_i is the projection onto the triangle's
 * plane (eq. 4), the offset o = v - r (eq. 5) is stored in the triangle's
 * orthonormal basis T = |p2 - p1|, N = |T x (p3 - p1)|, B = N x T (eq. 6,
 * N normalised; node order chosen so N faces the vertex normal) as
 * (o.T, o.N, o.B) (eq. 7), and so is the vertex normal (3.3.4). Per frame
 * v' = r' + o_x T' + o_y N' + o_z B' (eq. 9 with the erratum of
 * REFERENCE.md: the vector sum of the basis scaled by the stored offset).
 *
 * triangle_basis_curvature (3.3.2): the same binding, but the basis is
 * interpolated: N_c = |sum w_i N_a(i)| from the nodes' approximate normals,
 * B_c = |N_c x T|, T_c = B_c x N_c (eq. 8, normalised), with the offset and
 * normal stored in the rest pose's interpolated basis. Where the
 * approximate normals are not defined at rest (a weak sum of unit vectors,
 * or N_c more than 60 degrees from the triangle normal: the faces of a
 * one-node-thin part, whose nodes have no neighbour across it) the vertex
 * keeps the constant basis (3.5 and the paper's future work), counted in
 * sm_map_info.
 *
 * trilinear (the reference, SOFA's barycentric mapping): v' = v +
 * sum_c w_c(u) d_c over the 8 corners of the grid cell holding v (u its
 * position in the cell, d_c = p_c - rest_c), normals by the cofactor of
 * the map's Jacobian. Corners that are not nodes (cells around the surface
 * reach outside the node-filled inside) are extrapolated from their
 * nearest node n: d = d_n + sum_a delta_a (D_a - D_a at rest), delta the
 * corner's offset from n in cells and D_a the change of position per cell
 * along axis a at n, from n's neighbour on that axis (towards the corner
 * if it is a node, else away): exact for any affine motion. Across a
 * one-node-thin part (no neighbour on one axis) D_a is the cross product of
 * the other two over h, exact for rigid motions; with two axes missing (a
 * line of nodes, a single node) only n's translation is carried there. A
 * corner two cells or more from its node (a thin part of the mesh with no
 * node in it: a tail, a horn) follows n rigidly instead: its offset from n
 * turned by the rotation of n's frame (D orthonormalised), so a stretch
 * at n is not multiplied along a long lever (it fanned a tail out).
 *
 * Tangents (3.3.4: "vectors defining the tangent space" carried like the
 * normal), where the mesh has them: the triangle mappings store the rest
 * tangent in the basis the vertex maps by, (t.T, t.N, t.B) in the constant
 * basis and in the interpolated one, and rebuild it from this frame's
 * basis exactly as the normal (a rotation: unit and orthogonal to the
 * mapped normal to rounding; a frame whose N_c degenerates uses the
 * constant basis' for both); one_to_one has only the node's approximate
 * normal and no tangent frame (3.5), so the tangent is carried by the
 * vertex's constant triangle basis and made orthogonal to the node's
 * normal (Gram-Schmidt, mr_v3_tangent_to); trilinear moves it by the map's
 * Jacobian and makes it orthogonal to the cofactor-mapped normal. A vertex
 * following a node by translation keeps its rest tangent. A zero rest
 * tangent (a mesh without texture coordinates) stays zero.
 *
 * A vertex whose nearest surface node has no triangle (a grid of one or
 * two nodes) follows that node by translation in every triangle mapping
 * (counted). All mappings reproduce the rest mesh at rest and move it
 * rigidly under a rigid motion of the nodes (tests/unit/test_springmass_map.c),
 * up to float rounding. Results are the same for any thread count.
 */
#ifndef SM_MAP_H
#define SM_MAP_H

#include <stddef.h>
#include <stdint.h>

#include "kinds/springmass/sim.h"

typedef struct sm_map sm_map;

typedef struct sm_map_info {
    size_t constant_fallback; /* curvature (one_to_one): vertices (normals) kept on the constant basis */
    size_t translation_only;  /* triangle mappings: vertices with no triangle */
    size_t ghost_corners;     /* trilinear: cell corners extrapolated from nodes */
} sm_map_info;

/* Binds vertex_count vertices (world-space rest positions and unit normals,
 * 3 floats each, and rest_tangents: unit and orthogonal to the normals, or
 * 0 for a vertex without, 3 floats each; NULL: none to carry) to sim's
 * grid at rest for `mapping` (mr_springmass_mapping), whatever state the
 * sim is in now. */
int sm_map_new(const sm_sim *sim, int mapping, const float *rest_positions, const float *rest_normals,
               const float *rest_tangents, uint32_t vertex_count, unsigned threads, sm_map **out,
               mr_error *err);
void sm_map_free(sm_map *m);
const sm_map_info *sm_map_get_info(const sm_map *m);
/* The triangle mappings' base triangle of vertex v (an index shared by
 * the vertices bound to the same three nodes), UINT32_MAX for a vertex
 * that follows a node by translation or a mapping without triangles. */
uint32_t sm_map_triangle_of(const sm_map *m, uint32_t v);
/* Bytes the binding holds. */
size_t sm_map_bytes(const sm_map *m);

/* Positions, unit normals and (when the map has rest tangents and
 * tangents is not NULL) tangents, 3 floats per vertex each, from the sim's
 * current nodes. */
void sm_map_apply(sm_map *m, const sm_sim *sim, float *positions, float *normals, float *tangents,
                  unsigned threads);
/* The same for every stride-th vertex only (v = 0, stride, 2 stride, ...),
 * positions and normals, into full-size arrays whose other entries are
 * left as they are: a sample of the mapping, to compare mappings by
 * ("tolerance_px"). */
void sm_map_apply_every(sm_map *m, const sm_sim *sim, uint32_t stride, float *positions,
                        float *normals, unsigned threads);

#endif
