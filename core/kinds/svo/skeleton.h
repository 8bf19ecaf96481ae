/*
 * skeleton.h - feature-varying skeletonisation of a sparse voxel octree
 * (paper 004, Willcocks, chapter 5, sections 5.4-5.7), and a posable rig
 * built from it, so a voxelised static model (an asset without a skeleton)
 * can be posed like a skinned character.
 *
 * Graph. The vertices are the occupied cells at a working level L of the
 * octree (a cell is occupied when a leaf lies in it or covers it), placed at
 * their centres; edges join the 26 neighbours among them (found by binary
 * search on the sorted level-L Morton codes). Positions are normalised to
 * the octree's cube: u = (p - origin) / size, so the cube is [0, 1]^3 (for
 * octrees from mr_svo_voxelize the cube edge is the model's largest extent,
 * within 0.2 %: the thesis' preprocessing, 5.5). L is the level whose cell
 * edge 2^-L is nearest to omega in log scale (L = round(-log2 omega),
 * clamped to [0, depth]); when the graph would exceed
 * MR_SVO_SKELETON_MAX_VERTICES the next coarser level is taken until it fits,
 * and then omega is raised to that level's cell edge (else merging could not
 * reach the next cell). Default omega: 2^-min(depth, 5). The thesis suggests
 * 2^-d for depth d (one finest cell); we cap it because the contraction
 * needs about (R / omega)^2 iterations for a part of radius R (smoothing is
 * an explicit umbrella step): at 2^-5 the test models (capsule, plus,
 * spider, Wuson, BCN) converge in 18-260 iterations, at 2^-6 in 110 to more
 * than 1000 (measured). 2^-5 gives 15 bones along a capsule spanning the
 * cube, 20 for the BCN figure.
 *
 * Contraction (5.4), Jacobi style (all vertices read the previous positions
 * and write a second buffer, so results do not depend on the thread count):
 *  - smooth s (eq. 5.4.1): mean of the one-ring (graph neighbours, v
 *    excluded); s = v without neighbours;
 *  - merge m (eq. 5.4.2 with the REFERENCE.md erratum: the sum runs over G):
 *    mean of the current positions of all vertices within distance omega of
 *    v (inclusive), v itself included. Found on a dense uniform grid of
 *    cell max(omega, 1/64) over the unit cube, rebuilt every iteration;
 *    coincident vertices (groups that have merged) are visited once,
 *    weighted by their count;
 *  - one-ring "area" a. The thesis' a is the area of the triangle fan around
 *    a mesh vertex; a voxel graph has no triangles, so we use the triangles
 *    of its clique complex: a = sum of the areas of the triangles
 *    (v, n_a, n_b) over pairs of graph neighbours of v that are 26-neighbours
 *    of each other (at most 132 per vertex), at the current positions. It is
 *    > 0 for any neighbourhood spanning a plane or a volume, and 0 when the
 *    neighbours have collapsed onto a line through v or onto points, and -
 *    like the thesis' fan - also when v's own group separates the groups
 *    around it (then every triangle has two coincident corners), so a vertex
 *    inside a bone group of a bent chain counts as thin. (The brief's
 *    suggestion, pi sqrt(l1 l2) from the eigenvalues of the neighbours'
 *    second moment about v, was tried: it stays > 0 wherever a vertex sees
 *    three non-collinear groups, i.e. at every bend; at 2^-6 it left
 *    0.9-1.5 % thinness error after up to 1000 iterations where the fan
 *    leaves 0.1-0.3 %, and the spider did not converge in 1000 iterations
 *    where the fan needs 526.) rho = a of the rest graph;
 *  - interpolation (eq. 5.4.4): v' = m + beta (s - m), beta = a / rho
 *    clamped to [0, 1] (the thesis' prerequisites need 0 < beta <= 1 while
 *    thick); beta = 0 when rho = 0 (a vertex whose rest neighbourhood is
 *    already a line or a point is thin from the start);
 *  - termination (eq. 5.5.1): stop when sum_i |v'_i - v_i| < delta (unit
 *    cube units, default 0.05 as in the thesis, NOT scaled by the vertex
 *    count: merged groups reach exact fixed points and stop moving
 *    exactly), or after max_iterations. Default 1000, not 100: 100 stops
 *    thick models half contracted (the Wuson figure, which converges after
 *    260 iterations at 2^-5, stops at 3.1 % thinness error and welds into
 *    37 bones instead of 21). iterations and final_movement report where it
 *    stopped.
 *
 * Weld (5.5 postprocessing): contracted vertices within omega of each other
 * are joined (union-find over the merge grid); each group becomes one bone
 * at the mean of its contracted positions, mapped back to bind space
 * (origin + size * u). Skeleton edges are the graph edges between different
 * groups. The thesis' output is an undirected graph; a rig needs a forest,
 * so each connected component is made a tree by breadth-first search from
 * its most central group (midpoint of a longest BFS path, found by two
 * sweeps; exact centre for trees): bones are numbered in BFS order
 * (components in order of their first graph vertex, neighbours by
 * increasing group), so parent[k] < k, and roots have parent -1. Graph edges
 * that would close a cycle are dropped.
 *
 * Thinness error (eq. 5.7.1): 100 * sum a / sum rho over all vertices after
 * termination (0 when sum rho = 0). The thesis claims 0 %; we measure 0 %
 * on a capsule and a plus and 0.1-0.4 % on real models: a vertex of a
 * one-cell-thick group at a bend can keep a non-degenerate triangle whose
 * corners lie in three groups.
 *
 * Segmentation and skinning (5.6). Hard: every leaf takes the bone of its
 * level-L ancestor cell's group (leaves coarser than L: the cell holding
 * their centre). Soft: the one-hot bone weights of the graph vertices are
 * averaged over {v} + one-ring for smooth_rounds rounds (Jacobi; at most 8
 * bones kept per vertex, the largest, ties to the lower bone), then each leaf
 * interpolates them trilinearly at its centre from the occupied level-L
 * cells around it (weights of unoccupied cells dropped and the rest
 * renormalised: the leaf's own cell always contributes), keeps the 4 largest
 * (ties: lower bone) and quantises them with mr_svo_quantize_weights to
 * uint8 summing to 255, sorted by decreasing weight (ties: lower bone),
 * unused slots bone 0 weight 0.
 *
 * All results are bit-identical for any thread count.
 */
#ifndef MR_SVO_SKELETON_H
#define MR_SVO_SKELETON_H

#include <stdint.h>

#include "asset/asset.h"
#include "microray.h"
#include "kinds/svo/svo.h"

/* Largest contraction graph: coarser working levels are taken beyond it. */
#define MR_SVO_SKELETON_MAX_VERTICES 50000u
/* Accepted omega range (unit cube units): the finest octree cell is 2^-21,
 * and the merge grid packs 21 bits per axis. */
#define MR_SVO_SKELETON_MIN_OMEGA (1.0f / 1048576.0f)
#define MR_SVO_SKELETON_MAX_ITERATIONS 100000u
#define MR_SVO_SKELETON_MAX_SMOOTH_ROUNDS 64u

/* 0 selects the default of each field. */
typedef struct mr_svo_skeleton_params {
    float omega;             /* target feature size, unit cube units, [2^-20, 1]; 2^-min(depth, 5) */
    float delta;             /* termination threshold of eq. 5.5.1, > 0; 0.05 */
    unsigned max_iterations; /* <= MR_SVO_SKELETON_MAX_ITERATIONS; 1000 */
    unsigned smooth_rounds;  /* weight smoothing rounds of the soft segmentation, <= 64; 2 */
    unsigned threads;        /* 0 = all cores */
} mr_svo_skeleton_params;

typedef struct mr_svo_skeleton {
    uint32_t bone_count;
    mr_vec3 *position;       /* bone_count, bind space (the octree's space) */
    int32_t *parent;         /* bone_count, parent bone (< own index) or -1 */
    uint32_t graph_vertices; /* occupied level-L cells */
    unsigned iterations;     /* contraction iterations run */
    double thinness_error_percent; /* eq. 5.7.1 after termination */
    unsigned level;          /* working level L */
    float omega;             /* omega used (after defaults and the vertex cap) */
    double final_movement;   /* sum of movements of the last iteration (unit cube units) */
    /* Skeleton-mesh mapping (5.5 postprocessing): the graph vertices' level-L
     * Morton codes (mr_morton_encode of level-L coordinates), increasing, and
     * the bone each one was welded into. graph_vertices entries each. */
    uint64_t *cell_code;
    uint32_t *cell_bone;
} mr_svo_skeleton;

/* Skeletonises svo into *out (zeroed first; release with
 * mr_svo_skeleton_free, also after a failure). p may be NULL (defaults). An
 * empty octree gives an empty skeleton (bone_count 0) and MR_OK. Errors:
 * MR_ERR_INVALID for NULL svo/out or a parameter out of range (the message
 * names it); MR_ERR_FORMAT for a malformed octree (mr_svo_collect_keys);
 * MR_ERR_NOMEM. */
int mr_svo_skeletonize(const mr_svo *svo, const mr_svo_skeleton_params *p, mr_svo_skeleton *out,
                       mr_error *err);
void mr_svo_skeleton_free(mr_svo_skeleton *s);

/* Hard segmentation: leaf_bone[i] = bone of leaf i (svo->leaves order), see
 * the header comment. svo must be the octree s was made from (MR_ERR_INVALID
 * when a leaf's cell is not in s's mapping). */
int mr_svo_skeleton_segment(const mr_svo *svo, const mr_svo_skeleton *s, uint32_t *leaf_bone,
                            mr_error *err);

/* Soft skin weights of every leaf (svo->leaves order): MR_SVO_INFLUENCES bone
 * indices and uint8 weights summing to 255 per leaf, see the header
 * comment. p: smooth_rounds and threads (NULL: defaults). Same errors as
 * mr_svo_skeleton_segment. */
int mr_svo_skeleton_weights(const mr_svo *svo, const mr_svo_skeleton *s,
                            const mr_svo_skeleton_params *p, uint16_t *joints, uint8_t *weights,
                            mr_error *err);

/* A posable copy of asset and svo (svo voxelised from asset, s made from
 * svo).
 * out_asset: a deep copy of asset plus one node per bone, named "bone<k>"
 * (k = 0 .. bone_count - 1), appended after the asset's nodes and parented
 * per the skeleton; root bones hang under the asset's root node (node 0).
 * Rest local transforms: a translation to the bone's position relative to
 * its parent bone (root bones: inverse(root global) * translation, so every
 * bone's rest global is a translation to its bind-space position). Every
 * mesh of the copy becomes skinned over the bone nodes (joint k = bone k,
 * inverse_bind = inverse of the bone's rest global as mr_pose_eval composes
 * it); rigid meshes get their vertices and normals baked into bind space
 * (rest global of their node), skinned meshes keep mesh space, so posing the
 * copy at rest reproduces the rest model. Each vertex takes the soft
 * weights of the leaf containing it (so mesh and voxels move alike); a
 * vertex outside every leaf (an octree of another asset) is bound wholly to
 * the nearest bone.
 * out_svo: a deep copy of svo whose palette names the bones (joints = bone
 * indices = joint indices of every mesh of out_asset, mesh and albedo kept,
 * weights from mr_svo_skeleton_weights); entries are shared and numbered by
 * first use in Morton order. When more than MR_SVO_MAX_PALETTE entries
 * arise the weights are re-quantised to multiples of 3, 5, 15, 17, 51, 85,
 * 255 until they fit (as mr_svo_voxelize does); MR_ERR_LIMIT if even 255
 * does not. Release with mr_svo_voxelize_free.
 * Errors: MR_ERR_INVALID for NULL arguments, an empty skeleton, a palette
 * entry naming a mesh the asset lacks, a leaf outside s's mapping, a
 * singular root transform; MR_ERR_CONFLICT when the asset already has a node
 * named "bone<k>"; MR_ERR_LIMIT beyond MR_MAX_ASSET_JOINTS bones or the node
 * cap; MR_ERR_NOMEM. On failure *out_asset and *out_svo are NULL. */
int mr_svo_skeleton_rig(const mr_asset *asset, const mr_svo *svo, const mr_svo_skeleton *s,
                        const mr_svo_skeleton_params *p, mr_asset **out_asset, mr_svo **out_svo,
                        mr_error *err);

#endif /* MR_SVO_SKELETON_H */
