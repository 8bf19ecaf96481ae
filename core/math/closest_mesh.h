/*
 * closest_mesh.h - distances from points to a triangle mesh: an Embree
 * scene of the mesh (copied into Embree's own buffers, robust flag) and
 * exact closest-point queries on it (rtcPointQuery; the closest point of
 * each candidate triangle computed in double, Ericson's Real-Time Collision
 * Detection 5.1.5). The dmm bake measures its surface against the detailed
 * mesh with it; the mesh kind measures its levels of detail.
 *
 * The scene is an ordinary Embree scene: callers may also trace rays in it.
 * Queries are thread-safe once built.
 */
#ifndef MR_CLOSEST_MESH_H
#define MR_CLOSEST_MESH_H

#include <embree3/rtcore.h>
#include <stdint.h>

#include "microray.h"

typedef struct mr_closest_mesh {
    RTCDevice device;    /* owned when init was given none */
    RTCScene scene;
    const float *pos;    /* the caller's arrays: kept alive while queried */
    const uint32_t *idx;
    bool own_device;
} mr_closest_mesh;

/* Builds the scene of nt triangles idx over nv positions pos (3 floats
 * each), on device (NULL: a device of its own). who names the caller in
 * error messages ("dmm bake"). MR_ERR_EMBREE / MR_ERR_NOMEM on failure,
 * *m then needs no free. */
int mr_closest_mesh_init(mr_closest_mesh *m, RTCDevice device, const float *pos, uint32_t nv,
                         const uint32_t *idx, uint32_t nt, const char *who, mr_error *err);

/* Distance from p to the mesh; at (may be NULL) gets the closest point. */
double mr_closest_mesh_distance(const mr_closest_mesh *m, const double p[3], double at[3]);
/* The same, and *prim (may be NULL) the triangle holding the closest point
 * (UINT32_MAX for an empty mesh); of triangles at one distance, the first
 * the query met. */
double mr_closest_mesh_nearest(const mr_closest_mesh *m, const double p[3], double at[3],
                               uint32_t *prim);

void mr_closest_mesh_free(mr_closest_mesh *m);

#endif
