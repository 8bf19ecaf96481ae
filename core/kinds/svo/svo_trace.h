/*
 * svo_trace.h - ray casting of a sparse voxel octree (svo.h): the nearest
 * leaf voxel along a ray, and an any-hit query for shadow rays (paper 004,
 * 4.3, replaced: REFERENCE.md "004").
 *
 * The thesis restarts from the root after every empty node and pushes the
 * ray into the next cell by an unspecified epsilon, which is slow and skips
 * features thinner than the epsilon. This traversal keeps a fixed stack of
 * one entry per level instead (in the spirit of Laine and Karras 2010), so
 * it never restarts and never moves the ray:
 *  - Every t is that of an axis plane at an integer position k of the finest
 *    grid (2^21 cells per axis, whatever the octree's depth), computed in
 *    double from the integer: t(k) = (origin - org + k * size * 2^-21) /
 *    dir. k * size * 2^-21 is exact, so cell boundaries never accumulate
 *    error, and a plane shared by two cells gets one t for both: the
 *    children's closed t intervals tile their parent's exactly, and a ray
 *    that passes through a shared face, edge or corner touches every cell
 *    there (no leaks between voxels that share only an edge or a corner).
 *  - Cells are closed boxes: a ray that only grazes a leaf (enters and
 *    leaves it at the same t, through an edge or corner) hits it.
 *  - Children are visited in the order c ^ m, m the mask of axes along
 *    which dir is negative (Revelles-style mirroring). For two children the
 *    ray touches, the one earlier in that order ends no later than the other
 *    starts, so the first leaf the depth-first walk meets is the nearest:
 *    no sorting and no t-max bookkeeping, and the any-hit query is the same
 *    walk. One exception: a ray lying exactly in a midplane it is parallel
 *    to touches both halves over the same t interval; then the walk goes on
 *    after the first hit, pruning by the nearest t so far.
 *  - Per node: one t per axis (its midplane, (d0 + k * cell) / dir), and
 *    the touched children from nine comparisons between the midplane t and
 *    the node's interval, without branches (svo_trace.c).
 *  - Components of dir that are 0 (or -0) are handled explicitly: the ray is
 *    parallel to that axis' planes, its t interval there is unbounded, and
 *    the half of a node it lies in is chosen by comparing positions (on the
 *    midplane: both halves), so 0 * inf never produces a NaN. Denormal
 *    components are not zero and give large, finite t in double.
 * Non-finite org, dir, tmin or tmax (NaN; infinite org or dir) give no hit;
 * tmax may be +inf. No allocation, no recursion.
 */
#ifndef MR_SVO_TRACE_H
#define MR_SVO_TRACE_H

#include <stdbool.h>
#include <stdint.h>

#include "math/mr_math.h"
#include "kinds/svo/svo.h"

typedef struct mr_svo_hit {
    float t;          /* where the ray enters the leaf's box, clipped to tmin */
    uint32_t leaf;    /* index into svo->leaves; with a level of detail
                         (mr_svo_lod), leaf_count + n for interior node n */
    unsigned level;   /* the leaf's level, 0 (root leaf) .. depth */
    uint32_t x, y, z; /* its integer coordinates at that level, [0, 2^level) */
    int axis;         /* axis of the face the ray enters through (0, 1, 2; at an
                         edge or corner one of those faces' axes), or -1 when
                         the ray starts inside the leaf (t == tmin) */
    mr_vec3 ng;       /* that face's outward unit normal; 0 when axis == -1 */
} mr_svo_hit;

/* Nearest leaf whose closed box meets the ray org + t dir, t in [tmin,
 * tmax], in object space (dir need not be normalised). hit may be NULL.
 * Returns false and leaves hit untouched when nothing is hit, the octree is
 * empty or the input is not finite (see above). */
bool mr_svo_intersect(const mr_svo *svo, mr_vec3 org, mr_vec3 dir, float tmin, float tmax,
                      mr_svo_hit *hit);

/* Whether any leaf meets the ray segment (same rules as mr_svo_intersect). */
bool mr_svo_occluded(const mr_svo *svo, mr_vec3 org, mr_vec3 dir, float tmin, float tmax);

/* A subtree of the octree: interior node `node` at `level`, its cell xyz
 * at that level. Tracing from subtrees lets Embree's tree (SIMD boxes)
 * do the octree's top levels, where rays mostly cross empty space. */
typedef struct mr_svo_subtree {
    uint32_t node;
    uint32_t level;
    uint32_t xyz[3];
} mr_svo_subtree;

/* The subtrees to trace svo from: its interior nodes at `level`, or nearer
 * the root where a node has leaf children, so that every leaf lies below
 * exactly one. *out is allocated (free it with free()); an octree without
 * interior nodes has none (*out NULL, *count 0). MR_ERR_NOMEM;
 * MR_ERR_FORMAT for children beyond the node array. */
int mr_svo_subtrees(const mr_svo *svo, unsigned level, mr_svo_subtree **out, uint32_t *count, mr_error *err);
/* counts[L] for L = 0 .. max_level: how many subtrees mr_svo_subtrees
 * gives at level L, in one walk of the nodes above max_level (a caller
 * choosing a level by their number). MR_ERR_FORMAT as mr_svo_subtrees. */
int mr_svo_subtree_counts(const mr_svo *svo, unsigned max_level, uint32_t *counts, mr_error *err);
/* The finest-level cells [lo, hi) per axis that hold every leaf below s:
 * s's cell (below 0), or the box of its occupied cells `below` levels
 * under it (or its leaves, where they lie nearer), found by walking that
 * many levels of its nodes (a malformed octree: s's cell). False when s is
 * no cell of svo. */
bool mr_svo_subtree_cells(const mr_svo *svo, const mr_svo_subtree *s, unsigned below, uint32_t lo[3],
                          uint32_t hi[3]);

/* mr_svo_intersect / mr_svo_occluded over the leaves below s only: the
 * same t (bit for bit) and leaf as the whole walk finds in that cell.
 * False for a subtree that is not an interior node of svo. */
bool mr_svo_intersect_subtree(const mr_svo *svo, const mr_svo_subtree *s, mr_vec3 org, mr_vec3 dir, float tmin,
                              float tmax, mr_svo_hit *hit);
bool mr_svo_occluded_subtree(const mr_svo *svo, const mr_svo_subtree *s, mr_vec3 org, mr_vec3 dir, float tmin,
                             float tmax);
/* A level of detail for a cast: the walk hits an interior node as if it
 * were a leaf when its cell's edge is at most a . p + b, p the point (in
 * the octree's space) where the ray enters the cell; every node but the
 * root, a walk below a subtree its own node too (the whole walk's test of
 * that node: the same cut from any pieces). The caller makes a . p
 * + b what the screen allows at p (svo_kind.c: the camera's depth of p
 * times the tolerance over the focal length in pixels). The cell holds the
 * node's leaves, so the walk never hits later than without it (no holes),
 * and a ray's hits stay the same whatever rays it is traced with.
 * clip: a cut node is hit where the ray enters the part of its cell within
 * the box [clip_lo, clip_hi) of cells of level clip_level, which must hold
 * every leaf of the walk (a piece's box: svo_kind.c hands Embree that box,
 * and with the cut clipped to it no hit lies outside it), and missed when
 * the ray misses that part. */
typedef struct mr_svo_lod {
    double a[3], b;
    bool clip;
    unsigned clip_level;
    uint32_t clip_lo[3], clip_hi[3];
} mr_svo_lod;

/* n rays at once (n <= 32; rays past the 32nd are not traced): ray i is
 * org[i] + t dir[i], t in [tmin[i], tmax[i]], traced over the leaves
 * below s (NULL: the whole octree). With hit, the nearest leaf of each
 * ray, in hit[i] (untouched for a ray without one); hit NULL: any leaf
 * (mr_svo_occluded). Returns the mask of the rays that hit, bit i for ray
 * i: the same hits, bit for bit, as one query per ray. The rays take
 * turns in groups of MR_SVO_RAYS: one goes on until it enters a node,
 * whose children then come from memory while the others step. A single
 * ray in a deep octree waits for one miss after another, a level at a
 * time; the rays of a packet part ways below the top levels, so their
 * misses can overlap. lod: NULL, or the level of detail above (an octree
 * whose leaf_count + node_count passes 2^32 - 1 is walked without it). */
#define MR_SVO_RAYS 8
uint32_t mr_svo_intersect_rays(const mr_svo *svo, const mr_svo_subtree *s, unsigned n, const mr_vec3 *org,
                               const mr_vec3 *dir, const float *tmin, const float *tmax, const mr_svo_lod *lod,
                               mr_svo_hit *hit);

/* Where the whole walk meets subtree s along a ray of direction dir,
 * relative to other disjoint subtrees: of two subtrees holding hits at
 * one t, the whole walk reports the one with the smaller order (its child
 * order is mirrored along the axes dir runs down, and a ray crosses
 * mirrored cells in increasing order). */
uint64_t mr_svo_subtree_order(const mr_svo_subtree *s, mr_vec3 dir);

/* Object-space box of the occupied part of the octree: the leaves' box
 * when the octree knows it (mr_svo.has_occupied), else the cube shrunk to
 * the halves of the root that hold children; rounded outwards to float so
 * the box always contains every leaf. Returns false (lo = hi = origin) for
 * an empty octree or NULL svo. */
bool mr_svo_bounds(const mr_svo *svo, float lo[3], float hi[3]);
/* The same box in cells of the finest level, [lo, hi) (not rounded). */
bool mr_svo_bounds_cells(const mr_svo *svo, uint32_t lo[3], uint32_t hi[3]);

#endif /* MR_SVO_TRACE_H */
