/*
 * kind.h - what a geometry kind is: one descriptor (struct mr_kind) holding
 * its job name, its parameter table (params.h), its contracts and its ops.
 * Clients see kinds as opaque handles with accessors (microray.h: the
 * registry lookups, name, summary, parameter table, stats fields).
 *
 * A kind turns an imported asset into something Embree can trace and keeps
 * it up to date frame by frame:
 *   create      build the derived data once from the asset (for triangle
 *               meshes: vertex/index buffers sized for all of them); the
 *               context names the kind's own folder of the derived-data
 *               cache (<cache root>/<kind name>/, when it declares
 *               has_derived and the caller keeps a cache) and the threads;
 *   update      deform for this frame's pose and object transform (the
 *               frame says when and from where: kinds that refine for the
 *               screen need the camera);
 *   attach      put the geometry into an Embree scene under the given geometry
 *               id (the renderer's: it maps hits back to the object by it)
 *               with the build quality the renderer chose (REFIT for
 *               animated objects; see the refit trap in REFERENCE.md);
 *   commit      tell Embree the data changed (after update); returns whether
 *               anything did (false: the scene need not be committed again)
 *   normal      world-space shading normal at a hit (unnormalised is fine);
 *               ng is the hit's geometric normal as Embree returned it (the
 *               kind's own, for user geometry), for kinds that shade by it;
 *               the renderer asks for all of a packet's hits' normals
 *               before it shades any of them (their loads under way
 *               together): like every op a hit is shaded by, it reads the
 *               geometry and changes nothing, so their order is free;
 *   id_primitive  (NULL: prim itself) what the id pass's id.primitive
 *               names for a hit on primitive prim (as normal gets it),
 *               for a kind whose Embree primitives are pieces of what its
 *               users count (an instance traced as several pieces names
 *               the instance).
 *   tangent     (NULL: the kind has none) world-space tangent at a hit,
 *               along increasing u of the asset's texture coordinates
 *               (unnormalised is fine): false where the object has none
 *               there (a mesh without texture coordinates). The renderer
 *               makes it orthogonal to the shading normal and unit for the
 *               "t" pass (MR_AOV_T), 0 where false (paper 001, 3.3.4: the
 *               tangent space of normal mapping).
 *   tessellate  the kind's exact triangle reference, used for accuracy
 *               comparisons and as the pre-tessellation baseline;
 *   memory      bytes held by the kind's own data (not Embree's BVH).
 *   geometry_ids  how many consecutive Embree geometry ids attach uses
 *               (NULL: one). A kind that puts Embree instances into the
 *               scene needs one id per instance: the renderer hands it the
 *               first, and maps a hit's instID back to the object, passing
 *               the instance index (id - first) to normal as prim.
 *   lod         (NULL: none; has_lod kinds) the level of detail the frame
 *               just updated traces and its predicted error in pixels
 *               (mr_object_lod): false when the object picks none (it has
 *               no tolerance). The renderer lists them per object in the
 *               frame's stats.
 *   frame_stats the values of the kind's own per-frame statistics fields
 *               (`stats`, in that order; at most MR_FRAME_EXTRAS_MAX) for
 *               the frame just updated; the renderer combines them over
 *               the job's objects of the kind (summed, or the largest:
 *               mr_kind_stat.combine) and hands them on as the frame's
 *               extras (render/frame_stats.h), which reach stats.json, the
 *               HTTP stats and the events by the one generic path.
 *   rewind      (SEQUENTIAL kinds) back to the state before frame 0.
 *   checkpoint_* (SEQUENTIAL kinds, optional: all four or none) the state
 *               after the frames applied so far as bytes and back, so a
 *               resumed or retried job starts from the nearest checkpoint
 *               instead of frame 0 (render/checkpoint.h keeps them in the
 *               kind's derived-data folder, keyed by checkpoint_id and the
 *               frame count): checkpoint_every says how many frames apart
 *               (0: none), checkpoint_id hashes everything the state after
 *               N frames depends on (asset content, parameters, transform,
 *               the state format's version), save writes the state after
 *               `frames` frames, load restores it (validating what it
 *               reads: all or nothing, MR_ERR_FORMAT on anything wrong).
 *   surface_step  (NULL: 0) the size, in world units after the last
 *               update, of the steps the kind's surface makes around the
 *               smooth one it stands for, where primitive prim is hit at
 *               (u, v): the edge of the voxel hit. Faces of a staircase of
 *               boxes point up to 90 degrees away from the surface, so with
 *               a step the renderer lights by the shading normal alone and
 *               starts shadow rays a few steps along it, out of the
 *               staircase (the terminator problem; issue 13). Per hit,
 *               because one surface can be made of steps of many sizes
 *               (voxels selected coarser where they look small on screen,
 *               stretched by skinning). Exact surfaces (triangles) have
 *               none.
 *   shading_point  (NULL, or false: none) the point, near the hit point p
 *               of primitive prim at (u, v), of the smooth surface the
 *               kind's shading normals describe. A triangle mesh shaded by
 *               interpolated vertex normals stands for a curved surface its
 *               flat triangles cut through; where a triangle faces away
 *               from a light its normals face towards, a shadow ray from
 *               the flat triangle runs into the next one and the lit side
 *               ends in the triangles' jagged outline (the shadow
 *               terminator; issue 13). The renderer starts shadow rays from
 *               this point instead, when it lies on the viewer's side of
 *               the hit triangle, and then lets the shading normal alone
 *               decide which lights face the surface.
 *   reference   (NULL: the object is its own tessellation: a "tessellated"
 *               pass draws it as it is, and it has no ground truth) what a
 *               reference pass of type `type` draws for object obj of the
 *               kind (the job's "reference"; render/reference.h): objects
 *               appended to out, of any kind: its own kind with parameters
 *               overridden (mode "tessellated": the same micro-triangles as
 *               Embree triangles), or the asset as plain triangles
 *               (mr_kind_triangles(): the detailed mesh skinned directly),
 *               one per instance if need be; or nothing appended (MR_OK):
 *               the object has no such reference, and the pass draws its
 *               tessellation, or the object as it is, instead. Appended
 *               objects borrow what they do not change from obj (name,
 *               poses, the parameter block's arrays); a changed parameter
 *               block is a shallow copy in memory from mr_reference_alloc.
 *               The frame's error against a "tessellated" pass is the
 *               traversal's (0 for an exact one); against "ground_truth",
 *               the approximation's.
 * self_posed: the kind evaluates poses itself (say one per instance, maybe
 * of a skeleton it extracted): the renderer then passes a NULL pose to
 * update and leaves checking pose names to create.
 * animated: whether an object of the kind changes from frame to frame even
 * when its pose does not (NULL: only a pose animates it).
 * memory_floor: (NULL: none) the bytes an object of the kind surely holds
 * whatever its asset and its view, from its parameters alone (instances:
 * their matrices), which grow with the parameter memory_field names.
 * A job whose objects' floors pass the job's memory budget is refused
 * before anything is imported or allocated (mr_job_check_memory; the
 * daemon answers 422 naming the field); what an object holds beyond its
 * floor is the kind's to check against the budget as it allocates.
 * has_lod: the kind reads its objects' tolerance_px (microray.h) and picks
 * a level of detail per frame from the camera: the renderer updates such
 * an object every frame of a job of several, with view_only set when
 * nothing but the camera moved since its last update (the kind keeps its
 * posed geometry and re-picks its level).
 * frame_order: INDEPENDENT kinds can render any frame on its own;
 * SEQUENTIAL ones (a simulation) need frames 0..N-1 before N. The renderer
 * honours it: asked for frame N out of order (a resumed or retried job, a
 * frame range) it rewinds and replays the updates of the frames before N
 * without tracing them, so every frame is what an uninterrupted run gives.
 *
 * A new technique is a folder under core/kinds/ with its descriptor and one
 * line in core/kinds/registry.c; nothing else changes.
 */
#ifndef MR_KIND_H
#define MR_KIND_H

#include <embree3/rtcore.h>

#include "anim/pose.h"
#include "job.h"
#include "kinds/params.h"
#include "render/camera.h"

typedef struct mr_geom mr_geom; /* a kind's own instance data */

/* Largest |coordinate| any kind may hand Embree after update: far beyond any
 * scene, and well inside the range where Embree's builders and ray checks
 * work (about 1.8e19). */
#define MR_MAX_COORDINATE 1e15

/* The frame being prepared. */
typedef struct mr_geom_frame {
    size_t index;       /* frame number in the job */
    double time;        /* seconds on the job's timeline */
    mr_camera camera;   /* this frame's camera */
    int width, height;  /* film size in pixels */
    bool view_only;     /* only the camera moved since the last update: the object's pose
                           and transform are as they were (has_lod kinds re-pick a level) */
} mr_geom_frame;

/* Where a kind builds from: its folder of derived data and its threads. */
typedef struct mr_kind_context {
    const char *cache_dir; /* <cache root>/<kind name>, or NULL: no disk cache; valid
                              during create only */
    unsigned threads;      /* the job's thread count (0: all cores) */
    size_t memory_budget;  /* bytes the job's geometry may hold, 0: no limit
                              (mr_renderer_options.memory_budget) */
    /* the job's imported assets (mr_job.assets order), for kinds whose
     * parameters name more than the object's own asset (MR_PARAM_ASSET:
     * a height texture); they outlive the kind's object */
    const mr_asset *const *assets;
    size_t asset_count;
} mr_kind_context;

/* The objects a reference pass draws for the job's objects (kind.h
 * `reference`): object descriptions borrowing from the job's, and the
 * blocks of memory they own (changed parameter blocks, pose arrays),
 * freed with the list. */
typedef struct mr_reference_objects {
    mr_object_desc *objects;
    size_t count, cap;
    void **blocks;
    size_t block_count, block_cap;
} mr_reference_objects;

/* Appends a shallow copy of *desc. */
int mr_reference_objects_add(mr_reference_objects *out, const mr_object_desc *desc, mr_error *err);
/* bytes of zeroed memory owned by out (freed with it): a parameter block
 * to copy and change, an array of poses. */
void *mr_reference_alloc(mr_reference_objects *out, size_t bytes, mr_error *err);
/* Frees the list's arrays and blocks (never what its objects borrow) and
 * zeroes it. */
void mr_reference_objects_clear(mr_reference_objects *out);

/* The kind of an object that names none: the asset's own triangles, skinned
 * or rigid, as they are. A kind that approximates its asset's detailed mesh
 * draws this as its ground truth (kind.h `reference`). Defined by the
 * registry. */
const mr_kind *mr_kind_triangles(void);

typedef enum mr_frame_order {
    MR_FRAMES_INDEPENDENT = 0, /* any frame can be rendered alone */
    MR_FRAMES_SEQUENTIAL       /* frame N needs frames 0..N-1 (a simulation) */
} mr_frame_order;

struct mr_kind {
    const char *name;              /* the job's "kind" string and its block's key */
    const char *summary;           /* one line, for the schema and docs */
    const mr_param_table *params;  /* the block's fields, NULL: the kind takes none */
    mr_frame_order frame_order;
    bool has_derived;              /* keeps derived data in <cache root>/<name>/ */
    bool (*derives)(const mr_object_desc *desc); /* whether this object derives any (NULL:
                                                    every object of a has_derived kind) */
    const mr_kind_stat *stats;     /* its own per-frame stats fields */
    size_t stat_count;
    bool self_posed;
    bool takes_no_pose;            /* moves by itself (a simulation): an object's "pose" is
                                      refused when the job is read (mr_kind_takes_pose) */
    bool has_lod;
    bool (*animated)(const void *params);
    size_t (*memory_floor)(const void *params);
    const char *memory_field;
    int (*create)(const mr_asset *asset, const mr_object_desc *desc, const mr_kind_context *ctx,
                  mr_geom **out, mr_error *err);
    int (*update)(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                  const mr_mat4 *transform, unsigned threads, mr_error *err);
    int (*attach)(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                  enum RTCBuildQuality quality, mr_error *err);
    bool (*commit)(mr_geom *g);
    mr_vec3 (*normal)(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng);
    uint32_t (*id_primitive)(const mr_geom *g, unsigned prim);
    bool (*tangent)(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 *out);
    int (*tessellate)(const mr_geom *g, mr_trimesh *out, mr_error *err);
    size_t (*memory)(const mr_geom *g);
    uint64_t (*primitives)(const mr_geom *g);
    uint32_t (*geometry_ids)(const mr_geom *g);
    bool (*lod)(const mr_geom *g, uint32_t *level, double *error_px);
    void (*frame_stats)(const mr_geom *g, double *values);
    int (*rewind)(mr_geom *g, mr_error *err);
    uint32_t (*checkpoint_every)(const mr_geom *g);
    void (*checkpoint_id)(const mr_geom *g, uint8_t id[32]);
    int (*checkpoint_save)(const mr_geom *g, uint64_t frames, uint8_t **buf, size_t *size,
                           mr_error *err);
    int (*checkpoint_load)(mr_geom *g, uint64_t frames, const uint8_t *buf, size_t size,
                           mr_error *err);
    float (*surface_step)(const mr_geom *g, unsigned prim, float u, float v);
    bool (*shading_point)(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 p,
                          mr_vec3 *out);
    int (*reference)(const mr_object_desc *obj, mr_reference_type type, mr_reference_objects *out,
                     mr_error *err);
    void (*free)(mr_geom *g);
};

/* The registry's lookups (mr_kind_count, mr_kind_at, mr_kind_find) are
 * public: microray.h. */
/* Adds a kind (tests, plug-ins) before any job is parsed or rendered; not
 * thread-safe. Fails on a name already taken or a full registry. */
int mr_kind_register(const mr_kind *kind, mr_error *err);
/* <root>/<kind name> for a kind that keeps derived data, malloc'ed; NULL
 * (and MR_OK) when root is NULL/empty or the kind keeps none. */
int mr_kind_cache_dir(const mr_kind *kind, const char *root, char **out, mr_error *err);

/* mr_trimesh and mr_trimesh_free are public (microray.h, renderer). */
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

/* A USER geometry of count primitives with the kind's callbacks (user data
 * = user), attached under geom_id (RTC_INVALID_GEOMETRY_ID: whichever id
 * the scene gives it). Built LOW where the renderer asks for REFIT: over
 * user primitives, the trees Embree builds to refit sent rays into 2.2x
 * as many primitives as LOW trees, even on the frame they were built, and
 * rebuilding a few thousand boxes costs far less than that (README, the
 * micro-mesh goals: 20-25 % off a skinned example's frame). *out is NULL
 * on failure; what names the geometry in the error. */
int mr_geom_attach_user(RTCDevice device, RTCScene scene, unsigned geom_id,
                        enum RTCBuildQuality quality, unsigned count, void *user,
                        RTCBoundsFunction bounds, RTCIntersectFunctionN intersect,
                        RTCOccludedFunctionN occluded, const char *what, RTCGeometry *out,
                        mr_error *err);

#endif
