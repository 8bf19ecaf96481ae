/*
 * deform.h - per-frame selection, deformation and resampling of one octree
 * instance (paper 004, Willcocks, chapter 3; issue 5).
 *
 * The shared octree (svo.h) lives in bind space. Each frame, for each
 * instance, a top-down selection walks it from the root (3.2 "Selection"):
 * every visited voxel's box is deformed with two matrices, one mapped to
 * each of its extreme corners (3.3 "Direct", Fig. 16), and the deformed
 * box is projected to the screen. A voxel is
 *   (a) removed   when the deformed box (grown by its own largest side, a
 *                 margin for what its descendants may do) lies outside the
 *                 view frustum and culling is on;
 *   (b) selected  when it is a leaf, or its projected size (eq. 3.2.3, the
 *                 larger side of the screen rectangle in pixels) is below
 *                 the view's delta (eq. 3.2.5 with 1 replaced by delta), or
 *                 when the selection reached max_level;
 *   (c) expanded  otherwise (its existing children are visited).
 * The thesis also removes voxels hidden behind a hierarchical depth buffer
 * (eq. 3.2.6-3.2.7). A ray tracer cannot: shadow rays need what the camera
 * does not see, so there is no occlusion culling and eq. 3.2.6 is unused.
 *
 * Matrices at the extremes. Every voxel extreme takes the blended skin
 * matrix (sum of weight * joint matrix, the instance transform included) of
 * a palette entry: a leaf's own for both of its extremes; for an interior
 * voxel, that of its descendant leaf reached by always taking the lowest
 * existing child (b_min) and the highest (b_max). Matrices are 3x4 affine
 * (mr_affine, row-major: m[4 * row + col], translation in column 3); one
 * convention throughout (the thesis' Fig. 16 listing mixes two: REFERENCE.md).
 *
 * Resampling into a world-space octree (3.3), with the corrected floor
 * alignment of REFERENCE.md: for a deformed box [lo, hi] in a world cube of
 * edge S, with cells of level h being S / 2^h wide and cell index
 * floor((x - origin) / cell):
 *  - resize: h from the largest side (the coarsest level whose cell still
 *    holds it, eq. 3.3.6), then the 2 x 2 x 2 cells of level h + 1 whose
 *    indices per axis are floor(r c - 1/2) and that + 1, c the box centre in
 *    cells of level h + 1 (eq. 3.3.7-3.3.9 with floor); a box wider than a
 *    cell only by its outward float rounding (4 ulps of its coordinates)
 *    still fits that cell, so resize is exact under uniform scale;
 *  - emit: h from the smallest side (eq. 3.3.10), then every cell of level h
 *    with index floor(r lo) .. ceil(r hi) - 1 per axis (eq. 3.3.12
 *    corrected: covers the whole box). Boxes that would emit more than
 *    MR_SVO_EMIT_MAX_CELLS cells are emitted at a coarser level instead.
 *  Levels are clamped to the output depth. The cells become keys (morton.h),
 *  are radix sorted and compacted keeping the coarsest (svo_build.h), and
 *  built into the output octree. A cell emitted again by a later box of
 *  the same chunk of boxes is not sorted where the emission still
 *  remembers it (deform.c rs_write; packed keys, output depth <= 19):
 *  compaction would drop it, so the octree is the same.
 * Output voxels keep their source leaf's palette entry; their normal is the
 * bind-space normal moved by the cofactor of the mean of the two extreme
 * matrices (so non-uniform scale keeps it perpendicular), in world space.
 * The cofactor is taken times the sign of the determinant, so a mirroring
 * matrix keeps normals outward (a voxel has no winding that would flip with
 * it); a matrix that collapses the normal (zero scale) keeps the bind
 * normal. A selected interior voxel takes the palette entry of its lowest
 * descendant leaf (the b_min extreme's) and the mean of its leaves' bind
 * normals (mr_svo_extremes.normal).
 *
 * Numbers (deform.c): bind boxes and the deformation are evaluated in
 * double and the deformed box rounded outwards to float, so it always holds
 * the exact deformed box. Resampled cell ranges are decided with the plane
 * arithmetic of svo_trace.h ((origin - x) + K * size * 2^-21 in double),
 * so an emitted range covers its float box exactly as a ray cast sees it.
 * The output cube's edge is the largest extent times (1 + 2^-20), rounded
 * up to float (a point set of zero extent gets max(|coordinate|, 1) *
 * 2^-20); an empty selection gives an empty octree over [0, 1]^3.
 *
 * Results do not depend on the thread count.
 */
#ifndef MR_SVO_DEFORM_H
#define MR_SVO_DEFORM_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "anim/pose.h"
#include "math/mr_math.h"
#include "microray.h"
#include "kinds/svo/svo.h"

/* How an svo object's instances are deformed and traced (job "method"). */
typedef enum mr_svo_method {
    MR_SVO_RIGID = 0, /* instance transform only: the shared octree through Embree instancing */
    MR_SVO_DIRECT,    /* deformed voxel boxes (Fig. 16), traced as boxes, no resampling */
    MR_SVO_RESIZE,    /* resampled: 8 cells per box at a level from its largest side */
    MR_SVO_EMIT       /* resampled: every cell of a level from its smallest side covering the box */
} mr_svo_method;

/* Cap on cells one deformed box may emit (a box that would need more is
 * emitted at the next coarser level, repeatedly). */
#define MR_SVO_EMIT_MAX_CELLS 4096u

/* Per-frame inputs that say where voxels go.
 * Skinned: joint[m][j] is the world matrix of joint j of mesh m (global
 * joint transform * inverse bind, premultiplied by the instance transform);
 * mesh[m] is where voxels of mesh m without weights go (instance transform *
 * the mesh node's global pose, times the inverse of its rest global for
 * rigid meshes: the rule of voxelize.h). Voxel palette entries name
 * (attr.mesh, attr.joints[k]).
 * Field: when field is not NULL it replaces skinning: the matrix at a
 * bind-space point (test shapes, the thesis' shear and twist sweeps),
 * called with each voxel's b_min and b_max corners. It is called from
 * several threads at once and must be a pure function of the point. */
typedef struct mr_svo_deformer {
    size_t mesh_count;
    const mr_affine *const *joint; /* mesh_count arrays (NULL for a rigid mesh) */
    const uint32_t *joint_count;   /* mesh_count: entries of each joint[m] */
    const mr_affine *mesh;         /* mesh_count */
    mr_affine (*field)(void *ctx, mr_vec3 bind_point);
    void *field_ctx;
} mr_svo_deformer;

/* The skinning deformer of an asset under a pose, with the storage it
 * points into (the rule above: joint[m][j] = world * global(joint node) *
 * inverse bind; mesh[m] = world * global(mesh node), times the inverse of
 * that node's rest global for rigid meshes). */
typedef struct mr_svo_skin {
    mr_svo_deformer d;        /* points into the arrays below */
    mr_affine *storage;       /* every mesh's joints */
    const mr_affine **joint;  /* per mesh, into storage (NULL: rigid mesh) */
    uint32_t *joint_count;    /* per mesh */
    mr_affine *mesh;          /* per mesh */
    mr_mat4 *rest_inverse;    /* per mesh: inverse rest global of its node */
} mr_svo_skin;

/* Sizes *s for asset (zeroed first; release with mr_svo_skin_free, also
 * after a failure). Errors: MR_ERR_INVALID for a rigid mesh whose node's
 * rest transform is singular, MR_ERR_NOMEM. */
int mr_svo_skin_init(mr_svo_skin *s, const mr_asset *asset, mr_error *err);
/* Fills s->d's matrices for pose (of asset, as given to init) placed by
 * world. */
void mr_svo_skin_pose(mr_svo_skin *s, const mr_asset *asset, const mr_pose *pose,
                      const mr_mat4 *world);
void mr_svo_skin_free(mr_svo_skin *s);

/* Screen-space selection. view_proj maps world points to clip space
 * (OpenGL convention: visible when -w <= x, y, z <= w, w > 0). */
typedef struct mr_svo_view {
    bool enabled;       /* false: no camera, select every leaf */
    mr_mat4 view_proj;  /* row-major, applied to column vectors (mr_math.h) */
    int width, height;  /* pixels */
    float delta;        /* refinement threshold in pixels (> 0) */
    bool cull;          /* remove voxels outside the frustum (predicate a) */
} mr_svo_view;

/* Selected, deformed voxels of one instance (the "direct" output). */
typedef struct mr_svo_selection {
    size_t count, capacity;
    float *box;          /* 6 floats per voxel: world lo x, y, z, hi x, y, z */
    mr_svo_leaf *leaf;   /* world-space normal and palette entry per voxel */
    uint8_t *level;      /* source level per voxel */
    uint64_t visited;    /* voxels deformed during the walk (selected or not) */
} mr_svo_selection;

/* Side data derived once per shared octree for the selection: the palette
 * entries mapped to each interior node's two extremes, and the normal a
 * node selected whole shades with: the normalised sum of its leaves' unit
 * normals (the lowest leaf's when they cancel). */
typedef struct mr_svo_extremes {
    uint32_t node_count;
    uint16_t *lo_attr, *hi_attr; /* node_count each */
    uint8_t (*normal)[2];        /* node_count: the mean of its leaves' normals (encoded) */
} mr_svo_extremes;

/* out is zeroed first. Errors: MR_ERR_INVALID (NULL arguments, missing
 * arrays), MR_ERR_FORMAT (masks or child indices that do not fit, nodes
 * without children), MR_ERR_NOMEM. */
int mr_svo_extremes_build(const mr_svo *svo, mr_svo_extremes *out, mr_error *err);
void mr_svo_extremes_free(mr_svo_extremes *e);

/* Scratch arrays kept between calls of the _ws functions below, so a caller
 * that selects and resamples every frame allocates (and faults in fresh
 * pages) only while its frames grow. Opaque. One workspace serves one call
 * at a time (a per-frame caller keeps one per worker); a _ws function given
 * NULL allocates its own and frees it, as the plain functions do. It holds
 * about the largest arrays a call needed (resampling: ~44 bytes per cell). */
typedef struct mr_svo_workspace mr_svo_workspace;

/* Errors: MR_ERR_INVALID (NULL out), MR_ERR_NOMEM. */
int mr_svo_workspace_new(mr_svo_workspace **out, mr_error *err);
void mr_svo_workspace_free(mr_svo_workspace *ws);
/* Bytes the workspace holds now. */
size_t mr_svo_workspace_memory(const mr_svo_workspace *ws);
/* Where the last mr_svo_resample_ws through ws spent its time (0 for NULL,
 * before any, after a failed or empty one): emitting cells (the cube, each
 * box's level and cell range, the keys) and rebuilding (radix sort,
 * compaction, octree build). The svo kind reports them per frame. */
void mr_svo_workspace_resample_times(const mr_svo_workspace *ws, double *emit_s,
                                     double *rebuild_s);

/* Selects and deforms the voxels of svo for one instance (appends nothing:
 * out is reset, its buffers reused and grown). max_level: deepest level to
 * refine to (clamped to svo->depth). view may be NULL (= not enabled).
 * Errors: MR_ERR_INVALID for NULL svo/extremes/deformer/out, a palette
 * entry naming a mesh or joint the deformer lacks (checked for the entries
 * the walk reaches; message names the entry; joints with weight 0 are not
 * looked at), a non-finite matrix (any
 * of the deformer's, or the field's at some point), a bad view (non-finite
 * view_proj, width/height/delta not > 0), extremes of another octree, a
 * malformed octree or a deformed box beyond the float range;
 * MR_ERR_LIMIT above 2^32 - 1 voxels; MR_ERR_NOMEM. On error out->count
 * is 0. */
int mr_svo_select(const mr_svo *svo, const mr_svo_extremes *extremes, const mr_svo_deformer *d,
                  const mr_svo_view *view, unsigned max_level, unsigned threads,
                  mr_svo_selection *out, mr_error *err);
/* mr_svo_select with scratch from ws (NULL: its own); same results. */
int mr_svo_select_ws(const mr_svo *svo, const mr_svo_extremes *extremes, const mr_svo_deformer *d,
                     const mr_svo_view *view, unsigned max_level, unsigned threads, mr_svo_workspace *ws,
                     mr_svo_selection *out, mr_error *err);
void mr_svo_selection_free(mr_svo_selection *s);

/* Resamples sel with method RESIZE or EMIT into *out (freed first with
 * mr_svo_free; zeroed on error), a world-space octree of depth `depth`
 * (1..MR_SVO_MAX_DEPTH) over the cube around all boxes (edge = largest
 * extent, grown so no box touches its far faces). palette: the shared
 * octree's, which out borrows (mr_svo_build_frame: it must
 * outlive out). cells: NULL or receives the number of cells
 * emitted before compaction. Errors: MR_ERR_INVALID (bad method, depth,
 * non-finite boxes), MR_ERR_LIMIT, MR_ERR_NOMEM. An empty selection gives
 * an empty octree. */
int mr_svo_resample(const mr_svo_selection *sel, mr_svo_method method, unsigned depth,
                    const mr_svo_attr *palette, uint32_t palette_count, unsigned threads,
                    mr_svo *out, uint64_t *cells, mr_error *err);
/* mr_svo_resample with scratch from ws (NULL: its own); same results. */
int mr_svo_resample_ws(const mr_svo_selection *sel, mr_svo_method method, unsigned depth,
                       const mr_svo_attr *palette, uint32_t palette_count, unsigned threads,
                       mr_svo_workspace *ws, mr_svo *out, uint64_t *cells, mr_error *err);

#endif /* MR_SVO_DEFORM_H */
