/*
 * asset.h - what an imported model holds: meshes, node hierarchy, skins,
 * animation clips, cameras, as plain arrays (struct mr_asset). The handle,
 * its import caps, mr_asset_load/free and the accessors a client needs are
 * public (microray.h); the arrays are core's.
 *
 * Space conventions:
 *  - nodes[] are in parent-before-child order (parent < own index; root has
 *    parent -1); local is the node's rest transform relative to its parent.
 *  - A mesh that is not skinned is placed in the scene by the global
 *    transform of its node. A skinned mesh ignores its node's transform (the
 *    glTF rule; assimp's offset matrices already map mesh space to bone
 *    space): world = sum_i w_i * global(joint_node_i) * inverse_bind_i * v.
 *  - Skin influences: up to MR_MAX_INFLUENCES per vertex. assimp may deliver
 *    more; we keep the largest MR_MAX_INFLUENCES weights and renormalise them
 *    to sum to 1. A vertex whose weights sum to 0 (or that no bone names) is
 *    bound rigidly to the mesh's node instead.
 */
#ifndef MR_ASSET_H
#define MR_ASSET_H

#include "math/mr_math.h"
#include "microray.h"

#define MR_MAX_INFLUENCES 8

typedef struct mr_node {
    char *name;    /* never NULL (may be "") */
    int parent;    /* -1 for the root */
    mr_mat4 local; /* rest transform relative to the parent */
} mr_node;

typedef struct mr_mesh {
    char *name;
    int node;                  /* node that places the mesh */
    uint32_t vertex_count;
    uint32_t triangle_count;
    float *positions;          /* 3 per vertex, mesh space */
    float *normals;            /* 3 per vertex, unit; computed (area-weighted) when the file has none */
    float *uvs;                /* 2 per vertex or NULL */
    /* 4 per vertex (mr_mesh_tangents) when uvs are there, else NULL: a unit
     * tangent along increasing u orthogonal to the vertex normal, and the
     * handedness w (+1 or -1: the bitangent, along increasing v, is
     * w * normal x tangent), mesh space like the normals */
    float *tangents;
    uint32_t *indices;         /* 3 per triangle, all < vertex_count */
    /* Skin; joint_count == 0 for rigid meshes (then the arrays below are NULL). */
    uint32_t joint_count;
    int *joint_nodes;          /* node index of each joint */
    mr_mat4 *inverse_bind;     /* per joint: mesh space -> joint space */
    uint16_t *joints;          /* MR_MAX_INFLUENCES per vertex, indices into joint_nodes */
    float *weights;            /* MR_MAX_INFLUENCES per vertex, sum 1 (or all 0 = rigid) */
} mr_mesh;

typedef struct mr_vec3_key { double time; mr_vec3 value; } mr_vec3_key;
typedef struct mr_quat_key { double time; mr_quat value; } mr_quat_key;

/* Keys of one node in one clip, times in seconds, strictly increasing. */
typedef struct mr_channel {
    int node;
    size_t position_count, rotation_count, scale_count;
    mr_vec3_key *positions;
    mr_quat_key *rotations;
    mr_vec3_key *scales;
} mr_channel;

typedef struct mr_clip {
    char *name;
    double duration; /* seconds */
    size_t channel_count;
    mr_channel *channels;
} mr_clip;

typedef struct mr_camera_info {
    char *name;
    int node;          /* node carrying the camera (same name), -1 if none */
    mr_vec3 position;  /* in the node's space */
    mr_vec3 look_at;   /* direction, node space */
    mr_vec3 up;
    float yfov;        /* vertical field of view, radians; 0 for orthographic cameras */
    float aspect;      /* width / height, 0 if unknown */
} mr_camera_info;

typedef struct mr_image mr_image; /* asset/image.h */

struct mr_asset {
    char *path;
    mr_image *image;       /* an image asset (height texture, exemplar): no meshes; else NULL */
    size_t node_count, mesh_count, clip_count, camera_count;
    mr_node *nodes;
    mr_mesh *meshes;
    mr_clip *clips;
    mr_camera_info *cameras;
    size_t triangle_count; /* over all meshes */
};

/* mr_asset_from_mesh and mr_asset_faceted (assets made from arrays) are
 * public: microray.h. */

/* A deep copy of in's path, nodes (with room for extra_nodes more after
 * them; node_count counts the copied ones), clips and cameras, plus
 * mesh_count zeroed meshes and in's triangle_count, for a caller that makes
 * its own meshes (refine.h, the svo skeleton rig). *out is set even on
 * failure (a partial copy; release with mr_asset_free). Returns MR_OK or
 * MR_ERR_NOMEM. */
int mr_asset_copy_shell(const mr_asset *in, size_t extra_nodes, mr_asset **out);
/* Frees the arrays a mesh owns and zeroes it (the mesh struct itself is the
 * caller's). NULL is fine. */
void mr_mesh_release(mr_mesh *mesh);

/* Reduces one vertex's raw influences (count pairs, any count) to the stored
 * form: influences naming the same joint are summed, NaN / infinite /
 * non-positive weights are dropped, the MR_MAX_INFLUENCES largest are kept
 * (ties: the earlier one), sorted by decreasing weight and renormalised to sum
 * to 1. Joint indices above MR_MAX_ASSET_JOINTS are dropped. Unused slots
 * get joint 0, weight 0. Returns the number kept (0: the vertex is rigid and
 * all out_weights are 0), or MR_ERR_NOMEM when a long list (> 64 entries)
 * cannot get scratch memory. The importer uses it for every vertex; exposed
 * so tests and generated fixtures share the one rule. */
int mr_influences_normalize(const uint32_t *joints, const float *weights, size_t count,
                            uint16_t out_joints[MR_MAX_INFLUENCES],
                            float out_weights[MR_MAX_INFLUENCES]);

/* Fills mesh->tangents (replacing any) from its positions, normals, uvs
 * and indices, or frees them when it has no uvs. Per triangle the tangent
 * and bitangent are the directions of increasing u and v in its plane
 * (dp/du and dp/dv of the linear map from uv to position), normalised and
 * summed into its three vertices weighted by the triangle's area (like
 * the normals); per vertex the sum's part orthogonal to the normal,
 * normalised, is the tangent, and the handedness says on which side of
 * the normal's plane through the tangent the summed bitangent lies.
 * Triangles whose uvs are collinear (no uv direction) add nothing; a
 * vertex that gets no direction (all its triangles have such uvs, or the
 * sum lies along the normal) gets a unit vector orthogonal to its normal
 * (mr_v3_any_orthogonal) and w = +1. Vertices split at uv
 * seams (assimp splits them) get each side's own tangent. Returns MR_OK
 * or MR_ERR_NOMEM (tangents then NULL). */
int mr_mesh_tangents(mr_mesh *mesh);

/* Index of the node / clip with this exact name, or -1. */
int mr_asset_find_node(const mr_asset *asset, const char *name);
int mr_asset_find_clip(const mr_asset *asset, const char *name);
int mr_asset_find_camera(const mr_asset *asset, const char *name);

#endif
