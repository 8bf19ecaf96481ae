/*
 * displaced_kind.h - the displacement-mapped kind ("kind": "displaced",
 * paper 003, issue 14): a base mesh with texture coordinates, skinned or
 * rigid, displaced along its unit interpolated normals by a height texture
 * or a procedural tiling-and-blending texture, traced without tessellation
 * (or tessellated, or ray marched, for comparison). Its job block and
 * descriptor; displaced_kind.c says how it works.
 */
#ifndef MR_DISPLACED_KIND_H
#define MR_DISPLACED_KIND_H

#include <stdbool.h>
#include <stdint.h>

#include "kinds/kind.h"

typedef enum mr_displaced_method {
    MR_DISPLACED_TESSELLATION_FREE = 0, /* D-BVH traversal in an Embree user geometry */
    MR_DISPLACED_TESSELLATED,           /* the same surface as Embree triangles (reference) */
    MR_DISPLACED_RAYMARCH               /* fixed-step ray marching (the thesis' comparator) */
} mr_displaced_method;

#define MR_DISPLACED_MAX_LEVEL 16u
/* Levels of detail an object with "tolerance_px" keeps (mip levels). */
#define MR_DISPLACED_LOD_MAX 16u
#define MR_DISPLACED_MAX_RANGE 4096u
#define MR_DISPLACED_DEFAULT_RANGE 64u
#define MR_DISPLACED_DEFAULT_STEPS 300u
#define MR_DISPLACED_MAX_STEPS 100000u

/* The "displaced" block of a job object. */
typedef struct mr_displaced_params {
    uint32_t texture;       /* 1 + index of the height texture asset, 0: none */
    bool procedural;        /* the "procedural" block was given */
    uint32_t example;       /* procedural: 1 + index of the exemplar asset */
    float uv_offset[2];     /* procedural: eq. 4.5 offset */
    float uv_scale;         /* procedural: eq. 4.5 scale */
    float triangle_size;    /* procedural: lattice triangle edge in texture space */
    uint32_t seed;          /* procedural: lattice hash seed */
    float scale, offset;    /* height = offset + scale * texture value (0..1 for integer images) */
    uint32_t level;         /* texture: mip level sampled */
    uint32_t range;         /* procedural: subdivisions per lattice square (power of two) */
    int method;             /* mr_displaced_method */
    uint32_t steps;         /* raymarch: samples per ray and base triangle */
    int local;              /* mr_dlocal: leaf intersection */
} mr_displaced_params;

extern const mr_kind mr_kind_displaced;

#endif
