/*
 * refine.h - detailed skinned test meshes made from low-poly ones: Loop
 * subdivision plus a procedural displacement, with skin weights carried along.
 * mr_refine_params and mr_refine_asset are public (microray.h); this header
 * says what a refinement does and declares the per-mesh calls and the noise.
 *
 * Why: the real skinned characters available (assimp-testmodels) have a few
 * thousand triangles, while displaced micro-meshes must be baked from
 * detailed surfaces. Refining a real rig keeps its real skeleton and clips.
 *
 * What a refinement does, in order:
 *  1. Weld. assimp splits vertices at UV and normal seams, so the input's
 *     vertices ("wedges") are grouped by bit-equal position (-0 == +0) into
 *     welded vertices; the subdivision topology and the position and weight
 *     rules run on welded vertices only, so both sides of a seam move
 *     identically and the surface stays watertight. Seams are kept in the
 *     output: every input wedge stays a vertex (same index, first), and a new
 *     edge vertex is made per distinct wedge edge, so an edge on a UV seam
 *     gets two output vertices at the same (bit-identical) position with
 *     their own UVs. UVs are interpolated linearly (edge midpoints), not
 *     smoothed.
 *  2. N rounds of Loop subdivision (1:4 per triangle; children keep the
 *     parent's winding). Interior edge: 3/8 (a + b) + 1/8 (c + d); interior
 *     vertex of valence n: (1 - n beta) v + beta sum(neighbours), Loop's
 *     beta = (5/8 - (3/8 + 1/4 cos(2 pi / n))^2) / n. Edges with one face
 *     (boundary) or more than two (non-manifold) are creases: edge midpoint,
 *     and a vertex on exactly two crease edges gets 3/4 v + 1/8 (a + b);
 *     on other counts it is a corner and stays put. Degenerate edges (both
 *     ends welded together) give the vertex itself.
 *  3. Skin weights of each new vertex are the same stencil applied to the
 *     parents' influences, then mr_influences_normalize (summed per joint,
 *     the 8 largest kept, renormalised). Rigid parents (all weights 0)
 *     contribute nothing; a child whose whole stencil is rigid stays rigid.
 *     Before round 1, seam wedges whose weights differ are averaged.
 *  4. Detail: each welded vertex moves along the smoothed normal (the
 *     area-weighted normal of the refined mesh, close to the Loop limit
 *     normal) by amplitude * mr_refine_noise(frequency * p, octaves, seed),
 *     with p its object-space (mesh-space) position. The noise is gradient
 *     noise with values in [-1, 1], so |displacement| <= amplitude. The
 *     noise is evaluated per welded vertex, so seams stay closed.
 *  5. Normals of the result are area-weighted per welded vertex, so they are
 *     smooth across the input's hard-normal seams (the detail has no hard
 *     edges either). With 0 rounds and amplitude 0 the input mesh is
 *     returned unchanged (normals and weights included, bit for bit).
 *
 * Work is spread over threads with mr_parallel_for; every vertex and edge is
 * computed from its own inputs in a fixed order, so results are
 * bit-identical for any thread count.
 */
#ifndef MR_REFINE_H
#define MR_REFINE_H

#include "asset/asset.h"

/* Refines in into *out (overwritten; release with mr_refine_mesh_free).
 * name, node and skin (joint_nodes, inverse_bind) are copied. Fails with
 * MR_ERR_INVALID for bad params or a broken mesh (index out of range,
 * non-finite position, missing arrays) and MR_ERR_LIMIT when the result
 * would exceed MR_MAX_ASSET_TRIANGLES / MR_MAX_ASSET_VERTICES; *out is then
 * left zeroed. */
int mr_refine_mesh(const mr_mesh *in, const mr_refine_params *params, mr_mesh *out,
                   mr_error *err);

/* Frees the arrays of a mesh made by mr_refine_mesh and zeroes it. */
void mr_refine_mesh_free(mr_mesh *mesh);

/* Band-limited gradient noise at (x, y, z): sum of `octaves` (0 = 1) bands of
 * Perlin-style gradient noise (12 cube-edge gradients, quintic fade) on the
 * integer lattice, band k at 2^k times the frequency with weight 2^-k,
 * divided by the total weight. 0 at integer points; C2 smooth. The raw sum
 * can peak slightly above 1 (about 1.01 measured), so it is clamped to
 * [-1, 1] to make the amplitude a hard bound. 0 for non-finite input.
 * Deterministic and portable (integer hashing, double arithmetic). */
double mr_refine_noise(double x, double y, double z, unsigned octaves, uint32_t seed);

#endif
