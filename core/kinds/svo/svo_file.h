/*
 * svo_file.h - a voxelised asset on disk (issue 5): the octree of svo.h
 * (nodes, leaves, palette; never leaf_keys) as a `.mrsvo` file, and the disk
 * cache the scene uses so an asset is voxelised once per depth, mode and
 * albedo, not once per job.
 *
 * Why a file: voxelising (voxelize.h) a character at depth 10 takes seconds
 * and ~45 bytes per voxel of temporaries; loading the result is one read and
 * two checksums. The same conventions as the baked-DMM file
 * (kinds/dmm/dmm_file.h), and the same cache: util/derived.h.
 *
 * Layout (docs/svo-format.md): little-endian, magic and version, a 100-byte
 * header with its own CRC-32, then the arrays first_node, first_leaf,
 * child_mask, leaf_mask, leaves and palette and one CRC-32 over them:
 * 4 + 10 N/L + 16 P/L bytes per voxel for N nodes, L leaves and P palette
 * entries (7.9 for the BCN rig at depth 10, measured in the doc). The reader
 * checks every count against the bytes present and the caps, the octree
 * against the canonical layout mr_svo_build produces (breadth-first nodes,
 * children ranges as prefix sums, every node and leaf reached exactly once,
 * no interior node at the finest level: then mr_svo_collect_keys walks it),
 * every leaf's palette index and every palette entry's weights; any defect
 * gives MR_ERR_FORMAT with a message naming the byte offset and the field.
 * Garbage never crashes it and never makes it allocate more than the file's
 * own size. Writes go through a temporary file, fsync, rename and an fsync
 * of the directory, so a reader sees the old file or the new one.
 *
 * The cache is the derived-data cache (util/derived.h), which owns the
 * envelope (magic, version, header size, key, header CRC), the path
 * <dir>/<hex key>.mrsvo, the key builder and the hit/miss/replace policy.
 * This module adds what is the voxeliser's own: the layout
 * (mr_svo_file_format), what the key covers (mr_svo_cache_key: everything
 * the voxeliser reads), when a stored octree fits a request, and the
 * builder (mr_svo_voxelize). A file that is missing, corrupt, truncated, of
 * another version, under another key or not fitting is a miss: the asset is
 * voxelised again and the file replaced. A cache that cannot be written
 * costs the next job a voxelisation, never this job its result.
 */
#ifndef MR_SVO_FILE_H
#define MR_SVO_FILE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "asset/asset.h"
#include "microray.h"
#include "kinds/svo/svo.h"
#include "kinds/svo/voxelize.h"
#include "util/derived.h"

/* Version of the `.mrsvo` layout (part of the cache key). */
#define MR_SVO_FILE_VERSION 1u
/* Bump whenever voxelize.c or svo_build.c produce a different octree for
 * the same asset and parameters (another cube, overlap rule, attribute
 * rule, palette order, node or leaf order...): it is part of the cache key,
 * so old cache files stop matching instead of being rendered as if they
 * were fresh voxelisations. Changes that keep every output bit-identical
 * (speed, memory, messages) do not bump it. */
#define MR_SVO_VOXELIZER_REVISION 1u
/* Bytes of the header (payload starts there). */
#define MR_SVO_FILE_HEADER_BYTES 100u
/* Largest file a reader accepts: the voxeliser's cap of 2^28 voxels makes
 * about 1.9 GiB at the usual 0.33 nodes per leaf (a depth-10 character is
 * a few MB); the writer refuses larger octrees with MR_ERR_LIMIT. */
#define MR_SVO_FILE_MAX_BYTES ((uint64_t)1 << 31)

/* The layout's envelope for the derived-data cache: "svo file", files
 * named <hex key>.mrsvo, magic "MRSVO\0\r\n", the key at byte 64. */
extern const mr_derived_format mr_svo_file_format;

/* Header flags. VOXELIZED: written by the voxeliser's cache, the mode is
 * recorded; SOLID (only with VOXELIZED): mode MR_SVO_VOXELIZE_SOLID, else
 * surface. Without VOXELIZED nothing is known about how the octree was made. */
#define MR_SVO_FILE_VOXELIZED 1u
#define MR_SVO_FILE_SOLID 2u

/* What a file says beside the octree. */
typedef struct mr_svo_file_meta {
    uint32_t flags;                /* MR_SVO_FILE_* */
    uint8_t key[MR_DERIVED_KEY_BYTES]; /* the cache key it is stored under, or all zero */
} mr_svo_file_meta;

/* Serialises svo (leaf_keys are ignored) into a malloc'ed buffer (*buf owned
 * by the caller), with meta (NULL: flags 0, key all zero). Refuses
 * (MR_ERR_INVALID) anything the reader would refuse, e.g. an octree not in
 * mr_svo_build's layout, so what is written can always be read back;
 * MR_ERR_LIMIT above MR_SVO_FILE_MAX_BYTES. The output depends only on svo
 * and meta (deterministic, no padding garbage). */
int mr_svo_file_write(const mr_svo *svo, uint8_t **buf, size_t *size, mr_error *err);
int mr_svo_file_write_meta(const mr_svo *svo, const mr_svo_file_meta *meta, uint8_t **buf,
                           size_t *size, mr_error *err);
/* mr_svo_file_write to path: a temporary file in path's directory (mode
 * 0644), fsync, rename over path, fsync of the directory. MR_ERR_IO when a
 * step fails (the temporary file is removed). */
int mr_svo_file_write_path(const mr_svo *svo, const char *path, mr_error *err);

/* Parses and fully validates a buffer into *out, a heap-allocated octree
 * without leaf_keys (release with mr_svo_voxelize_free); *out is NULL on
 * failure. _meta also returns the header's flags and key (meta may be NULL). */
int mr_svo_file_read(const uint8_t *buf, size_t size, mr_svo **out, mr_error *err);
int mr_svo_file_read_meta(const uint8_t *buf, size_t size, mr_svo **out, mr_svo_file_meta *meta,
                          mr_error *err);
/* Reads and parses a file: MR_ERR_IO when it cannot be opened or read (or is
 * not a regular file), MR_ERR_FORMAT when larger than MR_SVO_FILE_MAX_BYTES
 * or broken (the message starts with the path). */
int mr_svo_file_read_path(const char *path, mr_svo **out, mr_error *err);

/* The cache key of mr_svo_voxelize(asset, params) (util/derived.h's
 * builder, tag "microray svo cache"): MR_SVO_FILE_VERSION,
 * MR_SVO_VOXELIZER_REVISION, every node's parent and rest transform (rigid
 * meshes are placed by them), per mesh its node, vertex, triangle and joint
 * counts, a presence word, positions, normals, indices, joints and weights
 * (what the voxeliser reads; uvs, names, inverse binds and clips are not),
 * then depth, mode and the albedo floats (not threads or keep_leaf_keys:
 * the octree does not depend on them). Host-independent (docs/svo-format.md
 * lists the bytes). NULL asset or params give an all-zero key. The file is
 * mr_derived_path(dir, key, mr_svo_file_format.ext). */
void mr_svo_cache_key(const mr_asset *asset, const mr_svo_voxelize_params *params,
                      uint8_t key[MR_DERIVED_KEY_BYTES]);
/* Loads the cache file at path: a hit sets *out (release with
 * mr_svo_voxelize_free; no leaf_keys) and returns MR_OK. A miss leaves *out
 * NULL: MR_ERR_IO when there is no such file (or it cannot be read),
 * MR_ERR_FORMAT when it is broken or stored under another key. Callers
 * treat both as "voxelise and store" (mr_svo_voxelize_cached does). */
int mr_svo_cache_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES], mr_svo **out,
                      mr_error *err);
/* Stores svo at path under key (flags 0), creating path's directory and its
 * parents (mode 0755) if missing; atomic as mr_svo_file_write_path
 * (mr_derived_store). MR_ERR_IO when the directory cannot be made or
 * written. */
int mr_svo_cache_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                       const mr_svo *svo, mr_error *err);

/* mr_svo_voxelize through the cache in cache_dir (NULL or "": no cache).
 * A hit needs a file that loads under the key and also fits the request:
 * same depth, flags recording the same mode, every palette entry naming a
 * mesh of asset and, where its weight is not 0, a joint of that mesh.
 * Anything else is a miss: the asset is voxelised and the file (re)written
 * with the mode recorded; a failure to write it (read-only or full disk,
 * a file where the directory should be) is ignored, as for DMM bakes, and
 * the fresh octree is returned. *from_cache (may be NULL) says which
 * happened. With params->keep_leaf_keys a hit recomputes leaf_keys
 * (mr_svo_collect_keys), so the result is the same either way. Errors are
 * mr_svo_voxelize's (parameters it would refuse are never looked up). */
int mr_svo_voxelize_cached(const mr_asset *asset, const mr_svo_voxelize_params *params,
                           const char *cache_dir, mr_svo **out, bool *from_cache, mr_error *err);

#endif /* MR_SVO_FILE_H */
