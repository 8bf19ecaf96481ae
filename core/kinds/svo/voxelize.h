/*
 * voxelize.h - triangle meshes of an asset -> sparse voxel octree (paper
 * 004, Willcocks: shapes enter the pipeline as voxelised SVOs; the thesis
 * leaves the voxeliser open, this is ours; issue 5).
 *
 * Space ("bind space"): the voxels live where the skinning input lives, so a
 * voxel follows the skeleton when skinned with its palette entry's joints
 * (indices into asset->meshes[attr.mesh].joint_nodes) and inverse binds,
 * exactly like a vertex of that mesh (pose.h, mr_skin_mesh):
 *  - skinned meshes (joint_count > 0): mesh space (their node transform is
 *    ignored, the glTF rule of asset.h). Voxels with all-zero weights follow
 *    the mesh's node, as such vertices do;
 *  - rigid meshes (joint_count == 0): placed by the rest-pose global
 *    transform of their node. Their voxels have all-zero weights; a consumer
 *    moves them by global_pose(node) * inverse(global_rest(node)).
 *
 * Cube: the bounding box of all triangles in that space, made cubic (edge =
 * largest extent * (1 + 2^-9) plus a tiny absolute pad) and centred on the
 * box, so no vertex lies on the far boundary and every point of the mesh maps
 * to a cell index in [0, 2^depth).
 *
 * Surface mode: a finest-level voxel exists iff its closed cell overlaps
 * some triangle (separating-axis test, mr_tri_box_overlap, with each cell
 * grown by 1e-4 of a finest cell so rounding never loses a touching
 * triangle: conservative). Each voxel takes its attributes from the
 * triangle nearest to the cell centre (ties: lowest global triangle id, the
 * triangles of mesh 0 first), evaluated at the closest point of that
 * triangle to the centre:
 *  - normal: barycentric blend of the vertex normals, normalised (geometric
 *    normal if that vanishes, +z if the triangle is degenerate too), encoded
 *    with mr_svo_normal_encode;
 *  - skin: barycentric blend of the three vertices' influences (same joint
 *    summed), the 4 largest kept (ties: lower joint index), quantised to
 *    uint8 summing exactly to 255 by largest remainder (ties: larger weight
 *    first); all zero for rigid meshes and weightless points;
 *  - albedo: the mesh's linear RGB from the params, * 255 rounded.
 * Equal (albedo, mesh, joints, weights) share one palette entry, numbered
 * in order of first use along the Morton order. If more than
 * MR_SVO_MAX_PALETTE entries arise, the weights are re-quantised to
 * multiples of 3, 5, 15, 17, 51, 85, then 255 (each divides 255, so sums
 * stay exact) until the palette fits; if even 255 does not fit,
 * MR_ERR_LIMIT.
 *
 * Solid mode (depth <= MR_SVO_SOLID_MAX_DEPTH): surface voxels plus every
 * finest cell whose centre is inside the mesh. Inside is decided per row of
 * cells along +x: the row's centre line is intersected with every triangle
 * (exact-sign edge functions in the yz projection with a consistent
 * symbolic perturbation, so a line through a shared edge or vertex of a
 * watertight mesh crosses exactly once), and cells between crossings 1-2,
 * 3-4, ... are inside. Open meshes: a row with an odd number of crossings
 * (the line went through a hole) gets no interior at all, so holes cost
 * missing rows, never streaks to the cube boundary; self-intersecting or
 * nested shells follow the even-odd rule. Interior voxels copy the leaf
 * (normal and palette entry) of the nearest surface voxel of the same row
 * (ties: the one at lower x). Interior is stored at the finest level (no
 * coarse interior leaves), hence the depth cap.
 *
 * Output octrees have no leaf_keys (NULL: they would cost 16 bytes per leaf
 * on top of the leaf's 4 and the nodes' ~3) unless params.keep_leaf_keys is
 * set; mr_svo_collect_keys recomputes them from the nodes. Results are
 * bit-identical for any thread count.
 */
#ifndef MR_VOXELIZE_H
#define MR_VOXELIZE_H

#include <stdbool.h>

#include "asset/asset.h"
#include "kinds/svo/svo.h"

/* Deepest level solid voxelisation accepts: interior voxels are all
 * finest-level, 2^30 cells at depth 10. */
#define MR_SVO_SOLID_MAX_DEPTH 10u
/* Cap on voxels (and on intermediate voxel/triangle pairs) of one call;
 * larger requests fail with MR_ERR_LIMIT instead of exhausting memory
 * (~45 bytes per voxel at the peak). */
#define MR_SVO_VOXELIZE_MAX_VOXELS (1ull << 28)
/* Meshes one octree can name: mr_svo_attr.mesh is 8 bits. */
#define MR_SVO_VOXELIZE_MAX_MESHES 256u

typedef enum mr_svo_voxelize_mode {
    MR_SVO_VOXELIZE_SURFACE = 0,
    MR_SVO_VOXELIZE_SOLID = 1
} mr_svo_voxelize_mode;

typedef struct mr_svo_voxelize_params {
    unsigned depth;            /* 1..MR_SVO_MAX_DEPTH (solid: ..MR_SVO_SOLID_MAX_DEPTH) */
    mr_svo_voxelize_mode mode;
    const float *albedo;       /* 3 linear RGB floats per mesh (asset->mesh_count), or NULL:
                                * 0.8 grey; values clamped to [0, 1], non-finite rejected */
    unsigned threads;          /* 0 = all cores */
    bool keep_leaf_keys;       /* keep mr_svo.leaf_keys (default false: dropped) */
} mr_svo_voxelize_params;

/* Voxelises every triangle of asset into *out, a heap-allocated octree
 * (release with mr_svo_voxelize_free). Errors: MR_ERR_INVALID for NULL arguments, depth outside
 * the range, an unknown mode, a non-finite albedo or vertex position (the
 * message names mesh and vertex) or a non-finite rest transform;
 * MR_ERR_LIMIT for more than MR_SVO_VOXELIZE_MAX_MESHES meshes, more than
 * MR_SVO_VOXELIZE_MAX_VOXELS voxels or a palette that cannot fit;
 * MR_ERR_NOMEM. An asset without triangles gives an empty octree. */
int mr_svo_voxelize(const mr_asset *asset, const mr_svo_voxelize_params *p, mr_svo **out,
                    mr_error *err);

/* mr_svo_free and free of the struct itself; NULL is fine. */
void mr_svo_voxelize_free(mr_svo *svo);

/* Separating-axis test of a triangle against the closed axis-aligned box
 * centre +- half (13 axes: 3 box axes, the triangle normal, 9 edge x box
 * axis cross products), in double precision so float inputs up to FLT_MAX
 * neither overflow nor lose the test. Degenerate triangles (segments,
 * points) are handled: their zero axes never separate and the remaining
 * axes are complete for them. Touching counts as overlap. Returns false for
 * non-finite input or a negative half extent. */
bool mr_tri_box_overlap(const double center[3], const double half[3], const double v0[3],
                        const double v1[3], const double v2[3]);

/* Closest point of triangle (a, b, c) to p, as barycentric weights w
 * (w[0] + w[1] + w[2] = 1, all >= 0); works for degenerate triangles.
 * Returns the squared distance. */
double mr_tri_closest_point(const double p[3], const double a[3], const double b[3],
                            const double c[3], double w[3]);

/* Quantises n (<= MR_SVO_INFLUENCES) non-negative weights to multiples of
 * step (a divisor of 255) summing exactly to 255 by largest remainder (ties:
 * the earlier slot). All-zero (or non-finite) input gives all zeros. */
void mr_svo_quantize_weights(const float *w, unsigned n, unsigned step, uint8_t *out);

/* The cube mr_svo_voxelize would use for asset (see the header comment).
 * Fails like mr_svo_voxelize on non-finite input; an asset without
 * triangles gives origin 0, size 1. */
int mr_svo_voxelize_bounds(const mr_asset *asset, mr_vec3 *origin, float *size, mr_error *err);

#endif /* MR_VOXELIZE_H */
