/*
 * dmm_file.h - a complete baked displaced micro-mesh on disk (issue 4): the
 * base mesh of every mesh of an asset (positions, directions, indices, the
 * detailed vertex each base vertex is, bone joints and weights, the bake's
 * report) together with its encoded displacements (dmm_encode.h's block,
 * embedded as is), and the disk cache of bakes the dmm kind uses so a bake
 * is done once per asset and parameter set, not once per job.
 *
 * Why a file of its own: baking (meshoptimizer simplification plus two
 * Embree rays per micro-vertex) takes seconds for big meshes, while loading
 * the result takes a read and a few checksums. The displacement-only
 * `.mrdmm` file cannot stand alone: it needs the base mesh it was baked on.
 * The bake's float displacements are not stored; what is rendered is the
 * encoding anyway (dmm.c decodes it), so nothing is lost.
 *
 * Layout (docs/dmm-format.md, "Baked DMM file"): little-endian, magic and
 * version, a CRC-32 per section; every count is checked against the bytes
 * present and the caps, every index against its range, every float for
 * being finite. Any defect gives MR_ERR_FORMAT with a message naming the
 * byte offset. Writes go through a temporary file in the same directory,
 * fsync, rename and an fsync of the directory, so a reader sees the old file
 * or the new one, never half of one, even after a crash.
 *
 * The cache is the derived-data cache (util/derived.h), which owns the
 * envelope (magic, version, header size, key, header CRC), the path
 * <dir>/<hex key>.dmm, the key builder and the hit/miss/replace policy.
 * This module adds what is the DMM's own: the layout (mr_dmm_file_format),
 * what the key covers (mr_dmm_cache_key: everything the bake reads), when a
 * stored bake fits an asset, and the builder (bake, then encode). A file
 * that is missing, corrupt, truncated, of another version, under another
 * key or not consistent with the asset is a miss: the asset is baked again
 * and the file replaced (mr_dmm_bake_cached).
 */
#ifndef MR_DMM_FILE_H
#define MR_DMM_FILE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "asset/asset.h"
#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "microray.h"
#include "util/derived.h"

/* Version of the baked-DMM file layout (part of the cache key). */
#define MR_DMM_FILE_VERSION 2u
/* Bump when dmm_bake.c or dmm_encode.c change what they produce for the same
 * input: it is part of the cache key, so old cache files stop matching
 * instead of being rendered as if they were fresh bakes. */
#define MR_DMM_BAKER_REVISION 3u
/* Bytes of the file header and of each mesh section header. */
#define MR_DMM_FILE_HEADER_BYTES 68u
#define MR_DMM_FILE_MESH_HEADER_BYTES 96u
/* Largest file a reader accepts from disk (the caps allow about 1.5 GiB). */
#define MR_DMM_FILE_MAX_BYTES ((uint64_t)1 << 31)

/* The layout's envelope for the derived-data cache: "dmm bake file", files
 * named <hex key>.dmm, magic "MRDMB\0\r\n", the key at byte 32. */
extern const mr_derived_format mr_dmm_file_format;

/* One mesh of the asset. */
typedef struct mr_dmm_file_mesh {
    uint32_t source_vertex_count; /* vertices of the detailed mesh baked (base_source < it) */
    uint32_t source_joint_count;  /* its joint count (nonzero-weight joints < it) */
    mr_dmm_bake *bake;            /* NULL: the mesh has no DMM (no triangles). Read from a
                                     file: displacements NULL, everything else filled in */
    mr_dmm_encoded *encoded;      /* NULL exactly when bake is; triangle_count ==
                                     bake->base_triangle_count, level == the file's */
} mr_dmm_file_mesh;

typedef struct mr_dmm_file {
    unsigned level;                  /* subdivision level of every mesh */
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1]; /* encoding widths of every mesh; above level: 0 */
    uint8_t key[MR_DERIVED_KEY_BYTES]; /* the cache key it is stored under, or all zero */
    uint32_t mesh_count;
    mr_dmm_file_mesh *meshes;
} mr_dmm_file;

/* Frees the meshes' bakes and encodings, the mesh array and f. NULL is fine.
 * (Writers pass borrowed bakes in a struct of their own and do not call it.) */
void mr_dmm_file_free(mr_dmm_file *f);

/* Serialises f into a malloc'ed buffer (*buf owned by the caller). Refuses
 * (MR_ERR_INVALID) anything the reader would not accept back, so what is
 * written can always be read. bits entries above level are ignored. */
int mr_dmm_file_write(const mr_dmm_file *f, uint8_t **buf, size_t *size, mr_error *err);
/* mr_dmm_file_write to path: a temporary file in path's directory, fsync,
 * rename over path, fsync of the directory. MR_ERR_IO when a step fails (the
 * temporary file is removed). */
int mr_dmm_file_write_path(const mr_dmm_file *f, const char *path, mr_error *err);
/* Parses and fully validates a buffer; *out is NULL on failure. */
int mr_dmm_file_read(const uint8_t *buf, size_t size, mr_dmm_file **out, mr_error *err);
/* Reads and parses a file: MR_ERR_IO when it cannot be opened or read (or is
 * not a regular file), MR_ERR_FORMAT when larger than MR_DMM_FILE_MAX_BYTES
 * or broken. */
int mr_dmm_file_read_path(const char *path, mr_dmm_file **out, mr_error *err);

/* The cache key of baking every mesh of asset with params and encoding with
 * bits (util/derived.h's builder, tag "microray baked dmm cache"):
 * MR_DMM_FILE_VERSION, MR_DMM_BAKER_REVISION, per mesh its vertex,
 * triangle and joint counts, whether it is skinned, positions, indices,
 * joints and weights (what the bake reads; normals and uvs are not), the
 * parameters (level, adaptive, target_triangles, target_ratio, max_error,
 * max_displacement; not threads: the bake does not depend on it) and
 * bits[0..MR_UMESH_MAX_LEVEL]. Host-independent (docs/dmm-format.md lists
 * the bytes). The file is mr_derived_path(dir, key, mr_dmm_file_format.ext). */
void mr_dmm_cache_key(const mr_asset *asset, const mr_dmm_bake_params *params,
                      const uint8_t bits[MR_UMESH_MAX_LEVEL + 1],
                      uint8_t key[MR_DERIVED_KEY_BYTES]);
/* Loads the cache file at path for asset: a hit fills bakes[i] / encoded[i]
 * (asset->mesh_count entries each, NULL for meshes without triangles; the
 * caller owns them; the bakes have no displacements) and returns MR_OK.
 * MR_ERR_IO: no such file (or it cannot be read, or is not a regular
 * file); MR_ERR_FORMAT: broken, or stored under another key, level or bits,
 * or not consistent with the asset (mesh count, which meshes are baked,
 * vertex and joint counts, skin, base vertices bit-identical to the
 * detailed vertices they name). On failure every entry is NULL. */
int mr_dmm_cache_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                      const mr_asset *asset, unsigned level,
                      const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], mr_dmm_bake **bakes,
                      mr_dmm_encoded **encoded, mr_error *err);
/* Stores the bakes of asset (bakes[i] / encoded[i] per mesh, borrowed) at
 * path under key, creating its directory (and parents, mode 0755) if
 * missing; atomic as mr_dmm_file_write_path (mr_derived_store). */
int mr_dmm_cache_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                       const mr_asset *asset, unsigned level,
                       const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], mr_dmm_bake *const *bakes,
                       mr_dmm_encoded *const *encoded, mr_error *err);

/* Bakes every mesh of asset that has triangles with params
 * (mr_dmm_bake_run) and encodes it with bits (mr_dmm_encode at
 * params->level), through the cache in cache_dir (NULL or "": no cache):
 * bakes[i] / encoded[i] as mr_dmm_cache_load fills them, from the cache
 * file when it loads for this asset (*from_cache true, may be NULL), else
 * freshly made and then stored under mr_dmm_cache_key; a store that fails
 * (a full disk, a read-only directory) is ignored. Either way the bakes
 * keep no float displacements: the encoding is what renders. Errors are the
 * bake's and the encoder's, prefixed "<asset path>: mesh i: "; on failure
 * every entry is NULL. */
int mr_dmm_bake_cached(const mr_asset *asset, const mr_dmm_bake_params *params,
                       const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], const char *cache_dir,
                       mr_dmm_bake **bakes, mr_dmm_encoded **encoded, bool *from_cache,
                       mr_error *err);

#endif /* MR_DMM_FILE_H */
