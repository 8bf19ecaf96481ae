/*
 * geom.h - the one interface every geometry kind implements.
 *
 * A kind turns an imported asset into something Embree can trace and keeps
 * it up to date frame by frame:
 *   create      build the derived data once from the asset (for a triangle
 *               mesh: vertex/index buffers sized for all its meshes);
 *   update      deform for this frame's pose and object transform (the
 *               frame says when and from where: kinds that refine for the
 *               screen, like svo, need the camera);
 *   attach      put the geometry into an Embree scene under the given geometry
 *               id (the renderer's: it maps hits back to the object by it)
 *               with the build quality the renderer chose (REFIT for
 *               animated objects; see the refit trap in REFERENCE.md);
 *   commit      tell Embree the data changed (after update);
 *   normal      world-space shading normal at a hit (unnormalised is fine);
 *   tessellate  the kind's exact triangle reference, used for accuracy
 *               comparisons and as the pre-tessellation baseline;
 *   memory      bytes held by the kind's own data (not Embree's BVH).
 *   geometry_ids  how many consecutive Embree geometry ids attach uses
 *               (NULL: one). A kind that puts Embree instances into the
 *               scene needs one id per instance: the renderer hands it the
 *               first, and maps a hit's instID back to the object, passing
 *               the instance index (id - first) to normal as prim.
 * self_posed: the kind evaluates poses itself (svo: one per instance, maybe
 * of a skeleton it extracted): the renderer then passes a NULL pose to
 * update and leaves checking pose names to create.
 * A new technique is a new module implementing mr_geom_ops plus a schema
 * entry; the renderer does not change.
 */
#ifndef MR_GEOM_H
#define MR_GEOM_H

#include <embree3/rtcore.h>

#include "anim/pose.h"
#include "job.h"
#include "render/camera.h"

typedef struct mr_geom mr_geom; /* a kind's own instance data */

/* Largest |coordinate| any kind may hand Embree after update: far beyond any
 * scene, and well inside the range where Embree's builders and ray checks
 * work (about 1.8e19). */
#define MR_MAX_COORDINATE 1e15

/* A plain triangle soup in world space (tessellation output). */
typedef struct mr_trimesh {
    uint32_t vertex_count, triangle_count;
    float *positions;   /* 3 per vertex */
    uint32_t *indices;  /* 3 per triangle */
} mr_trimesh;

/* The frame being prepared. */
typedef struct mr_geom_frame {
    size_t index;       /* frame number in the job */
    double time;        /* seconds on the job's timeline */
    mr_camera camera;   /* this frame's camera */
    int width, height;  /* film size in pixels */
} mr_geom_frame;

typedef struct mr_geom_ops {
    const char *name;   /* the job's "kind" string */
    bool self_posed;
    int (*create)(const mr_asset *asset, const mr_object_desc *desc, mr_geom **out, mr_error *err);
    int (*update)(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                  const mr_mat4 *transform, unsigned threads, mr_error *err);
    int (*attach)(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                  enum RTCBuildQuality quality, mr_error *err);
    void (*commit)(mr_geom *g);
    mr_vec3 (*normal)(const mr_geom *g, unsigned prim, float u, float v);
    int (*tessellate)(const mr_geom *g, mr_trimesh *out, mr_error *err);
    size_t (*memory)(const mr_geom *g);
    uint64_t (*primitives)(const mr_geom *g);
    uint32_t (*geometry_ids)(const mr_geom *g);
    void (*free)(mr_geom *g);
} mr_geom_ops;

/* The kind table: ops for a kind, or NULL. */
const mr_geom_ops *mr_geom_kind_ops(mr_geom_kind kind);

void mr_trimesh_free(mr_trimesh *m);
/* A copy of a triangle soup (what a kind whose Embree form is already
 * triangles returns from tessellate). */
int mr_trimesh_copy(const float *positions, uint32_t vertex_count, const uint32_t *indices,
                    uint32_t triangle_count, mr_trimesh *out, mr_error *err);

/* Helpers for kinds that hand Embree plain triangles: a TRIANGLE geometry
 * reading the kind's own arrays in place (shared buffers: Embree refits over
 * them and its memory monitor counts only its BVH; the vertex array needs
 * one float of padding because Embree loads vertices with 16-byte reads),
 * attached under geom_id; and the per-frame "vertices changed". */
int mr_geom_attach_triangles(RTCDevice device, RTCScene scene, unsigned geom_id,
                             enum RTCBuildQuality quality, float *positions, uint32_t vertex_count,
                             uint32_t *indices, uint32_t triangle_count, RTCGeometry *out,
                             mr_error *err);
void mr_geom_commit_vertices(RTCGeometry geom);

/* Triangle meshes (core/kinds/mesh/mesh_kind.c). */
extern const mr_geom_ops mr_geom_mesh_ops;

/* Displaced micro-meshes baked from an asset's meshes (core/kinds/dmm/dmm_kind.c). */
extern const mr_geom_ops mr_geom_dmm_ops;

/* Sparse voxel octree instances (core/kinds/svo/svo_kind.c). */
extern const mr_geom_ops mr_geom_svo_ops;

#endif
