/*
 * svo.h - sparse voxel octree (SVO) of one voxelised asset (paper 004,
 * Willcocks, chapters 3-4; issue 5): the shared, read-only data every
 * instance of an `svo` object points at, and the per-frame world-space
 * octrees that `resize` / `emit` rebuild.
 *
 * Grid. An octree of depth D (1..MR_SVO_MAX_DEPTH) divides the axis-aligned
 * cube [origin, origin + size]^3 into 2^D cells per axis. A voxel at level l
 * (0 = the whole cube, D = finest) has integer coordinates x, y, z in
 * [0, 2^l). Its key (mr_svo_key) is the Morton code of its coordinates
 * scaled to the finest level, (x << (D - l), ...), plus the level, so a
 * voxel's code is the code of its first (lowest-corner) finest descendant
 * and codes of nested voxels share a prefix of 3l bits (morton.h).
 *
 * Node layout (chosen here; the thesis gives none: REFERENCE.md). Leaves
 * may sit at any level (a rebuilt octree keeps the coarsest of nested
 * voxels), so every interior node says which children exist and which of
 * those are leaves:
 *  - interior node i: child_mask[i] (bit c = child c exists; child c covers
 *    x + (c & 1), y + ((c >> 1) & 1), z + (c >> 2) at the next level),
 *    leaf_mask[i] (subset of child_mask: those children are leaves),
 *    first_node[i]: interior children, in increasing c, at nodes
 *    first_node[i] + 0, 1, ...; first_leaf[i]: leaf children, in increasing
 *    c, at leaves first_leaf[i] + 0, 1, .... So child c's index is its base
 *    plus the popcount of the lower bits of its own mask. 10 bytes.
 *  - leaf: 4 bytes (mr_svo_leaf): an octahedral unit normal (8 + 8 bits)
 *    and an index into the attribute palette (albedo and skin weights are
 *    shared by many voxels: a skinned character has a few thousand distinct
 *    quantised weight sets).
 *  Node 0 is the root. An empty octree has node_count 0 and leaf_count 0;
 *  an octree whose root itself is a leaf (one voxel covering the cube) has
 *  node_count 0 and leaf_count 1.
 *  With surface voxels about 1/3 of a leaf's cost is its ancestors, i.e.
 *  ~4 + 0.33 x 10 = 7.3 bytes per leaf voxel (measured figures in README).
 */
#ifndef MR_SVO_H
#define MR_SVO_H

#include <stddef.h>
#include <stdint.h>

#include "math/mr_math.h"
#include "microray.h"

/* Deepest level: 21 bits per axis in a 63-bit Morton code. */
#define MR_SVO_MAX_DEPTH 21u

/* Bits set in a child or leaf mask: mr_popcount32's SWAR on 8 bits (a
 * step fewer, in the walk's inner loop). */
static inline unsigned mr_svo_popcount8(unsigned v)
{
    v &= 0xffu;
    v = v - ((v >> 1) & 0x55u);
    v = (v & 0x33u) + ((v >> 2) & 0x33u);
    return (v + (v >> 4)) & 0x0fu;
}

/* Skin influences kept per palette entry. */
#define MR_SVO_INFLUENCES 4u
/* Palette entries are indexed by 16 bits. */
#define MR_SVO_MAX_PALETTE 65536u

/* A voxel: Morton code of its lowest finest-level descendant, and its
 * level. Sorted by (code, level); two keys are nested when the coarser one's
 * 3 * level code prefix equals the finer one's. */
typedef struct mr_svo_key {
    uint64_t code;
    uint32_t level;
} mr_svo_key;

/* Per-voxel attributes, 4 bytes. */
typedef struct mr_svo_leaf {
    uint8_t normal[2]; /* octahedral encoding, mr_svo_normal_encode */
    uint16_t attr;     /* index into mr_svo.palette */
} mr_svo_leaf;

/* Shared attributes: linear albedo and skin weights (joint indices of the
 * source mesh's skin, weights / 255 summing to 255; all zero weights =
 * rigid). */
typedef struct mr_svo_attr {
    uint8_t albedo[3];
    uint8_t mesh;                            /* source mesh of the asset (skin owner) */
    uint16_t joints[MR_SVO_INFLUENCES];
    uint8_t weights[MR_SVO_INFLUENCES];
} mr_svo_attr;

typedef struct mr_svo {
    unsigned depth;        /* D, 1..MR_SVO_MAX_DEPTH */
    mr_vec3 origin;        /* cube corner (object space) */
    float size;            /* cube edge, > 0 */
    uint32_t node_count;
    uint32_t leaf_count;
    uint32_t palette_count;
    uint32_t *first_node;  /* node_count each */
    uint32_t *first_leaf;
    uint8_t *child_mask;
    uint8_t *leaf_mask;
    mr_svo_leaf *leaves;   /* leaf_count */
    mr_svo_key *leaf_keys; /* leaf_count, or NULL: the key of each leaf. mr_svo_build fills
                            * it; mr_svo_voxelize drops it unless asked to keep it, and
                            * files (svo_file.h) never store it: 16 bytes per leaf, more
                            * than the leaf itself. mr_svo_collect_keys recomputes it */
    mr_svo_attr *palette;  /* palette_count */
    bool has_occupied;     /* occupied_lo/hi hold the leaves' box (mr_svo_build fills it,
                            * mr_svo_fit_occupied for octrees made otherwise) */
    uint32_t occupied_lo[3], occupied_hi[3]; /* finest-level cells: every leaf lies in
                                              * [lo, hi) on each axis */
    bool palette_borrowed; /* palette is another octree's (mr_svo_build_frame):
                            * never written or freed through this one, not counted by
                            * mr_svo_memory */
} mr_svo;

void mr_svo_free(mr_svo *svo);
/* Frees leaf_keys and sets it to NULL (NULL svo is fine): nothing in the
 * renderer reads them, and they would double the octree's memory. */
void mr_svo_drop_leaf_keys(mr_svo *svo);
/* Bytes held by the octree's own arrays (a borrowed palette is its owner's). */
size_t mr_svo_memory(const mr_svo *svo);

/* Walks the octree depth-first in child order and writes, for every leaf in
 * Morton order, its key (keys) and its index in leaves (leaf_index); either
 * may be NULL, each has room for leaf_count. Checks the structure on the
 * way: MR_ERR_FORMAT for masks, indices or depths that do not fit, or a leaf
 * count that differs from the leaves reached. */
int mr_svo_collect_keys(const mr_svo *svo, mr_svo_key *keys, uint32_t *leaf_index, mr_error *err);

/* Grows the box [lo, hi) of finest-level cells by the occupied cells below
 * interior node n (at `level`, cell xyz) down to level `stop` (> level):
 * its leaves, and its interior nodes at `stop` whole. Children whose cell
 * the box already holds are skipped (nothing below them can grow it), so
 * once the box spans the model most of the octree is not visited.
 * MR_ERR_FORMAT for masks or child indices that do not fit, among the
 * nodes it visits. */
int mr_svo_grow_occupied(const mr_svo *svo, uint32_t n, unsigned level, const uint32_t xyz[3], unsigned stop,
                         uint32_t lo[3], uint32_t hi[3], mr_error *err);

/* Fills svo's occupied box from its leaves (mr_svo_grow_occupied from the
 * root, for octrees read from a file or put together without
 * mr_svo_build). An empty octree has none. MR_ERR_FORMAT as
 * mr_svo_grow_occupied, and for leaves without nodes. */
int mr_svo_fit_occupied(mr_svo *svo, mr_error *err);

/* Octahedral unit-vector encoding, 8 bits per coordinate; decode gives a
 * unit vector within ~1 degree of the input. Non-finite or zero input
 * encodes +z. */
void mr_svo_normal_encode(mr_vec3 n, uint8_t out[2]);
/* The first n (<= MR_SVO_NORMAL_LANES) normals at once (lane i: nx[i],
 * ny[i], nz[i]), each lane's code exactly mr_svo_normal_encode's; lanes
 * n.. of nx, ny, nz are overwritten. For callers with many normals
 * (selection re-encodes every moved normal each frame): one normal costs
 * a whole round, as mr_svo_normal_encode does, so they gather them. */
#define MR_SVO_NORMAL_LANES 8
void mr_svo_normal_encode_lanes(unsigned n, float nx[MR_SVO_NORMAL_LANES], float ny[MR_SVO_NORMAL_LANES],
                                float nz[MR_SVO_NORMAL_LANES], uint8_t out[MR_SVO_NORMAL_LANES][2]);
mr_vec3 mr_svo_normal_decode(const uint8_t in[2]);
/* The decoded direction before normalisation (on the octahedron |x| + |y| +
 * |z| = 1): for code that only needs the direction. The square's point,
 * the lower hemisphere's (|x| + |y| > 1) unfolded back over the diagonals,
 * (1 - |y|) sign(x), (1 - |x|) sign(y) with sign(-0) = 1. Inline: the
 * selection takes it for every moved normal. */
static inline mr_vec3 mr_svo_normal_direction(const uint8_t in[2])
{
    const float x = (float)in[0] * (2.0f / 255.0f) - 1.0f;
    const float y = (float)in[1] * (2.0f / 255.0f) - 1.0f;
    const float z = 1.0f - fabsf(x) - fabsf(y);
    if (z < 0.0f)
        return mr_v3((1.0f - fabsf(y)) * (x < 0.0f ? -1.0f : 1.0f), (1.0f - fabsf(x)) * (y < 0.0f ? -1.0f : 1.0f), z);
    return mr_v3(x, y, z);
}

#endif /* MR_SVO_H */
