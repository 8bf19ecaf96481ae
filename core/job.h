/*
 * job.h - a render job as plain C structs: what to load, how to pose it,
 * where the camera goes, which frames to render and how to write them.
 *
 * The server parses and validates job JSON (server/job_json.c) into this
 * form; core never sees JSON. Every string and array here is owned by the
 * job and released by mr_job_free(). Caps below are enforced by the parser
 * and documented in the README.
 */
#ifndef MR_JOB_H
#define MR_JOB_H

#include "anim/pose.h"
#include "asset/refine.h"
#include "render/camera.h"
#include "render/exr.h"
#include "kinds/svo/deform.h"
#include "kinds/svo/voxelize.h"

#define MR_MAX_ASSETS 256
#define MR_MAX_OBJECTS 1024
#define MR_MAX_LIGHTS 64
#define MR_MAX_FRAMES 100000
#define MR_MAX_SPP 1024
#define MR_MAX_JOINT_OVERRIDES 1024
#define MR_MAX_JOB_TRIANGLES (32u * 1024u * 1024u) /* over all objects (each holds its own copy) */
#define MR_MAX_NAME 256         /* bytes in any name or id */
#define MR_MAX_PATH 4096        /* bytes in an asset path */

/* Geometry kinds (core/kinds/). Each later technique adds one. */
typedef enum mr_geom_kind { MR_GEOM_MESH = 0, MR_GEOM_DMM, MR_GEOM_SVO } mr_geom_kind;

/* How a dmm object is traced (issue 4). */
typedef enum mr_dmm_mode {
    MR_DMM_TESSELLATED = 0, /* micro-triangles expanded into Embree triangles (reference) */
    MR_DMM_BASE,            /* skinned base mesh, prism traversal (paper 000, Alg. 2/4) */
    MR_DMM_INTERPOLATED     /* interpolated matrices, Bezier bounds (paper 000, Alg. 1/3) */
} mr_dmm_mode;

/* How micro-vertices follow the skeleton: along the skinned base mesh
 * (eq. 5) or under interpolated accumulated matrices (eq. 6-8). Mode BASE
 * implies DEFORM_BASE, INTERPOLATED implies DEFORM_INTERPOLATED; TESSELLATED
 * expands either. */
typedef enum mr_dmm_deform { MR_DMM_DEFORM_BASE = 0, MR_DMM_DEFORM_INTERPOLATED } mr_dmm_deform;

/* Shading normal of a dmm hit: the micro-triangle's geometric normal, or
 * the rest-pose micro-triangle normal moved by the interpolated matrix at
 * the hit (the paper's Fig. 1c "interpolated-matrix normals"). */
typedef enum mr_dmm_normals { MR_DMM_NORMALS_GEOMETRIC = 0, MR_DMM_NORMALS_MATRIX } mr_dmm_normals;

#define MR_DMM_DEFAULT_LEVEL 3u
#define MR_DMM_DEFAULT_BASE_RATIO 0.25f

/* Bake parameters of a dmm object ("dmm" in the job). */
typedef struct mr_dmm_desc {
    unsigned level;          /* subdivision level 0..5 (MR_UMESH_MAX_LEVEL); the largest
                                when adaptive */
    bool adaptive;           /* per-triangle levels from the detail ("levels": "adaptive") */
    float base_ratio;        /* base / detailed triangles, (0, 1]; used when base_triangles is 0 */
    uint32_t base_triangles; /* target base triangle count per mesh, or 0 */
    mr_dmm_mode mode;
    mr_dmm_deform deform;
    mr_dmm_normals normals;
    const char *cache_dir;   /* not from JSON: where baked DMMs are kept (core/kinds/dmm/dmm_file.h),
                                NULL = none; borrowed, must outlive the renderer */
} mr_dmm_desc;

/* An asset's "refine" (issue 4: detailed skinned meshes made from low-poly
 * rigs by core/asset/refine.h). The job allows less than refine.h does:
 * each round multiplies triangles by 4, and 4 rounds already turn a
 * 5000-triangle character into 1.3 million. */
#define MR_ASSET_REFINE_MAX_ROUNDS 4u
#define MR_ASSET_REFINE_MAX_OCTAVES 8u
#define MR_ASSET_REFINE_DEFAULT_ROUNDS 2u
#define MR_ASSET_REFINE_DEFAULT_FREQUENCY 8.0f
#define MR_ASSET_REFINE_DEFAULT_OCTAVES 3u
#define MR_ASSET_REFINE_DEFAULT_SEED 1u

typedef struct mr_asset_desc {
    char *name;   /* key in the job's "assets" object */
    char *path;   /* server-side path, resolved by the server before rendering;
                     for an "id" asset the server fills in the stored file */
    char *id;     /* SHA-256 (64 hex) of an asset uploaded to the daemon, or NULL */
    bool refine;  /* "refine" given: the import is refined (mr_refine_asset) once */
    mr_refine_params refine_params; /* when refine; threads 0 (the worker sets its own) */
} mr_asset_desc;

/* Sparse voxel octree objects (issue 5, paper 004): the asset voxelised
 * once (shared by all instances), each instance placed by its own transform
 * and pose. */
#define MR_SVO_DEFAULT_DEPTH 8u
#define MR_SVO_JOB_MAX_DEPTH 12u        /* 4096^3; surface voxels of a character: ~15 M */
#define MR_SVO_MAX_INSTANCES 100000u    /* per object */
#define MR_SVO_DEFAULT_DELTA 1.0f       /* pixels */

typedef struct mr_svo_instance_desc {
    mr_mat4 transform;       /* instance to object space (then the object's transform) */
    bool has_pose;           /* else the object's pose (or rest) */
    mr_pose_desc pose;
} mr_svo_instance_desc;

typedef struct mr_svo_desc {
    unsigned depth;              /* voxelisation depth 1..MR_SVO_JOB_MAX_DEPTH */
    mr_svo_voxelize_mode voxelize;
    mr_svo_method method;
    float delta;                 /* screen-space refinement threshold, pixels, > 0 */
    bool cull;                   /* frustum culling of deformed voxels */
    bool skeleton;               /* extract a skeleton (chapter 5) and skin to it */
    float omega;                 /* skeleton feature size (fraction of the cube), 0 = default */
    size_t instance_count;       /* 0 = one instance at the object's transform */
    mr_svo_instance_desc *instances;
    const char *cache_dir;       /* not from JSON: where voxelised assets are kept, NULL = none;
                                    borrowed, must outlive the renderer */
} mr_svo_desc;

typedef struct mr_object_desc {
    char *name;
    size_t asset;            /* index into mr_job.assets */
    mr_geom_kind kind;
    mr_dmm_desc dmm;         /* kind MR_GEOM_DMM only */
    mr_svo_desc svo;         /* kind MR_GEOM_SVO only */
    mr_mat4 transform;       /* object to world, applied after posing */
    mr_vec3 color;           /* Lambert albedo, linear */
    size_t pose_count;       /* 0 = rest pose; 1 = same for every frame; else one per frame */
    mr_pose_desc *poses;
} mr_object_desc;

typedef struct mr_light_desc {
    mr_vec3 direction;       /* unit; the direction light travels (sun rays) */
    mr_vec3 color;           /* linear, already multiplied by intensity */
} mr_light_desc;

typedef enum mr_camera_source { MR_CAMERA_SOURCE_PATH = 0, MR_CAMERA_SOURCE_NODE } mr_camera_source;

typedef struct mr_camera_desc {
    mr_camera_source source;
    mr_camera_path path;     /* SOURCE_PATH */
    size_t node_asset;       /* SOURCE_NODE: asset holding the camera ... */
    char *node_name;         /* ... and its camera (or node) name */
} mr_camera_desc;

typedef struct mr_output_desc {
    int width, height;       /* 1..MR_MAX_RESOLUTION, width*height <= MR_MAX_PIXELS */
    int spp;                 /* samples per pixel, 1..MR_MAX_SPP */
    bool shadows;            /* trace shadow rays to directional lights */
    uint32_t seed;           /* jitter seed */
    mr_exr_options exr;
} mr_output_desc;

#define MR_MAX_PRIORITY 1000     /* priorities run from -1000 to 1000 */
#define MR_MAX_RETRIES 10        /* per frame */

typedef struct mr_job {
    char *name;
    int priority;            /* queue order in the daemon: higher first (default 0) */
    int max_retries;         /* failed attempts allowed per frame (default 2) */
    size_t asset_count, object_count, light_count;
    mr_asset_desc *assets;
    mr_object_desc *objects;
    mr_light_desc *lights;
    mr_vec3 ambient;         /* linear radiance added to every hit */
    mr_vec3 background;      /* colour of missed samples, linear, not premultiplied */
    float background_alpha;  /* alpha of missed samples */
    mr_camera_desc camera;
    double fps;              /* frames per second of the timeline (> 0) */
    size_t frame_count;      /* 1..MR_MAX_FRAMES */
    double *frame_times;     /* seconds, one per frame */
    mr_output_desc output;
} mr_job;

/* Frees everything the job owns, then the job. NULL is fine. */
void mr_job_free(mr_job *job);

#endif
