/*
 * mesh_lod_file.h - a mesh's levels of detail (mesh_lod.h) through the
 * derived-data cache (util/derived.h): built once per mesh and set of
 * measured poses, then read from <cache root>/mesh/<key>.mrlod by every
 * later job (the chain of an 82k-triangle dancer takes ~2 s to build).
 *
 * The key holds everything the chain is a function of: the rest-pose
 * positions, normals and triangles, and each pose the levels are measured
 * in as its posed positions (so a clip, a joint override, a speed or an
 * asset's animation that poses the mesh otherwise is another key, whatever
 * in the job made it so). The chain does not depend on the thread count.
 *
 * File (little-endian), a header of 96 bytes:
 *   0  magic "MRMLOD\r\n"   8 version (1)   12 header bytes (96)
 *  16  vertex count   20 triangle count   24 level count   28 distinct count
 *  32  payload bytes (u64)   40 payload CRC-32   44 zero
 *  48  key (32 bytes)   80 zero   92 header CRC-32
 * then per level: its triangle count (u32), 4 zero bytes and its error
 * (f64); the triangles of levels 1.. (3 u32 each, level by level); the
 * distinct vertices (u32 each). A file that does not fit the mesh asked
 * for (counts, level 0 not the mesh itself, a level not smaller than the
 * one before, an index past the vertices, an error not finite and >= 0) is
 * refused, which the cache treats as a miss.
 */
#ifndef MR_MESH_LOD_FILE_H
#define MR_MESH_LOD_FILE_H

#include <stdbool.h>
#include <stdint.h>

#include "kinds/mesh/mesh_lod.h"
#include "microray.h"

#define MR_MESH_LOD_FILE_VERSION 1u

/* The chain of the nt triangles idx over the nv rest positions pos and
 * normals (as mr_mesh_lod_build), measured again in each of pose_count
 * poses posed[j] (nv positions each, mr_mesh_lod_measure with stride
 * MR_LOD_POSE_STRIDE): read from cache_dir when a file there has it,
 * else built and stored there (cache_dir NULL: built only). *hit (may be
 * NULL) says which. Errors are the build's. */
int mr_mesh_lod_cached(const char *cache_dir, mr_mesh_lod *lod, const float *pos, const float *normals,
                       uint32_t nv, const uint32_t *idx, uint32_t nt, const float *const *posed,
                       uint32_t pose_count, unsigned threads, const char *who, bool *hit,
                       mr_error *err);

#endif
