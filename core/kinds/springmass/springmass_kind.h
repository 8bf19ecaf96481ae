/*
 * springmass_kind.h - the spring-mass kind ("kind": "springmass", paper 001,
 * Mosegaard and Sorensen): a coarse grid of nodes filling the asset's mesh
 * is simulated as a spring-mass system (sim.h), and the detailed mesh
 * follows it through one of the paper's mappings (map.h), frame by frame.
 *
 * Frame k shows the simulation after k * steps_per_frame steps of dt: the
 * simulation has its own clock, starting at 0 on frame 0 whatever the
 * job's frame times; the paths of pins and probes and the force windows
 * are in simulation seconds. Everything in the block is in world space:
 * the grid is built around the asset's rest pose placed by the object's
 * transform, and gravity, pins, probes and forces act there. The kind is
 * SEQUENTIAL (frame N needs 0..N-1) and checkpoints its state every
 * checkpoint_every frames into the derived-data cache (kind.h), so a
 * resumed or retried job replays from the nearest checkpoint.
 */
#ifndef MR_SPRINGMASS_KIND_H
#define MR_SPRINGMASS_KIND_H

#include "kinds/kind.h"

/* Caps of the block's arrays. */
#define MR_SPRINGMASS_MAX_PINS 16u
#define MR_SPRINGMASS_MAX_PROBES 8u
#define MR_SPRINGMASS_MAX_FORCES 16u
#define MR_SPRINGMASS_MAX_KEYS 1024u
#define MR_SPRINGMASS_MAX_POINTS 4096u

typedef enum mr_springmass_mapping {
    MR_SPRINGMASS_ONE_TO_ONE = 0,         /* 3.2: each vertex at its nearest surface node */
    MR_SPRINGMASS_TRIANGLE_BASIS,         /* 3.3.1: offsets in a constant triangle basis */
    MR_SPRINGMASS_TRIANGLE_CURVATURE,     /* 3.3.2: the basis interpolated from node normals */
    MR_SPRINGMASS_TRILINEAR               /* the reference: trilinear displacement of the cell */
} mr_springmass_mapping;

typedef enum mr_springmass_force_type {
    MR_SPRINGMASS_FORCE_POINT = 0, /* on the node nearest to position at rest */
    MR_SPRINGMASS_FORCE_WIND       /* on every surface node */
} mr_springmass_force_type;

/* A key of a pin's path: the pinned nodes are turned by rotation about the
 * pin's pivot and moved by translation, interpolated linearly (slerp for
 * the rotation) between keys and held before the first and after the
 * last. */
typedef struct mr_springmass_pin_key {
    float t;
    mr_vec3 translation;
    mr_quat rotation;
} mr_springmass_pin_key;

/* A node of a pin's node set: the node nearest to position at rest. */
typedef struct mr_springmass_pin_point {
    mr_vec3 position;
} mr_springmass_pin_point;

typedef struct mr_springmass_pin {
    mr_vec3 box_min, box_max;  /* nodes whose rest position lies in the box */
    bool points_only;          /* points given and no box: the box holds nothing */
    mr_springmass_pin_point *points; /* a node set, besides (or instead of) the box */
    size_t point_count;
    mr_vec3 pivot;             /* centre of rotation; default the pinned nodes' centroid */
    bool has_pivot;
    mr_springmass_pin_key *path;
    size_t path_count;         /* 0: the nodes stay where they are */
} mr_springmass_pin;

typedef struct mr_springmass_probe_key {
    float t;
    mr_vec3 position;
} mr_springmass_probe_key;

/* A sphere pushing nodes out of its way along its path (linear between
 * keys, held outside them): every step, a node inside the capsule the
 * sphere sweeps is moved to its surface, so a probe faster than a node
 * spacing per step pushes nodes ahead instead of tunnelling through. */
typedef struct mr_springmass_probe {
    float radius;
    mr_springmass_probe_key *path;
    size_t path_count;
} mr_springmass_probe;

typedef struct mr_springmass_force {
    int type;            /* mr_springmass_force_type */
    mr_vec3 position;    /* point: where (its nearest node at rest takes it) */
    mr_vec3 force;       /* point: the force; wind: the force on each surface node */
    float start, end;    /* active for start <= t < end, simulation seconds */
} mr_springmass_force;

typedef struct mr_springmass_params {
    float spacing;            /* node spacing, world units; 0: from nodes */
    uint32_t nodes;           /* target node count when spacing is 0 */
    float stiffness;          /* k_s of the axis springs */
    float shear_stiffness;    /* k_d of the diagonal springs (default: stiffness) */
    float damping;            /* c, viscous */
    float mass;               /* per node */
    mr_vec3 gravity;
    float dt;                 /* seconds per step */
    uint32_t steps_per_frame;
    int mapping;              /* mr_springmass_mapping */
    uint32_t checkpoint_every; /* frames; 0: no checkpoints */
    mr_springmass_pin *pins;
    size_t pin_count;
    mr_springmass_probe *probes;
    size_t probe_count;
    mr_springmass_force *forces;
    size_t force_count;
} mr_springmass_params;

extern const mr_kind mr_kind_springmass;

#endif
