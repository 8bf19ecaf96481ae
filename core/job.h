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

#define MR_MAX_ASSETS 256
#define MR_MAX_OBJECTS 1024
#define MR_MAX_LIGHTS 64
#define MR_MAX_FRAMES 100000
#define MR_MAX_SPP 1024
#define MR_MAX_JOINT_OVERRIDES 1024
#define MR_MAX_JOB_TRIANGLES (32u * 1024u * 1024u) /* over all objects (each holds its own copy) */
#define MR_MAX_NAME 256         /* bytes in any name or id */
#define MR_MAX_PATH 4096        /* bytes in an asset path */

/* A geometry kind (core/kinds/kind.h): its descriptor, from the registry. */
typedef struct mr_kind mr_kind;

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

typedef struct mr_object_desc {
    char *name;
    size_t asset;            /* index into mr_job.assets */
    const mr_kind *kind;     /* never NULL in a parsed job */
    void *params;            /* the kind's parameter struct (its table's size), owned;
                                NULL for a kind without parameters */
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
