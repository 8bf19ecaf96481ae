/*
 * pose.h - poses and linear blend skinning. The job's pose descriptions
 * (mr_pose_desc, mr_joint_override, mr_pose_desc_clear) are public:
 * microray.h.
 *
 * A pose is the global transform of every node of an asset at one instant:
 * clip keys sampled at a time (positions and scales linearly, rotations by
 * slerp; clamped to the first/last key outside their range), then explicit
 * joint overrides replace the local transform of the named nodes, then
 * globals are composed parent to child.
 */
#ifndef MR_POSE_H
#define MR_POSE_H

#include "asset/asset.h"

/* Global transforms of every node of one asset. */
typedef struct mr_pose {
    size_t node_count;
    mr_mat4 *local;
    mr_mat4 *global;
} mr_pose;

/* Makes a pose for asset (in its rest pose). Poses are only made here: the
 * struct carries private data behind the public fields, and mr_pose_eval
 * refuses (MR_ERR_INVALID) an asset other than the one given here. */
int mr_pose_new(const mr_asset *asset, mr_pose **out, mr_error *err);
void mr_pose_free(mr_pose *pose);

/* Evaluates desc at frame_time (seconds on the job's timeline). Unknown clip
 * or joint names fail with MR_ERR_NOT_FOUND naming them. desc may be NULL
 * (rest pose). */
int mr_pose_eval(mr_pose *pose, const mr_asset *asset, const mr_pose_desc *desc,
                 double frame_time, mr_error *err);

/* Checks that every clip and joint desc names exists in asset (and that its
 * transforms are finite) without evaluating anything: renderers call it for
 * every pose of a job before the first frame, so a bad name is reported up
 * front rather than halfway through a render. Same errors as mr_pose_eval. */
int mr_pose_desc_check(const mr_asset *asset, const mr_pose_desc *desc, mr_error *err);

/* Clip time actually sampled for desc at frame_time (after loop/clamp).
 * desc NULL: frame_time, looped. Non-finite times and clips of zero duration
 * give 0. */
double mr_pose_clip_time(const mr_clip *clip, const mr_pose_desc *desc, double frame_time);

/* Skins (or rigidly places) mesh `mesh_index` of asset under pose, then
 * applies object_transform: writes world-space positions (3 floats per
 * vertex) and unit normals (3 per vertex). Normals go through the cofactor
 * of each blended matrix, so non-uniform scale keeps them perpendicular.
 * Runs on `threads` workers (0 = all cores); results do not depend on it.
 * Vertices whose weights are all 0 follow the mesh's node. With a NULL pose
 * (or one whose node count does not match the asset) the mesh-space vertices
 * are written, moved by object_transform only; NULL object_transform means
 * identity; NULL out_normals skips normals. Bad mesh_index or NULL
 * out_positions: no-op. */
void mr_skin_mesh(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                  const mr_mat4 *object_transform, float *out_positions,
                  float *out_normals, unsigned threads);

/* mr_skin_mesh plus the mesh's tangents (asset.h: mr_mesh.tangents; 3
 * floats per vertex, world space, unit, orthogonal to the vertex's
 * output normal: moved by the vertex's matrix and made orthogonal to the
 * moved normal) into out_tangents; untouched when the mesh has no
 * tangents or out_tangents is NULL. */
void mr_skin_mesh_tangents(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                           const mr_mat4 *object_transform, float *out_positions,
                           float *out_normals, float *out_tangents, unsigned threads);

/* mr_skin_mesh_tangents for the listed vertices only (count indices into
 * the mesh, each below its vertex count; out_normals and out_tangents may
 * be NULL), each written at its own index of the output arrays (the
 * others are left as they are): the same bits as the whole mesh's call
 * gives those vertices. A mesh's level of detail poses only the vertices
 * it uses. */
void mr_skin_mesh_vertices(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                           const mr_mat4 *object_transform, const uint32_t *vertices, size_t count,
                           float *out_positions, float *out_normals, float *out_tangents,
                           unsigned threads);

/* The matrix mr_skin_mesh applies to each vertex of the mesh (the blended
 * skin matrix, or object * mesh node for rigid meshes and vertices without
 * influences): the accumulated matrices M_a of paper 000 (eq. 1) that
 * displaced micro-meshes interpolate (eq. 6). One per vertex; same
 * conditions and determinism as mr_skin_mesh. */
void mr_skin_matrices(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                      const mr_mat4 *object_transform, mr_affine *out_matrices, unsigned threads);

#endif
